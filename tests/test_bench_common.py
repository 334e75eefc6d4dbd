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


def test_a_process_not_ours_counts_as_others_and_marks_the_run_loaded(tmp_path):
    """A busy process this one has not waited for (so not among its children's times) during the run:
    about a core of others' use, and the run written under the `_loaded` name."""
    quiet = {
        "loadavg_start": [0.0, 0.0, 0.0],
        "waited_s": 0.0,
        "loaded": False,
        "cpu_start": bench_common.cpu_snapshot(),
    }
    child = subprocess.Popen([sys.executable, "-c", SPIN])
    time.sleep(1.2)
    others = bench_common.others_cores(quiet["cpu_start"])
    assert others is not None and others > 0.5
    out = tmp_path / "result.json"
    bench_common.emit_with_load({"benchmark": "x"}, str(out), quiet, load_threshold=1.0)
    written = json.loads((tmp_path / "result_loaded.json").read_text())
    assert written["loaded"] is True and written["others_cores"] > 0.5 and not out.exists()
    child.wait()


def test_a_huge_threshold_turns_the_verdict_off(tmp_path):
    quiet = {
        "loadavg_start": [0.0, 0.0, 0.0],
        "waited_s": 0.0,
        "loaded": False,
        "cpu_start": bench_common.cpu_snapshot(),
    }
    child = subprocess.Popen([sys.executable, "-c", SPIN])
    time.sleep(1.2)
    out = tmp_path / "result.json"
    bench_common.emit_with_load({"benchmark": "x"}, str(out), quiet, load_threshold=1000.0)
    child.wait()
    assert json.loads(out.read_text())["loaded"] is False
