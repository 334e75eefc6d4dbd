"""Writes benchmarks/results/INDEX.md: what each committed result JSON measured, on which device and commit.

    python benchmarks/results_index.py            # rewrite benchmarks/results/INDEX.md
    python benchmarks/results_index.py --check    # exit 1 when INDEX.md is out of date; write nothing

One row per `benchmarks/results/*.json`: the file, its benchmark, the device (platform / kind, host
cores), the commit and date it records, whether it was measured on a loaded machine, and one line on
what it measured. A file is *superseded* when a newer file measures the same thing: the same benchmark
and the same file name once the status words (`cpu`, `gpu`, `loaded`, `packed`, `rerun`) are taken off
its end, or where `SUPERSEDED` below says so (the cases the names cannot tell). Superseded files are kept
(the docs cite some as the "before" of a change) and marked, never deleted.
"""

from __future__ import annotations

import argparse
import json
import re
import sys
from pathlib import Path
from typing import Any, Dict, List, Optional

RESULTS = Path(__file__).resolve().parent / "results"
INDEX = RESULTS / "INDEX.md"

STATUS_WORDS = {"cpu", "gpu", "loaded", "packed", "rerun"}

# Supersessions the file names cannot tell: {older file: (newer file, why)}.
SUPERSEDED = {
    "train_fox_ds8_fast_cpu_loaded.json": (
        "train_quality_fox_cpu_packed.json",
        "the same fast-preset fox training, with the packed training step",
    ),
    "train_lego_tiny_fast_cpu.json": (
        "train_quality_lego_tiny_cpu_packed.json",
        "the same fast-preset lego_tiny training, with the packed step",
    ),
    "render_trained_fox_steps_cpu_loaded.json": (
        "render_trained_fox_cpu.json",
        "the marching-step curve of the packed renderer on the same fox run",
    ),
    "render_population_cpu_p64_r64.json": (
        "render_population_cpu_p256.json",
        "256 poses at 64^2, 128^2 and 256^2 (64^2 included)",
    ),
    "paper_tables_room_cpu_loaded.json": (
        "paper_tables_room_seed0_paper_budget_cpu.json",
        "the same room and criteria at the paper's budgets, 10 seeds",
    ),
}

HEX = re.compile(r"\b[0-9a-f]{7,40}\b")


def _key(name: str) -> str:
    """The file name without `.json` and without the status words at its end."""
    words = name[: -len(".json")].split("_")
    while len(words) > 1 and words[-1] in STATUS_WORDS:
        words.pop()
    return "_".join(words)


def _device(data: Dict[str, Any]) -> str:
    device = data.get("device")
    if isinstance(device, dict):
        kind = device.get("device_kind", "?")
        text = device.get("platform", "?") + ("" if kind == device.get("platform") else f" / {kind}")
        if device.get("device_count", 1) != 1:
            text += f" x{device['device_count']}"
        if device.get("host_cpu_count"):
            text += f" ({device['host_cpu_count']} host cores)"
        return text
    machine = data.get("machine")
    if isinstance(machine, str):
        return "cpu (" + machine.split(",")[0] + ")"
    return "not recorded"


def _commit(data: Dict[str, Any]) -> str:
    raw = data.get("commit") or data.get("commit_code") or ""
    match = HEX.search(str(raw))
    if not match:
        return "not recorded"
    text = match.group(0)[:7]
    rest = str(raw)[match.end() :]
    return text + ("+dirty" if rest.startswith("+dirty") or rest.startswith("+") else "")


def _date(data: Dict[str, Any]) -> str:
    return str(data.get("date", ""))[:10] or "not recorded"


def _loaded(name: str, data: Dict[str, Any]) -> str:
    loaded = data.get("loaded")
    if loaded is None and isinstance(data.get("load"), dict):
        loaded = data["load"].get("loaded")
    if loaded is None:
        loaded = True if name.endswith("_loaded.json") else None
    return "n/r" if loaded is None else ("yes" if loaded else "no")


def _join(values) -> str:
    return ", ".join(str(v) for v in values)


def _argv_value(argv: str, flag: str) -> Optional[str]:
    match = re.search(rf"{flag}[ =](\S+)", argv or "")
    return match.group(1) if match else None


def _what(name: str, data: Dict[str, Any]) -> str:
    """One line on what the file measured."""
    bench = data.get("benchmark", "?")
    s = data.get("settings") or {}
    if bench == "paper_tables":
        children = s.get("children_override") or {}
        budget = (
            ("children per epoch " + ", ".join(f"{k}={v}" for k, v in children.items()))
            if children
            else "the paper's budgets"
        )
        scenes = [f"room (seed {s.get('room_seed', 0)})" if x == "room" else x for x in s.get("scenes", [])]
        criteria = list(s.get("criteria") or [])
        if "room" in s.get("scenes", []):
            criteria += [c for c in s.get("waldo_criteria") or [] if c not in criteria]
        return (
            f"CVIR / mCVIR of GRS, PIBS, EGPS: {_join(scenes)}; {_join(criteria)}; "
            f"{s.get('resolution')} px, {s.get('seeds')} seeds, {budget}"
        )
    if bench == "methods":
        argv = s.get("argv", "")
        scenes = s.get("scenes") or _argv_value(argv, "--scenes") or "room,fox"
        budgets = s.get("budgets") or _argv_value(argv, "--budgets") or "low,high"
        methods = s.get("methods") or _argv_value(argv, "--methods") or "all six"
        seeds = s.get("seeds") or _argv_value(argv, "--seeds")
        return f"search methods at equal cost: {scenes}; budgets {budgets}; methods {methods}; {seeds} seeds"
    if bench == "paths":
        return (
            f"camera-path search on the room ({s.get('methods')}; {s.get('aggregates')}) against the straight "
            f"path and the training trajectory; {s.get('seeds')} seeds, {s.get('budget')} budget"
        )
    if bench == "render_trained":
        info = data.get("run_info") or {}
        scene = Path(str(data.get("scene_path", ""))).name or "?"
        extra = ""
        chunk = re.search(r"field_chunk_(\d+)", name)
        if chunk:
            extra = f"; field calls of {chunk.group(1)} slots" if chunk.group(1) != "0" else "; one field call per pass"
        if "steps" in name[len("render_trained") :]:
            extra += "; coarser marching steps"
        return (
            f"marched renderer on a trained {scene} run ({info.get('steps')} steps): rays/s, evaluations/ray, "
            f"passes/view, the field alone, batched vs loop{extra}"
        )
    if bench == "render_population":
        sizes = (
            [f"{x['resolution']}^2" for x in data["sizes"]]
            if isinstance(data.get("sizes"), list)
            else [f"{data.get('resolution')}^2"]
        )
        return f"room, {data.get('poses')} poses at {_join(sizes)}: one batched render_views call vs a per-pose loop"
    if bench == "render_splats":
        syn = s.get("counts")
        return (
            f"splat renderer on synthetic splats ({_join(syn or [])} splats; sizes {_join(s.get('sizes', []))}; "
            f"populations {_join(s.get('populations', []))}): views/s and stage times"
        )
    if bench == "train_quality":
        size = data.get("image_size") or ["?", "?"]
        return (
            f"held-out PSNR against training time: {data.get('scene')} {size[0]}x{size[1]}, "
            f"{data.get('preset')} preset, {data.get('steps')} steps"
        )
    if bench == "train_step":
        return (
            f"ms per training step against the field's forward + backward: {data.get('scene')}, "
            f"{data.get('samples_per_batch')} samples a step"
        )
    if bench.startswith("field_pass"):
        grid = data.get("hashgrid") or {}
        return (
            f"the hash-grid field's forward and forward + backward passes, ms: {data.get('points')} points, "
            f"L {grid.get('L')}, T {grid.get('T')}, N_max {grid.get('N_max')}"
            + (f" (this change against {data['baseline_commit']})" if "baseline_commit" in data else "")
        )
    if bench == "compile_cache_writes":
        cfg = data.get("settings") or {}
        return (
            f"ms per small program compiled into a compilation-cache folder of {cfg.get('entries')} programs: "
            "JAX bounding the folder at every write against the `waldo` command's prune at start"
        )
    if bench == "criteria_throughput":
        return (
            f"images/s of every image criterion: batch {data.get('batch')} at {data.get('size')}^2 "
            f"({data.get('images')})"
        )
    if bench == "search_overhead":
        return (
            f"us per generated pose of GRS / PIBS / EGPS without render or score ({data.get('generated_poses')} "
            f"poses), vs evosax SimpleGA"
        )
    if bench == "explore_room":
        return (
            f"whole `waldo explore {data.get('source')}` command at {data.get('resolution')} px, "
            f"{data.get('budget')} budget, criteria {_join(data.get('runs', {}))}"
        )
    if bench == "trust_guard":
        methods = sorted({row.get("method") for row in data.get("guard", [])})
        return (
            f"the trust guard on the demo's NeRF (procedural:{data.get('room_seed')}): waldo_found guarded by "
            f"trust at thresholds, {_join(methods)}, {s.get('seeds')} seeds; trust vs render PSNR"
        )
    if bench == "perf":
        return f"the collected performance report: {data.get('mode')}"
    if bench == "suite_profile":
        programs = data.get("programs") or {}
        return (
            f"the test suite's {(data.get('settings') or {}).get('tier', 'suite')} tier: {data.get('tests')} test "
            f"records, {data.get('test_seconds')} test-seconds, "
            f"{programs.get('compiled')} programs compiled ({programs.get('compiled_again')} compiled again)"
        )
    if bench == "room_reachable":
        return (
            f"per room ({s.get('rooms')}), the dense search's best visible share of Waldo beside "
            f"{(s.get('methods') or '').replace(',', ', ')} at the {s.get('budget', 'low')} budget"
        )
    if bench == "before_packed_renderer":
        return "baseline: the renderer and training step before the packed ones, on the same runs and settings"
    if bench.startswith("waldo demo"):
        settings = "--quick settings" if "--quick" in bench else "full settings"
        codes = {r.get("code") for r in data.get("runs") or []}
        flags = {r.get("xla_flags") for r in data.get("runs") or [] if "xla_flags" in r}
        if len(flags) > 1:
            return "`waldo demo` and `--quick` first runs of one commit under two XLA settings: wall and stage times"
        if data.get("runs") and {r.get("run") for r in data["runs"]} >= {"full", "--quick"}:
            what = "two commits" if len(codes) <= 2 else f"{len(codes)} variants of the code or settings"
            return f"`waldo demo` and `--quick` first runs (`--quick` at {what}, A against B): wall and stage times"
        if data.get("runs"):
            return f"`waldo demo` ({settings}) first runs at two commits, A against B: wall and stage times"
        return f"`waldo demo` end to end ({settings}): stage times, CVIR / mCVIR per method"
    if bench.startswith("waldo train"):
        info = data.get("train_json") or {}
        return (
            f"`waldo train` ({info.get('preset')} preset, {info.get('steps')} steps): "
            f"{Path(str(info.get('scene_path', ''))).name}"
        )
    return bench


def rows() -> List[Dict[str, str]]:
    entries = []
    for path in sorted(RESULTS.glob("*.json")):
        data = json.loads(path.read_text(encoding="utf-8"))
        entries.append(
            {
                "file": path.name,
                "benchmark": str(data.get("benchmark", "?")),
                "device": _device(data),
                "commit": _commit(data),
                "date": _date(data),
                "sort_date": str(data.get("date", "")),
                "loaded": _loaded(path.name, data),
                "what": _what(path.name, data),
                "key": _key(path.name),
                "status": "current",
            }
        )
    by_key: Dict[tuple, List[Dict[str, str]]] = {}
    for entry in entries:
        by_key.setdefault((entry["benchmark"], entry["key"]), []).append(entry)
    for group in by_key.values():
        newest = max(group, key=lambda e: e["sort_date"])
        for entry in group:
            if entry is not newest:
                entry["status"] = f"superseded by [{newest['file']}]({newest['file']})"
    names = {e["file"] for e in entries}
    for entry in entries:
        if entry["file"] in SUPERSEDED:
            newer, why = SUPERSEDED[entry["file"]]
            if newer in names:
                entry["status"] = f"superseded by [{newer}]({newer}): {why}"
    return entries


def render() -> str:
    lines = [
        "# Result files",
        "",
        "Generated by `python benchmarks/results_index.py` from the JSONs in this folder: do not edit by hand.",
        "Each JSON holds the full record (settings, versions, XLA flags, load averages); figures folders",
        "(`*_figures/`) belong to the JSON of the same name. *loaded*: measured while other jobs shared the",
        "machine, so its timings are pessimistic (its scores are not affected); n/r: not recorded.",
        'A superseded file is kept because the docs cite it as the "before" of a change.',
        "",
        "| file | benchmark | device | commit | date | loaded | what it measured | status |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for e in rows():
        lines.append(
            f"| [{e['file']}]({e['file']}) | {e['benchmark']} | {e['device']} | `{e['commit']}` | {e['date']} | "
            f"{e['loaded']} | {e['what']} | {e['status']} |"
        )
    return "\n".join(lines) + "\n"


def main(argv: Optional[List[str]] = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--check", action="store_true", help="exit 1 when INDEX.md is out of date; write nothing")
    args = parser.parse_args(argv)
    text = render()
    old = INDEX.read_text(encoding="utf-8") if INDEX.exists() else ""
    if args.check:
        print(
            "INDEX.md is up to date"
            if old == text
            else "INDEX.md is out of date: run python benchmarks/results_index.py"
        )
        return 0 if old == text else 1
    if old != text:
        INDEX.write_text(text, encoding="utf-8")
    print(f"wrote {INDEX}" if old != text else f"{INDEX} is up to date")
    return 0


if __name__ == "__main__":
    sys.exit(main())
