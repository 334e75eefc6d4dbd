"""Which method finds Waldo when a finder, not the oracle, scores the views? The `waldo` finder (a reference
image of him, `procedural.waldo_reference`) scores the room's own analytic views, no NeRF between: each method
at the low budget, K seeds, each seed's best view then checked by the exact oracle (his visible share; found:
>= 90 %).

It separates the criterion's part from the NeRF's in `waldo demo --search-renders` (which scores the NeRF's
renders): a method that does not find him here will not find him through a NeRF either. The rooms are built as
`waldo demo` builds them (`room_reachable.demo_room`: Waldo's size, the training cameras). Per room and method:
each seed's best visible share and finder score, the seeds found, and the search's time.

  python benchmarks/finder_methods.py --rooms 6 --out benchmarks/results/finder_methods_room6_cpu.json
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import waldo_jax  # noqa: E402,F401  (XLA flags before the first computation)
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

from bench_common import emit_with_load, header, refuse_existing_out, wait_for_quiet  # noqa: E402
from room_reachable import demo_room  # noqa: E402
from waldo_jax.criteria import CriterionContext, make_criterion  # noqa: E402
from waldo_jax.pipeline import run_explore  # noqa: E402
from waldo_jax.pipeline.demo import DEMO_ROOM_SEED, RENDERS_CRITERION, RENDERS_METHODS  # noqa: E402
from waldo_jax.procedural import FOUND_VISIBILITY, waldo_reference, waldo_visibility_batch  # noqa: E402
from waldo_jax.search import ExploreConfig  # noqa: E402


def room_rows(seed: int, methods, seeds: int) -> list:
    source, _, reach = demo_room(seed, 4096)
    finder = make_criterion(
        RENDERS_CRITERION, CriterionContext(room=source.room, source=source.spec, target=waldo_reference(source.room))
    )
    rows = []
    for method in methods:
        start = time.perf_counter()
        run = run_explore(source, finder, ExploreConfig(method=method, budget="low"), seed=0, seeds=seeds)
        seconds = time.perf_counter() - start
        best = jnp.asarray(np.stack([np.asarray(r.top_c2w[0]) for r in run.results]))
        visible = np.asarray(waldo_visibility_batch(source.room, best, source.intrinsics), np.float64)
        rows.append(
            {
                "room": seed,
                "method": method,
                "best_visible": visible.round(4).tolist(),
                "found": int(np.sum(visible >= FOUND_VISIBILITY)),
                "best_score": [round(float(r.metrics.best[-1]), 4) for r in run.results],
                "seeds": seeds,
                "reachable_best": reach["best"],
                "seconds": round(seconds, 1),
            }
        )
        print(
            f"[finder] room {seed} {method}: found {rows[-1]['found']}/{seeds}, best visible "
            f"{np.mean(visible):.3f} (reachable {reach['best']:.3f}), {seconds:.0f} s",
            file=sys.stderr,
            flush=True,
        )
    return rows


def table(rows: list) -> str:
    lines = [
        "| room | method | seeds found (>= 90 % visible) | best visible share (mean over seeds) | finder score (mean) "
        "|",
        "|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['room']} | {r['method']} | {r['found']} / {r['seeds']} | {np.mean(r['best_visible']):.3f} | "
            f"{np.mean(r['best_score']):.3f} |"
        )
    return "\n".join(lines)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--rooms", default=str(DEMO_ROOM_SEED), help="room seeds")
    parser.add_argument("--methods", default=",".join(RENDERS_METHODS))
    parser.add_argument("--seeds", type=int, default=8)
    parser.add_argument("--load-threshold", type=float, default=1.0)
    parser.add_argument("--out", default=None)
    args = parser.parse_args(argv)
    methods = args.methods.split(",")
    unknown = sorted(set(methods) - set(RENDERS_METHODS))
    if unknown:
        parser.error(f"--methods: unknown {', '.join(unknown)} (choose from {', '.join(RENDERS_METHODS)})")
    refuse_existing_out(args.out)
    quiet = wait_for_quiet(args.load_threshold)
    result = header("finder_methods")
    result["settings"] = vars(args)
    rows = [row for seed in args.rooms.split(",") for row in room_rows(int(seed), methods, args.seeds)]
    result.update({"rows": rows, "table": table(rows)})
    print(result["table"], file=sys.stderr)
    emit_with_load(result, args.out, quiet, args.load_threshold)


if __name__ == "__main__":
    main()
