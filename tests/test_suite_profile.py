"""`benchmarks/suite_profile.py` and the per-test log it reads (tests/conftest.py, `WALDO_TEST_COMPILE_LOG`):
counts on a hand-written log, bad logs refused by name, and a real pytest run whose log records the
programs it compiled and the one it loaded from the cache."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "benchmarks"))

import suite_profile  # noqa: E402


def _record(test, seconds, programs, **phases):
    return json.dumps({"test": test, "seconds": seconds, **phases, "programs": programs})


def test_counts_programs_compiled_again_and_loaded(tmp_path):
    log = tmp_path / "log.jsonl"
    log.write_text(
        "\n".join(
            [
                _record("tests/test_a.py::one", 3.0, [["jit_f", "k1", False, 1.5], ["jit_g", "k2", False, 0.1]]),
                _record("tests/test_a.py::two", 1.0, [["jit_f", "k1", True, 1], ["jit_g", "k2", False, 0.1]]),
                _record("tests/test_b.py::three", 5.0, [["jit_f", "k3", False, 2.0]], backend_compile_duration=2.5),
            ]
        )
        + "\n"
    )
    result = suite_profile.profile(suite_profile.read_log(log))
    assert result["tests"] == 3 and result["test_seconds"] == 9.0 and result["backend_compile_s"] == 2.5
    programs = result["programs"]
    assert (programs["asked"], programs["loaded_from_cache"], programs["compiled"]) == (5, 1, 4)
    assert programs["distinct_keys_compiled"] == 3 and programs["compiled_again"] == 1
    assert programs["compiled_again_s"] == 0.1 and programs["xla_compile_s"] == 3.7
    files = {row["file"]: row for row in result["files"]}
    assert [row["file"] for row in result["files"]] == ["tests/test_b.py", "tests/test_a.py"]  # slowest first
    assert files["tests/test_a.py"]["compiled_again"] == 1 and files["tests/test_b.py"]["compiled_again"] == 0
    top = {row["name"]: row for row in result["top_programs"]}
    assert top["jit_f"] == {"name": "jit_f", "compiled": 2, "distinct": 2, "seconds": 3.5}


def test_the_tier_sets_the_target(tmp_path):
    log = tmp_path / "log.jsonl"
    log.write_text(_record("tests/test_a.py::one", 1.0, []) + "\n")
    whole = suite_profile.main([str(log), "--wall", "9"])
    fast = suite_profile.main([str(log), "--wall", "9", "--tier", "fast"])
    assert (whole["settings"]["tier"], whole["settings"]["target_s"], whole["target_test_seconds"]) == (
        "suite",
        480.0,
        960.0,
    )
    assert (fast["settings"]["tier"], fast["settings"]["target_s"], fast["target_test_seconds"]) == (
        "fast",
        60.0,
        120.0,
    )


@pytest.mark.parametrize(
    "text, message",
    [
        (None, "no such file"),
        ("", "holds no test records"),
        ("{]\n", "line 1: not JSON"),
        ("[1]\n", "not a test"),
        ('{"test": "t.py::a", "programs": [["jit_f", "k"]]}\n', "line 1: not a test record"),
    ],
    ids=["missing", "empty", "not-json", "not-a-record", "short-program"],
)
def test_a_bad_log_is_one_line_naming_it(tmp_path, capsys, text, message):
    log = tmp_path / "log.jsonl"
    if text is not None:
        log.write_text(text)
    with pytest.raises(SystemExit) as raised:
        suite_profile.main([str(log)])
    assert str(log) in str(raised.value) and message in str(raised.value)


def test_an_earlier_result_is_never_overwritten(tmp_path):
    out = tmp_path / "profile.json"
    out.write_text("{}")
    log = tmp_path / "log.jsonl"
    log.write_text(_record("tests/test_a.py::one", 1.0, []) + "\n")
    with pytest.raises(SystemExit, match="refusing to overwrite"):
        suite_profile.main([str(log), "--out", str(out)])
    assert out.read_text() == "{}"


@pytest.mark.slow
def test_a_real_run_logs_its_programs_and_cache_hits(tmp_path):
    """Two tests that compile the same program in a fresh cache: the second loads it (the log's keys are
    the cache's own, read through the wrapped cache functions of this jaxlib)."""
    test_file = tmp_path / "test_twice.py"
    test_file.write_text(
        "import functools\n"
        "import jax, jax.numpy as jnp\n"
        "def work(x):\n"
        "    for _ in range(30):\n"
        "        x = jnp.sin(x) @ x\n"
        "    return x\n"
        "def test_first():\n"
        "    jax.jit(work)(jnp.ones((64, 64))).block_until_ready()\n"
        "def test_second():\n"
        "    again = functools.wraps(work)(lambda x: work(x))  # a new function of the same name: the same program\n"
        "    jax.jit(again)(jnp.ones((64, 64))).block_until_ready()\n"
    )
    (tmp_path / "conftest.py").write_text((ROOT / "tests" / "conftest.py").read_text())
    log = tmp_path / "log.jsonl"
    env = dict(
        os.environ,
        WALDO_TEST_COMPILE_LOG=str(log),
        JAX_COMPILATION_CACHE_DIR=str(tmp_path / "cache"),
        JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS="0",
        PYTHONPATH=os.pathsep.join([str(ROOT), *filter(None, [os.environ.get("PYTHONPATH")])]),
    )
    env.pop("PYTEST_XDIST_WORKER", None)
    run = subprocess.run(
        [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-p", "no:xdist", str(test_file)],
        cwd=tmp_path,
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert run.returncode == 0, run.stdout[-2000:] + run.stderr[-2000:]
    records = {json.loads(line)["test"].rsplit("::", 1)[-1]: json.loads(line) for line in log.read_text().splitlines()}
    first, second = records["test_first"]["programs"], records["test_second"]["programs"]
    compiled = [p for p in first if not p[2] and p[0].startswith("jit_work")]
    assert len(compiled) == 1 and compiled[0][3] > 0
    loaded = [p for p in second if p[2]]
    assert [p[1] for p in loaded] == [compiled[0][1]]  # the same key, loaded from the cache
    result = suite_profile.profile(suite_profile.read_log(log))
    assert result["programs"]["loaded_from_cache"] >= 1 and result["tests"] == 2
