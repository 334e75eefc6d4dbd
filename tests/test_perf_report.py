"""`benchmarks/perf.py`: the one-report assembly (collect mode, summaries, never overwriting) and a
real measured part (search overhead, the cheapest) run through the same path as a full report."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "benchmarks"))

import perf  # noqa: E402

RESULTS = Path(__file__).resolve().parent.parent / "benchmarks" / "results"


def _component(benchmark: str, date: str, **fields) -> dict:
    return {
        "benchmark": benchmark,
        "date": date,
        "commit": "abc1234def",
        "loaded": False,
        "device": {"platform": "cpu", "device_kind": "cpu", "device_count": 1, "host_cpu_count": 2},
        **fields,
    }


def test_collect_picks_the_newest_file_of_each_part_and_ignores_other_benchmarks(tmp_path):
    old = _component(
        "render_population",
        "2026-01-01T00:00:00",
        poses=8,
        resolution=16,
        samples_per_ray=32,
        batched_rays_per_s=1.0,
        loop_rays_per_s=1.0,
        speedup_batched_over_loop=1.0,
    )
    new = dict(old, date="2026-02-01T00:00:00", batched_rays_per_s=5.0, speedup_batched_over_loop=2.5)
    other = {"benchmark": "paper_tables", "date": "2026-03-01"}
    files = []
    for name, data in (("old.json", old), ("new.json", new), ("other.json", other)):
        (tmp_path / name).write_text(json.dumps(data))
        files.append(str(tmp_path / name))
    out = tmp_path / "perf.json"
    assert perf.main(["--collect", *files, "--parts", "render_population,search_overhead", "--out", str(out)]) == 1
    report = json.loads(out.read_text())
    entry = report["parts"]["render_population"]
    assert entry["status"] == "collected" and entry["file"].endswith("new.json")
    values = {row["figure"]: row["value"] for row in report["summary"]}
    assert values["dense render, batched"] == 5.0 and values["batched / loop"] == 2.5
    assert report["parts"]["search_overhead"]["status"] == "missing"
    assert "| render_population | dense render, batched | 5 |" in report["table_markdown"]
    with pytest.raises(SystemExit, match="refusing to overwrite"):
        perf.main(["--collect", *files, "--out", str(out)])


def test_collect_summarises_every_committed_component_result():
    files = sorted(str(p) for p in RESULTS.glob("*.json"))
    entries = perf.collect(files)
    for part, entry in entries.items():
        rows = perf.summarise(part, entry["result"])
        assert rows, part
        for row in rows:
            assert row["commit"] != "?" and row["date"] != "?" and "cpu" in row["device"], row


def test_unknown_part_is_a_clear_error():
    with pytest.raises(SystemExit, match="unknown"):
        perf.main(["--parts", "render,bogus"])


@pytest.mark.slow
def test_measured_part_runs_the_component_benchmark(tmp_path):
    out = tmp_path / "perf.json"
    # no waiting for a quiet machine inside the test suite (the figures are not kept)
    perf.main(["--parts", "search_overhead", "--quick", "--load-threshold", "1000", "--out", str(out)])
    written = out if out.exists() else Path(perf.loaded_name(str(out)))
    report = json.loads(written.read_text())
    entry = report["parts"]["search_overhead"]
    assert entry["status"] == "measured", entry
    assert entry["command"].startswith("python benchmarks/search_overhead.py")
    figures = {row["figure"] for row in report["summary"]}
    assert {"search overhead GRS", "search overhead PIBS", "search overhead EGPS"} <= figures
    assert all(row["value"] > 0 for row in report["summary"])
