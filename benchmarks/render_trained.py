"""Rendering a trained Instant-NGP field: occupancy-grid marching vs dense sampling, batched vs a loop,
1 vs several (forced CPU) devices.

From a run directory written by `waldo train` (or `benchmarks/train_quality.py --checkpoint-out`) and
its scene (for the held-out images), this measures:

  (a) dense vs marched. Marched: `train.render_trained` with the run's occupancy grid (the renderer of
      `waldo render`). Dense: `render.render_views` of the same field with S stratified-midpoint
      samples in [near, far] clipped to the scene box, for each S of `--dense-samples`. For each, the
      held-out PSNR (the run's test split: every 8th view, at the training resolution) and, over the
      timing poses, seconds, rays/s and field evaluations per ray. Field evaluations: dense = S for
      every ray; marched = what the renderer itself reports (`_OccupancySampler.render_views_counted`:
      the field evaluations each ray took before early termination). The renderer packs the live
      rays' next samples into a fixed budget per `lax.while_loop` pass; the slots it actually
      evaluates, padding included, are `passes x view_budget()` (`marched_slots_per_ray`). The dense
      S "at equal PSNR" is the smallest measured S whose PSNR is within 0.3 dB of the marched one (or
      above it); none may qualify. An occupancy-trained field is fitted only inside the occupied
      cells (outside them its densities never get a gradient), so plain dense sampling also
      integrates untrained density there and levels off below the marched PSNR. The fair dense
      baseline is therefore also measured: S uniform samples per ray with the density zeroed outside
      the occupied cells (`--masked-samples`; every sample still evaluated), i.e. the same volume
      without empty-space skipping and early termination; `equal_psnr_occupied` compares with it.
      `--step-scales` renders the held-out views again with a coarser marching step (PSNR and
      evaluations per ray), to see how much of the marched cost the step size alone sets.
  (b) batched vs loop: one `render_trained` call for all timing poses vs a Python loop of
      `render_trained` calls for one pose each (both jitted; compilation excluded).
  (c) devices: `train.render_trained` (the marched renderer; with several devices it splits the poses
      over a one-axis mesh, `render.shard_over_poses`) in a subprocess with
      XLA_FLAGS=--xla_force_host_platform_device_count=D, for D = 1 and `--devices`; with
      `--shard-samples S` the dense `render.render_views_sharded` at S samples is timed as well.

Compilation is excluded everywhere: every timed function runs once first; best and median of
`--repeats` are reported. The 1-minute load average is recorded before and after, and CPU time used
by other processes during the run (see train_quality.py); `--out` gets a `_loaded` suffix when the
machine was shared.

  python benchmarks/render_trained.py /tmp/bench_runs/fox /work/shared/scenes/fox --downscale 8 \
      --out benchmarks/results/render_trained_fox_cpu.json
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import waldo_jax  # noqa: E402,F401  (XLA flags before the first computation)
import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

from _common import emit, header, loaded_name, timed  # noqa: E402
from train_quality import CpuShare, load_splits  # noqa: E402
from waldo_jax.cameras import slerp_c2w  # noqa: E402
from waldo_jax.nerf import occupancy  # noqa: E402
from waldo_jax.nerf.checkpoint import load_checkpoint  # noqa: E402
from waldo_jax.nerf.field import make_field  # noqa: E402
from waldo_jax.nerf.train import _render_config, make_sampler, render_trained  # noqa: E402
from waldo_jax.render import RenderConfig, render_views, render_views_sharded  # noqa: E402

PSNR_TOLERANCE_DB = 0.3




def psnr(rendered, images):
    """Mean over images of per-image PSNR (dB), as `train.evaluate`."""
    mse = np.mean((np.asarray(rendered, np.float64) - np.asarray(images, np.float64)) ** 2, axis=(1, 2, 3))
    return float(np.mean(-10.0 * np.log10(np.maximum(mse, 1e-12))))


def occupancy_masked(field):
    """`field` with zero density outside the occupied cells of a grid: `masked((params, grid), x, d)`.

    Rendered with S uniform samples this is dense sampling that sees exactly the volume the marched
    renderer sees (an occupancy-trained field is only fitted inside the occupied cells; outside them
    its densities are untrained), while still evaluating the field at every one of the S samples.
    """
    def masked(state, x, d):
        params, grid = state
        sigma, rgb = field(params, x, d)
        return jnp.where(occupancy.is_occupied(grid, x), sigma, 0.0), rgb

    return masked


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


def child(args):
    """Times the marched renderer (and, with --shard-samples, the dense one) on this process's devices.

    `render_trained` shards over all local devices when there is more than one. Prints one JSON line.
    """
    checkpoint = load_checkpoint(args.run)
    scene, config = checkpoint.scene, checkpoint.config
    data = np.load(args.child)
    c2w, background = data["c2w"], data["background"]
    intrinsics = scene.intrinsics.downscaled(args.timing_downscale) if args.timing_downscale != 1 else scene.intrinsics
    params = jax.device_put(checkpoint.params)
    grid = jax.device_put(checkpoint.occupancy)
    best, median, times = timed(
        lambda: render_trained(params, grid, config, c2w, intrinsics, scene.near, scene.far, background,
                               aabb=scene.aabb).rgb, args.repeats)
    out = {"devices": jax.device_count(), "marched": {"seconds_best": best, "seconds_median": median,
                                                       "seconds_all": times}}
    if args.shard_samples:
        field = make_field(config.field)
        dense_config = RenderConfig.create(near=scene.near, far=scene.far, aabb=scene.aabb, background=background,
                                           num_samples=args.shard_samples)
        best, median, times = timed(
            lambda: render_views_sharded(field, params, jnp.asarray(c2w), intrinsics, dense_config).rgb,
            args.repeats)
        out["dense"] = {"samples_per_ray": args.shard_samples, "seconds_best": best, "seconds_median": median,
                        "seconds_all": times}
    print(json.dumps(out))


def run_child(argv_base, devices, env_flags):
    env = dict(os.environ, XLA_FLAGS=f"{env_flags} --xla_force_host_platform_device_count={devices}".strip())
    result = subprocess.run([sys.executable, __file__] + argv_base, env=env, capture_output=True, text=True)
    if result.returncode != 0:
        raise SystemExit(f"sharded child with {devices} devices failed:\n{result.stderr[-4000:]}")
    return json.loads(result.stdout.strip().splitlines()[-1])


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("run", help="run directory with checkpoint.ckpt")
    parser.add_argument("scene_path", help="the run's scene (for the held-out images)")
    parser.add_argument("--downscale", type=float, default=None, help="as the run was trained")
    parser.add_argument("--poses", type=int, default=64, help="timing poses")
    parser.add_argument("--timing-downscale", type=float, default=1.0,
                        help="render the timing poses at the training resolution / this (PSNR is always at full)")
    parser.add_argument("--dense-samples", default="128,256,512,1024", help="plain dense S values (PSNR)")
    parser.add_argument("--masked-samples", default="256,512,1024",
                        help="dense S values with the density zeroed outside the occupied cells (PSNR)")
    parser.add_argument("--step-scales", default="",
                        help="also render the held-out views with the marching step x each of these (e.g. 2,4)")
    parser.add_argument("--dense-repeats", type=int, default=1, help="timed repeats of the dense renderers")
    parser.add_argument("--shard-samples", type=int, default=None,
                        help="also time the dense renderer at S samples on 1 and N devices (default: not)")
    parser.add_argument("--devices", type=int, default=4)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--skip", default="", help="comma-separated parts to skip: loop, shard, masked-timing")
    parser.add_argument("--load-threshold", type=float, default=1.5)
    parser.add_argument("--others-threshold", type=float, default=0.5)
    parser.add_argument("--child", default=None, help=argparse.SUPPRESS)
    parser.add_argument("--out", default=None, help="also write the JSON here (never overwrites)")
    args = parser.parse_args(argv)
    if args.child:
        return child(args)

    load_before = os.getloadavg()
    for out in (args.out, args.out and loaded_name(args.out)):
        if out and Path(out).exists():
            raise SystemExit(f"{out} exists: refusing to overwrite an earlier result (choose another --out)")
    skip = {s.strip() for s in args.skip.split(",") if s.strip()}
    share = CpuShare()
    share.start()

    checkpoint = load_checkpoint(args.run)
    config, scene = checkpoint.config, checkpoint.scene
    _, test_scene = load_splits(args.scene_path, args.downscale)
    if (test_scene.width, test_scene.height) != (scene.intrinsics.width, scene.intrinsics.height):
        raise SystemExit(f"held-out images are {test_scene.width}x{test_scene.height}, the run was trained at "
                         f"{scene.intrinsics.width}x{scene.intrinsics.height}: pass the run's --downscale")
    background = np.zeros(3, np.float32) if scene.background is None else np.asarray(scene.background, np.float32)
    params = jax.device_put(checkpoint.params)
    grid = jax.device_put(checkpoint.occupancy)
    field = make_field(config.field)
    c2w = timing_poses(scene.c2w, test_scene.c2w, args.poses)
    intrinsics = scene.intrinsics
    timing_intrinsics = intrinsics.downscaled(args.timing_downscale) if args.timing_downscale != 1 else intrinsics
    rays = args.poses * timing_intrinsics.width * timing_intrinsics.height

    def marched(poses, intr):
        return render_trained(params, grid, config, poses, intr, scene.near, scene.far, background,
                              aabb=scene.aabb).rgb

    masked_field = occupancy_masked(field)

    def dense(poses, intr, samples, masked=False):
        render_config = RenderConfig.create(near=scene.near, far=scene.far, aabb=scene.aabb,
                                            background=background, num_samples=samples)
        if masked:
            return render_views(masked_field, (params, grid), jnp.asarray(poses), intr, render_config).rgb
        return render_views(field, params, jnp.asarray(poses), intr, render_config).rgb

    # (a) quality: held-out PSNR of each renderer (training resolution).
    log = lambda msg: print(msg, file=sys.stderr, flush=True)  # noqa: E731
    sampler = make_sampler(config)
    count_config = _render_config(config, scene.near, scene.far, scene.aabb, background, config.eval_samples)
    out, psnr_evaluations, _ = jax.device_get(
        sampler.render_views_counted(params, grid, jnp.asarray(test_scene.c2w), intrinsics, count_config))
    marched_psnr = psnr(out.rgb, test_scene.images)
    psnr_evaluations_per_ray = float(np.mean(np.asarray(psnr_evaluations, np.float64)))
    log(f"marched held-out PSNR {marched_psnr:.3f} dB, {psnr_evaluations_per_ray:.1f} evaluations/ray")
    coarser = []
    for scale in [float(v) for v in args.step_scales.split(",") if v.strip()]:
        scaled = dataclasses.replace(config, steps_per_diagonal=config.steps_per_diagonal / scale)
        scaled_sampler = make_sampler(scaled)
        out_s, evals_s, passes_s = jax.device_get(scaled_sampler.render_views_counted(
            params, grid, jnp.asarray(test_scene.c2w), intrinsics,
            _render_config(scaled, scene.near, scene.far, scene.aabb, background, scaled.eval_samples)))
        coarser.append({"step_scale": scale, "steps_per_diagonal": scaled.steps_per_diagonal,
                        "psnr_test": psnr(out_s.rgb, test_scene.images),
                        "field_evaluations_per_ray": float(np.mean(np.asarray(evals_s, np.float64))),
                        "marched_slots_per_ray": float(np.asarray(passes_s, np.int64).sum() * scaled_sampler.view_budget()
                                                       / np.asarray(evals_s).size)})
        log(f"marched, step x{scale:g}: {coarser[-1]['psnr_test']:.3f} dB, "
            f"{coarser[-1]['field_evaluations_per_ray']:.1f} evaluations/ray")
    dense_results = []
    for samples in [int(s) for s in args.dense_samples.split(",") if s.strip()]:
        value = psnr(jax.device_get(dense(test_scene.c2w, intrinsics, samples)), test_scene.images)
        dense_results.append({"samples_per_ray": samples, "psnr_test": value})
        log(f"dense S={samples}: held-out PSNR {value:.3f} dB")
    masked_results = []
    for samples in [int(s) for s in args.masked_samples.split(",") if s.strip()]:
        value = psnr(jax.device_get(dense(test_scene.c2w, intrinsics, samples, masked=True)), test_scene.images)
        masked_results.append({"samples_per_ray": samples, "psnr_test": value})
        log(f"dense S={samples} inside the occupied cells: held-out PSNR {value:.3f} dB")
    equal = [d for d in dense_results if d["psnr_test"] >= marched_psnr - PSNR_TOLERANCE_DB]
    equal_samples = min(d["samples_per_ray"] for d in equal) if equal else None
    equal_masked = [d for d in masked_results if d["psnr_test"] >= marched_psnr - PSNR_TOLERANCE_DB]
    equal_masked_samples = min(d["samples_per_ray"] for d in equal_masked) if equal_masked else None

    # (a) speed over the timing poses: the renderer's own counts (field evaluations per ray, passes).
    _, evaluations, passes = jax.device_get(
        sampler.render_views_counted(params, grid, jnp.asarray(c2w), timing_intrinsics, count_config))
    evaluations, passes = np.asarray(evaluations, np.int64), np.asarray(passes, np.int64)
    marched_evals = int(evaluations.sum())
    budget = sampler.view_budget()
    slots = int(passes.sum()) * budget
    best, median, _ = timed(lambda: marched(c2w, timing_intrinsics), args.repeats)
    marched_timing = {"seconds_best": best, "seconds_median": median, "rays_per_s": rays / best,
                      "field_evaluations_per_ray": marched_evals / rays,
                      "field_evaluations_per_s": marched_evals / best,
                      "marched_slots_per_ray": slots / rays, "packing_passes": int(passes.sum()),
                      "packing_budget": budget, "slots_per_s": slots / best,
                      "max_evaluations_of_a_ray": int(evaluations.max()),
                      "median_evaluations_per_ray": float(np.median(evaluations)),
                      "rays_with_no_evaluation_fraction": float(np.mean(evaluations == 0))}
    log(f"marched: {best:.2f} s, {marched_evals / rays:.1f} evaluations/ray, {slots / rays:.1f} slots/ray")
    dense_timing_samples = sorted({s for s in (equal_samples, args.shard_samples) if s} or
                                  {dense_results[-1]["samples_per_ray"]})
    dense_timing = []
    for samples in dense_timing_samples:
        best, median, _ = timed(lambda: dense(c2w, timing_intrinsics, samples), args.dense_repeats)
        dense_timing.append({"samples_per_ray": samples, "seconds_best": best, "seconds_median": median,
                             "rays_per_s": rays / best, "field_evaluations_per_ray": float(samples),
                             "field_evaluations_per_s": rays * samples / best})
        log(f"dense S={samples}: {best:.2f} s")
    masked_timing = None
    if equal_masked_samples and "masked-timing" not in skip:
        samples = equal_masked_samples
        best, median, _ = timed(lambda: dense(c2w, timing_intrinsics, samples, masked=True), args.dense_repeats)
        masked_timing = {"samples_per_ray": samples, "seconds_best": best, "seconds_median": median,
                         "repeats": args.dense_repeats, "rays_per_s": rays / best,
                         "field_evaluations_per_ray": float(samples),
                         "field_evaluations_per_s": rays * samples / best,
                         "time_ratio_over_marched": best / marched_timing["seconds_best"]}
        log(f"dense S={samples} inside the occupied cells: {best:.2f} s")

    # (b) batched vs a loop of per-pose calls (marched renderer).
    loop = None
    if "loop" not in skip:
        best, median, _ = timed(lambda: [marched(c2w[i:i + 1], timing_intrinsics) for i in range(len(c2w))],
                                args.repeats)
        loop = {"seconds_best": best, "seconds_median": median, "rays_per_s": rays / best,
                "speedup_batched_over_loop": best / marched_timing["seconds_best"]}
        log(f"loop of per-pose calls: {best:.2f} s")

    # (c) 1 vs N devices: the marched renderer (render_trained shards the poses over the local devices),
    # and the dense one at --shard-samples when given.
    sharded = None
    if "shard" not in skip:
        flags = " ".join(f for f in os.environ.get("XLA_FLAGS", "").split()
                         if not f.startswith("--xla_force_host_platform_device_count"))
        with tempfile.TemporaryDirectory() as tmp:
            np.savez(Path(tmp) / "poses.npz", c2w=c2w, background=background)
            base = [args.run, args.scene_path, "--child", str(Path(tmp) / "poses.npz"), "--repeats", str(args.repeats),
                    "--timing-downscale", str(args.timing_downscale)]
            if args.shard_samples:
                base += ["--shard-samples", str(args.shard_samples)]
            per_devices = [run_child(base, d, flags) for d in sorted({1, args.devices})]
        for entry in per_devices:
            entry["marched"]["rays_per_s"] = rays / entry["marched"]["seconds_best"]
            if "dense" in entry:
                entry["dense"]["rays_per_s"] = rays / entry["dense"]["seconds_best"]
        sharded = {"renderer": "train.render_trained (marched; poses split over a one-axis mesh when devices > 1)"
                               + ("; dense render_views_sharded too" if args.shard_samples else ""),
                   "by_devices": per_devices,
                   "speedup_marched": (per_devices[0]["marched"]["seconds_best"]
                                       / per_devices[-1]["marched"]["seconds_best"]),
                   "note": "forced host devices share the same CPU cores: this checks the sharded path and its "
                           "overhead, not a multi-device speedup"}
        log(f"sharded: {[(e['devices'], round(e['marched']['seconds_best'], 2)) for e in per_devices]}")

    cpu = share.stop()
    load_after = os.getloadavg()
    loaded = load_before[0] > args.load_threshold or cpu["others_cores"] > args.others_threshold
    dense_equal = next((d for d in dense_timing if d["samples_per_ray"] == equal_samples), None)
    result = header("render_trained")
    result.update({
        "run": str(Path(args.run).resolve()),
        "run_info": {k: checkpoint.info.get(k) for k in ("psnr_test", "steps", "seconds", "n_train", "n_test")},
        "scene_path": str(Path(args.scene_path).resolve()),
        "training_resolution": [intrinsics.width, intrinsics.height],
        "timing_resolution": [timing_intrinsics.width, timing_intrinsics.height],
        "timing_poses": args.poses,
        "timing_poses_are": "training poses, then held-out poses, then SLERP midpoints of consecutive training poses",
        "psnr_views": test_scene.n_images,
        "repeats": args.repeats,
        "marched": {"psnr_test": marched_psnr, "max_samples_per_ray": config.eval_samples,
                    "field_evaluations_per_ray_psnr_views": psnr_evaluations_per_ray, **marched_timing},
        "marched_coarser_steps": coarser,
        "marched_coarser_steps_are": ("the same run rendered with its marching step (base diagonal / "
                                      "steps_per_diagonal) multiplied by step_scale, on the held-out views"),
        "dense_psnr": dense_results,
        "dense_timing": dense_timing,
        "dense_occupied_psnr": masked_results,
        "dense_occupied_timing": masked_timing,
        "dense_occupied_is": ("S uniform samples per ray, density zeroed outside the occupied cells (the volume the "
                              "marched renderer sees), every sample evaluated: the cost without skipping and "
                              "early termination"),
        "equal_psnr": {
            "rule": f"smallest measured dense S with PSNR >= marched PSNR - {PSNR_TOLERANCE_DB} dB",
            "dense_samples_per_ray": equal_samples,
            "evaluation_ratio_dense_over_marched": (
                None if equal_samples is None else equal_samples / psnr_evaluations_per_ray),
            "evaluation_ratio_is_on": "the held-out views at the training resolution (where the PSNRs are measured)",
            "slot_ratio_dense_over_marched_packed": (
                None if equal_samples is None else equal_samples / marched_timing["marched_slots_per_ray"]),
            "time_ratio_dense_over_marched": (
                None if dense_equal is None else dense_equal["seconds_best"] / marched_timing["seconds_best"]),
            "target": ">= 5x fewer field evaluations at equal PSNR (+/- 0.3 dB)",
        },
        "equal_psnr_occupied": {
            "rule": f"smallest measured occupied-cells dense S with PSNR >= marched PSNR - {PSNR_TOLERANCE_DB} dB",
            "dense_samples_per_ray": equal_masked_samples,
            "evaluation_ratio_dense_over_marched": (
                None if equal_masked_samples is None else equal_masked_samples / psnr_evaluations_per_ray),
            "time_ratio_dense_over_marched": None if masked_timing is None else masked_timing["time_ratio_over_marched"],
            "target": ">= 5x fewer field evaluations at equal PSNR (+/- 0.3 dB)",
        },
        "batched_vs_loop": loop,
        "devices": sharded,
        "loadavg_start": list(load_before),
        "loadavg_end": list(load_after),
        "cpu_during_run": {k: round(v, 3) for k, v in cpu.items()},
        "loaded": loaded,
    })
    out = args.out
    if out and loaded:
        out = loaded_name(out)
        print(f"the machine was shared during this run: writing {out}", file=sys.stderr)
    emit(result, out)


if __name__ == "__main__":
    main()
