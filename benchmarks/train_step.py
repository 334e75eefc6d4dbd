"""The training step against the field alone: how much of a step is the field's forward and backward pass.

Trains a scene with a preset exactly as `waldo train` does (`train.train`, the same chunks), for
`--steps` steps, and times the chunks that did not compile (`ms_per_step`, `rays_per_step`: rays in
the loss, `samples_per_step`: their field evaluations, `rays_marched`). In the same process it then
times the field alone at the same sample budget: `jax.value_and_grad` of the sum of sigma and rgb
over `samples_per_batch` points (inside the trained occupied cells, seen from random directions),
with respect to the parameters (`field_fwd_bwd_ms`). `step_over_field` = ms_per_step /
field_fwd_bwd_ms: what marching, packing, compositing, the loss, Adam and the occupancy updates add
on top of the field (1 would be the field alone).

  python benchmarks/train_step.py ../shared/scenes/fox --downscale 8 --steps 400 \\
      --out benchmarks/results/train_step_fox_cpu.json
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import waldo_jax  # noqa: E402,F401  (XLA flags before the first computation)
import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

from bench_common import emit_with_load, header, refuse_existing_out, steady_chunks, wait_for_quiet  # noqa: E402
from waldo_jax.nerf.config import PIXEL_SAMPLINGS, PRESETS, TrainConfig  # noqa: E402
from waldo_jax.nerf.field import make_field  # noqa: E402
from waldo_jax.nerf.train import train  # noqa: E402
from waldo_jax.render import occupancy  # noqa: E402
from waldo_jax.scenes import load_scene  # noqa: E402


def occupied_points(key, grid: occupancy.OccupancyGrid, count: int) -> np.ndarray:
    """`count` points uniform in the occupied cells of `grid` (all cells when none is occupied)."""
    bits = np.asarray(grid.bitfield).reshape(-1)
    cells = np.flatnonzero(bits) if bits.any() else np.arange(bits.size)
    key_cell, key_jitter = jax.random.split(key)
    pick = np.asarray(jax.random.choice(key_cell, jnp.asarray(cells), (count,)))
    cascade, cell = pick // grid.cells_per_cascade, pick % grid.cells_per_cascade
    jitter = jax.random.uniform(key_jitter, (count, 3))
    return np.asarray(occupancy.cell_points(grid, jnp.asarray(cascade), jnp.asarray(cell), jitter), np.float32)


def time_field(config: TrainConfig, params, points: np.ndarray, repeats: int) -> dict:
    """Forward + backward of the field alone over `points` (a jitted value_and_grad), best and median ms."""
    field = make_field(config.field)
    directions = jax.random.normal(jax.random.key(7), points.shape)
    directions = directions / jnp.linalg.norm(directions, axis=-1, keepdims=True)

    @jax.jit
    def fwd_bwd(p, x, d):
        def total(q):
            sigma, rgb = jax.vmap(field, in_axes=(None, 0, 0))(q, x, d)
            return jnp.sum(sigma) + jnp.sum(rgb)

        return jax.value_and_grad(total)(p)

    x, d = jnp.asarray(points), jnp.asarray(directions)
    jax.block_until_ready(fwd_bwd(params, x, d))
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        jax.block_until_ready(fwd_bwd(params, x, d))
        times.append(time.perf_counter() - start)
    return {
        "field_fwd_bwd_ms": 1e3 * min(times),
        "field_fwd_bwd_ms_median": 1e3 * statistics.median(times),
        "points": int(points.shape[0]),
    }


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("scene_path")
    parser.add_argument("--downscale", type=float, default=None)
    parser.add_argument("--preset", default="fast", choices=PRESETS)
    parser.add_argument("--steps", type=int, default=400, help="steps to train (the learning-rate decay follows)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--pixel-sampling", default="uniform", choices=PIXEL_SAMPLINGS, help="TrainConfig.pixel_sampling"
    )
    parser.add_argument("--repeats", type=int, default=5, help="timed repeats of the field alone")
    parser.add_argument("--load-threshold", type=float, default=1.5)
    parser.add_argument("--out", default=None, help="also write the JSON here (never overwrites)")
    args = parser.parse_args(argv)
    refuse_existing_out(args.out)

    quiet = wait_for_quiet(args.load_threshold)
    scene = load_scene(args.scene_path, downscale=args.downscale, split="train")
    config = TrainConfig.preset(
        args.preset, scene, steps=args.steps, render_step_scale=1.0, pixel_sampling=args.pixel_sampling
    )
    chunks = []

    def record(state, entry):
        chunks.append(dict(entry))
        return False

    result = train(jax.random.key(args.seed), scene, config, progress=False, on_chunk=record)
    # A chunk that compiled took longer than the last steady chunk before it (`steady_chunks`).
    steady, main_phase = steady_chunks(chunks)
    if not steady:
        raise SystemExit("no chunk ran without compiling: train for more steps (--steps)")
    seconds = sum(c["chunk_seconds"] for c in main_phase)
    steps = sum(c["chunk_steps"] for c in main_phase)
    rays = sum(c["rays"] * c["chunk_steps"] for c in main_phase) / steps
    samples = sum(c["samples"] * c["chunk_steps"] for c in main_phase) / steps
    ms_per_step = 1e3 * seconds / steps

    points = occupied_points(jax.random.key(args.seed), result.occupancy, config.samples_per_batch)
    field = time_field(config, result.params, points, args.repeats)
    out = header("train_step")
    out.update(
        {
            "scene_path": str(Path(args.scene_path).resolve()),
            "scene": scene.name,
            "downscale": scene.metadata.get("downscale"),
            "image_size": [scene.width, scene.height],
            "preset": args.preset,
            "pixel_sampling": args.pixel_sampling,
            "steps": result.steps,
            "samples_per_batch": config.samples_per_batch,
            "ms_per_step": ms_per_step,
            "rays_per_step": rays,
            "samples_per_step": samples,
            "budget_filled": samples / config.samples_per_batch,
            "rays_marched_last": main_phase[-1]["rays_marched"],
            "steady_steps_timed": steps,
            **field,
            "step_over_field": ms_per_step / field["field_fwd_bwd_ms"],
            "compile_seconds": result.compile_seconds,
            "train_seconds": result.seconds,
            "chunks": [
                {k: c[k] for k in ("step", "rays", "samples", "rays_marched", "warmup", "chunk_seconds", "chunk_steps")}
                for c in steady
            ],
            "definitions": {
                "ms_per_step": "wall-clock per step over the chunks after the warm-up that did not compile",
                "field_fwd_bwd_ms": "jitted value_and_grad of sum(sigma) + sum(rgb) over samples_per_batch points in "
                "the trained occupied cells, wrt the field parameters (best of --repeats)",
                "step_over_field": "ms_per_step / field_fwd_bwd_ms",
            },
            "config": result.config.to_dict(),
        }
    )
    emit_with_load(out, args.out, quiet, args.load_threshold)


if __name__ == "__main__":
    main()
