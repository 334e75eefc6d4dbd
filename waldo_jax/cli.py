"""The `waldo` command line (also `python -m waldo_jax`).

Commands:
  waldo scene info PATH [--json]                       summary of a scene on disk
  waldo train SCENE_PATH --out RUN_DIR                 train an Instant-NGP field (waldo_jax.nerf.commands)
  waldo render procedural[:SEED] --out DIR             the procedural room's training views, PNGs + sheet
  waldo render RUN_DIR --poses FILE|train --out DIR    render poses with a trained field
  waldo explore SOURCE --criterion NAME --method M     search a scene (GRS / PIBS / EGPS), write results
  waldo demo [--out DIR] [--quick]                     the room end to end: train, search, report
  waldo score --criterion NAME IMAGE... [--json]        score image files with a criterion
  waldo weights convert SRC DST                        criterion weights to the native .npz format

Bad input (a missing file, a malformed scene, an existing output folder) prints one line
`waldo: error: ...` on stderr and exits with status 1, without a traceback.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
import warnings
from typing import List, Optional

from waldo_jax.errors import WaldoError, check_resolution, check_seed

__all__ = ["main", "build_parser", "parse_procedural"]


def parse_procedural(source: str, seed: Optional[int] = None) -> Optional[int]:
    """Seed of a `procedural` / `procedural:SEED` source (None if `source` is not procedural)."""
    if source != "procedural" and not source.startswith("procedural:"):
        return None
    spec = source.partition(":")[2]
    if spec:
        try:
            spec_seed = int(spec)
        except ValueError:
            raise WaldoError(f"bad source {source!r}: expected procedural or procedural:SEED with an integer SEED")
        check_seed(spec_seed, f"the seed of source {source!r}")
        if seed is not None and seed != spec_seed:
            raise WaldoError(f"source {source!r} and --seed {seed} disagree")
        return spec_seed
    return 0 if seed is None else seed


def _cmd_scene_info(args) -> int:
    from waldo_jax.scenes import load_scene

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
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
        + (f", {summary['skipped_missing']} listed frames without an image skipped" if summary["skipped_missing"] else ""),
        f"intrinsics fx={intr['fx']:.2f} fy={intr['fy']:.2f} cx={intr['cx']:.2f} cy={intr['cy']:.2f}"
        + (f" k1={intr['k1']:.4g} k2={intr['k2']:.4g} p1={intr['p1']:.4g} p2={intr['p2']:.4g}"
           if any(intr[k] for k in ("k1", "k2", "p1", "p2")) else ""),
        f"near/far   {summary['near']:.4g} / {summary['far']:.4g}",
        f"aabb       {summary['aabb'][0]} .. {summary['aabb'][1]}",
        f"cameras    origins in {summary['camera_origin_min']} .. {summary['camera_origin_max']}",
        f"rgba       {summary['rgba']}",
    ]
    print("\n".join(lines))
    return 0


def _cmd_render_procedural(args, seed: int) -> int:
    import jax.numpy as jnp
    import numpy as np

    from waldo_jax import io
    from waldo_jax.procedural import RoomCameraConfig, room_scene, waldo_visibility_batch

    resolution = 128 if args.resolution is None else args.resolution
    args.resolution = resolution
    if args.poses is not None:
        raise WaldoError("--poses is for trained runs; the procedural room renders its own training views")
    from waldo_jax.sources import DEFAULT_PROCEDURAL_VIEWS, check_views

    args.views = check_views(DEFAULT_PROCEDURAL_VIEWS if args.views is None else args.views)
    check_resolution(args.resolution)
    args.samples = 128 if args.samples is None else args.samples
    if not 1 <= args.samples <= 1024:
        raise WaldoError(f"--samples must be between 1 and 1024, got {args.samples}")
    out = io.prepare_output_dir(args.out, force=args.force)
    start = time.perf_counter()
    try:
        scene, room = room_scene(seed, num_views=args.views, resolution=args.resolution,
                                 num_samples=args.samples, camera_config=RoomCameraConfig())
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
    io.save_png(out / "contact_sheet.png", io.contact_sheet(list(scene.images), labels=labels))
    io.write_transforms(out / "transforms.json", scene.c2w, scene.intrinsics, scene.file_names,
                        extra={"waldo_procedural_seed": seed, "aabb": scene.aabb.tolist()})
    io.write_json(out / "room.json", {
        "seed": seed,
        "views": args.views,
        "resolution": args.resolution,
        "samples_per_ray": args.samples,
        "waldo_base": np.asarray(room.waldo_base).tolist(),
        "waldo_visibility": visibility.tolist(),
        "max_training_visibility": float(visibility.max()),
        "render_seconds": seconds,
    })
    print(f"wrote {args.views} views of procedural:{seed} at {args.resolution}x{args.resolution} to {out} "
          f"(contact_sheet.png, transforms.json, room.json) in {seconds:.1f} s; "
          f"best training-view Waldo visibility {visibility.max():.0%}")
    return 0


def _cmd_render(args) -> int:
    seed = parse_procedural(args.source, args.seed)
    if seed is not None:
        return _cmd_render_procedural(args, seed)
    from waldo_jax.nerf.commands import cmd_render

    ignored = [flag for flag, value in (("--seed", args.seed), ("--views", args.views), ("--samples", args.samples))
               if value is not None]
    if ignored:
        raise WaldoError(f"{', '.join(ignored)}: for procedural sources only; {args.source} renders its trained field")
    args.run_dir = args.source
    return cmd_render(args)


def _cmd_demo(args) -> int:
    from waldo_jax.demo import run_demo

    out = run_demo(args.out, quick=args.quick, seed=args.seed, progress=not args.quiet)
    print(f"wrote {out / 'report.md'}")
    return 0


def build_parser() -> argparse.ArgumentParser:
    """The argparse parser of the `waldo` command."""
    parser = argparse.ArgumentParser(
        prog="waldo",
        description="Explore NeRF scene spaces in JAX (Finding Waldo, MMSys'24).",
    )
    commands = parser.add_subparsers(dest="command", metavar="COMMAND")
    commands.required = True

    scene = commands.add_parser("scene", help="inspect scenes on disk")
    scene_cmds = scene.add_subparsers(dest="scene_command", metavar="SUBCOMMAND")
    scene_cmds.required = True
    info = scene_cmds.add_parser("info", help="summarise a scene (format, images, cameras, bounds)")
    info.add_argument("path", help="scene folder or its transforms.json / poses_bounds.npy")
    info.add_argument("--json", action="store_true", help="print exactly one JSON object")
    info.add_argument("--downscale", type=float, default=None, help="load images downscaled by this factor")
    info.add_argument("--split", default=None, help="train, val, test or all (default: the dataset's training set)")
    info.set_defaults(handler=_cmd_scene_info)

    from waldo_jax.nerf.commands import add_commands

    add_commands(commands)  # train

    from waldo_jax.commands_explore import add_explore_command

    add_explore_command(commands)

    from waldo_jax.commands_criteria import add_score_command, add_weights_command

    add_score_command(commands)
    add_weights_command(commands)

    demo = commands.add_parser(
        "demo", help="the procedural Waldo room end to end: train a NeRF, run GRS/PIBS/EGPS, write a report",
        description="Build the procedural Waldo room, train the hash-grid NeRF on its views, run GRS, PIBS and "
                    "EGPS at the low budget with the waldo_oracle criterion (several seeds each), and write "
                    "report.md with CVIR/mCVIR per method, contact sheets and pose clouds into a new folder.")
    demo.add_argument("--out", default=None, help="output folder (default runs/demo-<timestamp>; never overwritten)")
    demo.add_argument("--quick", action="store_true", help="smaller settings (under 2 minutes on 2 CPU cores)")
    demo.add_argument("--seed", type=int, default=0, help="room seed and first search seed (default 0)")
    demo.add_argument("--quiet", action="store_true", help="no progress output")
    demo.set_defaults(handler=_cmd_demo)

    render = commands.add_parser(
        "render", help="render views to PNGs",
        description="Render the procedural Waldo room's training views (SOURCE = procedural[:SEED]), or "
                    "poses with a trained field (SOURCE = a run directory of `waldo train`, with --poses).")
    render.add_argument("source", metavar="SOURCE", help="procedural, procedural:SEED, or RUN_DIR")
    render.add_argument("--out", required=True, help="output folder (must not exist or be empty)")
    render.add_argument("--poses", default=None, metavar="FILE|train",
                        help="RUN_DIR only: a transforms.json-like file, or 'train' for the training poses")
    render.add_argument("--resolution", type=int, default=None,
                        help="procedural: image side (default 128); RUN_DIR: longer side (default: camera's)")
    render.add_argument("--seed", type=int, default=None, help="procedural: room seed (default 0)")
    render.add_argument("--views", type=int, default=None,
                        help="procedural only: number of training views (default 24, at most 1000)")
    render.add_argument("--samples", type=int, default=None,
                        help="procedural only: samples per ray (default 128, at most 1024)")
    render.add_argument("--force", action="store_true", help="write into a non-empty output folder")
    render.set_defaults(handler=_cmd_render)
    return parser


def main(argv: Optional[List[str]] = None) -> int:
    """Entry point of `waldo`; returns the exit status."""
    parser = build_parser()
    args = parser.parse_args(argv)
    show = warnings.showwarning
    # Warnings are one line each, like errors: "waldo: warning: ..." (not Python's file:line form).
    warnings.showwarning = lambda message, *rest, **kw: print(f"waldo: warning: {message}", file=sys.stderr)
    try:
        if getattr(args, "seed", None) is not None:  # before anything is created, trained or written
            check_seed(args.seed, "--seed", getattr(args, "seeds", 1) or 1)
        return int(args.handler(args) or 0)
    except WaldoError as e:
        print(f"waldo: error: {e}", file=sys.stderr)
        return 1
    except OSError as e:  # the machine refused (disk full, permissions): name the file, no traceback
        where = f"{e.filename}: " if e.filename else ""
        print(f"waldo: error: {where}{e.strerror or e}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print("waldo: interrupted", file=sys.stderr)
        return 130
    finally:
        warnings.showwarning = show


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
