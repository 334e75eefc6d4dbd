"""`waldo scene info PATH [--json]`: a summary of a scene on disk (format, images, cameras, bounds)."""

from __future__ import annotations

import argparse
import json
import sys
import warnings

from waldo_jax.cli.conventions import Progress, add_quiet
from waldo_jax.scenes import load_scene
from waldo_jax.scenes.common import SPLITS

__all__ = ["add_command", "cmd_scene_info"]


def add_command(subparsers) -> None:
    """Registers `scene info` on an argparse subparsers object (function as `handler`)."""
    scene = subparsers.add_parser("scene", help="inspect scenes on disk")
    scene_cmds = scene.add_subparsers(dest="scene_command", metavar="SUBCOMMAND")
    scene_cmds.required = True
    info = scene_cmds.add_parser("info", help="summarise a scene (format, images, cameras, bounds)")
    info.add_argument("path", help="scene folder or its transforms.json / poses_bounds.npy")
    info.add_argument("--json", action="store_true", help="print exactly one JSON object")
    info.add_argument("--downscale", type=float, default=None, help="load images downscaled by this factor")
    info.add_argument(
        "--split", default=None, choices=SPLITS, help="which images (default: the dataset's training set)"
    )
    add_quiet(info, "progress (the loading phase's bar)")
    info.set_defaults(handler=cmd_scene_info)


def cmd_scene_info(args: argparse.Namespace) -> int:
    """`waldo scene info`: prints the summary (with --json, exactly one JSON object)."""
    with warnings.catch_warnings(record=True) as caught, Progress(args.quiet) as progress:
        warnings.simplefilter("always")
        progress.phase(f"loading {args.path}")
        scene = load_scene(args.path, downscale=args.downscale, split=args.split)
    for w in caught:  # warnings (e.g. skipped frames) go to stderr, never into the JSON
        print(f"waldo: warning: {w.message}", file=sys.stderr)
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
