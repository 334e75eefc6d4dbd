"""Population rendering: one batched `render_views` call vs a Python loop over a jitted single view.

Renders P poses of the procedural Waldo room at R x R with S samples per ray, both ways, and prints
JSON (rays/s for each, their ratio, device, commit, date). Compilation is excluded: each path is
run once to compile, then timed over `--repeats` runs (best and median reported).

  python benchmarks/render_population.py --poses 64 --resolution 64            # the CPU report
  python benchmarks/render_population.py --poses 256 --resolution 128           # on a GPU
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

from _common import emit, header, timed  # noqa: E402
from waldo_jax.cameras import look_at  # noqa: E402
from waldo_jax.procedural import make_room, room_field, room_render_config  # noqa: E402
from waldo_jax.render import render_view, render_views  # noqa: E402
from waldo_jax.types import Intrinsics  # noqa: E402


def population(key, room, num_poses):
    """Random cameras inside the room looking at points near its middle."""
    k_o, k_t = jax.random.split(key)
    origins = jax.random.uniform(k_o, (num_poses, 3), minval=jnp.array([-3.0, 0.8, -3.0]), maxval=jnp.array([3.0, 1.8, 3.0]))
    targets = jax.random.uniform(k_t, (num_poses, 3), minval=jnp.array([-1.0, 0.2, -1.0]), maxval=jnp.array([1.0, 0.8, 1.0]))
    return jax.vmap(look_at, in_axes=(0, 0, None))(origins, targets, jnp.array([0.0, 1.0, 0.0]))




def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--poses", type=int, default=64)
    parser.add_argument("--resolution", type=int, default=64)
    parser.add_argument("--samples", type=int, default=64)
    parser.add_argument("--pose-chunk", type=int, default=None, help="default: render.default_chunks()")
    parser.add_argument("--ray-chunk", type=int, default=None, help="default: render.default_chunks()")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--out", default=None, help="also write the JSON here (never overwrites)")
    args = parser.parse_args(argv)

    room = make_room(0)
    intrinsics = Intrinsics.from_fov(args.resolution, args.resolution, np.radians(60.0))
    config = room_render_config(room, num_samples=args.samples, pose_chunk=args.pose_chunk, ray_chunk=args.ray_chunk)
    c2w = population(jax.random.key(0), room, args.poses)

    batched = lambda: render_views(room_field, room, c2w, intrinsics, config).rgb  # noqa: E731
    single = jax.jit(render_view, static_argnames=("field",))

    def loop():
        return [single(room_field, room, c2w[i], intrinsics, config).rgb for i in range(args.poses)]

    batched_best, batched_median, _ = timed(batched, args.repeats)
    loop_best, loop_median, _ = timed(loop, args.repeats)
    # Both paths must agree: the batch is the same computation, only scheduled differently.
    max_diff = float(jnp.max(jnp.abs(batched() - jnp.stack(loop()))))
    rays = args.poses * args.resolution**2
    result = header("render_population")
    result.update({
        "poses": args.poses,
        "resolution": args.resolution,
        "samples_per_ray": args.samples,
        "pose_chunk": config.pose_chunk,
        "ray_chunk": config.ray_chunk,
        "repeats": args.repeats,
        "batched_seconds_best": batched_best,
        "batched_seconds_median": batched_median,
        "loop_seconds_best": loop_best,
        "loop_seconds_median": loop_median,
        "batched_rays_per_s": rays / batched_best,
        "loop_rays_per_s": rays / loop_best,
        "batched_samples_per_s": rays * args.samples / batched_best,
        "speedup_batched_over_loop": loop_best / batched_best,
        "max_abs_diff_batched_vs_loop": max_diff,
    })
    emit(result, args.out)


if __name__ == "__main__":
    main()
