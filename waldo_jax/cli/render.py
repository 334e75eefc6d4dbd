"""`waldo render`: views to PNGs, of the procedural room or of a trained run.

    waldo render procedural[:SEED] --out DIR [--resolution R] [--views N] [--samples S]
    waldo render procedural[:SEED] --poses FILE --out DIR [--resolution R] [--samples S]
    waldo render RUN_DIR --poses FILE|train --out DIR [--resolution R]
    waldo render SPLATS --poses FILE|train --out DIR [--resolution R]     (a .ply or a 3DGS model folder)

The room renders its training views analytically, with a contact sheet, transforms.json and
room.json (Waldo's visibility per view), or, with --poses, the cameras of a poses file. A run renders
the poses of a file read by `waldo_jax.scenes.read_poses_file` (a JSON object with
`frames[].transform_matrix`: instant-ngp / nerfstudio transforms, OpenGL camera-to-world in the
scene's world frame, as the training poses; nerfstudio viewer camera paths are refused) or its
training poses. Intrinsics come from the file when it has a focal length, else from the checkpoint;
`--resolution` rescales them so that the longer side has R pixels.
"""

from __future__ import annotations

import argparse
import dataclasses
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from waldo_jax import io
from waldo_jax.cli.conventions import Progress, add_quiet
from waldo_jax.errors import WaldoError, check_resolution
from waldo_jax.nerf.checkpoint import load_checkpoint
from waldo_jax.nerf.trained import TrainedField, render_trained
from waldo_jax.pipeline.sources import DEFAULT_PROCEDURAL_VIEWS, check_views, parse_procedural
from waldo_jax.pipeline.splat_sources import calibrate_max_pairs, is_splat_spec, splat_renderer, splat_source
from waldo_jax.procedural import (
    RoomCameraConfig,
    make_room,
    room_field,
    room_render_config,
    room_scene,
    waldo_visibility_batch,
)
from waldo_jax.render import render_views
from waldo_jax.types import Intrinsics
from waldo_jax.scenes import read_poses_file

__all__ = ["add_command", "cmd_render", "MAX_RENDER_POSES", "RENDER_GROUP_PIXELS"]

MAX_RENDER_POSES = 100_000  # one `waldo render` call; its PNG names have at least four digits
RENDER_GROUP_PIXELS = 2**24  # pixels rendered per call (~200 MB of float32 colour): bounds memory


def add_command(subparsers) -> None:
    """Registers `render` on an argparse subparsers object (function as `handler`)."""
    render = subparsers.add_parser(
        "render",
        help="render views to PNGs",
        description="Render the procedural Waldo room's training views (SOURCE = procedural[:SEED]), or "
        "poses with a trained field (SOURCE = a run directory of `waldo train`, with --poses).",
    )
    render.add_argument(
        "source", metavar="SOURCE", help="procedural, procedural:SEED, RUN_DIR, or a splat scene (.ply or 3DGS folder)"
    )
    render.add_argument("--out", required=True, help="output folder (must not exist or be empty)")
    render.add_argument(
        "--poses",
        default=None,
        metavar="FILE|train",
        help="a transforms.json-like file or a camera path of `waldo path`; RUN_DIR also takes "
        "'train' for its training poses",
    )
    render.add_argument(
        "--resolution",
        type=int,
        default=None,
        help="procedural: image side; RUN_DIR: longer side (default: procedural 128, RUN_DIR the camera's)",
    )
    render.add_argument("--seed", type=int, default=None, help="procedural: room seed (default: 0)")
    render.add_argument(
        "--views", type=int, default=None, help="procedural only: number of training views, at most 1000 (default: 24)"
    )
    render.add_argument(
        "--samples", type=int, default=None, help="procedural only: samples per ray, at most 1024 (default: 128)"
    )
    render.add_argument("--force", action="store_true", help="write into a non-empty output folder")
    add_quiet(render)
    render.set_defaults(handler=cmd_render)


def cmd_render(args: argparse.Namespace) -> int:
    """`waldo render`: the procedural room's training views, or poses rendered by a trained run or splats."""
    seed = parse_procedural(args.source, args.seed)
    if seed is not None:
        return _render_procedural(args, seed)
    ignored = [
        flag
        for flag, value in (("--seed", args.seed), ("--views", args.views), ("--samples", args.samples))
        if value is not None
    ]
    if ignored:
        raise WaldoError(f"{', '.join(ignored)}: for procedural sources only; {args.source} renders its trained field")
    if is_splat_spec(args.source):
        return _render_splats(args)
    return _render_run(args)


def _write_groups(render_group, c2w: np.ndarray, intrinsics: Intrinsics, out: Path, names, progress: Progress) -> None:
    """Renders `c2w` in groups of one size (the last padded by repeating a pose: one compiled program,
    memory bounded by RENDER_GROUP_PIXELS however many poses) and writes out/names[i]."""
    group = max(1, min(len(c2w), RENDER_GROUP_PIXELS // (intrinsics.width * intrinsics.height)))
    progress.phase("rendering (the first group compiles)", total=len(c2w), unit="view")
    for first in range(0, len(c2w), group):
        part = c2w[first : first + group]
        padded = np.concatenate([part, np.repeat(part[-1:], group - len(part), 0)])
        images = np.asarray(jax.device_get(render_group(padded)))[: len(part)]
        for name, image in zip(names[first : first + group], images):
            io.save_png(out / name, image)
        progress.advance(len(part))
    progress.close()


def _render_splats(args: argparse.Namespace) -> int:
    """`waldo render SPLATS --poses FILE|train`: renders poses of a splat scene to DIR/0000.png, ..."""
    if args.poses is None:
        raise WaldoError(
            "rendering a splat scene needs --poses FILE (a transforms.json) or --poses train "
            "(its cameras.json, else a ring of views around it)"
        )
    if args.poses != "train" and not Path(args.poses).exists():
        raise WaldoError(f"{args.poses}: no such poses file (or pass --poses train)")
    if args.resolution is not None:
        check_resolution(args.resolution)
    source = splat_source(args.source, args.resolution, images=False)
    if args.poses == "train":
        c2w, intrinsics = source.train_c2w, source.intrinsics
    else:
        c2w, intrinsics, _ = read_poses_file(Path(args.poses), source.intrinsics)
        if args.resolution is not None:
            intrinsics = intrinsics.with_max_side(args.resolution)
    if len(c2w) > MAX_RENDER_POSES:
        raise WaldoError(
            f"{args.poses}: {len(c2w)} poses; one render writes at most {MAX_RENDER_POSES} (split the file)"
        )
    out = io.prepare_output_dir(args.out, force=args.force)
    names = [f"{i:04d}.png" for i in range(len(c2w))]
    stale = io.stale_files(out, r"\d{4,}\.png", names)
    # Pairs sized to these very poses: no view drops a splat.
    config = dataclasses.replace(
        source.splat_config,
        max_pairs=calibrate_max_pairs(source.splats, c2w, intrinsics, source.splat_config, margin=1.0),
    )
    render = splat_renderer(source.splats, intrinsics, config)
    progress = Progress(args.quiet)
    progress.say(f"rendering {len(c2w)} views at {intrinsics.width}x{intrinsics.height} ...")
    start = time.perf_counter()
    with progress:
        _write_groups(
            lambda poses: render(jnp.asarray(poses)), np.asarray(c2w, np.float32), intrinsics, out, names, progress
        )
    seconds = time.perf_counter() - start
    for path in stale:
        path.unlink()
    removed = f"; removed {len(stale)} PNGs of an earlier render" if stale else ""
    print(
        f"wrote {len(names)} PNGs of {source.info['splats']} splats to {out} in {seconds:.1f} s "
        f"(max_pairs {config.max_pairs}: no view dropped a splat){removed}"
    )
    return 0


def _render_procedural(args: argparse.Namespace, seed: int) -> int:
    """`waldo render procedural[:SEED]`: the room's training views, a sheet, transforms.json, room.json."""
    if args.poses is not None:
        return _render_procedural_poses(args, seed)
    resolution = 128 if args.resolution is None else args.resolution
    args.resolution = resolution
    args.views = check_views(DEFAULT_PROCEDURAL_VIEWS if args.views is None else args.views)
    check_resolution(args.resolution)
    args.samples = 128 if args.samples is None else args.samples
    if not 1 <= args.samples <= 1024:
        raise WaldoError(f"--samples must be between 1 and 1024, got {args.samples}")
    out = io.prepare_output_dir(args.out, force=args.force)
    start = time.perf_counter()
    try:
        with Progress(args.quiet) as progress:
            progress.phase(f"rendering {args.views} views (compiling first)")
            scene, room = room_scene(
                seed,
                num_views=args.views,
                resolution=args.resolution,
                num_samples=args.samples,
                camera_config=RoomCameraConfig(),
            )
    except ValueError as e:
        raise WaldoError(str(e)) from None
    seconds = time.perf_counter() - start
    visibility = np.asarray(waldo_visibility_batch(room, jnp.asarray(scene.c2w), scene.intrinsics))
    stale = io.stale_files(out, r"view_\d{3,}\.png", scene.file_names)  # --force: an earlier render's views
    for name, image in zip(scene.file_names, scene.images):
        io.save_png(out / name, image)
    for path in stale:
        path.unlink()
    labels = [f"{i}: waldo {v:.0%}" for i, v in enumerate(visibility)]
    io.save_png(
        out / "contact_sheet.png",
        io.contact_sheet(
            list(scene.images),
            labels=labels,
            caption="View: Waldo visible, the share of his projected area in frame and unoccluded (exact, from the "
            "room's geometry)",
        ),
    )
    io.write_transforms(
        out / "transforms.json",
        scene.c2w,
        scene.intrinsics,
        scene.file_names,
        extra={"waldo_procedural_seed": seed, "aabb": scene.aabb.tolist()},
    )
    io.write_json(
        out / "room.json",
        {
            "seed": seed,
            "views": args.views,
            "resolution": args.resolution,
            "samples_per_ray": args.samples,
            "waldo_base": np.asarray(room.waldo_base).tolist(),
            "waldo_visibility": visibility.tolist(),
            "max_training_visibility": float(visibility.max()),
            "render_seconds": seconds,
        },
    )
    print(
        f"wrote {args.views} views of procedural:{seed} at {args.resolution}x{args.resolution} to {out} "
        f"(contact_sheet.png, transforms.json, room.json) in {seconds:.1f} s; "
        f"best training-view Waldo visibility {visibility.max():.0%}"
    )
    return 0


def _render_procedural_poses(args: argparse.Namespace, seed: int) -> int:
    """`waldo render procedural[:SEED] --poses FILE`: the room's analytic renders of a poses file's cameras."""
    if args.poses == "train":
        raise WaldoError(
            "--poses train is for trained runs; `waldo render procedural` renders the room's training "
            "views without --poses"
        )
    if args.views is not None:
        raise WaldoError("--views: the procedural room renders the poses of --poses, not training views")
    samples = 128 if args.samples is None else args.samples
    if not 1 <= samples <= 1024:
        raise WaldoError(f"--samples must be between 1 and 1024, got {samples}")
    poses_path = Path(args.poses)
    if not poses_path.exists():
        raise WaldoError(f"{poses_path}: no such poses file")
    default = Intrinsics.from_fov(128, 128, RoomCameraConfig().fov_x)
    c2w, intrinsics, _ = read_poses_file(poses_path, default)
    if args.resolution is not None:
        check_resolution(args.resolution)
        intrinsics = intrinsics.with_max_side(args.resolution)
    if len(c2w) > MAX_RENDER_POSES:
        raise WaldoError(
            f"{args.poses}: {len(c2w)} poses; one render writes at most {MAX_RENDER_POSES} (split the file)"
        )
    out = io.prepare_output_dir(args.out, force=args.force)
    names = [f"{i:04d}.png" for i in range(len(c2w))]
    stale = io.stale_files(out, r"\d{4,}\.png", names)
    room = make_room(seed)
    config = room_render_config(room, num_samples=samples)
    start = time.perf_counter()
    with Progress(args.quiet) as progress:
        _write_groups(
            lambda poses: render_views(room_field, room, jnp.asarray(poses), intrinsics, config).rgb,
            np.asarray(c2w, np.float32),
            intrinsics,
            out,
            names,
            progress,
        )
    seconds = time.perf_counter() - start
    for path in stale:
        path.unlink()
    print(
        f"wrote {len(names)} PNGs of procedural:{seed} at {intrinsics.width}x{intrinsics.height} to {out} "
        f"in {seconds:.1f} s"
    )
    return 0


def _render_run(args: argparse.Namespace) -> int:
    """`waldo render RUN_DIR --poses FILE|train`: renders poses with a trained field to DIR/0000.png, ..."""
    if args.poses is None:
        raise WaldoError("rendering a trained run needs --poses FILE (a transforms.json) or --poses train")
    run = Path(args.source)
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
        raise WaldoError(
            f"{args.poses}: {len(c2w)} poses; one render writes at most {MAX_RENDER_POSES} (split the file)"
        )
    force = getattr(args, "force", False)
    out = io.prepare_output_dir(args.out, force=force)
    names = [f"{i:04d}.png" for i in range(len(c2w))]
    stale = io.stale_files(out, r"\d{4,}\.png", names)  # --force: an earlier render's PNGs, removed at the end

    field = TrainedField.from_checkpoint(checkpoint)
    progress = Progress(args.quiet)
    progress.say(f"rendering {len(c2w)} views at {intrinsics.width}x{intrinsics.height} ...")
    start = time.perf_counter()
    with progress:
        _write_groups(lambda poses: render_trained(field, poses, intrinsics).rgb, c2w, intrinsics, out, names, progress)
    seconds = time.perf_counter() - start
    for path in stale:
        path.unlink()
    removed = f"; removed {len(stale)} PNGs of an earlier render" if stale else ""
    print(f"wrote {len(names)} PNGs to {out} in {seconds:.1f} s{removed}")
    return 0
