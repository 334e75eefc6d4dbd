"""`benchmarks/bench_common.py`'s verdict on a shared machine: other processes' CPU time during a run
(the machine's busy time less the benchmark's own and its children's) marks it loaded."""

from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "benchmarks"))

import bench_common  # noqa: E402

pytestmark = [
    pytest.mark.slow,  # each spins a process for 1.5 s
    pytest.mark.skipif(bench_common.cpu_snapshot() is None, reason="no /proc/stat (not Linux)"),
]

SPIN = "import time\nend = time.perf_counter() + 1.5\nwhile time.perf_counter() < end: pass\n"


def _emit_beside_a_busy_process(out, load_threshold):
    """`emit_with_load` of a run during which a busy process this one has not waited for (so not among
    its children's times) ran for about a second; returns others' cores measured just before it."""
    quiet = bench_common.wait_for_quiet(threshold=1e9)  # starts the count at once
    child = subprocess.Popen([sys.executable, "-c", SPIN])
    try:
        time.sleep(1.2)
        others = bench_common.others_cores(quiet["cpu_start"])
        bench_common.emit_with_load({"benchmark": "x"}, str(out), quiet, load_threshold=load_threshold)
    finally:
        child.wait()
    return others


def test_a_process_not_ours_counts_as_others_and_marks_the_run_loaded(tmp_path):
    """About a core of others' use, and the run written under the `_loaded` name."""
    out = tmp_path / "result.json"
    others = _emit_beside_a_busy_process(out, load_threshold=1.0)
    assert others is not None and others > 0.5
    written = json.loads((tmp_path / "result_loaded.json").read_text())
    assert written["loaded"] is True and written["others_cores"] > 0.5 and not out.exists()


def test_a_huge_threshold_turns_the_verdict_off(tmp_path):
    out = tmp_path / "result.json"
    _emit_beside_a_busy_process(out, load_threshold=1000.0)
    assert json.loads(out.read_text())["loaded"] is False
