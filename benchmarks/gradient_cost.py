"""What a gradient costs in renders: the `+refine` methods' budget rate (`RefineConfig.gradient_cost`).

For each SOURCE:CRITERION case, P poses (training poses) are scored in one call three ways, each
jitted, compilation excluded, best and median of `--repeats` taken alternately:

  score      the exact score function a search renders and scores children with (render + criterion);
  smooth     the smooth stand-in refinement follows (`Criterion.smooth`), forward only;
  gradient   `search.refine.values_and_gradients`: the smooth value and its gradient with respect to
             origin and look-at point, what one refinement step evaluates: in the source's own mode
             (`Source.gradient`: reverse mode, one vjp, through the marched NeRF renderer's backward
             pass and the splat renderer), or the mode `--gradient` names (`pipeline.with_gradient`;
             forward mode is six tangents).

`ratio` = gradient / score (best times): how many renders one gradient evaluation of one pose is
worth. `RefineConfig.gradient_cost` is the largest ratio measured, rounded up (and at least 2).

  python benchmarks/gradient_cost.py --cases procedural:waldo_oracle,procedural:saliency,RUN:saliency \\
      --resolution 64 --out benchmarks/results/gradient_cost_cpu.json

The NeRF's reverse mode against its forward mode (before it), on one fox run:

  waldo train ../shared/scenes/fox --downscale 8 --out runs/fox_nerf
  python benchmarks/gradient_cost.py --cases runs/fox_nerf:saliency --gradient forward,reverse \\
      --resolution 64 --out benchmarks/results/gradient_cost_fox_reverse_cpu.json
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import waldo_jax  # noqa: E402,F401  (XLA flags before the first computation)
import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402

from bench_common import emit_with_load, header, refuse_existing_out, timed_alternately, wait_for_quiet  # noqa: E402
from waldo_jax.criteria import CriterionContext, build_criterion  # noqa: E402
from waldo_jax.pipeline import load_source, objective_function, score_function, with_gradient  # noqa: E402
from waldo_jax.search import Population, init_population, training_poses  # noqa: E402
from waldo_jax.search.refine import GRADIENT_COST, scene_box, values_and_gradients  # noqa: E402


def measure(spec: str, resolution: int, poses: int, repeats: int, gradient: str = "source") -> dict:
    source_spec, criterion_name = spec.rsplit(":", 1)
    source = load_source(source_spec, resolution)
    if gradient != "source":
        source = with_gradient(source, gradient)
    criterion = build_criterion(criterion_name, CriterionContext(room=source.room, source=source.spec))
    score_fn = score_function(source, criterion)
    objective = objective_function(source, criterion)
    c2w = jnp.asarray(source.train_c2w[:poses])
    start = training_poses(source.train_c2w)
    start = jax.tree.map(lambda a: a[:poses], start)
    population: Population = init_population(
        training_poses(source.train_c2w), jnp.zeros(source.n_train), source.n_train
    )
    extent = scene_box(population).extent
    offsets = jnp.zeros((poses, 6), jnp.float32)

    score = jax.jit(lambda c: score_fn(c))
    smooth = jax.jit(lambda c: objective(c))
    mode = source.gradient if criterion.inputs != "poses" else "forward"  # as `pipeline.refine_for_source`
    gradient_fn = jax.jit(lambda o: values_and_gradients(objective, start, extent, o, mode))
    times = timed_alternately(
        {"score": lambda: score(c2w), "smooth": lambda: smooth(c2w), "gradient": lambda: gradient_fn(offsets)}, repeats
    )
    values, grads = gradient_fn(offsets)
    return {
        "case": spec,
        "source": source.spec,
        "criterion": criterion.name,
        "poses": poses,
        "gradient_mode": mode,
        "gradients": [[float(g) for g in row] for row in grads],
        "resolution": [source.intrinsics.width, source.intrinsics.height],
        "seconds_best": {k: round(v[0], 5) for k, v in times.items()},
        "seconds_median": {k: round(v[1], 5) for k, v in times.items()},
        "ratio": round(times["gradient"][0] / times["score"][0], 3),
        "ratio_median": round(times["gradient"][1] / times["score"][1], 3),
        "gradient_finite": bool(jnp.all(jnp.isfinite(grads))),
        "gradient_nonzero": bool(jnp.any(grads != 0)),
        "values": [float(v) for v in values],
    }


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "--cases", default="procedural:waldo_oracle,procedural:saliency", help="comma-separated SOURCE:CRITERION cases"
    )
    parser.add_argument("--resolution", type=int, default=64)
    parser.add_argument("--poses", type=int, default=4, help="poses per call (RefineConfig.poses)")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument(
        "--gradient",
        default="source",
        help="comma-separated modes to measure each case in: source (its own), forward, reverse",
    )
    parser.add_argument("--load-threshold", type=float, default=1.0)
    parser.add_argument("--out", default=None)
    args = parser.parse_args(argv)
    refuse_existing_out(args.out)
    quiet = wait_for_quiet(args.load_threshold)
    cases = [
        measure(spec, args.resolution, args.poses, args.repeats, mode)
        for spec in args.cases.split(",")
        for mode in args.gradient.split(",")
    ]
    largest = max(case["ratio"] for case in cases)
    result = header("gradient_cost")
    result.update(
        {
            "cases": cases,
            "largest_ratio": largest,
            "gradient_cost_rule": max(2, math.ceil(largest)),
            "gradient_cost_in_code": GRADIENT_COST,
        }
    )
    emit_with_load(result, args.out, quiet, args.load_threshold)


if __name__ == "__main__":
    main()
