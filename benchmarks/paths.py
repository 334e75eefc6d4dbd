"""Camera-path search on the Waldo room: is the found path better than the obvious ones?

Per seed s (K seeds): an EGPS `explore` run on procedural:0 (`waldo_oracle`, low budget, seed s)
gives the anchor poses (its top 10); the path search (seed s, each of `--methods`) starts from
them, once per path score (`--aggregates`: the mean over frames, and a soft minimum). The found path is compared with
(a) the straight path between the two best anchors and
(b) the training trajectory (the spline through all training cameras in their order), all at the
same F frames: the mean and the worst per-frame oracle score, with a 95 % bootstrap interval over
the seeds, the rate of seeds where the found path beats each reference, the paths' smoothness
(max speed, max turn, max jerk) against the limits, and the time per path search.

  python benchmarks/paths.py --seeds 8 --out benchmarks/results/paths_room_cpu.json
  python benchmarks/paths.py --seeds 2 --quick          # a smoke run

Writes JSON (never over an existing file) and prints it.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import waldo_jax  # noqa: E402,F401  (XLA flags before the first computation)
import jax  # noqa: E402
import numpy as np  # noqa: E402

from bench_common import emit_with_load, header, refuse_existing_out, wait_for_quiet  # noqa: E402
from methods import summary  # noqa: E402
from waldo_jax.criteria import CriterionContext, build_criterion  # noqa: E402
from waldo_jax.pipeline import load_source, run_explore  # noqa: E402
from waldo_jax.pipeline.path_run import PathRunOptions, run_path  # noqa: E402
from waldo_jax.search import ExploreConfig  # noqa: E402
from waldo_jax.search.path_search import PathConfig, path_limits  # noqa: E402

FIGURES = ("mean", "worst", "max_speed", "max_turn_degrees", "max_jerk", "violation")


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seeds", type=int, default=8)
    parser.add_argument("--methods", default="egps,evosax:CMA_ES")
    parser.add_argument(
        "--aggregates", default="mean,softmin", help="path scores to run each method with (softmin at --temperature)"
    )
    parser.add_argument(
        "--temperature",
        type=float,
        default=0.005,
        help="softmin temperature (default 0.005: the room's oracle scores are ~0.01-0.1)",
    )
    parser.add_argument("--budget", default="low")
    parser.add_argument("--keyframes", type=int, default=4)
    parser.add_argument("--frames", type=int, default=24)
    parser.add_argument("--resolution", type=int, default=64)
    parser.add_argument("--bootstrap", type=int, default=10000)
    parser.add_argument("--quick", action="store_true", help="smoke run: low budget explore with few children")
    parser.add_argument("--load-threshold", type=float, default=1.0)
    parser.add_argument("--out", default=None)
    args = parser.parse_args(argv)
    refuse_existing_out(args.out)
    quiet = wait_for_quiet(args.load_threshold, max_wait_s=0 if args.quick else 300)
    result = header("paths")
    result["settings"] = dict(vars(args))
    source = load_source("procedural:0", args.resolution)
    criterion = build_criterion("waldo_oracle", CriterionContext(room=source.room, source=source.spec))
    limits = path_limits(source.train_c2w)
    explore_config = ExploreConfig(method="egps", budget="low", **({"children_per_epoch": 10} if args.quick else {}))
    anchors = {}
    start = time.perf_counter()
    for seed in range(args.seeds):
        run = run_explore(source, criterion, explore_config, seed=seed, initial="images")
        valid = np.asarray(run.result.top_valid)
        anchors[seed] = np.asarray(run.result.top_c2w)[valid]
    result["explore_seconds"] = round(time.perf_counter() - start, 1)
    cells = []
    for method, aggregate in [(m, a) for m in args.methods.split(",") for a in args.aggregates.split(",")]:
        config = PathConfig(
            keyframes=args.keyframes,
            frames=args.frames,
            method=method,
            budget=args.budget,
            aggregate=aggregate,
            temperature=args.temperature,
        )
        rows, seconds = [], []
        for seed in range(args.seeds):
            begin = time.perf_counter()
            path = run_path(
                source,
                criterion,
                config,
                limits,
                seed=seed,
                options=PathRunOptions(anchor_c2w=anchors[seed], anchors=f"explore egps seed {seed}"),
            )
            jax.block_until_ready(path.results[0].best_c2w)
            seconds.append(path.seconds["search"])
            rows.append(
                {
                    "seed": seed,
                    "found": {k: path.found[0][k] for k in FIGURES},
                    "kept_limits": bool(path.results[0].found),
                    **{name: {k: ref[k] for k in FIGURES} for name, ref in path.references.items()},
                }
            )
            print(
                f"[paths] {method} {aggregate} seed {seed}: found mean {rows[-1]['found']['mean']:.4g} worst "
                f"{rows[-1]['found']['worst']:.4g}; straight {rows[-1]['straight']['mean']:.4g} / "
                f"{rows[-1]['straight']['worst']:.4g}; training {rows[-1]['training']['mean']:.4g}; "
                f"{time.perf_counter() - begin:.0f} s",
                file=sys.stderr,
                flush=True,
            )
        cell = {
            "method": method,
            "aggregate": aggregate,
            "config": dataclasses.asdict(path.config),
            "cost": path.config.cost(),
            "per_seed": rows,
            "search_seconds": summary(seconds, args.bootstrap),
        }
        for who in ("found", "straight", "training"):
            cell[who] = {k: summary([r[who][k] for r in rows], args.bootstrap) for k in FIGURES}
        for ref in ("straight", "training"):
            cell[f"beats_{ref}_rate"] = {
                k: float(np.mean([r["found"][k] > r[ref][k] for r in rows])) for k in ("mean", "worst")
            }
        cell["kept_limits_rate"] = float(np.mean([r["kept_limits"] for r in rows]))
        cells.append(cell)
    result.update(
        {
            "scene": source.spec,
            "criterion": criterion.name,
            "limits": {
                "max_speed": float(limits.max_speed),
                "max_turn": float(limits.max_turn),
                "extent": float(limits.extent),
            },
            "cells": cells,
        }
    )
    emit_with_load(result, args.out, quiet, args.load_threshold)


if __name__ == "__main__":
    main()
