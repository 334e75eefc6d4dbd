"""`waldo train SCENE_PATH --out RUN_DIR`: an Instant-NGP field (or 3D Gaussian splats) fitted to a scene.

    waldo train SCENE_PATH --out RUN_DIR [--steps N] [--downscale K] [--seed S]
                [--preset fast|quality] [--sampler auto|dense|occupancy] [--force] [--quiet]
    waldo train SCENE_PATH --model splat --out RUN_DIR [--steps N] [--capacity C] [--downscale K] [--seed S]

A NeRF run directory holds `checkpoint.ckpt` (see `waldo_jax.nerf.checkpoint`) and `train.json` (the
statistics of the run; `waldo_jax.nerf.runs`); a splat run the reference 3DGS layout
(`point_cloud/iteration_N/point_cloud.ply`, `cameras.json`) and `train.json` (`waldo_jax.splats.runs`).
`--force` overwrites the run files in a non-empty run directory and leaves any other file there alone.
"""

from __future__ import annotations

import argparse

from waldo_jax.cli.conventions import add_quiet, path_argument
from waldo_jax.errors import MIN_RESOLUTION, WaldoError
from waldo_jax.nerf.checkpoint import CHECKPOINT_NAME
from waldo_jax.nerf.config import PIXEL_SAMPLINGS, PRESETS
from waldo_jax.nerf.runs import SAMPLER_CHOICES, Sampling, train_scene_run
from waldo_jax.nerf.train import EVAL_MAX_PIXELS
from waldo_jax.types import RunOptions

MODELS = ("nerf", "splat")

__all__ = ["add_command", "cmd_train"]


def add_command(subparsers) -> None:
    """Registers `train` on an argparse subparsers object (function as `handler`)."""
    p = subparsers.add_parser(
        "train",
        help="train an Instant-NGP field on a scene",
        description="Train an Instant-NGP field on a scene's training split and report the held-out PSNR "
        "on its test split (Blender: transforms_test.json; other formats: every 8th image).",
    )
    p.add_argument("scene_path", type=path_argument, metavar="SCENE_PATH", help="scene folder or scene file")
    p.add_argument(
        "--model",
        default="nerf",
        choices=MODELS,
        help="nerf (Instant-NGP) or splat (3D Gaussian splats, the reference 3DGS layout)",
    )
    p.add_argument(
        "--capacity", type=int, default=None, help="splat: the most splats the fit may hold (default: 32768)"
    )
    p.add_argument("--out", required=True, metavar="RUN_DIR", help="run directory to write")
    p.add_argument("--steps", type=int, default=None, help="training steps (default: the preset's; splat: 3000)")
    p.add_argument("--downscale", type=float, default=None, help="load images downscaled K times")
    p.add_argument("--seed", type=int, default=0, help="random seed")
    p.add_argument("--preset", default="fast", choices=PRESETS, help="training settings")
    p.add_argument("--sampler", default="auto", choices=SAMPLER_CHOICES, help="auto (= occupancy), dense or occupancy")
    p.add_argument(
        "--pixel-sampling",
        default="uniform",
        choices=PIXEL_SAMPLINGS,
        help="which pixels a step trains: uniform, or error, three quarters of them by each pixel's last error "
        "as Instant-NGP's error map (default: uniform)",
    )
    p.add_argument(
        "--render-step-scale",
        type=float,
        default=None,
        metavar="X",
        help="march renders X times coarser than training (default: measured after training on the "
        "held-out views, the largest of 2, 3, 4 within 0.05 dB of X = 1)",
    )
    p.add_argument(
        "--eval-max-pixels",
        type=int,
        default=EVAL_MAX_PIXELS,
        metavar="N",
        help="render and compare the held-out views at most N pixels each, their images area-filtered by a "
        f"whole factor; 0: the test images' full size (default: {EVAL_MAX_PIXELS})",
    )
    p.add_argument("--force", action="store_true", help="overwrite the run files in a non-empty RUN_DIR")
    add_quiet(p, "progress bar")
    p.set_defaults(handler=cmd_train)


def _run_options(args: argparse.Namespace) -> RunOptions:
    return RunOptions(downscale=args.downscale, seed=args.seed, force=args.force, progress=not args.quiet)


def cmd_train(args: argparse.Namespace) -> int:
    """`waldo train`: trains, writes RUN_DIR/checkpoint.ckpt and RUN_DIR/train.json (or a splat run)."""
    if args.model == "splat":
        return _fit_splats(args)
    if args.capacity is not None:
        raise WaldoError("--capacity is for --model splat")
    if args.eval_max_pixels < 0 or 0 < args.eval_max_pixels < MIN_RESOLUTION**2:  # 1 compared 1x1 views
        raise WaldoError(
            f"--eval-max-pixels must be 0 (full size) or at least {MIN_RESOLUTION**2} pixels ({MIN_RESOLUTION}x"
            f"{MIN_RESOLUTION}, the smallest image side), got {args.eval_max_pixels}"
        )
    result, _, out = train_scene_run(
        args.scene_path,
        args.out,
        preset=args.preset,
        steps=args.steps,
        sampling=Sampling(samples=args.sampler, pixels=args.pixel_sampling),
        render_step_scale=args.render_step_scale,
        options=_run_options(args),
        eval_max_pixels=args.eval_max_pixels or None,
    )
    psnr = "n/a" if result.psnr_test is None else f"{result.psnr_test:.2f} dB"
    notes = []
    if result.eval_size is not None and result.eval_downscale > 1:
        notes.append(f"at {result.eval_size[0]}x{result.eval_size[1]}, 1/{result.eval_downscale} size")
    if result.config.render_step_scale is not None:
        notes.append(f"renders march x{result.config.render_step_scale:g} the training step")
    step = f" ({'; '.join(notes)})" if notes else ""
    print(
        f"trained {result.steps} steps in {result.seconds:.1f} s ({result.rays_per_second:,.0f} rays/s, "
        f"{result.device}); held-out PSNR {psnr}{step}; wrote {out / CHECKPOINT_NAME}"
    )
    return 0


def _fit_splats(args: argparse.Namespace) -> int:
    """`waldo train --model splat`: fits splats, writes the reference layout and train.json."""
    from waldo_jax.splats.runs import fit_scene_run

    nerf_only = [
        flag
        for flag, value, default in (
            ("--preset", args.preset, "fast"),
            ("--sampler", args.sampler, "auto"),
            ("--pixel-sampling", args.pixel_sampling, "uniform"),
            ("--render-step-scale", args.render_step_scale, None),
            ("--eval-max-pixels", args.eval_max_pixels, EVAL_MAX_PIXELS),
        )
        if value != default
    ]
    if nerf_only:
        raise WaldoError(f"{', '.join(nerf_only)}: for NeRF training only, not --model splat")
    result, stats, out = fit_scene_run(
        args.scene_path, args.out, steps=args.steps, capacity=args.capacity, options=_run_options(args)
    )
    psnr = "n/a" if result.psnr_test is None else f"{result.psnr_test:.2f} dB"
    print(
        f"fitted {stats['splats']} splats in {result.steps} steps, {result.seconds:.1f} s ({stats['device']}); "
        f"held-out PSNR {psnr}; wrote {out / stats['point_cloud']}"
    )
    return 0
