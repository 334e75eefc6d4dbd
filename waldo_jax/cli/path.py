"""`waldo path`: the camera path whose frames best satisfy a criterion, exported for other tools.

    waldo path SOURCE --criterion NAME --keyframes K --frames F --budget low|high --seed N --out DIR
               [--method egps|evosax:NAME] [--from-explore DIR] [--aggregate mean|softmin]
               [--max-speed S] [--max-turn DEG] [--min-opacity A] [--fps FPS] [--video-resolution R]

SOURCE is `procedural[:SEED]` or a run directory. See `waldo_jax.search.path_search` for the search and
`waldo_jax.pipeline.path_run` for the files written.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import time
import warnings
from pathlib import Path

import jax
import numpy as np

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
from waldo_jax.errors import (
    MemoryBudgetError,
    WaldoError,
    check_float32,
    check_input_file,
    check_memory,
    check_resolution,
    host_memory_bytes,
)
from waldo_jax.pipeline import INITIAL_MODES, load_source
from waldo_jax.pipeline.sources import source_world, warn_other_world
from waldo_jax.pipeline.experiment import EPOCH_BYTES_PER_PIXEL, memory_bytes, seed_keys
from waldo_jax.pipeline.path_run import (
    PathRunOptions,
    gif_frame_ms,
    check_nerfstudio_export,
    frame_function,
    path_check,
    read_explore_anchors,
    resolve_paths_per_call,
    run_path,
    write_path_outputs,
)
from waldo_jax.search.path_search import search_path_memory

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
        default=None,  # None: "low", and a --budget given beside --paths-per-epoch can be told from it
        choices=tuple(PATH_BUDGETS),
        help=f"rendered frames in all: low {PATH_BUDGETS['low']} or high {PATH_BUDGETS['high']} (default: low; "
        "it sets the paths per epoch, so --paths-per-epoch overrides it)",
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


def _warn_ignored(args: argparse.Namespace) -> None:
    """A flag off its default that the other flags make change nothing says so (as `waldo explore`'s do):
    the softmin's temperature with the mean, how the training views are scored when --from-explore's
    poses are the anchors instead, a budget (given at all) when --paths-per-epoch sets what it derives."""
    ignored = [
        (
            "--budget",
            args.budget is not None and args.paths_per_epoch is not None,
            f"--paths-per-epoch {args.paths_per_epoch} wins (the budget only derives the paths per epoch)",
        ),
        ("--temperature", args.temperature != 0.05 and args.aggregate == "mean", "it is for --aggregate softmin"),
        (
            "--initial",
            args.initial != "images" and args.from_explore is not None,
            "the anchors are --from-explore's poses, not the training views",
        ),
    ]
    for flag, unused, why in ignored:
        if unused:
            warnings.warn(f"{flag} {getattr(args, flag[2:])} has no effect: {why}", stacklevel=3)


def _config_from_args(args: argparse.Namespace) -> PathConfig:
    try:
        check_method(args.method)
    except ValueError as e:
        raise WaldoError(f"--method: {e}") from None
    budget = "low" if args.budget is None else args.budget
    if budget not in PATH_BUDGETS:
        raise WaldoError(f"unknown --budget {budget!r}: expected one of {', '.join(PATH_BUDGETS)}")
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
    if args.max_turn >= 180:  # a frame's view turns at most 180 degrees from the last
        warnings.warn(f"--max-turn {args.max_turn:g}: no frame turns more than 180 degrees, so the turn limit is off")
    gif_fps = 1000 / gif_frame_ms(args.fps)
    if args.fps > 50 or abs(gif_fps - args.fps) > 0.2 * args.fps:
        # A GIF stores whole centiseconds, at least 2 (browsers slow shorter frames): past 50 fps, and where
        # the rounding is coarse (40 fps: 20 ms, 50 fps), path.gif plays at another rate than --fps, which the
        # other files keep. The usual rates round by at most a ninth (30 fps: 30 ms, 33.3 fps), said by no line.
        warnings.warn(
            f"--fps {args.fps:g}: path.gif shows each frame {gif_frame_ms(args.fps)} ms, {gif_fps:g} frames a "
            f"second (path.mp4 and the exports keep {args.fps:g})"
        )
    _warn_ignored(args)
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
            budget=budget,
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


# Bytes a video frame's pixel takes at once while `run_path` renders and `write_path_outputs` encodes it:
# RGBA float32 twice (the calls' parts and their concatenation), the frame as uint8 twice (the stack, its
# even-sided copy for H.264); a NeRF of the room adds its truth (RGB float32 twice) and the side-by-side
# path_truth.mp4 (float32 and uint8).
VIDEO_BYTES_PER_PIXEL = 2 * 16 + 2 * 3
TRUTH_BYTES_PER_PIXEL = 2 * 12 + 2 * 12 + 2 * 6


def _anchor_check(check, anchor_c2w, from_explore: str):
    """`path_check` and a bound on the anchors of --from-explore: `run_path` scores them in one call, every
    anchor's render at once (`EPOCH_BYTES_PER_PIXEL`), before the search; a poses.json of 100,000 poses
    would take the whole machine. Called by `load_source` with the renders' size, before it renders."""

    def both(width: int, height: int, n_train: int) -> None:
        check(width, height, n_train)
        if anchor_c2w is None:
            return
        need, available = len(anchor_c2w) * width * height * EPOCH_BYTES_PER_PIXEL, memory_bytes()
        if need > available:
            raise MemoryBudgetError(
                f"--from-explore {from_explore}: its poses.json holds {len(anchor_c2w):,} poses, rendered and "
                f"scored at once at {width}x{height}: about {need / 2**30:,.1f} GiB, more than the "
                f"{available / 2**30:.1f} GiB at hand; keep at most "
                f"{max(1, available // (width * height * EPOCH_BYTES_PER_PIXEL)):,} poses (or a lower --resolution)"
            )

    return both


def _check_video_memory(width: int, height: int, truth: bool, frames: int, flag: str) -> None:
    """Refuses a video of `frames` frames of width x height whose pixels (`VIDEO_BYTES_PER_PIXEL`, and
    `TRUTH_BYTES_PER_PIXEL` with the room's truth beside a NeRF's frames) cannot be held in the host's
    memory, before the search runs: they are rendered after it, and `--frames 2000 --video-resolution
    4096` would have ended hours later in a MemoryError. `flag` is the flag that sets the size."""
    per_pixel = VIDEO_BYTES_PER_PIXEL + (TRUTH_BYTES_PER_PIXEL if truth else 0)
    check_memory(
        frames * width * height * per_pixel,
        f"--frames {frames} x {flag} {max(width, height)}: the video's {frames} frames of {width}x{height}",
        f"pass fewer --frames or a lower {flag}",
    )


# The compiled search's memory is checked (`_check_search_memory`) when its candidates alone would take
# more than this share of the memory at hand: the check compiles the search once more (2-16 s here), which
# a run of the usual budgets (about 120 paths of 24 frames: kilobytes) need not pay.
SEARCH_CHECK_SHARE = 1 / 16


def _population_bytes(config: PathConfig, seeds: int) -> int:
    """Bytes every candidate of every seed keeps through the search (`PathPopulation`: keyframes' origin,
    target and up [K, 3] each, the --frames scores, score, violation, epoch: float32 / int32; valid: bool)."""
    paths = config.initial_paths + config.epochs * config.paths_per_epoch
    return seeds * paths * (4 * (9 * config.keyframes + config.frames + 3) + 1)


def _check_search_memory(source, criterion, config: PathConfig, limits, anchor_c2w, seed: int, seeds: int) -> None:
    """Refuses a search whose compiled program needs more memory than the machine has free, before it runs.

    The flags set the work: every candidate (--initial-paths + --epochs x --paths-per-epoch, for each of
    --seeds) keeps its keyframes and its --frames scores, and `--frames 2000 --initial-paths 10000
    --paths-per-epoch 10000 --epochs 100` filled 23 GiB and was killed. Where the candidates are more
    than a small share of memory (`SEARCH_CHECK_SHARE`), XLA's analysis of the program `run_path` runs
    (its config resolved as there: the criterion's direction, the paths per call that fit) says what it
    needs, scan copies and an epoch's frames included.
    """
    config = dataclasses.replace(config, direction=criterion.direction).resolve()
    # XLA's figure is what the program takes at once: set against the memory free now (the host's on a
    # CPU, as `waldo explore` does), the device's on an accelerator.
    available = memory_bytes() if jax.devices()[0].platform != "cpu" else host_memory_bytes()
    if not available or _population_bytes(config, seeds) <= SEARCH_CHECK_SHARE * available:
        return
    try:
        config = resolve_paths_per_call(source, config, seeds)  # as `run_path` resolves it
    except WaldoError:
        return  # `run_path` refuses the resolution or the seeds with its own message
    anchors = source.train_c2w if anchor_c2w is None else anchor_c2w
    keys = jax.random.key(seed) if seeds == 1 else seed_keys(seed, seeds)
    scores = np.zeros(len(anchors), np.float32)  # only their shape is compiled
    try:
        need = search_path_memory(
            keys, frame_function(source, criterion), anchors, scores, source.train_c2w, limits, config
        )
    except ValueError:
        return  # too few anchors for the keyframes: `run_path` says so with its own message
    if need is not None and need > available:
        paths = config.initial_paths + config.epochs * config.paths_per_epoch
        raise MemoryBudgetError(
            f"--initial-paths {config.initial_paths} + --epochs {config.epochs} x --paths-per-epoch "
            f"{config.paths_per_epoch} = {paths:,} paths of --frames {config.frames}, x --seeds {seeds}: the "
            f"compiled search needs {need / 2**30:,.1f} GiB, more than the {available / 2**30:.1f} GiB at hand; "
            "use fewer paths, epochs, frames or seeds"
        )


def cmd_path(args: argparse.Namespace) -> int:
    """`waldo path`: searches the path and writes its files into --out."""
    config = _config_from_args(args)
    dataparser = None if args.nerfstudio_transforms is None else _dataparser(args.nerfstudio_transforms)
    anchor_c2w, anchor_world = (None, None) if args.from_explore is None else read_explore_anchors(args.from_explore)
    if anchor_c2w is not None and len(anchor_c2w) < max(2, config.keyframes):
        raise WaldoError(
            f"--from-explore {args.from_explore}: its poses.json holds {len(anchor_c2w)} pose"
            f"{'s' if len(anchor_c2w) != 1 else ''}; a path of --keyframes {config.keyframes} starts from at "
            f"least {max(2, config.keyframes)}"
        )
    io.check_output_dir(args.out, force=args.force)  # refuse early, before any slow work
    start = time.perf_counter()
    criterion = criterion_before_source(args)  # a bad criterion is refused before the source loads
    with Progress(args.quiet) as progress:  # phases on a terminal's stderr: loading, compiling, searching...
        progress.phase(f"loading {args.source}")
        # refused before the source renders its training views: the search's renders, the anchors'
        check = _anchor_check(path_check(config, args.seeds), anchor_c2w, args.from_explore)
        source = load_source(args.source, args.resolution, args.views, check=check, **splat_pose_options(args))
        if args.from_explore is not None:  # its poses in another scene's world: said, as `render --poses` says
            warn_other_world(f"--from-explore {args.from_explore}", anchor_world, source_world(source), source.name)
        check_nerfstudio_export(source, dataparser)  # before the search: the export must be able to undo it
        flag = "--resolution" if args.video_resolution is None else "--video-resolution"
        if args.video_resolution is None:
            video = source
        else:  # its size checked before the room renders its training views at it
            video = load_source(
                args.source,
                args.video_resolution,
                args.views,
                check=lambda width, height, _: _check_video_memory(width, height, False, config.frames, flag),
                **splat_pose_options(args),
            )
        frame = video.intrinsics
        _check_video_memory(frame.width, frame.height, video.truth is not None, config.frames, flag)
        if criterion is None:  # a poses criterion: the room's oracles need the source
            criterion = criterion_from_args(args, room=source.room, source=source.spec, train_c2w=source.train_c2w)
        limits = path_limits(source.train_c2w, args.max_speed, args.max_turn, args.min_opacity, args.min_travel)
        _check_search_memory(source, criterion, config, limits, anchor_c2w, args.seed, args.seeds)
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
