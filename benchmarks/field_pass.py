"""The hash-grid field's own passes: forward, and forward + backward, over a batch of points.

Times, in one process, jitted calls of the Instant-NGP field (`nerf.field.make_field`, vmapped) on
`--points` points uniform in the middle of the box, seen from random directions, at a given hash grid
(default: the demo's, L = 16, T = 2**16, N_max = 150, the size `waldo demo` trains at 64 px):

  forward_ms    sigma and rgb of every point (what a render spends per field pass)
  fwd_bwd_ms    `jax.value_and_grad` of sum(sigma**2) + sum(rgb**2) with respect to the parameters
                (what a training step spends on the field)

best and median of `--repeats`, the two interleaved. `--digest` adds a SHA-256 of the outputs and of
the gradient (to tell whether two commits compute the same numbers bit for bit). Run it at two commits
alternately to compare them; the JSON names the device, the commit and the JAX version.

  python benchmarks/field_pass.py --out benchmarks/results/field_pass_cpu.json
"""

from __future__ import annotations

import argparse
import hashlib
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import waldo_jax  # noqa: E402,F401  (XLA flags before the first computation)
import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

from bench_common import emit_with_load, header, refuse_existing_out, wait_for_quiet  # noqa: E402
from waldo_jax.nerf.field import NGPFieldConfig, init_field, make_field  # noqa: E402
from waldo_jax.nerf.hashgrid import HashGridConfig  # noqa: E402


def programs(config: NGPFieldConfig):
    """The jitted forward and forward + backward of the field over a batch of points."""
    field = jax.vmap(make_field(config), in_axes=(None, 0, 0))

    def loss(params, x, d):
        sigma, rgb = field(params, x, d)
        return jnp.sum(sigma * sigma) + jnp.sum(rgb * rgb)

    return jax.jit(field), jax.jit(jax.value_and_grad(loss))


def digest(tree) -> str:
    """SHA-256 of the leaves' bytes, in tree order."""
    h = hashlib.sha256()
    for leaf in jax.tree_util.tree_leaves(tree):
        h.update(np.asarray(leaf).tobytes())
    return h.hexdigest()


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--points", type=int, default=2**15, help="points a call (default 2**15, a training step's)")
    parser.add_argument("--levels", type=int, default=16)
    parser.add_argument("--table-log2", type=int, default=16)
    parser.add_argument("--n-max", type=int, default=150)
    parser.add_argument("--repeats", type=int, default=20)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--digest", action="store_true", help="add SHA-256 digests of the outputs and gradient")
    parser.add_argument("--load-threshold", type=float, default=1.5)
    parser.add_argument("--out", default=None, help="also write the JSON here (never overwrites)")
    args = parser.parse_args(argv)
    refuse_existing_out(args.out)

    quiet = wait_for_quiet(args.load_threshold)
    hashgrid = HashGridConfig(L=args.levels, T=2**args.table_log2, F=2, N_min=16, N_max=args.n_max)
    config = NGPFieldConfig(aabb=(-1.0, -1.0, -1.0, 1.0, 1.0, 1.0), hashgrid=hashgrid)
    key_init, key_x, key_d = jax.random.split(jax.random.key(args.seed), 3)
    params = init_field(key_init, config)
    x = jax.random.uniform(key_x, (args.points, 3), minval=-0.6, maxval=0.6)
    d = jax.random.normal(key_d, (args.points, 3))
    forward, fwd_bwd = programs(config)

    start = time.perf_counter()
    outputs = jax.block_until_ready(forward(params, x, d))
    gradient = jax.block_until_ready(fwd_bwd(params, x, d))
    first_calls = time.perf_counter() - start
    times = {"forward": [], "fwd_bwd": []}
    for _ in range(args.repeats):
        for name, fn in (("forward", forward), ("fwd_bwd", fwd_bwd)):
            start = time.perf_counter()
            jax.block_until_ready(fn(params, x, d))
            times[name].append(1e3 * (time.perf_counter() - start))

    out = header("field_pass")
    out.update(
        {
            "points": args.points,
            "hashgrid": {
                "L": hashgrid.L,
                "T": hashgrid.T,
                "F": hashgrid.F,
                "N_min": hashgrid.N_min,
                "N_max": hashgrid.N_max,
            },
            "repeats": args.repeats,
            "forward_ms": min(times["forward"]),
            "forward_ms_median": statistics.median(times["forward"]),
            "fwd_bwd_ms": min(times["fwd_bwd"]),
            "fwd_bwd_ms_median": statistics.median(times["fwd_bwd"]),
            "first_calls_s": first_calls,
            "definitions": {
                "forward_ms": "jitted vmapped field (sigma, rgb) over the points, best of --repeats (ms)",
                "fwd_bwd_ms": "jitted value_and_grad of sum(sigma**2) + sum(rgb**2) wrt the parameters, best (ms)",
                "first_calls_s": "the two programs' first calls: tracing, compiling and one run each",
            },
        }
    )
    if args.digest:
        out["digest"] = {"outputs": digest(outputs), "gradient": digest(gradient)}
    emit_with_load(out, args.out, quiet, args.load_threshold)


if __name__ == "__main__":
    main()
