"""`waldo path`: the camera path whose frames best satisfy a criterion, exported for other tools.

    waldo path SOURCE --criterion NAME --keyframes K --frames F --budget low|high --seed N --out DIR
               [--method egps|evosax:NAME] [--from-explore DIR] [--aggregate mean|softmin]
               [--max-speed S] [--max-turn DEG] [--min-opacity A] [--fps FPS] [--video-resolution R]

SOURCE is `procedural[:SEED]` or a run directory. See `waldo_jax.search.path_search` for the search and
`waldo_jax.pipeline.path_run` for the files written.
"""

from __future__ import annotations

import argparse
import math
import time
from pathlib import Path

from waldo_jax.io import read_json_file
from waldo_jax import io
from waldo_jax.scenes.camera_paths import read_dataparser_transform
from waldo_jax.search.path_search import (
    AGGREGATES,
    MAX_TEMPERATURE,
    PATH_BUDGETS,
    PathConfig,
    check_method,
    path_limits,
)
from waldo_jax.cli.conventions import Progress, add_quiet
from waldo_jax.cli.flags import (
    add_criterion_arguments,
    add_splat_pose_arguments,
    criterion_before_source,
    criterion_from_args,
    splat_pose_options,
)
from waldo_jax.errors import WaldoError, check_float32, check_input_file, check_resolution
from waldo_jax.pipeline import INITIAL_MODES, load_source
from waldo_jax.pipeline.path_run import (
    PathRunOptions,
    check_nerfstudio_export,
    path_check,
    read_explore_anchors,
    run_path,
    write_path_outputs,
)

__all__ = ["add_command", "cmd_path", "MAX_FRAMES", "MAX_KEYFRAMES"]

MAX_FRAMES = 2000  # frames of one path (over a minute at 24 fps)
MAX_KEYFRAMES = 64


def add_command(subparsers) -> None:
    """Registers `path` on an argparse subparsers object (function as `handler`)."""
    p = subparsers.add_parser(
        "path",
        help="search a camera path whose frames satisfy a criterion; export it (nerfstudio, Instant-NGP, MP4)",
        description="Search the K keyframes of a smooth camera path (Catmull-Rom positions and look-at points, "
        "SLERP up vectors, F frames evenly spaced) whose frames maximise an aggregate of the "
        "criterion under speed, turn, scene-box and opacity limits; write camera_path.json "
        "(nerfstudio), instant_ngp_path.json, poses.json, path.mp4, path.gif, scores.png, "
        "path_plot.png and results.json.",
    )
    p.add_argument(
        "source",
        metavar="SOURCE",
        help="procedural, procedural:SEED, a RUN_DIR of waldo train, or a splat scene (.ply or 3DGS folder)",
    )
    add_splat_pose_arguments(p)
    add_criterion_arguments(p, default="waldo_oracle")
    p.add_argument("--method", default="egps", help="egps or evosax:NAME (e.g. evosax:CMA_ES)")
    p.add_argument("--keyframes", type=int, default=4, help="keyframes K of the path")
    p.add_argument("--frames", type=int, default=24, help="frames F of the path")
    p.add_argument(
        "--budget",
        default="low",
        choices=tuple(PATH_BUDGETS),
        help=f"rendered frames in all: low {PATH_BUDGETS['low']} or high {PATH_BUDGETS['high']}",
    )
    p.add_argument("--epochs", type=int, default=5, help="epochs")
    p.add_argument("--initial-paths", type=int, default=16, help="starting paths")
    p.add_argument(
        "--paths-per-epoch",
        type=int,
        default=None,
        help="paths per epoch (default: derived from the budget, the frames and the starting paths)",
    )
    p.add_argument("--seed", type=int, default=0, help="random seed")
    p.add_argument("--seeds", type=int, default=1, help="run K seeds in one vmapped call (files show the first)")
    p.add_argument(
        "--from-explore",
        default=None,
        metavar="DIR",
        help="build the starting paths from the top poses of a `waldo explore` --out folder: its poses.json, "
        "the different shots (or the paper's top-k where it ran with --min-separation 0); without it, from the "
        "training views",
    )
    p.add_argument("--aggregate", default="mean", choices=AGGREGATES, help="a path's score from its frames")
    p.add_argument(
        "--temperature",
        type=float,
        default=0.05,
        help="softmin temperature in score units (default: 0.05, for scores in [0, 1])",
    )
    p.add_argument("--max-speed", type=float, default=0.05, help="largest camera move per frame, in scene extents")
    p.add_argument("--max-turn", type=float, default=5.0, help="largest rotation per frame in degrees")
    p.add_argument(
        "--min-opacity",
        type=float,
        default=0.0,
        help="smallest mean opacity of a frame, 0 to 1 (default: 0, off; a pose criterion renders "
        "nothing during the search, so the limit is checked only on rendering criteria)",
    )
    p.add_argument(
        "--min-travel",
        type=float,
        default=0.0,
        help="shortest camera travel over the whole path, in scene extents (default: 0, off; e.g. 0.5 "
        "for a move, since a path that stays at the best view scores best)",
    )
    p.add_argument(
        "--resolution",
        type=int,
        default=None,
        help="longer image side of the search's renders (default: procedural 64, runs: the training size, at most 256)",
    )
    p.add_argument(
        "--video-resolution",
        type=int,
        default=None,
        help="longer image side of the video frames (default: --resolution)",
    )
    p.add_argument("--fps", type=float, default=12.0, help="frames per second of the video and the exports")
    p.add_argument(
        "--initial",
        default="images",
        choices=INITIAL_MODES,
        help="score the training-view anchors on the real 'images' or on 'renders'",
    )
    p.add_argument("--views", type=int, default=None, help="procedural only: number of training views (default: 24)")
    p.add_argument(
        "--nerfstudio-transforms",
        default=None,
        metavar="FILE",
        help="a nerfstudio model's dataparser_transforms.json: write camera_path.json in its world",
    )
    p.add_argument("--out", required=True, help="output folder (must not exist or be empty)")
    p.add_argument("--force", action="store_true", help="write into a non-empty output folder")
    add_quiet(p)
    p.set_defaults(handler=cmd_path)


def _config_from_args(args: argparse.Namespace) -> PathConfig:
    try:
        check_method(args.method)
    except ValueError as e:
        raise WaldoError(f"--method: {e}") from None
    if args.budget not in PATH_BUDGETS:
        raise WaldoError(f"unknown --budget {args.budget!r}: expected one of {', '.join(PATH_BUDGETS)}")
    for flag, value, low, high in (
        ("--keyframes", args.keyframes, 2, MAX_KEYFRAMES),
        ("--frames", args.frames, 4, MAX_FRAMES),
        ("--epochs", args.epochs, 1, 100),
        ("--initial-paths", args.initial_paths, 3, 10000),
        ("--seeds", args.seeds, 1, 1000),
        ("--paths-per-epoch", args.paths_per_epoch, 2, 10000),
    ):
        if value is not None and not low <= value <= high:
            raise WaldoError(f"{flag} must be between {low} and {high}, got {value}")
    if args.aggregate not in AGGREGATES:
        raise WaldoError(f"unknown --aggregate {args.aggregate!r}: expected one of {', '.join(AGGREGATES)}")
    for flag, value in (
        ("--temperature", args.temperature),
        ("--fps", args.fps),
        ("--max-speed", args.max_speed),
        ("--max-turn", args.max_turn),
    ):
        if not (value > 0 and math.isfinite(value)):
            raise WaldoError(f"{flag} must be a positive number, got {value}")
        check_float32(value, flag, positive=True)  # 1e-300 > 0 is 0 in float32 (and in a video's frame rate)
    check_float32(args.fps, "--fps", minimum=0.01, maximum=1000.0)  # what a video's frame rate can be
    check_float32(args.temperature, "--temperature", maximum=MAX_TEMPERATURE)  # past it, softmin underflows
    if not 0 <= args.min_opacity <= 1:
        raise WaldoError(f"--min-opacity must lie between 0 and 1, got {args.min_opacity}")
    check_float32(args.min_travel, "--min-travel")
    check_float32(args.frames * args.max_speed, "--frames x --max-speed")  # the path's longest travel, float32
    if not (0 <= args.min_travel <= args.frames * args.max_speed):
        raise WaldoError(
            f"--min-travel must lie between 0 and --frames x --max-speed = "
            f"{args.frames * args.max_speed:g} extents, got {args.min_travel}"
        )
    if args.initial not in INITIAL_MODES:
        raise WaldoError(f"unknown --initial {args.initial!r}: expected one of {', '.join(INITIAL_MODES)}")
    for flag, value in (("--resolution", args.resolution), ("--video-resolution", args.video_resolution)):
        if value is not None:
            check_resolution(value, flag)
    try:
        return PathConfig(
            keyframes=args.keyframes,
            frames=args.frames,
            method=args.method,
            epochs=args.epochs,
            budget=args.budget,
            initial_paths=args.initial_paths,
            paths_per_epoch=args.paths_per_epoch,
            aggregate=args.aggregate,
            temperature=args.temperature,
        ).resolve()
    except ValueError as e:
        raise WaldoError(str(e).replace("PathConfig.", "--").replace("_", "-")) from None


def _dataparser(path: str):
    file = check_input_file(Path(path), "--nerfstudio-transforms file")
    try:
        return read_dataparser_transform(read_json_file(file, "dataparser transforms file"))
    except ValueError as e:
        raise WaldoError(f"{path}: {e}") from None


def cmd_path(args: argparse.Namespace) -> int:
    """`waldo path`: searches the path and writes its files into --out."""
    config = _config_from_args(args)
    dataparser = None if args.nerfstudio_transforms is None else _dataparser(args.nerfstudio_transforms)
    anchor_c2w = None if args.from_explore is None else read_explore_anchors(args.from_explore)
    io.check_output_dir(args.out, force=args.force)  # refuse early, before any slow work
    start = time.perf_counter()
    criterion = criterion_before_source(args)  # a bad criterion is refused before the source loads
    with Progress(args.quiet) as progress:  # phases on a terminal's stderr: loading, compiling, searching...
        progress.phase(f"loading {args.source}")
        check = path_check(config, args.seeds)  # refused before the source renders its training views
        source = load_source(args.source, args.resolution, args.views, check=check, **splat_pose_options(args))
        check_nerfstudio_export(source, dataparser)  # before the search: the export must be able to undo it
        video = (
            source
            if args.video_resolution is None
            else load_source(args.source, args.video_resolution, args.views, **splat_pose_options(args))
        )
        if criterion is None:  # a poses criterion: the room's oracles need the source
            criterion = criterion_from_args(args, room=source.room, source=source.spec, train_c2w=source.train_c2w)
        limits = path_limits(source.train_c2w, args.max_speed, args.max_turn, args.min_opacity, args.min_travel)
        options = PathRunOptions(
            anchor_c2w=anchor_c2w,
            initial=args.initial,
            video_source=video,
            anchors="training views" if anchor_c2w is None else f"explore run {args.from_explore}",
            setup_seconds=time.perf_counter() - start,
            on_phase=progress.phase,
        )
        run = run_path(source, criterion, config, limits, seed=args.seed, seeds=args.seeds, options=options)
        progress.phase("writing the exports, the video and the plots")
        out = io.prepare_output_dir(args.out, force=args.force)  # created only once everything is valid
        results = write_path_outputs(run, out, fps=args.fps, dataparser=dataparser)
    found, straight, training = results["found"], results["references"]["straight"], results["references"]["training"]
    kept = (
        "keeps every limit"
        if found["kept_limits"]
        else "NO path kept the limits (relax --max-speed, --max-turn, --min-travel or --min-opacity)"
    )
    print(
        f"{config.method.upper()} path on {source.name} with {criterion.name}: {config.keyframes} keyframes, "
        f"{config.frames} frames, {results['cost']['frames']} frames rendered; {args.aggregate} {found['score']:.4g} "
        f"(worst frame {found['worst']:.4g}) vs straight {straight['score']:.4g}, training trajectory "
        f"{training['score']:.4g}; {kept}; {run.seconds['total']:.1f} s; wrote {out}"
    )
    return 0
