"""One performance report: rendering, training, criteria, search overhead and end-to-end explore.

Each part is one of the component benchmarks of this folder, run as its own process (so its
compilations, memory and device count are its own) and parsed from the JSON it prints:

  part               script                    what it measures
  render_population  render_population.py     batched vs per-pose loop, dense renderer (Waldo room)
  render_trained     render_trained.py        the marched renderer on a trained run: rays/s, field
                                              evaluations per ray, passes per view, against the field
                                              alone (render efficiency); needs --run and --scene
  train              train_quality.py         training rays/s and held-out PSNR after a time budget
  train_step         train_step.py            ms per training step against the field's forward and
                                              backward pass at the same sample budget
  criteria           criteria_throughput.py   images/s of every image criterion inside one jit
  search_overhead    search_overhead.py       us per generated pose of GRS / PIBS / EGPS without render
                                              or score, vs the paper's 0.7-0.8 ms and vs evosax's
                                              SimpleGA in the same process
  explore            explore_room.py          end-to-end low-budget `waldo explore` of the room

The report keeps every part's whole JSON (each with its own device, commit and date: a part may come
from another run), a flat `summary` of the headline figures (one row per figure: part, figure, value,
unit, device, commit, date, loaded) and the same rows as a Markdown table (`table_markdown`, also
printed to stderr), which is what the README's performance table is made from.

Two ways to fill it:
  * measure: run the parts now (`--parts`, default all that can run; `render_trained` needs a
    trained run, `train` a scene). `--quick` uses small settings (minutes on a CPU; the figures are
    then smaller-batch figures and say so in each part's settings);
  * `--collect FILE...`: assemble the report from component JSONs measured earlier (for instance
    `benchmarks/results/*.json`); each file's `benchmark` field says which part it is, and the
    newest file of each part wins. Nothing is re-measured, and the report says which files it read.

Output: the JSON on stdout, and in `--out` (never overwritten; `_loaded` added when any part was
measured on a shared machine).

  # every part on this machine (a GPU run: add nothing, the scripts pick the device up)
  python benchmarks/perf.py --run runs/paper_nerfs_cpu/fox --scene ../shared/scenes/fox --downscale 8 \
      --train-scene ../shared/scenes/lego_tiny --out benchmarks/results/perf_cpu.json
  # the committed CPU report, assembled from the component results
  python benchmarks/perf.py --collect benchmarks/results/*.json --out benchmarks/results/perf_cpu_collected.json
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

from bench_common import emit, header, loaded_name  # noqa: E402

PARTS = ("render_population", "render_trained", "train", "train_step", "criteria", "search_overhead", "explore")
BENCHMARK_OF_PART = {
    "render_population": "render_population",
    "render_trained": "render_trained",
    "train": "train_quality",
    "train_step": "train_step",
    "criteria": "criteria_throughput",
    "search_overhead": "search_overhead",
    "explore": "explore_room",
}
PART_OF_BENCHMARK = {v: k for k, v in BENCHMARK_OF_PART.items()}
PAPER_SEARCH_US_PER_POSE = (700.0, 800.0)


# ---------------------------------------------------------------------------------------------
# Running the parts.


def part_command(part: str, args) -> list[str] | None:
    """The component benchmark's argv for `part`, or None when its inputs are missing."""
    argv = _part_command(part, args)
    if argv is not None and args.load_threshold is not None:
        flag = "--quiet-load" if part == "criteria" else "--load-threshold"
        argv += [flag, str(args.load_threshold)]
    return argv


def _part_command(part: str, args) -> list[str] | None:
    quick = args.quick
    if part == "render_population":
        extra = (
            ["--poses", "16", "--resolutions", "32,64"] if quick else ["--poses", "256", "--resolutions", "64,128,256"]
        )
        return ["render_population.py", *extra]
    if part == "render_trained":
        if not (args.run and args.scene):
            return ["render_trained.py", "--quick"] if quick else None
        extra = [args.run, args.scene, "--poses", "4" if quick else "16", "--repeats", "1" if quick else "3"]
        if args.downscale:
            extra += ["--downscale", str(args.downscale)]
        return ["render_trained.py", *extra]
    if part == "train_step":
        if not args.train_scene:
            return None
        return ["train_step.py", args.train_scene, "--steps", "200" if quick else "400"]
    if part == "train":
        if not args.train_scene:
            return None
        return [
            "train_quality.py",
            args.train_scene,
            "--seconds",
            "60" if quick else "300",
            "--eval-at",
            "60" if quick else "60,120,300",
        ]
    if part == "criteria":
        extra = ["--batch", "8", "--size", "128", "--repeats", "1"] if quick else []
        return ["criteria_throughput.py", *extra]
    if part == "search_overhead":
        return ["search_overhead.py", *(["--repeats", "5"] if quick else [])]
    if part == "explore":
        return ["explore_room.py", *(["--methods", "egps", "--criteria", "waldo_oracle"] if quick else [])]
    raise ValueError(part)


def parse_json_output(text: str) -> dict:
    """The last top-level JSON object printed on stdout (the component scripts print exactly one)."""
    decoder = json.JSONDecoder()
    found = None
    for i, ch in enumerate(text):
        if ch == "{" and (i == 0 or text[i - 1] == "\n"):
            try:
                found, _ = decoder.raw_decode(text[i:])
            except json.JSONDecodeError:
                continue
    if found is None:
        raise ValueError("no JSON object on stdout")
    return found


def run_part(part: str, argv: list[str]) -> dict:
    command = [sys.executable, str(HERE / argv[0]), *argv[1:]]
    print(f"[perf] {part}: {' '.join(argv)}", file=sys.stderr, flush=True)
    start = time.perf_counter()
    proc = subprocess.run(command, capture_output=True, text=True)
    wall = time.perf_counter() - start
    entry = {"command": "python benchmarks/" + " ".join(argv), "wall_s": round(wall, 1)}
    if proc.returncode != 0:
        entry.update(status="failed", returncode=proc.returncode, stderr_tail=proc.stderr[-3000:])
        print(f"[perf] {part} FAILED ({proc.returncode}):\n{proc.stderr[-1500:]}", file=sys.stderr, flush=True)
        return entry
    try:
        entry.update(status="measured", result=parse_json_output(proc.stdout))
    except ValueError as error:
        entry.update(status="failed", error=str(error), stdout_tail=proc.stdout[-2000:])
    return entry


def collect(paths: list[str]) -> dict:
    """Parts from component JSON files: per part the newest (by its `date`) file."""
    chosen: dict[str, tuple[str, str, dict]] = {}
    for name in paths:
        path = Path(name)
        try:
            data = json.loads(path.read_text())
        except (OSError, json.JSONDecodeError) as error:
            raise SystemExit(f"{path}: cannot read a benchmark JSON ({error})")
        part = PART_OF_BENCHMARK.get(data.get("benchmark")) if isinstance(data, dict) else None
        if part is None:
            continue  # another benchmark's file (paper tables, perf reports ...)
        date = str(data.get("date", ""))
        if part not in chosen or date > chosen[part][0]:
            chosen[part] = (date, str(path), data)
    return {part: {"status": "collected", "file": file, "result": data} for part, (_, file, data) in chosen.items()}


# ---------------------------------------------------------------------------------------------
# Headline figures.


def _row(part, result, figure, value, unit, note=""):
    device = result.get("device", {})
    loaded = result.get("loaded", result.get("load", {}).get("loaded"))
    return {
        "part": part,
        "figure": figure,
        "value": value,
        "unit": unit,
        "note": note,
        "device": f"{device.get('platform', '?')}:{device.get('device_kind', '?')} x{device.get('device_count', '?')}"
        f" ({device.get('host_cpu_count', '?')} host cores)",
        "commit": str(result.get("commit", "?"))[:10],
        "date": str(result.get("date", "?"))[:10],
        "loaded": bool(loaded),
    }


def summarise(part: str, r: dict) -> list[dict]:
    rows = []
    if part == "render_population":
        for size in r.get("sizes", [r]):  # older results hold one size at the top level
            setting = f"{r['poses']} poses {size['resolution']}^2, S={r['samples_per_ray']}"
            rows.append(_row(part, r, "dense render, batched", size["batched_rays_per_s"], "rays/s", setting))
            rows.append(_row(part, r, "dense render, per-pose loop", size["loop_rays_per_s"], "rays/s", setting))
            rows.append(_row(part, r, "batched / loop", size["speedup_batched_over_loop"], "x", setting))
    elif part == "render_trained" and "marched" in r:  # the renderer before the packed one
        m = r["marched"]
        setting = f"{r['timing_poses']} poses at {'x'.join(str(v) for v in r['timing_resolution'])}"
        rows.append(_row(part, r, "occupancy-grid render (trained)", m["rays_per_s"], "rays/s", setting))
        rows.append(
            _row(
                part,
                r,
                "field evaluations per ray, occupancy grid",
                m.get("field_evaluations_per_ray_psnr_views", m["field_evaluations_per_ray"]),
                "evals/ray",
                f"held-out PSNR {m['psnr_test']:.2f} dB",
            )
        )
    elif part == "render_trained":
        setting = f"{r['timing_poses']} poses at {'x'.join(str(v) for v in r['timing_size'])}"
        rows.append(_row(part, r, "marched render (trained)", r["rays_per_s"], "rays/s", setting))
        rows.append(
            _row(
                part,
                r,
                "field evaluations per ray",
                r["evaluations_per_ray"],
                "evals/ray",
                f"step x{r['render_step_scale']:g}, held-out PSNR {r['psnr_test']:.2f} dB "
                f"({r['psnr_delta_db']:+.2f} dB)",
            )
        )
        rows.append(_row(part, r, "field passes per view", r["passes_per_view"], "passes", setting))
        rows.append(
            _row(part, r, "field alone", r["field_points_per_s"], "points/s", "as many points, one pass a call")
        )
        rows.append(
            _row(part, r, "render efficiency", r["render_efficiency"], "x", "rays/s x evaluations/ray / field points/s")
        )
        if r.get("speedup_batched_over_loop") is not None:
            rows.append(
                _row(part, r, "batched / per-pose loop (trained)", r["speedup_batched_over_loop"], "x", setting)
            )
    elif part == "train_step":
        setting = (
            f"{r['scene']} {r['image_size'][0]}x{r['image_size'][1]}, {r['preset']} preset, "
            f"{r['samples_per_batch']} samples"
        )
        rows.append(_row(part, r, "training step", r["ms_per_step"], "ms", setting))
        rows.append(_row(part, r, "field forward + backward alone", r["field_fwd_bwd_ms"], "ms", setting))
        rows.append(_row(part, r, "step / field", r["step_over_field"], "x", setting))
        rows.append(_row(part, r, "rays per step", r["rays_per_step"], "rays", setting))
    elif part == "train":
        setting = f"{r['scene']} {r['image_size'][0]}x{r['image_size'][1]}, {r['preset']} preset"
        rows.append(_row(part, r, "training", r["rays_per_second"], "rays/s", setting))
        rows.append(
            _row(
                part, r, f"held-out PSNR after {r['seconds']:.0f} s ({r['steps']} steps)", r["psnr_test"], "dB", setting
            )
        )
    elif part == "criteria":
        for name, c in sorted(r["criteria"].items(), key=lambda kv: -kv[1]["images_per_s"]):
            rows.append(
                _row(
                    part, r, f"criterion {name}", c["images_per_s"], "images/s", f"batch {r['batch']} at {r['size']}^2"
                )
            )
    elif part == "search_overhead":
        n = r["generated_poses"]
        for name, m in r["methods"].items():
            rows.append(
                _row(
                    part,
                    r,
                    f"search overhead {name.upper()}",
                    m["us_per_pose_best"],
                    "us/pose",
                    f"{n} poses, compiled; paper {PAPER_SEARCH_US_PER_POSE[0]:.0f}-"
                    f"{PAPER_SEARCH_US_PER_POSE[1]:.0f} us",
                )
            )
        ga = r.get("evosax_simple_ga", {})
        if ga.get("available"):
            rows.append(
                _row(
                    part,
                    r,
                    "evosax SimpleGA (same run)",
                    ga["us_per_pose_best"],
                    "us/pose",
                    f"population {ga['population_size']}, {ga['generations']} generations",
                )
            )
    elif part == "explore":
        for criterion, methods in r["runs"].items():
            for method, run in methods.items():
                rows.append(
                    _row(
                        part,
                        r,
                        f"waldo explore room, {criterion}, {method.upper()}",
                        run["cli"]["wall_s"],
                        "s",
                        f"low budget, {r['resolution']}^2, whole command",
                    )
                )
    return rows


def markdown(rows: list[dict]) -> str:
    lines = [
        "| part | figure | value | unit | setting | device | commit | date | loaded |",
        "| --- | --- | ---: | --- | --- | --- | --- | --- | --- |",
    ]
    for row in rows:
        value = row["value"]
        text = "n/a" if value is None else (f"{value:,.0f}" if abs(value) >= 100 else f"{value:.3g}")
        lines.append(
            f"| {row['part']} | {row['figure']} | {text} | {row['unit']} | {row['note']} | "
            f"{row['device']} | {row['commit']} | {row['date']} | {'yes' if row['loaded'] else 'no'} |"
        )
    return "\n".join(lines)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--parts", default=",".join(PARTS), help=f"comma list of {', '.join(PARTS)}")
    parser.add_argument("--quick", action="store_true", help="small settings (minutes on a CPU)")
    parser.add_argument("--run", default=None, help="trained run for render_trained (`waldo train` output)")
    parser.add_argument("--scene", default=None, help="that run's scene (held-out images)")
    parser.add_argument("--downscale", default=None, help="the run's --downscale")
    parser.add_argument("--train-scene", default=None, help="scene for the training part (e.g. lego_tiny)")
    parser.add_argument(
        "--collect", nargs="+", default=None, metavar="FILE", help="assemble from component JSONs instead of measuring"
    )
    parser.add_argument(
        "--load-threshold",
        type=float,
        default=None,
        help="passed to every part: the 1-min load average above which it waits (up to 5 min) "
        "and marks its result loaded (default: each part's own)",
    )
    parser.add_argument("--out", default=None, help="also write the report here (never overwritten)")
    args = parser.parse_args(argv)

    parts = [p.strip() for p in args.parts.split(",") if p.strip()]
    unknown = sorted(set(parts) - set(PARTS))
    if unknown:
        raise SystemExit(f"--parts: unknown {unknown}; choose from {', '.join(PARTS)}")
    for out in (args.out, args.out and loaded_name(args.out)):
        if out and Path(out).exists():
            raise SystemExit(f"{out} exists: refusing to overwrite an earlier report (choose another --out)")

    report = header("perf")
    if args.collect:
        entries = {p: e for p, e in collect(args.collect).items() if p in parts}
        report["mode"] = "collected from earlier component results (nothing re-measured)"
    else:
        entries = {}
        for part in parts:
            argv_part = part_command(part, args)
            if argv_part is None:
                need = "--run and --scene" if part == "render_trained" else "--train-scene"
                entries[part] = {"status": "skipped", "reason": f"needs {need}"}
                continue
            entries[part] = run_part(part, argv_part)
        report["mode"] = "measured now" + (" (--quick settings)" if args.quick else "")
    for part in parts:
        entries.setdefault(part, {"status": "missing", "reason": "no component result for this part"})
    rows = []
    for part in parts:
        if "result" in entries[part]:
            try:
                rows += summarise(part, entries[part]["result"])
            except (KeyError, TypeError, ValueError) as error:
                entries[part]["summary_error"] = f"{type(error).__name__}: {error}"
    report.update(
        parts=entries,
        summary=rows,
        table_markdown=markdown(rows),
        paper_search_us_per_pose=list(PAPER_SEARCH_US_PER_POSE),
        loaded=any(row["loaded"] for row in rows),
    )
    print(report["table_markdown"], file=sys.stderr)
    out = args.out
    if out and report["loaded"]:
        out = loaded_name(out)
        print(f"some parts were measured on a shared machine: writing {out}", file=sys.stderr)
    emit(report, out)
    return 0 if all(e["status"] in ("measured", "collected", "skipped") for e in entries.values()) else 1


if __name__ == "__main__":
    sys.exit(main())
