"""`waldo scene info PATH [--json]`: a summary of a scene on disk (format, images, cameras, bounds).

For a splat scene: its file, splat count, SH degree, robust bounds and cameras, and the up and layout
(orbit an object or stand inside a surrounding scene) that a ring of views would use, with the reason
(`waldo_jax.splats.upright`); where the scene has cameras, the angle between that up and theirs."""

from __future__ import annotations

import argparse
import json
import math
import sys
import warnings

import numpy as np

from waldo_jax.cli.conventions import Progress, add_quiet, path_argument
from waldo_jax.errors import MIN_RESOLUTION
from waldo_jax.scenes import load_scene
from waldo_jax.scenes.common import SPLITS

__all__ = ["add_command", "cmd_scene_info"]


def add_command(subparsers) -> None:
    """Registers `scene info` on an argparse subparsers object (function as `handler`)."""
    scene = subparsers.add_parser("scene", help="inspect scenes on disk")
    scene_cmds = scene.add_subparsers(dest="scene_command", metavar="SUBCOMMAND")
    scene_cmds.required = True
    info = scene_cmds.add_parser("info", help="summarise a scene (format, images, cameras, bounds)")
    info.add_argument(
        "path", type=path_argument, help="scene folder or its transforms.json / poses_bounds.npy, or a splat scene"
    )
    info.add_argument("--json", action="store_true", help="print exactly one JSON object")
    info.add_argument("--downscale", type=float, default=None, help="load images downscaled by this factor")
    info.add_argument(
        "--split", default=None, choices=SPLITS, help="which images (default: the dataset's training set)"
    )
    add_quiet(info, "progress (the loading phase's bar)")
    info.set_defaults(handler=cmd_scene_info)


def splat_summary(path: str) -> dict:
    """The summary of a splat scene (see the module docstring), JSON-ready."""
    from waldo_jax.pipeline.splat_sources import robust_bounds, splat_upright
    from waldo_jax.splats.io import load_splat_model

    model = load_splat_model(path)
    valid = np.asarray(model.splats.valid)
    low, high = robust_bounds(np.asarray(model.splats.means), valid) if model.bounds is None else model.bounds
    upright = splat_upright(model)
    summary = {
        "path": str(path),
        "format": "splats",
        "model": model.source,
        "splat_file": str(model.ply_path),
        "splats": int(valid.sum()),
        "sh_degree": model.splats.sh_degree,
        "bounds_2_98": [low.round(6).tolist(), high.round(6).tolist()],
        "cameras": None if model.cameras is None else len(model.cameras),
        "upright": upright.as_json(),
    }
    if model.cameras is not None:
        camera_up = np.mean(np.asarray(model.cameras.c2w)[:, :3, 1], axis=0)  # OpenGL: column 1 is the camera's up
        cosine = float(np.dot(camera_up, upright.up) / max(float(np.linalg.norm(camera_up)), 1e-30))
        summary["cameras_up"] = (camera_up / max(float(np.linalg.norm(camera_up)), 1e-30)).round(6).tolist()
        summary["upright_vs_cameras_deg"] = round(math.degrees(math.acos(max(-1.0, min(1.0, cosine)))), 2)
    return summary


def _print_splat_summary(summary: dict) -> None:
    up = summary["upright"]
    lines = [
        f"scene      {summary['path']}",
        f"format     {summary['model']}",
        f"splats     {summary['splats']:,}, SH degree {summary['sh_degree']}",
        f"bounds     {summary['bounds_2_98'][0]} .. {summary['bounds_2_98'][1]} (2 % and 98 % quantiles)",
        f"up         ({', '.join(f'{v:.3f}' for v in up['up'])}) by {up['rule']}: {up['reason']}",
        f"layout     {up['layout']}: {up['layout_reason']}",
    ]
    if summary["cameras"] is None:
        lines.append("cameras    none: explore uses a ring of views with this up and layout (--up, --orbit override)")
    else:
        lines.append(
            f"cameras    {summary['cameras']} (explore starts from them); their mean up {summary['cameras_up']} "
            f"is {summary['upright_vs_cameras_deg']:.1f} deg from the splats' up"
        )
    print("\n".join(lines))


def cmd_scene_info(args: argparse.Namespace) -> int:
    """`waldo scene info`: prints the summary (with --json, exactly one JSON object)."""
    from waldo_jax.pipeline.splat_sources import is_splat_spec

    if is_splat_spec(args.path):
        with Progress(args.quiet) as progress:
            progress.phase(f"loading {args.path}")
            summary = splat_summary(args.path)
        if args.json:
            print(json.dumps(summary))
        else:
            _print_splat_summary(summary)
        return 0
    with warnings.catch_warnings(record=True) as caught, Progress(args.quiet) as progress:
        warnings.simplefilter("always")
        progress.phase(f"loading {args.path}")
        scene = load_scene(args.path, downscale=args.downscale, split=args.split)
    for w in caught:  # warnings (e.g. skipped frames) go to stderr, never into the JSON
        print(f"waldo: warning: {w.message}", file=sys.stderr)
    if min(scene.width, scene.height) < MIN_RESOLUTION:  # `train` and the searches refuse such images
        how = f"--downscale {args.downscale:g} leaves" if args.downscale else "the scene has"
        print(
            f"waldo: warning: {args.path}: {how} {scene.width}x{scene.height} images; training and searches "
            f"need sides of at least {MIN_RESOLUTION} pixels",
            file=sys.stderr,
        )
    summary = scene.summary()
    if args.json:
        print(json.dumps(summary))
        return 0
    intr = summary["intrinsics"]
    lines = [
        f"scene      {summary['path'] or summary['name']}",
        f"format     {summary['format']} (split: {summary['split']})",
        f"images     {summary['n_images']} at {summary['width']}x{summary['height']}"
        + (
            f", {summary['skipped_missing']} listed frames without an image skipped"
            if summary["skipped_missing"]
            else ""
        ),
        f"intrinsics fx={intr['fx']:.2f} fy={intr['fy']:.2f} cx={intr['cx']:.2f} cy={intr['cy']:.2f}"
        + (
            f" k1={intr['k1']:.4g} k2={intr['k2']:.4g} p1={intr['p1']:.4g} p2={intr['p2']:.4g}"
            if any(intr[k] for k in ("k1", "k2", "p1", "p2"))
            else ""
        ),
        f"near/far   {summary['near']:.4g} / {summary['far']:.4g}",
        f"aabb       {summary['aabb'][0]} .. {summary['aabb'][1]}",
        f"cameras    origins in {summary['camera_origin_min']} .. {summary['camera_origin_max']}",
        f"rgba       {summary['rgba']}",
    ]
    print("\n".join(lines))
    return 0
