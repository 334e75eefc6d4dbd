"""Rendering a trained Instant-NGP field: the marched renderer (`render.marched`) against the field alone.

From a run directory written by `waldo train` and its scene (for the held-out images), or with
`--quick` from a small lego_tiny run trained here (about a minute on 2 CPU cores), this measures in
one process:

  quality   held-out PSNR (every held-out view at the training resolution) at each marching step of
            `--step-scales` (x the training step; the quality/speed curve), and at the run's render
            step (`render_step_scale`, calibrated after training; for a run trained before
            calibration existed, calibrated here by the same rule, `nerf.trained.calibrate_render_step`).
            `psnr_delta_db` = that PSNR minus `--baseline-psnr` (today's renderer on the same run,
            measured by the caller) or, without it, minus the PSNR at the training step (scale 1).
  speed     `--poses` poses (training poses, then held-out ones, then SLERP midpoints) at `--size`
            (default 144x256, W x H, square pixels at the scene's focal length), rendered in one
            `render_trained` call (compilation excluded, best of `--repeats`): `rays_per_s`,
            `evaluations_per_ray` (field evaluations the renderer spent), `passes_per_view` (field
            passes of the call / poses), `slots_used_fraction` (evaluations / slots the passes
            evaluated, padding included).
  field     the field alone on the very points that render evaluated (each ray's first marched samples,
            in ray order), in calls of the renderer's largest pass size: `field_points_per_s`. `render_efficiency` =
            rays_per_s x evaluations_per_ray /
            field_points_per_s (1: the render costs its field evaluations and nothing more).
  loop      the same poses as a Python loop of one-pose calls: `speedup_batched_over_loop`.

The JSON names the device, the commit and the JAX version; its last line is the whole JSON.

  python benchmarks/render_trained.py RUN ../shared/scenes/fox --downscale 8 --baseline-psnr 23.4746 \\
      --out benchmarks/results/render_trained_fox_cpu.json
  python benchmarks/render_trained.py --quick
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import waldo_jax  # noqa: E402,F401  (XLA flags before the first computation)
import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

from bench_common import emit_with_load, header, refuse_existing_out, timed_alternately, wait_for_quiet  # noqa: E402
from waldo_jax import paths  # noqa: E402
from waldo_jax.cameras import slerp_c2w  # noqa: E402
from waldo_jax.metrics import image_psnr  # noqa: E402
from waldo_jax.nerf.checkpoint import load_checkpoint  # noqa: E402
from waldo_jax.nerf.config import TrainConfig  # noqa: E402
from waldo_jax.nerf.field import make_field  # noqa: E402
from waldo_jax.nerf.trained import (  # noqa: E402
    TrainedField,
    calibrate_render_step,
    evaluate,
    render_setup,
    render_trained,
    render_trained_counted,
)
from waldo_jax.nerf.train import HeldOut, train  # noqa: E402
from waldo_jax.render import marched  # noqa: E402
from waldo_jax.scenes import load_scene  # noqa: E402
from waldo_jax.types import Intrinsics  # noqa: E402


def timing_poses(train_c2w, test_c2w, count):
    """`count` poses: the training poses, the held-out poses, then SLERP midpoints of consecutive training
    poses (novel views), cut to `count`."""
    poses = [np.asarray(train_c2w, np.float32), np.asarray(test_c2w, np.float32)]
    have = sum(len(p) for p in poses)
    if have < count:
        a, b = jnp.asarray(train_c2w[:-1]), jnp.asarray(train_c2w[1:])
        mid = np.asarray(jax.vmap(slerp_c2w, in_axes=(0, 0, None))(a, b, 0.5), np.float32)
        poses.append(mid[: count - have])
    out = np.concatenate(poses)[:count]
    if len(out) < count:
        raise SystemExit(f"only {len(out)} poses available, asked for {count}")
    return out


def timing_camera(intrinsics: Intrinsics, width: int, height: int) -> Intrinsics:
    """A width x height camera with square pixels whose longer side sees what the scene camera's longer side sees."""
    scale = max(width, height) / max(intrinsics.width, intrinsics.height)
    focal = float(max(np.asarray(intrinsics.fx), np.asarray(intrinsics.fy))) * scale
    return Intrinsics.create(width, height, focal, distortion=np.asarray(intrinsics.distortion))


def render_points(field: TrainedField, c2w, camera, evaluations: np.ndarray):
    """The points the renderer evaluated, in ray order: each ray's first `evaluations` marched samples.

    Returns points [E, 3] and unit directions [E, 3] (host arrays), E = evaluations.sum().
    """
    from waldo_jax.render import marching
    from waldo_jax.render.volume import view_rays

    grid_, render_config, march = render_setup(field)
    c2w = jnp.asarray(np.asarray(c2w, np.float32))[:, :3, :4]
    evaluations = np.asarray(evaluations, np.int64).reshape(-1)

    @jax.jit
    def march_block(ids):
        origins, directions, _, _ = view_rays(c2w, camera, ids)
        t_start, t_end = jax.vmap(lambda o, d: marching.ray_interval(grid_, o, d, render_config))(origins, directions)
        t, _, _ = jax.vmap(lambda o, d, a, b: marching.march_ray(grid_, o, d, a, b, march))(
            origins, directions, t_start, t_end
        )
        return origins, directions, t

    points, directions = [], []
    block = 2**14
    for first in range(0, evaluations.size, block):
        ids = np.arange(first, first + block)
        o, d, t = (np.asarray(a) for a in march_block(jnp.asarray(np.minimum(ids, evaluations.size - 1))))
        take = np.arange(t.shape[1])[None, :] < evaluations[np.minimum(ids, evaluations.size - 1)][:, None]
        take &= (ids < evaluations.size)[:, None]
        ray, sample = np.nonzero(take)
        points.append(o[ray] + t[ray, sample, None] * d[ray])
        directions.append(d[ray])
    return np.concatenate(points).astype(np.float32), np.concatenate(directions).astype(np.float32)


def field_alone(config, params, points: np.ndarray, directions: np.ndarray, pass_slots: int, packing: marched.Packing):
    """The field on `points` [E, 3] along `directions` [E, 3] (the render's own samples, in ray order), in
    calls of `pass_slots` (the renderer's largest pass; the last call padded), each split into
    `packing.field_chunk` slots like the renderer's passes. Returns (a function that runs it, calls)."""
    field = make_field(config.field)
    count = points.shape[0]
    calls = max(1, math.ceil(count / pass_slots))
    pad = calls * pass_slots - count
    x = np.concatenate([points, np.repeat(points[-1:], pad, axis=0)]).reshape(calls, pass_slots, 3)
    d = np.concatenate([directions, np.repeat(directions[-1:], pad, axis=0)]).reshape(calls, pass_slots, 3)
    chunk = packing.field_chunk or pass_slots

    @jax.jit
    def run(params, x, d):
        return jax.lax.map(lambda xd: marched.field_slots(field, params, xd[0], xd[1], chunk), (x, d))

    x, d = jnp.asarray(x), jnp.asarray(d)
    return (lambda: run(params, x, d)), calls


def psnr(rendered, images):
    return float(np.mean(image_psnr(rendered, images)))


def quick_run(folder: Path, steps: int) -> tuple:
    """Trains lego_tiny (fast preset, `steps` steps) into `folder`; returns (run dir, scene path)."""
    from waldo_jax.nerf.checkpoint import CHECKPOINT_NAME, save_checkpoint

    data = paths.data_dir()
    scene_path = None if data is None else data / "scenes" / "lego_tiny"
    if scene_path is None or not scene_path.exists():
        raise SystemExit("--quick needs lego_tiny in $WALDO_DATA/scenes (see ../shared/README.md)")
    train_scene = load_scene(scene_path, split="train")
    test_scene = load_scene(scene_path, split="test")
    config = TrainConfig.preset("fast", train_scene, steps=steps)
    result = train(jax.random.key(0), train_scene, config, test_scene, progress=False, held_out=HeldOut(None))
    save_checkpoint(
        folder / CHECKPOINT_NAME,
        result.params,
        result.config,
        train_scene,
        result.occupancy,
        info={"psnr_test": result.psnr_test, "steps": result.steps, "seconds": result.seconds},
    )
    return folder, scene_path


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("run", nargs="?", help="run directory with checkpoint.ckpt")
    parser.add_argument("scene_path", nargs="?", help="the run's scene (for the held-out images)")
    parser.add_argument(
        "--quick",
        action="store_true",
        help="train lego_tiny here (--quick-steps steps) and measure it: about a minute on 2 CPU cores",
    )
    parser.add_argument("--quick-steps", type=int, default=200)
    parser.add_argument("--downscale", type=float, default=None, help="as the run was trained")
    parser.add_argument("--poses", type=int, default=None, help="timing poses (default 16; --quick 2)")
    parser.add_argument("--size", default="144x256", help="timing image size WxH (default 144x256, fox's timing size)")
    parser.add_argument("--step-scales", default="1,2,3,4", help="marching steps (x the training step) for the curve")
    parser.add_argument(
        "--baseline-psnr",
        type=float,
        default=None,
        help="today's renderer's held-out PSNR on this run (default: this renderer at scale 1)",
    )
    parser.add_argument("--repeats", type=int, default=None, help="timed repeats (default 3; --quick 1)")
    parser.add_argument(
        "--field-chunk",
        type=int,
        default=None,
        help="slots per field call within a pass (default: the backend's, Packing.for_backend; "
        "0: the whole pass in one call)",
    )
    parser.add_argument("--skip", default="", help="comma-separated parts to skip: loop, curve")
    parser.add_argument("--load-threshold", type=float, default=1.5)
    parser.add_argument("--out", default=None, help="also write the JSON here (never overwrites)")
    args = parser.parse_args(argv)
    if not args.quick and (args.run is None or args.scene_path is None):
        parser.error("give RUN and SCENE_PATH, or --quick")
    refuse_existing_out(args.out)
    skip = {s.strip() for s in args.skip.split(",") if s.strip()}
    width, height = (int(v) for v in args.size.lower().split("x"))
    log = lambda msg: print(msg, file=sys.stderr, flush=True)  # noqa: E731

    quiet = wait_for_quiet(args.load_threshold)
    tmp = None
    if args.quick:
        tmp = tempfile.TemporaryDirectory()
        start = time.perf_counter()
        run, scene_path = quick_run(Path(tmp.name), args.quick_steps)
        log(f"trained lego_tiny ({args.quick_steps} steps) in {time.perf_counter() - start:.0f} s")
    else:
        run, scene_path = Path(args.run), Path(args.scene_path)
    poses = args.poses or (2 if args.quick else 16)
    repeats = args.repeats or (1 if args.quick else 3)
    if args.quick:
        skip.add("curve")

    checkpoint = load_checkpoint(run)
    config, scene = checkpoint.config, checkpoint.scene
    test_scene = load_scene(scene_path, downscale=args.downscale, split="test")
    if (test_scene.width, test_scene.height) != (scene.intrinsics.width, scene.intrinsics.height):
        raise SystemExit(
            f"held-out images are {test_scene.width}x{test_scene.height}, the run was trained at "
            f"{scene.intrinsics.width}x{scene.intrinsics.height}: pass the run's --downscale"
        )
    background = np.zeros(3, np.float32) if scene.background is None else np.asarray(scene.background, np.float32)
    params, grid = jax.device_put(checkpoint.params), jax.device_put(checkpoint.occupancy)
    packing = marched.Packing.for_backend(**({} if args.field_chunk is None else {"field_chunk": args.field_chunk}))

    # Quality: the run's render step (calibrated by the training rule when the run predates it) and the curve.
    calibrated_here = config.render_step_scale is None
    curve_calibration = []
    if calibrated_here:
        scale, curve_calibration = calibrate_render_step(params, grid, config, test_scene)
        config = config.replace(render_step_scale=scale)
    scale = config.render_step_scale
    curve = []
    scales = sorted({float(v) for v in args.step_scales.split(",") if v.strip()} | {1.0, scale})
    for s in [1.0, scale] if "curve" in skip else scales:
        if any(c["step_scale"] == s for c in curve):
            continue
        result = evaluate(params, grid, config, test_scene, step_scale=s)
        curve.append(
            {"step_scale": s, "psnr_test": result["psnr"], "evaluations_per_ray": result["evaluations_per_ray"]}
        )
        log(f"step x{s:g}: held-out PSNR {result['psnr']:.3f} dB, {result['evaluations_per_ray']:.1f} evaluations/ray")
    at_scale = next(c for c in curve if c["step_scale"] == scale)
    at_training_step = next(c for c in curve if c["step_scale"] == 1.0)
    baseline = args.baseline_psnr if args.baseline_psnr is not None else at_training_step["psnr_test"]

    # Speed: one call for all timing poses.
    c2w = timing_poses(scene.c2w, test_scene.c2w, poses)
    camera = timing_camera(scene.intrinsics, width, height)
    rays = poses * width * height

    field = TrainedField.create(params, grid, config, scene.near, scene.far, background, scene.aabb)

    def render(poses_c2w):
        return render_trained(field, poses_c2w, camera, packing=packing).rgb

    counted = jax.device_get(render_trained_counted(field, c2w, camera, packing=packing))
    evaluations = int(np.asarray(counted.evaluations, np.int64).sum())
    passes = int(np.asarray(counted.passes, np.int64).sum())
    slots = int(np.asarray(counted.slots, np.int64).sum())
    shape = marched.block_shape(packing, rays, render_setup(field).march.max_samples)
    pass_slots = shape.rows[0] * shape.row_length
    points, directions = render_points(field, c2w, camera, counted.evaluations)
    field_points = points.shape[0]
    field_fn, field_calls = field_alone(config, params, points, directions, pass_slots, packing)
    del points, directions
    # The batched call, the field alone and the loop of one-pose calls are timed in turn, round by
    # round, so that a drift in the machine's speed falls on all of them alike.
    timings = {"batched": lambda: render(c2w), "field": field_fn}
    if "loop" not in skip:
        timings["loop"] = lambda: [render(c2w[i : i + 1]) for i in range(poses)]
    times = timed_alternately(timings, repeats)
    best, median, _ = times["batched"]
    speed = {
        "seconds_best": best,
        "seconds_median": median,
        "rays_per_s": rays / best,
        "evaluations_per_ray": evaluations / rays,
        "passes": passes,
        "passes_per_view": passes / poses,
        "blocks": int(np.asarray(counted.passes).size),
        "rays_per_block": shape.rays,
        "pass_slots": [r * shape.row_length for r in shape.rows],
        "slots_evaluated": slots,
        "slots_used_fraction": evaluations / max(slots, 1),
        "max_evaluations_of_a_ray": int(np.asarray(counted.evaluations).max()),
        "rays_with_no_evaluation_fraction": float(np.mean(np.asarray(counted.evaluations) == 0)),
    }
    log(
        f"render: {best:.2f} s, {rays / best:,.0f} rays/s, {evaluations / rays:.1f} evaluations/ray, "
        f"{passes / poses:.2f} passes/view"
    )
    # The padding of the field's last call is evaluated too: count only the render's points.
    field = {
        "field_points": field_points,
        "field_calls": field_calls,
        "field_seconds_best": times["field"][0],
        "field_seconds_median": times["field"][1],
        "field_points_per_s": field_points / times["field"][0],
    }
    efficiency = speed["rays_per_s"] * speed["evaluations_per_ray"] / field["field_points_per_s"]
    log(f"field alone: {field['field_points_per_s']:,.0f} points/s; render efficiency {efficiency:.3f}")

    loop = None
    if "loop" in times:
        loop_best, loop_median, _ = times["loop"]
        loop = {"seconds_best": loop_best, "seconds_median": loop_median, "speedup_batched_over_loop": loop_best / best}
        log(f"loop of one-pose calls: {loop_best:.2f} s ({loop_best / best:.2f}x)")

    out = header("render_trained")
    out.update(
        {
            "run": "lego_tiny trained here (--quick)" if args.quick else str(Path(run).resolve()),
            "run_info": {k: checkpoint.info.get(k) for k in ("psnr_test", "steps", "seconds")},
            "scene_path": str(Path(scene_path).resolve()),
            "training_resolution": [scene.intrinsics.width, scene.intrinsics.height],
            "timing_size": [width, height],
            "timing_poses": poses,
            "psnr_views": test_scene.n_images,
            "render_step_scale": scale,
            "render_step_scale_calibrated_here": calibrated_here,
            "calibration_curve": curve_calibration,
            "quality_speed_curve": curve,
            "psnr_test": at_scale["psnr_test"],
            "psnr_test_training_step": at_training_step["psnr_test"],
            "baseline_psnr": baseline,
            "baseline_is": (
                "today's renderer on this run (--baseline-psnr)"
                if args.baseline_psnr is not None
                else "this renderer at the training step (scale 1)"
            ),
            "psnr_delta_db": at_scale["psnr_test"] - baseline,
            "evaluations_per_ray_psnr_views": at_scale["evaluations_per_ray"],
            **speed,
            **field,
            "render_efficiency": efficiency,
            "batched_vs_loop": loop,
            "speedup_batched_over_loop": None if loop is None else loop["speedup_batched_over_loop"],
            "packing": {
                "rays_per_block": packing.rays_per_block,
                "slots_per_ray": packing.slots_per_ray,
                "row_length": packing.row_length,
                "max_rows_per_ray": packing.max_rows_per_ray,
                "field_chunk": packing.field_chunk,
            },
            "definitions": {
                "evaluations_per_ray": "field evaluations the renderer spent per ray of the timing render",
                "passes_per_view": "field passes (one per pass of a block) of the timing call / poses",
                "field_points_per_s": "the field alone on the points the render evaluated, in calls of its largest "
                "pass",
                "render_efficiency": "rays_per_s * evaluations_per_ray / field_points_per_s",
                "psnr_delta_db": "held-out PSNR at the run's render step minus baseline_psnr",
            },
        }
    )
    emit_with_load(out, args.out, quiet, args.load_threshold)
    print(json.dumps(out))
    if tmp is not None:
        tmp.cleanup()


if __name__ == "__main__":
    main()
