"""Population rendering: one batched `render_views` call vs a Python loop over a jitted single view.

Renders P poses of the procedural Waldo room with S samples per ray at each R x R of
`--resolutions`, both ways, with the backend's default ray chunk (`render.default_ray_chunk`), and
prints JSON (rays/s for each, `speedup_batched_over_loop` per size, device, commit, date).
Compilation is excluded: each path runs once to compile, then the two are timed alternately,
`--repeats` runs each (best and median reported). The batched call renders the P * R * R rays as one
flat list in chunks; the loop renders each view's R * R rays in the same chunks, one call per pose.

  python benchmarks/render_population.py --poses 256 --resolutions 64,128,256      # the issue's sizes
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import waldo_jax  # noqa: E402,F401  (XLA flags before the first computation)
import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

from bench_common import emit_with_load, header, refuse_existing_out, timed_alternately, wait_for_quiet  # noqa: E402
from waldo_jax.cameras import look_at  # noqa: E402
from waldo_jax.procedural import make_room, room_field, room_render_config  # noqa: E402
from waldo_jax.render import render_view, render_views  # noqa: E402
from waldo_jax.types import Intrinsics  # noqa: E402


def population(key, room, num_poses):
    """Random cameras inside the room looking at points near its middle."""
    k_o, k_t = jax.random.split(key)
    origins = jax.random.uniform(
        k_o, (num_poses, 3), minval=jnp.array([-3.0, 0.8, -3.0]), maxval=jnp.array([3.0, 1.8, 3.0])
    )
    targets = jax.random.uniform(
        k_t, (num_poses, 3), minval=jnp.array([-1.0, 0.2, -1.0]), maxval=jnp.array([1.0, 0.8, 1.0])
    )
    return jax.vmap(look_at, in_axes=(0, 0, None))(origins, targets, jnp.array([0.0, 1.0, 0.0]))


def measure(room, c2w, resolution: int, samples: int, ray_chunk, repeats: int) -> dict:
    """Batched vs loop at one resolution."""
    num_poses = c2w.shape[0]
    intrinsics = Intrinsics.from_fov(resolution, resolution, np.radians(60.0))
    config = room_render_config(room, num_samples=samples, ray_chunk=ray_chunk)
    single = jax.jit(render_view, static_argnames=("field",))

    def batched():
        return render_views(room_field, room, c2w, intrinsics, config).rgb

    def loop():
        return [single(room_field, room, c2w[i], intrinsics, config).rgb for i in range(num_poses)]

    times = timed_alternately({"batched": batched, "loop": loop}, repeats)
    batched_best, batched_median, batched_times = times["batched"]
    loop_best, loop_median, loop_times = times["loop"]
    # Both paths must agree: the batch is the same computation, only scheduled differently.
    max_diff = float(jnp.max(jnp.abs(batched() - jnp.stack(loop()))))
    rays = num_poses * resolution**2
    return {
        "resolution": resolution,
        "ray_chunk": config.ray_chunk,
        "batched_seconds_best": batched_best,
        "batched_seconds_median": batched_median,
        "loop_seconds_best": loop_best,
        "loop_seconds_median": loop_median,
        "batched_rays_per_s": rays / batched_best,
        "loop_rays_per_s": rays / loop_best,
        "batched_samples_per_s": rays * samples / batched_best,
        "batched_seconds_all": batched_times,
        "loop_seconds_all": loop_times,
        "speedup_batched_over_loop": loop_best / batched_best,
        "max_abs_diff_batched_vs_loop": max_diff,
    }


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--poses", type=int, default=256)
    parser.add_argument("--resolutions", default="64,128,256")
    parser.add_argument("--samples", type=int, default=64)
    parser.add_argument("--ray-chunk", type=int, default=None, help="default: render.default_ray_chunk()")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--load-threshold", type=float, default=1.5)
    parser.add_argument("--out", default=None, help="also write the JSON here (never overwrites)")
    args = parser.parse_args(argv)
    refuse_existing_out(args.out)

    quiet = wait_for_quiet(args.load_threshold)
    room = make_room(0)
    c2w = population(jax.random.key(0), room, args.poses)
    sizes = [
        measure(room, c2w, int(r), args.samples, args.ray_chunk, args.repeats)
        for r in args.resolutions.split(",")
        if r.strip()
    ]
    for size in sizes:
        print(
            f"{size['resolution']}^2: batched {size['batched_seconds_best']:.2f} s, loop "
            f"{size['loop_seconds_best']:.2f} s "
            f"({size['speedup_batched_over_loop']:.3f}x)",
            file=sys.stderr,
        )
    result = header("render_population")
    result.update(
        {
            "poses": args.poses,
            "samples_per_ray": args.samples,
            "repeats": args.repeats,
            "sizes": sizes,
            "speedup_batched_over_loop": {str(s["resolution"]): s["speedup_batched_over_loop"] for s in sizes},
            "min_speedup_batched_over_loop": min(s["speedup_batched_over_loop"] for s in sizes),
        }
    )
    emit_with_load(result, args.out, quiet, args.load_threshold)


if __name__ == "__main__":
    main()
