"""Reachable, not only found: the best visible share of Waldo any camera of the search space reaches, per room,
beside what each method reaches at the low budget (`--budget high`: the high).

For each room seed (the demo's room first), the room is built as `waldo demo` builds it (its settings: Waldo's
size, the training cameras) and its analytic source explored with `waldo_visible` (exact: the visible fraction
of Waldo) by GRS, PIBS, EGPS, MAP-Elites and EGPS+refine, K seeds each. EGPS+refine is EGPS whose last
epoch's last children are gradient steps from the best poses on the oracle's smooth stand-in, scored
exactly; each gradient counts as `GRADIENT_COSTS["poses"]` renders, within the same budget. The reachable
best is a dense exact search: `--samples` camera centres uniform in the box of the training cameras'
centres (where GRS draws; the other methods start from the same cameras), each aimed at Waldo
(`paper_cells.reachable_visibility`: occlusion depends on the centre alone, so aiming at him is the best a
camera there can do, up to the frame). Per method and room: each seed's best visible share, its gap to the
reachable best, and the seeds within `--tolerance` (0.03) of it.

  python benchmarks/room_reachable.py --out benchmarks/results/room_reachable_cpu.json
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import waldo_jax  # noqa: E402,F401  (XLA flags before the first computation)
import numpy as np  # noqa: E402

from bench_common import emit_with_load, header, refuse_existing_out, wait_for_quiet  # noqa: E402
from paper_cells import reachable_visibility  # noqa: E402
from waldo_jax.criteria import CriterionContext, make_criterion  # noqa: E402
from waldo_jax.pipeline import gradient_cost_for, procedural_source, run_explore  # noqa: E402
from waldo_jax.pipeline.demo import DEMO_ROOM_SEED, SETTINGS, room_scenes  # noqa: E402
from waldo_jax.search import ExploreConfig, RefineConfig  # noqa: E402

METHODS = ("grs", "pibs", "egps", "map-elites", "egps+refine")


def demo_room(seed: int, samples: int):
    """(source, criterion `waldo_visible`, the reachable best of `samples` centres) of room `seed` as
    `waldo demo` builds it (also `egps_settings.py`'s)."""
    settings = SETTINGS["full"]
    scene, room, _ = room_scenes(seed, settings)
    source = procedural_source(seed, settings.resolution, settings.views, scene=scene, room=room)
    criterion = make_criterion("waldo_visible", CriterionContext(room=room, source=source.spec))
    return source, criterion, reachable_visibility(source, samples, 0.9)


def add_room_arguments(parser: argparse.ArgumentParser) -> None:
    """The flags this script and `egps_settings.py` share: seeds, dense samples, tolerance, load, output."""
    parser.add_argument("--seeds", type=int, default=8)
    parser.add_argument("--samples", type=int, default=32768, help="camera centres of the dense search")
    parser.add_argument("--tolerance", type=float, default=0.03)
    parser.add_argument("--load-threshold", type=float, default=1.0)
    parser.add_argument("--out", default=None)


def room_rows(seed: int, args) -> list:
    source, criterion, reach = demo_room(seed, args.samples)
    rows = []
    for method in args.methods.split(","):
        # A +refine method's gradients cost what `waldo explore` charges for this criterion (its default).
        options = {"refine": RefineConfig(gradient_cost=gradient_cost_for(criterion))} if "+refine" in method else {}
        config = ExploreConfig(method=method, budget=args.budget, options=options)
        run = run_explore(source, criterion, config, seed=0, seeds=args.seeds)
        best = [float(r.metrics.best[-1]) for r in run.results]
        gaps = [reach["best"] - b for b in best]
        rows.append(
            {
                "room": seed,
                "method": method,
                "reachable": reach,
                "best_visible": best,
                "gap": gaps,
                "within_tolerance": int(sum(g <= args.tolerance for g in gaps)),
                "seeds": args.seeds,
                "cost": run.config.cost(source.n_train),
            }
        )
        print(
            f"[reachable] room {seed} {method}: reachable {reach['best']:.3f}, best {np.mean(best):.3f}, "
            f"within {args.tolerance}: {rows[-1]['within_tolerance']}/{args.seeds}",
            file=sys.stderr,
            flush=True,
        )
    return rows


def table(rows: list, tolerance: float) -> str:
    lines = [
        f"| room | reachable best visible share | method | best visible share (mean over seeds) | seeds within "
        f"{tolerance:g} of the reachable |",
        "|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['room']} | {r['reachable']['best']:.3f} | {r['method']} | {np.mean(r['best_visible']):.3f} | "
            f"{r['within_tolerance']} / {r['seeds']} |"
        )
    return "\n".join(lines)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    others = ",".join(str(seed) for seed in range(8) if seed != DEMO_ROOM_SEED)
    parser.add_argument("--rooms", default=f"{DEMO_ROOM_SEED},{others}", help="room seeds, the demo's first")
    parser.add_argument("--methods", default=",".join(METHODS))
    parser.add_argument("--budget", default="low", choices=("low", "high"), help="the searches' budget")
    add_room_arguments(parser)
    args = parser.parse_args(argv)
    refuse_existing_out(args.out)
    quiet = wait_for_quiet(args.load_threshold)
    result = header("room_reachable")
    result["settings"] = vars(args)
    rows = [row for seed in args.rooms.split(",") for row in room_rows(int(seed), args)]
    by_method = {
        method: [sum(r[k] for r in rows if r["method"] == method) for k in ("within_tolerance", "seeds")]
        for method in dict.fromkeys(r["method"] for r in rows)
    }
    within, total = by_method.get("egps", [0, 0])
    result.update(
        {
            "rows": rows,
            "within_tolerance_by_method": by_method,
            "egps_within_tolerance": [within, total],
            "egps_within_share": within / max(total, 1),
            "table": table(rows, args.tolerance),
        }
    )
    print(result["table"], file=sys.stderr)
    emit_with_load(result, args.out, quiet, args.load_threshold)


if __name__ == "__main__":
    main()
