"""The `waldo train` and `waldo render` commands.

    waldo train SCENE_PATH --out RUN_DIR [--steps N] [--downscale K] [--seed S]
                [--preset fast|quality] [--sampler auto|dense|occupancy] [--force] [--quiet]
    waldo render RUN_DIR --poses FILE|train --out DIR [--resolution R]

`add_commands(subparsers)` registers both on an argparse subparsers object; each parser gets
`handler=<function>` as its default (the convention of `waldo_jax.cli`). A handler takes the parsed
`argparse.Namespace`, returns the exit status 0 and raises `WaldoError` (one clear line, naming the
offending path or value) on bad input.

A run directory holds `checkpoint.ckpt` (see `waldo_jax.nerf.checkpoint`) and `train.json` (the
statistics of the run). `--force` overwrites those two files in a non-empty run directory and leaves
any other file there alone.

Poses files for `render` are read by `waldo_jax.scenes.read_poses_file`: a JSON object with
`frames[].transform_matrix` (instant-ngp / nerfstudio transforms: OpenGL camera-to-world in the
scene's own world frame, as the training poses). Intrinsics come from the file when it has a focal
length, else from the checkpoint; `--resolution` then rescales them so that the longer side has R
pixels. nerfstudio viewer camera paths (`camera_path`) are refused.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import sys
import time
import warnings
from pathlib import Path
from typing import Any, Dict, Optional

import numpy as np

from waldo_jax import io
from waldo_jax.errors import MIN_RESOLUTION, SceneFormatError, WaldoError, check_resolution

__all__ = ["TRAIN_JSON", "add_commands", "cmd_render", "cmd_train"]

TRAIN_JSON = "train.json"
MAX_RENDER_POSES = 100_000  # one `waldo render` call; its PNG names have at least four digits
RENDER_GROUP_PIXELS = 2**24  # pixels rendered per call (~200 MB of float32 colour): bounds memory
_SAMPLER_CHOICES = ("auto", "dense", "occupancy")


def add_commands(subparsers) -> None:
    """Registers `train` on an argparse subparsers object (function as `handler`).

    `waldo render RUN_DIR --poses ...` is part of `waldo_jax.cli`'s `render` command, which
    dispatches to `cmd_render` for run directories.
    """
    p = subparsers.add_parser(
        "train", help="train an Instant-NGP field on a scene",
        description="Train an Instant-NGP field on a scene's training split and report the held-out PSNR "
                    "on its test split (Blender: transforms_test.json; other formats: every 8th image).")
    p.add_argument("scene_path", metavar="SCENE_PATH", help="scene folder or scene file")
    p.add_argument("--out", required=True, metavar="RUN_DIR", help="run directory to write")
    p.add_argument("--steps", type=int, default=None, help="training steps (default: the preset's)")
    p.add_argument("--downscale", type=float, default=None, help="load images downscaled K times")
    p.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    p.add_argument("--preset", default="fast", help="fast or quality (default fast)")
    p.add_argument("--sampler", default="auto",
                   help="auto (= occupancy, the default), dense or occupancy")
    p.add_argument("--render-step-scale", type=float, default=None, metavar="X",
                   help="march renders X times coarser than training (default: measured after training on the "
                        "held-out views, the largest of 2, 3, 4 within 0.05 dB of X = 1)")
    p.add_argument("--force", action="store_true", help="overwrite the run files in a non-empty RUN_DIR")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(handler=cmd_train)



# ----------------------------------------------------------------------------------------------
# train


def _load_splits(scene_path: str, downscale: Optional[float]):
    """(train scene, test scene or None) with the format's own hold-out."""
    from waldo_jax.scenes import load_scene

    train_scene = load_scene(scene_path, downscale=downscale, split="train")
    if min(train_scene.width, train_scene.height) < MIN_RESOLUTION:
        how = f"--downscale {downscale:g} leaves" if downscale else "the scene has"
        raise WaldoError(f"{scene_path}: {how} {train_scene.width}x{train_scene.height} training images; a NeRF "
                         f"needs sides of at least {MIN_RESOLUTION} pixels")
    test_scene = None
    splits = ("test", "val") if train_scene.format == "blender" else ("test",)
    for split in splits:
        try:
            with warnings.catch_warnings():  # the train split already warned about skipped frames
                warnings.simplefilter("ignore", UserWarning)
                test_scene = load_scene(scene_path, downscale=downscale, split=split)
            break
        except SceneFormatError as e:
            problem = str(e)
    if test_scene is None:
        warnings.warn(f"{scene_path}: no held-out views ({problem}); psnr_test will be null", stacklevel=2)
    return train_scene, test_scene


def cmd_train(args: argparse.Namespace) -> int:
    """`waldo train`: trains, writes RUN_DIR/checkpoint.ckpt and RUN_DIR/train.json."""
    from waldo_jax.nerf.checkpoint import CHECKPOINT_NAME, save_checkpoint
    from waldo_jax.nerf.train import PRESETS, TrainConfig, train

    if args.preset not in PRESETS:
        raise WaldoError(f"unknown preset {args.preset!r}: expected one of {', '.join(PRESETS)}")
    if args.sampler not in _SAMPLER_CHOICES:
        raise WaldoError(f"unknown sampler {args.sampler!r}: expected one of {', '.join(_SAMPLER_CHOICES)}")
    if args.steps is not None and args.steps < 1:
        raise WaldoError(f"--steps must be a positive integer, got {args.steps}")
    if args.downscale is not None and not (math.isfinite(args.downscale) and args.downscale > 0):
        raise WaldoError(f"--downscale must be a positive number, got {args.downscale}")
    if args.render_step_scale is not None and not (math.isfinite(args.render_step_scale)
                                                   and args.render_step_scale > 0):
        raise WaldoError(f"--render-step-scale must be a positive number, got {args.render_step_scale}")
    # Refuse an output folder that is not empty, not writable or badly named before the (slow) scene
    # load and training: a training must never be lost to a folder it cannot write.
    out = io.check_output_dir(args.out, force=args.force)

    import jax

    train_scene, test_scene = _load_splits(args.scene_path, args.downscale)
    out = io.prepare_output_dir(out, force=args.force)
    overrides: Dict[str, Any] = {}
    if args.steps is not None:
        overrides["steps"] = args.steps
    overrides["sampler"] = "occupancy" if args.sampler == "auto" else args.sampler
    if args.render_step_scale is not None:
        overrides["render_step_scale"] = args.render_step_scale
    config = TrainConfig.preset(args.preset, train_scene, **overrides)
    result = train(jax.random.key(args.seed), train_scene, config, test_scene, progress=not args.quiet)
    config = result.config  # with the calibrated render step

    last = next((h for h in reversed(result.history) if "loss" in h), {})
    stats = {
        "psnr_test": result.psnr_test,
        "psnr_test_training_step": result.psnr_test_training_step,
        "render_step_scale": config.render_step_scale,
        "render_step_curve": result.render_step_curve,
        "steps": result.steps,
        "seconds": round(result.seconds, 3),
        "compile_seconds": round(result.compile_seconds, 3),
        "rays_per_second": round(result.rays_per_second, 1),
        "device": result.device,
        "n_train": result.n_train,
        "n_test": result.n_test,
        "preset": args.preset,
        "sampler": config.sampler,
        "seed": args.seed,
        "scene_path": str(Path(args.scene_path).resolve()),
        "scene_format": train_scene.format,
        "downscale": train_scene.metadata.get("downscale"),
        "image_size": [train_scene.width, train_scene.height],
        "train_loss": last.get("loss"),
        "train_psnr": last.get("psnr"),
        "checkpoint": CHECKPOINT_NAME,
        "config": config.to_dict(),
        "hparams": {f.name: float(getattr(result.hparams, f.name)) for f in dataclasses.fields(result.hparams)},
        "history": result.history,
    }
    save_checkpoint(out / CHECKPOINT_NAME, result.params, config, train_scene, result.occupancy,
                    info={k: v for k, v in stats.items() if k != "history"})
    io.write_json(out / TRAIN_JSON, stats)
    psnr = "n/a" if result.psnr_test is None else f"{result.psnr_test:.2f} dB"
    scale = config.render_step_scale
    step = "" if scale is None else f" (renders march x{scale:g} the training step)"
    print(f"trained {result.steps} steps in {result.seconds:.1f} s ({result.rays_per_second:,.0f} rays/s, "
          f"{result.device}); held-out PSNR {psnr}{step}; wrote {out / CHECKPOINT_NAME}")
    return 0


# ----------------------------------------------------------------------------------------------
# render


def cmd_render(args: argparse.Namespace) -> int:
    """`waldo render`: renders poses with a trained field to DIR/0000.png, DIR/0001.png, ..."""
    import jax

    from waldo_jax.nerf.checkpoint import load_checkpoint
    from waldo_jax.nerf.train import render_trained
    from waldo_jax.scenes import read_poses_file

    if args.poses is None:
        raise WaldoError("rendering a trained run needs --poses FILE (a transforms.json) or --poses train")
    run = Path(args.run_dir)
    if not run.exists():
        raise WaldoError(f"run directory {run} does not exist")
    checkpoint = load_checkpoint(run)
    scene = checkpoint.scene
    if args.poses == "train":
        c2w, intrinsics = np.asarray(scene.c2w, np.float32), scene.intrinsics
    else:
        poses_path = Path(args.poses)
        if not poses_path.exists():
            raise WaldoError(f"{poses_path}: no such poses file (or pass --poses train)")
        c2w, intrinsics, _ = read_poses_file(poses_path, scene.intrinsics)
    if args.resolution is not None:
        check_resolution(args.resolution)
        intrinsics = intrinsics.with_max_side(args.resolution)
    if len(c2w) > MAX_RENDER_POSES:
        raise WaldoError(f"{args.poses}: {len(c2w)} poses; one render writes at most {MAX_RENDER_POSES} "
                         "(split the file)")
    force = getattr(args, "force", False)
    out = io.prepare_output_dir(args.out, force=force)
    names = [f"{i:04d}.png" for i in range(len(c2w))]
    stale = io.stale_files(out, r"\d{4,}\.png", names)  # --force: an earlier render's PNGs, removed at the end

    background = scene.background if scene.background is not None else np.zeros(3, np.float32)
    print(f"rendering {len(c2w)} views at {intrinsics.width}x{intrinsics.height} ...", file=sys.stderr)
    start = time.perf_counter()
    # Groups of poses of one size (the last padded by repeating a pose): one compiled program, and
    # memory bounded by RENDER_GROUP_PIXELS however many poses the file holds.
    group = max(1, min(len(c2w), RENDER_GROUP_PIXELS // (intrinsics.width * intrinsics.height)))
    for first in range(0, len(c2w), group):
        part = c2w[first:first + group]
        padded = np.concatenate([part, np.repeat(part[-1:], group - len(part), 0)])
        rendered = render_trained(checkpoint.params, checkpoint.occupancy, checkpoint.config, padded, intrinsics,
                                  scene.near, scene.far, background, aabb=scene.aabb)
        images = np.asarray(jax.device_get(rendered.rgb))[:len(part)]
        for name, image in zip(names[first:first + group], images):
            io.save_png(out / name, image)
    seconds = time.perf_counter() - start
    for path in stale:
        path.unlink()
    removed = f"; removed {len(stale)} PNGs of an earlier render" if stale else ""
    print(f"wrote {len(names)} PNGs to {out} in {seconds:.1f} s{removed}")
    return 0
