"""The README and the docs as a new user meets them: short, free of lab-notebook dates and commit hashes,
with the test command CI really runs, and no link to a file that is not there. Fast: no mkdocs run (CI
builds the site with `mkdocs build --strict`)."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
README = ROOT / "README.md"
MAX_README_LINES = 300

ISO_DATE = re.compile(r"\b\d{4}-\d{2}-\d{2}\b")
# 7 to 40 hex digits with at least one letter and one digit: a commit hash, not a number or a word.
COMMIT_HASH = re.compile(r"\b(?=[0-9a-f]*[a-f])(?=[0-9a-f]*[0-9])[0-9a-f]{7,40}\b")
FENCE = re.compile(r"^(```|~~~).*?^\1", re.S | re.M)
INLINE_CODE = re.compile(r"`[^`\n]*`")
HTML_COMMENT = re.compile(r"<!--.*?-->", re.S)
LINK = re.compile(r"!?\[(?:[^\[\]]|\[[^\]]*\])*\]\(\s*<?([^)\s>]+)>?(?:\s+\"[^\"]*\")?\s*\)")
TEST_COMMAND = re.compile(r'^\s*(python -m pip install -e "\.\[test\]" && python -m pytest[^#\n]*?)\s*(#.*)?$', re.M)


def _pages():
    """README, the root documents and every Markdown page of docs/."""
    pages = [README, ROOT / "CONTRIBUTING.md", ROOT / "CHANGELOG.md"] + sorted((ROOT / "docs").rglob("*.md"))
    return [p for p in pages if p.is_file()]


def _prose(text: str) -> str:
    """The text without fenced code blocks, inline code and HTML comments (where links are not links)."""
    return INLINE_CODE.sub("", FENCE.sub("", HTML_COMMENT.sub("", text)))


def _ci_test_command() -> str:
    lines = [line.strip() for line in (ROOT / ".ci" / "run").read_text(encoding="utf-8").splitlines()]
    commands = [line for line in lines if line and not line.startswith("#")]
    return commands[-1]


def test_readme_is_short():
    lines = README.read_text(encoding="utf-8").splitlines()
    assert len(lines) <= MAX_README_LINES, (
        f"README.md has {len(lines)} lines (at most {MAX_README_LINES}): move the detail into docs/"
    )


def test_readme_has_no_dates_or_commit_hashes():
    text = README.read_text(encoding="utf-8")
    found = [
        f"line {text[: m.start()].count(chr(10)) + 1}: {m.group(0)}"
        for pattern in (ISO_DATE, COMMIT_HASH)
        for m in pattern.finditer(text)
    ]
    assert not found, (
        "README.md holds dates or commit hashes (the result JSONs record them; cite the JSON): " + "; ".join(found)
    )


def test_readme_test_command_is_the_one_ci_runs():
    ci = _ci_test_command()
    assert TEST_COMMAND.match(ci), f".ci/run must end with the test command, ends with {ci!r}"
    readme = [m.group(1).strip() for m in TEST_COMMAND.finditer(README.read_text(encoding="utf-8"))]
    assert readme, "README.md gives no test command"
    assert set(readme) == {ci}, f"README.md's test command {readme} differs from .ci/run's {ci!r}"
    for page in _pages():  # the docs repeat it: the same command everywhere
        for m in TEST_COMMAND.finditer(page.read_text(encoding="utf-8")):
            assert m.group(1).strip() == ci, f"{page.relative_to(ROOT)}: test command {m.group(1)!r} is not CI's {ci!r}"


@pytest.mark.parametrize("page", _pages(), ids=lambda p: p.relative_to(ROOT).as_posix())
def test_relative_links_point_to_files(page):
    broken = []
    for target in LINK.findall(_prose(page.read_text(encoding="utf-8"))):
        if re.match(r"^[a-z][a-z0-9+.-]*:", target) or target.startswith(("#", "/")):
            continue  # a URL, an anchor in the page, or a site-absolute path
        path = (page.parent / target.split("#", 1)[0]).resolve()
        if not path.exists():
            broken.append(target)
    assert not broken, f"{page.relative_to(ROOT)} links to files that do not exist: {broken}"


def test_generated_blocks_are_filled():
    """Every table between `generated` markers holds what `python docs/make_tables.py` wrote."""
    marker = re.compile(r"<!-- generated: ([\w-]+) .*?-->\n(.*?)<!-- end generated: \1 -->", re.S)
    for page in _pages():
        for name, body in marker.findall(page.read_text(encoding="utf-8")):
            assert "|" in body, (
                f"{page.relative_to(ROOT)}: generated block {name!r} is empty: run python docs/make_tables.py"
            )


def test_license_and_citation():
    license_text = (ROOT / "LICENSE").read_text(encoding="utf-8")
    assert "Apache License" in license_text and "Version 2.0, January 2004" in license_text
    assert "Apache-2.0" in (ROOT / "pyproject.toml").read_text(encoding="utf-8")
    citation = (ROOT / "CITATION.cff").read_text(encoding="utf-8")
    assert citation.startswith("cff-version:")
    assert "10.1145/3625468.3647620" in citation and "Finding Waldo" in citation
