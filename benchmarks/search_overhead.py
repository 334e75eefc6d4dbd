"""Search overhead per generated pose, without render or score: GRS, PIBS, EGPS vs evosax's SimpleGA.

The paper reports 0.7-0.8 ms of search overhead per generated pose in Python; the target here is
<= 5 us per pose on the CPU at ~1000 poses. Each method runs the whole search of `explore` (one
`lax.scan` over epochs in one jit) from `--train` training views for `--epochs` epochs of
`--children` children, scored by a trivial jnp function (minus the distance of the camera origin to
a point), so what is timed is the search itself: proposing, writing the population, sorting, the
per-epoch curves and the final top-k.

Timed per method, compilation excluded (one warm-up call, then best and median of `--repeats`):
  * `compiled`: `jax.jit(lambda key: explore(key, ...))`, the compiled whole search alone;
  * `explore_call`: a plain `explore(...)` call, adding its host-side checks and pose set-up.
us_per_pose divides by every child slot (epochs x children); PIBS masks the slots it cannot fill,
so its valid count is reported too.

For comparison, in the same run: evosax's SimpleGA (`evosax.algorithms.SimpleGA`) at the same
population size (`--children`) on 9-dimensional solutions (origin, look-at point, up, as a pose),
`init` then `--epochs` generations of ask -> score -> tell in one jitted `lax.scan` (minimising
the distance), plus one jitted ask + tell step on its own. When evosax is missing or its API
differs, the JSON says so instead of giving numbers (`pip install evosax`).

The 2 cores may be shared: the 1-minute load average is recorded at start and end; above
`--load-threshold` the script polls every 30 s for up to 5 minutes, then measures anyway and
writes `--out` with a `_loaded` suffix.

  python benchmarks/search_overhead.py --out benchmarks/results/search_overhead_cpu.json
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import waldo_jax  # noqa: E402,F401  (XLA flags before the first computation)
import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

from bench_common import emit_with_load, header, timed, wait_for_quiet  # noqa: E402
from waldo_jax.cameras import look_at  # noqa: E402
from waldo_jax.search import ExploreConfig, Initial, explore  # noqa: E402
from waldo_jax.search.registry import PAPER_METHODS  # noqa: E402

GOAL = jnp.array([0.3, 1.0, -0.2], jnp.float32)  # the point the trivial score pulls cameras towards
SOLUTION_DIMS = 9  # SimpleGA solutions: origin, look-at point and up, like a pose


def trivial_score(c2w):
    """Scores [P] of c2w [P, 4, 4]: minus the distance of each camera origin to GOAL (higher is better)."""
    return -jnp.linalg.norm(c2w[:, :3, 3] - GOAL, axis=-1)


def training_ring(num_views: int) -> np.ndarray:
    """float32 [num_views, 4, 4]: cameras on a ring of radius 3 at heights 1..2, looking at the middle."""
    angle = np.linspace(0.0, 2.0 * np.pi, num_views, endpoint=False)
    origins = np.stack([3.0 * np.cos(angle), 1.0 + (np.arange(num_views) % 3) / 2.0, 3.0 * np.sin(angle)], -1)
    c2w = jax.vmap(look_at, in_axes=(0, None, None))(
        jnp.asarray(origins, jnp.float32), jnp.zeros(3), jnp.array([0.0, 1.0, 0.0])
    )
    return np.asarray(c2w, np.float32)


def time_method(name: str, initial: Initial, config: ExploreConfig, repeats: int) -> dict:
    key = jax.random.key(0)
    compiled = jax.jit(lambda k: explore(k, trivial_score, initial, name, config))
    start = time.perf_counter()
    result = jax.block_until_ready(compiled(key))
    first_call = time.perf_counter() - start
    best, median, _ = timed(lambda: compiled(key), repeats)
    call_best, call_median, _ = timed(lambda: explore(key, trivial_score, initial, name, config), repeats)
    slots = config.epochs * config.children_per_epoch
    valid = int(np.sum(np.asarray(result.population.valid))) - len(initial.scores)
    return {
        "generated_slots": slots,
        "generated_valid": valid,
        "compile_and_first_call_s": round(first_call, 3),
        "compiled_seconds_best": best,
        "compiled_seconds_median": median,
        "us_per_pose_best": 1e6 * best / slots,
        "us_per_pose_median": 1e6 * median / slots,
        "us_per_valid_pose_best": 1e6 * best / max(valid, 1),
        "us_per_epoch_best": 1e6 * best / config.epochs,
        "explore_call_seconds_best": call_best,
        "explore_call_seconds_median": call_median,
        "explore_call_us_per_pose_best": 1e6 * call_best / slots,
        "best_score": float(result.top_scores[0]),
        "mcvir": float(result.mcvir),
    }


def time_simple_ga(population_size: int, generations: int, repeats: int) -> dict:
    """evosax SimpleGA: init + `generations` x (ask, score, tell) in one jit, and one ask + tell step."""
    try:
        import evosax
        from evosax.algorithms import SimpleGA
    except ImportError as e:
        return {"available": False, "error": f"evosax not importable: {e}"}
    try:
        version = getattr(evosax, "__version__", None)
        if version is None:
            from importlib.metadata import version as dist_version

            version = dist_version("evosax")
        strategy = SimpleGA(population_size=population_size, solution=jnp.zeros(SOLUTION_DIMS))
        params = strategy.default_params

        def fitness_fn(population):  # SimpleGA minimises: the distance of the origin part to GOAL
            return jnp.linalg.norm(population[:, :3] - GOAL, axis=-1)

        def run(key):
            key, k_pop, k_init = jax.random.split(key, 3)
            population = jax.random.normal(k_pop, (population_size, SOLUTION_DIMS))
            state = strategy.init(k_init, population, fitness_fn(population), params)

            def generation(state, k):
                k_ask, k_tell = jax.random.split(k)
                population, state = strategy.ask(k_ask, state, params)
                state, _ = strategy.tell(k_tell, population, fitness_fn(population), state, params)
                return state, None

            state, _ = jax.lax.scan(generation, state, jax.random.split(key, generations))
            return state.best_fitness

        run_jit = jax.jit(run)
        key = jax.random.key(0)
        best_fitness = float(run_jit(key))
        best, median, _ = timed(lambda: run_jit(key), repeats)

        population0 = jax.random.normal(jax.random.key(1), (population_size, SOLUTION_DIMS))
        state0 = strategy.init(jax.random.key(2), population0, fitness_fn(population0), params)

        @jax.jit
        def step(key, state):
            k_ask, k_tell = jax.random.split(key)
            population, state = strategy.ask(k_ask, state, params)
            state, _ = strategy.tell(k_tell, population, fitness_fn(population), state, params)
            return state

        step_best, step_median, _ = timed(lambda: step(key, state0), repeats)
    except Exception as e:  # noqa: BLE001  (an API change is a result to record, not a crash)
        return {"available": False, "error": f"{type(e).__name__}: {e}"}
    slots = generations * population_size
    return {
        "available": True,
        "version": version,
        "population_size": population_size,
        "solution_dims": SOLUTION_DIMS,
        "generations": generations,
        "scan_seconds_best": best,
        "scan_seconds_median": median,
        "us_per_pose_best": 1e6 * best / slots,
        "us_per_pose_median": 1e6 * median / slots,
        "us_per_generation_best": 1e6 * best / generations,
        "ask_tell_step_us_best": 1e6 * step_best,
        "ask_tell_step_us_median": 1e6 * step_median,
        "best_fitness": best_fitness,
    }


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--train", type=int, default=20, help="training views (default 20)")
    parser.add_argument("--epochs", type=int, default=5)
    parser.add_argument("--children", type=int, default=196, help="children per epoch (default 196: 980 poses)")
    parser.add_argument("--repeats", type=int, default=30)
    parser.add_argument("--methods", default=",".join(PAPER_METHODS))
    parser.add_argument("--load-threshold", type=float, default=1.5)
    parser.add_argument("--out", default=None, help="also write the JSON here (never overwrites)")
    args = parser.parse_args(argv)

    quiet = wait_for_quiet(args.load_threshold)
    c2w = training_ring(args.train)
    initial = Initial(c2w=c2w, scores=np.asarray(trivial_score(jnp.asarray(c2w))))
    config = ExploreConfig(epochs=args.epochs, children_per_epoch=args.children)
    methods = {}
    for name in args.methods.split(","):
        methods[name] = time_method(name, initial, config, args.repeats)
        print(f"{name}: {methods[name]['us_per_pose_best']:.2f} us/pose", file=sys.stderr, flush=True)
    simple_ga = time_simple_ga(args.children, args.epochs, args.repeats)

    result = header("search_overhead")
    result.update(
        {
            "train_views": args.train,
            "epochs": args.epochs,
            "children_per_epoch": args.children,
            "generated_poses": args.epochs * args.children,
            "repeats": args.repeats,
            "score_fn": "minus the distance of the camera origin to a fixed point (no render)",
            "target_us_per_pose": 5.0,
            "paper_us_per_pose_python": [700.0, 800.0],
            "methods": methods,
            "evosax_simple_ga": simple_ga,
            "egps_vs_simple_ga_per_generation": (
                methods["egps"]["us_per_epoch_best"] / simple_ga["us_per_generation_best"]
                if "egps" in methods and simple_ga.get("available")
                else None
            ),
        }
    )
    emit_with_load(result, args.out, quiet, args.load_threshold)


if __name__ == "__main__":
    main()
