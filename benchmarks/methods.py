"""The search methods compared at equal cost: GRS, PIBS, EGPS, MAP-Elites, EGPS + gradient refinement and
evosax strategies, on the Waldo room (`waldo_found` by default), a trained fox NeRF (`saliency`), the donut
splats (`saliency`) and a trained lego_tiny NeRF (`colorfulness`), low and high budgets, K seeds per cell:
mean, std and a 95 % bootstrap interval of CVIR, mCVIR, dCVIR and the best view's score; the different
shots (`--min-separation`, default 20 degrees) among the paper's top-10 and how many of the 10 best
different shots beat the best training view; the archive's coverage and QD-score (`ExploreConfig.grid`);
on the room also Waldo's visible share in each seed's best view and how many seeds found him (>= 90 %
visible).

Equal cost: every method of a (scene, budget) cell costs the same number of renders, training views
included (`ExploreConfig.cost`); a `+refine` method pays for its gradient evaluations at
`gradient_cost` renders each, measured here first for each scene with `gradient_cost.measure` (the
time of a gradient in the source's own mode over that of a render and exact score, rounded up, at
least 2: reverse mode through a NeRF run, `Source.gradient`), and so has fewer children. On the room
the global methods follow the exact oracle; refinement follows its smooth stand-in (`Criterion.smooth`:
sigmoids at the image borders and at the 90 % bar instead of steps) and every score reported is the
exact oracle's. On fox, refinement follows the smooth salient fraction (a sigmoid instead of the 0.5
threshold); scores are the exact salient fraction.

The full table (many CPU-hours on 2 cores; the fox run: `waldo train ../shared/scenes/fox --downscale 8
--out runs/fox_nerf`):

  python benchmarks/methods.py --fox-run runs/fox_nerf --seeds 8 --out benchmarks/results/methods_cpu.json

The room target (EGPS finds Waldo whole in >= 90 % of 16 seeds at the low budget, on several rooms):

  python benchmarks/methods.py --scenes room --room-seeds 1,4,5,6,7 --budgets low --methods egps \\
      --seeds 16 --out benchmarks/results/methods_room_found_cpu.json
  python benchmarks/methods.py --scenes room --budgets low --seeds 2 --quick   # a minute

The different-shots table (issue 41; the NeRF runs as for fox, and `waldo train ../shared/scenes/lego_tiny
--out runs/lego_nerf`):

  python benchmarks/methods.py --scenes fox,room,donut,lego --fox-run runs/fox_nerf --lego-run runs/lego_nerf \
      --room-criterion waldo_visible --methods grs,pibs,egps,map-elites --seeds 8 \
      --out benchmarks/results/methods_shots_cpu.json

The interval is the 2.5 and 97.5 percentiles of the mean over `--bootstrap` resamples of the seeds
(NumPy generator seeded with 0). `beats_egps`: the method's mCVIR interval lies wholly above EGPS's;
`best_vs_egps`: the method's mean best score against EGPS's best-score interval ("above", "within" or
"below"); `more_shots_than_egps`: its mean count of different shots beating the best training view
exceeds EGPS's.
Writes `<out>.partial` after each cell, the final JSON (never over an existing file) at the end.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import waldo_jax  # noqa: E402,F401  (XLA flags before the first computation)
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

from bench_common import emit_with_load, header, refuse_existing_out, wait_for_quiet  # noqa: E402
from gradient_cost import measure  # noqa: E402
from waldo_jax.criteria import CriterionContext, build_criterion  # noqa: E402
from waldo_jax.paths import data_dir  # noqa: E402
from waldo_jax.pipeline import load_source, run_explore  # noqa: E402
from waldo_jax.procedural import FOUND_VISIBILITY, waldo_visibility_batch  # noqa: E402
from waldo_jax.search import ExploreConfig, RefineConfig, get_method  # noqa: E402
from waldo_jax.search.views import DEFAULT_MIN_SEPARATION  # noqa: E402

METHODS = ("grs", "pibs", "egps", "map-elites", "egps+refine", "evosax:CMA_ES", "evosax:SNES")
# scene -> its default criterion (the room's is --room-criterion) and its --resolution flag's default.
SCENES = {"room": (None, 64), "fox": ("saliency", 32), "donut": ("saliency", 64), "lego": ("colorfulness", 64)}


def bootstrap_interval(values, resamples: int, seed: int = 0):
    """(low, high): the 2.5 and 97.5 percentiles of the mean of `values` resampled with replacement."""
    values = np.asarray([v for v in values if v is not None and math.isfinite(v)], np.float64)
    if len(values) == 0:
        return None, None
    rng = np.random.default_rng(seed)
    means = rng.choice(values, size=(resamples, len(values)), replace=True).mean(axis=1)
    return float(np.percentile(means, 2.5)), float(np.percentile(means, 97.5))


def summary(values, resamples: int) -> dict:
    finite = [v for v in values if v is not None and math.isfinite(v)]
    low, high = bootstrap_interval(finite, resamples)
    return {
        "mean": float(np.mean(finite)) if finite else None,
        "std": float(np.std(finite)) if finite else None,
        "ci95": [low, high],
        "values": values,
        "finite": len(finite),
    }


def run_cell(source, criterion, method: str, budget: str, refine: RefineConfig, args) -> dict:
    options = {"refine": refine} if "refine" in get_method(method).options else {}
    config = ExploreConfig(
        method=method, budget=budget, epochs=5, top_k=10, min_separation=args.min_separation, options=options
    )
    run = run_explore(source, criterion, config, seed=args.seed, seeds=args.seeds, initial=args.initial)

    def per_seed(field):
        return [float(getattr(r, field)) if np.isfinite(getattr(r, field)) else None for r in run.results]

    resolved = run.config
    best = [float(r.metrics.best[-1]) for r in run.results]
    cell = {
        "method": method,
        "budget": budget,
        "cost": resolved.cost(source.n_train),
        "children_per_epoch": resolved.children_per_epoch,
        "initial_scores": run.initial,
        "cvir": summary(per_seed("cvir"), args.bootstrap),
        "mcvir": summary(per_seed("mcvir"), args.bootstrap),
        "dcvir": summary(per_seed("dcvir"), args.bootstrap),
        "best": best,
        "best_summary": summary(best, args.bootstrap),
        "best_train": float(
            np.nanmax(run.scores_train) if run.criterion.direction == "max" else np.nanmin(run.scores_train)
        ),
        "min_separation": resolved.min_separation,
        "paper_top_shots": summary([float(r.paper_top_shots) for r in run.results], args.bootstrap),
        "shots_beating_train": summary([float(r.shots_beating_train) for r in run.results], args.bootstrap),
        "coverage": summary(per_seed("coverage"), args.bootstrap),
        "qd_score": summary(per_seed("qd_score"), args.bootstrap),
        "grid": resolved.grid.to_dict(),
        "seconds": run.seconds,
    }
    if source.room is not None:  # the known answer: how much of Waldo each seed's best view shows
        best_c2w = jnp.asarray(np.stack([np.asarray(r.top_c2w[0]) for r in run.results]))
        visible = np.asarray(waldo_visibility_batch(source.room, best_c2w, source.intrinsics), np.float64)
        cell["best_visible"] = [float(v) for v in visible]
        cell["found_seeds"] = int(np.sum(visible >= FOUND_VISIBILITY))
    return cell


def compare(cells: list) -> None:
    """Marks each cell against EGPS's of the same scene and budget: `beats_egps` (mCVIR interval wholly
    above), `best_vs_egps` (mean best score above, within or below EGPS's best-score interval; the sign
    follows the criterion's direction) and `more_shots_than_egps` (mean different shots beating the best
    training view above EGPS's)."""
    egps = {(c["scene"], c["budget"]): c for c in cells if c["method"] == "egps"}
    for cell in cells:
        reference = egps.get((cell["scene"], cell["budget"]))
        if reference is None or cell["method"] == "egps":
            cell["beats_egps"], cell["best_vs_egps"], cell["more_shots_than_egps"] = False, None, None
            continue
        low = cell["mcvir"]["ci95"][0]
        high = reference["mcvir"]["ci95"][1]
        cell["beats_egps"] = bool(low is not None and high is not None and low > high)
        sign = 1.0 if cell.get("direction", "max") == "max" else -1.0
        mean, (lo, hi) = cell["best_summary"]["mean"], reference["best_summary"]["ci95"]
        if None not in (mean, lo, hi):
            lo, hi = sorted((sign * lo, sign * hi))
            cell["best_vs_egps"] = "above" if sign * mean > hi else "within" if sign * mean >= lo else "below"
        shots, egps_shots = cell["shots_beating_train"]["mean"], reference["shots_beating_train"]["mean"]
        cell["more_shots_than_egps"] = None if None in (shots, egps_shots) else bool(shots > egps_shots)


def table(cells: list) -> str:
    """A Markdown table: one row per scene, budget and method."""

    def fmt(s):
        if s["mean"] is None:
            return "n/a"
        return f"{s['mean']:.1f} ± {s['std']:.1f} [{s['ci95'][0]:.1f}, {s['ci95'][1]:.1f}]"

    lines = [
        "| scene | budget | method | cost (renders) | CVIR % mean ± std [95 % CI] | mCVIR % mean ± std [95 % CI] "
        "| Waldo found (seeds >= 90 % visible) |",
        "|---|---|---|---|---|---|---|",
    ]
    for c in cells:
        mark = " **(> EGPS)**" if c.get("beats_egps") else ""
        found = (
            f"{c['found_seeds']}/{len(c['best_visible'])} ({np.mean(c['best_visible']):.0%} visible)"
            if "best_visible" in c
            else ""
        )
        lines.append(
            f"| {c['scene']} | {c['budget']} | {c['method']}{mark} | {c['cost']['renders']} | "
            f"{fmt(c['cvir'])} | {fmt(c['mcvir'])} | {found} |"
        )
    return "\n".join(lines)


def shots_table(cells: list) -> str:
    """A Markdown table of different shots: one row per scene, budget and method."""

    def fmt(s, digits=1):
        if s["mean"] is None:
            return "n/a"
        return f"{s['mean']:.{digits}f} [{s['ci95'][0]:.{digits}f}, {s['ci95'][1]:.{digits}f}]"

    lines = [
        "| scene | budget | method | best score [95 % CI] | mCVIR % | dCVIR % [95 % CI] | different shots in the "
        "paper's top 10 | of the 10 best different shots, beating the best training view [95 % CI] | coverage |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for c in cells:
        marks = []
        if c.get("best_vs_egps"):
            marks.append(f"best {c['best_vs_egps']} EGPS's interval")
        if c.get("more_shots_than_egps") is not None:
            marks.append("more shots than EGPS" if c["more_shots_than_egps"] else "not more shots than EGPS")
        note = f" ({'; '.join(marks)})" if marks else ""
        lines.append(
            f"| {c['scene']} | {c['budget']} | {c['method']}{note} | {fmt(c['best_summary'], 4)} | "
            f"{c['mcvir']['mean']:.1f} | {fmt(c['dcvir'])} | {c['paper_top_shots']['mean']:.1f} | "
            f"{fmt(c['shots_beating_train'])} | {c['coverage']['mean']:.0%} |"
        )
    return "\n".join(lines)


def _scene_source(scene_kind: str, room_seed, args):
    """(source, criterion name, resolution) of one scene of the table."""
    criterion_name, _ = SCENES[scene_kind]
    resolution = getattr(args, f"{scene_kind}_resolution")
    if scene_kind == "room":
        spec, criterion_name = f"procedural:{room_seed}", args.room_criterion
    elif scene_kind == "donut":
        spec = args.donut or str((data_dir() or Path("../shared")) / "splats" / "donut" / "point_cloud.ply")
    else:
        spec = getattr(args, f"{scene_kind}_run")
        if not spec:
            raise SystemExit(f"--{scene_kind}-run RUN is needed for the {scene_kind} scene (a run of `waldo train`)")
    return load_source(spec, resolution), criterion_name, resolution


def _refine(scene_kind: str, spec: str, criterion_name: str, resolution: int, costs: dict, scene: str, args):
    """The `+refine` methods' `RefineConfig` of a scene (the gradient cost measured unless given)."""
    if args.gradient_cost is not None:
        gradient_cost = args.gradient_cost
    elif any("+refine" in m for m in args.methods.split(",")):
        poses = 4 if scene_kind == "room" else 2
        costs[scene] = measure(f"{spec}:{criterion_name}", resolution, poses, 1 if args.quick else 3)
        gradient_cost = max(2, math.ceil(costs[scene]["ratio"]))
    else:
        gradient_cost = RefineConfig().gradient_cost  # unused: no method refines
    return RefineConfig(
        poses=args.refine_poses or (4 if scene_kind == "room" else 2),
        steps=args.refine_steps or (4 if scene_kind == "room" else 3),
        step_size=args.step_size,
        gradient_cost=gradient_cost,
    )


def _arguments(argv):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scenes", default="room,fox", help=f"comma-separated, of {', '.join(SCENES)}")
    parser.add_argument("--room-seeds", default="1", help="comma-separated rooms (procedural:SEED); 1: the demo's")
    parser.add_argument("--room-criterion", default="waldo_found", help="the room's criterion (a pose criterion)")
    parser.add_argument("--fox-run", default=None, help="run directory of `waldo train` on fox (needed for fox)")
    parser.add_argument("--lego-run", default=None, help="run directory of `waldo train` on lego_tiny (for lego)")
    parser.add_argument("--donut", default=None, help="the donut splats (default: $WALDO_DATA/splats/donut)")
    parser.add_argument("--methods", default=",".join(METHODS))
    parser.add_argument("--budgets", default="low,high")
    parser.add_argument("--seeds", type=int, default=8)
    parser.add_argument("--seed", type=int, default=0, help="first seed")
    for scene, (_, resolution) in SCENES.items():
        flag = "--resolution" if scene == "fox" else f"--{scene}-resolution"
        parser.add_argument(flag, dest=f"{scene}_resolution", type=int, default=resolution)
    parser.add_argument("--min-separation", type=float, default=DEFAULT_MIN_SEPARATION, help="degrees")
    parser.add_argument("--initial", default="renders", help="initial scores: images or renders")
    parser.add_argument("--refine-poses", type=int, default=None, help="default: 4 on the room, 2 elsewhere")
    parser.add_argument("--refine-steps", type=int, default=None, help="default: 4 on the room, 3 elsewhere")
    parser.add_argument("--step-size", type=float, default=0.02)
    parser.add_argument("--gradient-cost", type=int, default=None, help="default: measured per scene")
    parser.add_argument("--bootstrap", type=int, default=10000)
    parser.add_argument("--quick", action="store_true", help="smoke run: no timing repeats")
    parser.add_argument("--load-threshold", type=float, default=1.0)
    parser.add_argument("--out", default=None)
    return parser.parse_args(argv)


def main(argv=None) -> None:
    args = _arguments(argv)
    refuse_existing_out(args.out)
    quiet = wait_for_quiet(args.load_threshold, max_wait_s=0 if args.quick else 300)
    result = header("methods")
    result["settings"] = {k: v for k, v in vars(args).items()}
    cells, costs = [], {}
    start = time.perf_counter()
    scenes = [
        (scene, room_seed)
        for scene in args.scenes.split(",")
        for room_seed in ([int(k) for k in args.room_seeds.split(",")] if scene == "room" else [None])
    ]
    for scene_kind, room_seed in scenes:
        several_rooms = len(args.room_seeds.split(",")) > 1
        scene = f"room:{room_seed}" if scene_kind == "room" and several_rooms else scene_kind
        source, criterion_name, resolution = _scene_source(scene_kind, room_seed, args)
        criterion = build_criterion(criterion_name, CriterionContext(room=source.room, source=source.spec))
        refine = _refine(scene_kind, source.spec, criterion_name, resolution, costs, scene, args)
        for budget in args.budgets.split(","):
            for method in args.methods.split(","):
                cell = run_cell(source, criterion, method, budget, refine, args)
                cell.update(
                    {
                        "scene": scene,
                        "source": source.spec,
                        "criterion": criterion.name,
                        "direction": criterion.direction,
                        "resolution": resolution,
                        "refine": dataclasses.asdict(refine) if "+refine" in method else None,
                    }
                )
                cells.append(cell)
                print(
                    f"[methods] {scene} {budget} {method}: mCVIR {cell['mcvir']['mean']}, dCVIR "
                    f"{cell['dcvir']['mean']}, shots {cell['shots_beating_train']['mean']}, best "
                    f"{cell['best_summary']['mean']}, cost {cell['cost']['renders']}, {cell['seconds']['total']:.0f} s",
                    file=sys.stderr,
                    flush=True,
                )
                if args.out:
                    Path(args.out + ".partial").write_text(json.dumps({"cells": cells, "gradient_cost": costs}))
    compare(cells)
    result.update(
        {
            "cells": cells,
            "gradient_cost": costs,
            "table": table(cells),
            "shots_table": shots_table(cells),
            "seconds": round(time.perf_counter() - start, 1),
        }
    )
    print(result["table"] + "\n\n" + result["shots_table"], file=sys.stderr)
    emit_with_load(result, args.out, quiet, args.load_threshold)
    if args.out:
        Path(args.out + ".partial").unlink(missing_ok=True)


if __name__ == "__main__":
    main()
