"""`waldo demo [--out DIR] [--quick] [--seed S] [--train-steps N] [--min-separation DEG]
[--search-renders [METHOD]]`: the procedural room end to end (`waldo_jax.pipeline.demo`)."""

from __future__ import annotations

import argparse
import dataclasses

from waldo_jax.cli.conventions import add_quiet
from waldo_jax.cli.shots import add_shot_arguments, shot_separation
from waldo_jax.errors import MAX_TRAIN_STEPS, check_int
from waldo_jax.pipeline.demo import (
    DEMO_ROOM_SEED,
    RENDERS_METHOD,
    RENDERS_METHODS,
    RENDERS_TRAIN_STEPS,
    SETTINGS,
    demo_settings,
    run_demo,
)

__all__ = ["add_command", "cmd_demo"]


def add_command(subparsers) -> None:
    """Registers `demo` on an argparse subparsers object (function as `handler`)."""
    demo = subparsers.add_parser(
        "demo",
        help="the procedural Waldo room end to end: train a NeRF, run GRS/PIBS/EGPS, write a report",
        description="Build the procedural Waldo room, train the hash-grid NeRF on its views, run GRS, PIBS and "
        "EGPS at the low budget with the waldo_found criterion (Waldo whole, then as large as possible; several "
        "seeds each), and write report.md with CVIR/mCVIR per method, Waldo's visible share and the "
        "NeRF's PSNR at the best views, contact sheets and pose clouds into a new folder.",
    )
    demo.add_argument("--out", default=None, help="output folder (default: runs/demo-<timestamp>; never overwritten)")
    demo.add_argument("--quick", action="store_true", help="smaller settings (under 2 minutes on 2 CPU cores)")
    demo.add_argument(
        "--seed",
        type=int,
        default=None,
        help=f"room seed and first search seed (default: {DEMO_ROOM_SEED}, the room whose NeRF renders Waldo best "
        "where the searches find him; in rooms 0, 2 and 3 no view shows him whole)",
    )
    demo.add_argument(
        "--train-steps",
        type=int,
        default=None,
        help=f"NeRF training steps (default: {SETTINGS['full'].train_steps}, {RENDERS_TRAIN_STEPS} with "
        f"--search-renders, {SETTINGS['quick'].train_steps} with --quick); more steps render Waldo better where "
        "the time allows, e.g. on a GPU",
    )
    demo.add_argument(
        "--search-renders",
        nargs="?",
        const=RENDERS_METHOD,
        default=None,
        choices=RENDERS_METHODS,
        metavar="METHOD",
        help=f"also run METHOD ({RENDERS_METHOD} when the flag is given alone; one of "
        f"{', '.join(RENDERS_METHODS)}) scored by the waldo finder on the NeRF's renders (the paper's setting; its "
        "best views checked by the exact oracle). It renders "
        "every view it scores: about 2,200 NeRF renders, and the NeRF trains longer so that it renders Waldo "
        "whole (about 11 minutes on 2 CPU cores)",
    )
    add_shot_arguments(demo, grid=False)
    add_quiet(demo)
    demo.set_defaults(handler=cmd_demo)


def cmd_demo(args: argparse.Namespace) -> int:
    """`waldo demo`: runs the demo into a new folder and names its report."""
    settings = demo_settings(args.quick, args.search_renders)
    if args.train_steps is not None:
        settings = dataclasses.replace(
            settings, train_steps=check_int(args.train_steps, "--train-steps", maximum=MAX_TRAIN_STEPS)
        )
    settings = dataclasses.replace(settings, min_separation=shot_separation(args))
    out = run_demo(args.out, quick=args.quick, seed=args.seed, progress=not args.quiet, settings=settings)
    print(f"wrote {out / 'report.md'}")
    return 0
