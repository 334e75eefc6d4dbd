"""mkdocs hooks: files outside docs/ that the documentation shows or links to.

The pages link to the committed results (`../benchmarks/results/...`: JSONs, figures, INDEX.md) and to
the repository's CHANGELOG.md, CONTRIBUTING.md and LICENSE with relative paths that also work on disk and
on GitHub. `on_files` adds those files to the site at their repository paths, and `on_page_markdown`
rewrites each such link to the file's place in the site, so that `mkdocs build --strict` checks every
one of them like any other link (a link to a file outside docs/ that is not mounted still fails).

`KNOWN_DOCSTRING_WARNINGS` lists the few docstring warnings of the package that are known and waiting
for a fix in waldo_jax/: `on_config` shows them as INFO instead of failing the strict build. Any other
warning still fails it; delete an entry once its docstring is fixed.
"""

from __future__ import annotations

import logging
import posixpath
import re
from pathlib import Path

from mkdocs.structure.files import File
from mkdocs.utils import CountHandler

ROOT = Path(__file__).resolve().parent.parent
DOCS = ROOT / "docs"
MOUNTED_FILES = ("CHANGELOG.md", "CONTRIBUTING.md", "LICENSE")
MOUNTED_DIRS = ("benchmarks/results",)
MOUNTED_SUFFIXES = {".md", ".json", ".png", ".gif", ".jpg"}

# (file, part of griffe's message): why. Each is a docstring layout griffe's Google parser misreads.
# No line numbers, so that edits elsewhere in the file do not make an entry stale.
KNOWN_DOCSTRING_WARNINGS: dict = {}


def _known(record: logging.LogRecord) -> bool:
    message = record.getMessage()
    return record.levelno == logging.WARNING and any(
        where in message and start in message for where, start in KNOWN_DOCSTRING_WARNINGS
    )


class _Demote(logging.Filter):
    """Shows a known docstring warning as INFO; drops it from strict mode's count."""

    def __init__(self, counter: bool):
        super().__init__()
        self.counter = counter

    def filter(self, record: logging.LogRecord) -> bool:
        if not _known(record):
            return True
        if self.counter:
            return False
        record.levelno, record.levelname = logging.INFO, "INFO"
        record.msg = f"{record.msg} (known, see KNOWN_DOCSTRING_WARNINGS in docs/hooks.py)"
        return True


def on_config(config):
    for handler in logging.getLogger("mkdocs").handlers:
        if not any(isinstance(f, _Demote) for f in handler.filters):
            handler.addFilter(_Demote(counter=isinstance(handler, CountHandler)))
    return config


_LINK = re.compile(r"(\]\()([^)\s#]+)([^)]*\))")


def _mounted() -> list:
    paths = [ROOT / name for name in MOUNTED_FILES if (ROOT / name).is_file()]
    for folder in MOUNTED_DIRS:
        paths += sorted(p for p in (ROOT / folder).rglob("*") if p.is_file() and p.suffix in MOUNTED_SUFFIXES)
    return [p.relative_to(ROOT).as_posix() for p in paths]


def on_files(files, config):
    for uri in _mounted():
        if files.get_file_from_path(uri) is None:
            files.append(
                File(
                    uri, src_dir=str(ROOT), dest_dir=config["site_dir"], use_directory_urls=config["use_directory_urls"]
                )
            )
    return files


def on_page_markdown(markdown, page, config, files):
    """Relative links that leave docs/ (or, in a mounted page, point into it) -> the file's site path."""
    source = Path(page.file.abs_src_path).resolve()
    page_dir = posixpath.dirname(page.file.src_uri)
    mounted = set(_mounted())

    def site_uri(target: Path):
        if target.is_relative_to(DOCS):
            return target.relative_to(DOCS).as_posix()
        rel = target.relative_to(ROOT).as_posix() if target.is_relative_to(ROOT) else None
        return rel if rel in mounted else None

    def replace(match: re.Match) -> str:
        link = match.group(2)
        if re.match(r"^[a-z][a-z0-9+.-]*:", link) or link.startswith("/"):
            return match.group(0)  # absolute URL or site-absolute path: left to mkdocs
        target = (source.parent / link).resolve()
        uri = site_uri(target)
        if uri is None:
            return match.group(0)  # not ours to map: mkdocs reports it if it is broken
        new = posixpath.relpath(uri, page_dir or ".")
        return match.group(1) + new + match.group(3)

    return _LINK.sub(replace, markdown)
