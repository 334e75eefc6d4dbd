"""`waldo render`: views to PNGs, of the procedural room, a trained run or a splat scene.

    waldo render procedural[:SEED] --out DIR [--resolution R] [--views N] [--samples S]
    waldo render procedural[:SEED] --poses FILE --out DIR [--resolution R] [--samples S]
    waldo render RUN_DIR --poses FILE|train --out DIR [--resolution R]
    waldo render SPLATS --poses FILE|train --out DIR [--resolution R]     (a .ply or a 3DGS model folder)

The room renders its training views analytically, with a contact sheet, transforms.json and
room.json (Waldo's visibility per view). With --poses every SOURCE renders through its scene's one
renderer (`Source.renderer`; the room's analytic one, --samples per ray): the poses of a file read
by `waldo_jax.scenes.read_poses_file` (a JSON object with `frames[].transform_matrix`: instant-ngp /
nerfstudio transforms, OpenGL camera-to-world in the scene's world frame, as the training poses;
nerfstudio viewer camera paths are refused) or the training poses of a run or a splat scene.
Intrinsics come from the file when it has a focal length, else from the scene; `--resolution`
rescales them so that the longer side has R pixels.
"""

from __future__ import annotations

import argparse
import dataclasses
import time
from pathlib import Path
from typing import Callable, Optional, Tuple

import jax
import jax.numpy as jnp
import numpy as np

from waldo_jax import io
from waldo_jax.cli.conventions import Progress, add_quiet
from waldo_jax.errors import WaldoError, check_resolution
from waldo_jax.pipeline.load import check_source_spec, load_source
from waldo_jax.pipeline.sources import (
    DEFAULT_PROCEDURAL_VIEWS,
    check_views,
    parse_procedural,
    room_renderer,
    source_world,
    warn_other_world,
)
from waldo_jax.procedural import RoomCameraConfig, make_room, training_cameras, waldo_visibility_batch
from waldo_jax.types import Intrinsics
from waldo_jax.scenes import load_poses_file

__all__ = ["add_command", "cmd_render", "MAX_RENDER_POSES", "RENDER_GROUP_PIXELS"]

MAX_RENDER_POSES = 100_000  # one `waldo render` call; its PNG names have at least four digits
# Rays rendered per call (whole views, or strips of rows of a larger view): bounds memory (~20 MB of
# float32 output a call) and makes the first time estimate come after seconds, not after the whole render.
RENDER_GROUP_PIXELS = 2**20
ESTIMATE_EVERY_S = 60.0  # a progress line with the time left at most this often (after the first timed call)
SHEET_CELL = 256  # the contact sheet's views are box-filtered down to at most this side


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
        help="procedural: image side; RUN_DIR: longer side "
        "(default: procedural 128, RUN_DIR the camera's, at most 256)",
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
    """`waldo render`: the procedural room's training views, or poses rendered by any SOURCE's renderer."""
    check_source_spec(args.source)
    seed = parse_procedural(args.source, args.seed)
    if seed is not None and args.poses is None:
        return _render_procedural(args, seed)
    if seed is None:
        ignored = [
            flag
            for flag, value in (("--seed", args.seed), ("--views", args.views), ("--samples", args.samples))
            if value is not None
        ]
        if ignored:
            raise WaldoError(
                f"{', '.join(ignored)}: for procedural sources only; {args.source} renders its trained field"
            )
    return _render_poses(args, seed)


@dataclasses.dataclass(frozen=True)
class _PosedScene:
    """What `--poses` renders with: a scene's renderer (`Source.renderer`), its default camera, its
    training poses (None: it has none) and its `Source.sized_renderer`."""

    name: str
    renderer: jax.tree_util.Partial
    intrinsics: Intrinsics
    train_c2w: Optional[np.ndarray] = None
    sized_renderer: Optional[Callable] = None
    world: Optional[str] = None  # the world its poses are in (`source_world`)


def _posed_scene(args: argparse.Namespace, seed: Optional[int]) -> _PosedScene:
    """The scene `--poses` renders: the procedural room (its analytic renderer, --samples per ray, a
    128 px camera), else the SOURCE's own (`load_source` without its training images)."""
    if seed is None:
        if args.poses is None:
            raise WaldoError(
                f"rendering {args.source} needs --poses FILE (a transforms.json) or --poses train "
                "(its training cameras; a splat scene's cameras.json, else a ring of views around it)"
            )
        if args.poses != "train" and not Path(args.poses).exists():
            raise WaldoError(f"{args.poses}: no such poses file (or pass --poses train)")
        if not Path(args.source).exists():
            raise WaldoError(f"SOURCE {args.source} does not exist (a run directory or a splat scene)")
        if args.resolution is not None:
            check_resolution(args.resolution)
        source = load_source(args.source, args.resolution, images=False)
        return _PosedScene(
            source.name,
            source.renderer,
            source.intrinsics,
            source.train_c2w,
            source.sized_renderer,
            source_world(source),
        )
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
    if not Path(args.poses).exists():
        raise WaldoError(f"{args.poses}: no such poses file")
    camera = Intrinsics.from_fov(128, 128, RoomCameraConfig().fov_x)
    return _PosedScene(
        f"procedural:{seed}", room_renderer(make_room(seed), samples), camera, world=f"procedural:{seed}"
    )


def _render_poses(args: argparse.Namespace, seed: Optional[int]) -> int:
    """`waldo render SOURCE --poses FILE|train`: the poses rendered by the scene's renderer to DIR/0000.png, ..."""
    scene = _posed_scene(args, seed)
    if args.poses == "train":
        c2w, intrinsics = scene.train_c2w, scene.intrinsics
    else:
        # The count is checked from the list's length, before each pose is (10^6 took 49 s and 2 GB to refuse).
        c2w, intrinsics, _, recorded = load_poses_file(Path(args.poses), scene.intrinsics, max_poses=MAX_RENDER_POSES)
        warn_other_world(f"--poses {args.poses}", recorded, scene.world, scene.name)
    if args.resolution is not None:
        check_resolution(args.resolution)
        intrinsics = intrinsics.with_max_side(args.resolution)
    if len(c2w) > MAX_RENDER_POSES:
        raise WaldoError(
            f"{args.poses}: {len(c2w)} poses; one render writes at most {MAX_RENDER_POSES} (split the file)"
        )
    out = io.prepare_output_dir(args.out, force=args.force)
    names = [f"{i:04d}.png" for i in range(len(c2w))]
    stale = io.stale_files(out, r"\d{4,}\.png", names)  # --force: an earlier render's PNGs, removed at the end
    c2w = np.asarray(c2w, np.float32)
    renderer, sized = scene.renderer, ""
    if scene.sized_renderer is not None:  # capacities sized to these very poses
        renderer, note = scene.sized_renderer(c2w, intrinsics)
        sized = f" ({note})"
    progress = Progress(args.quiet)
    progress.say(f"rendering {len(c2w)} views at {intrinsics.width}x{intrinsics.height} ...")
    start = time.perf_counter()
    with progress:
        _write_groups(renderer, c2w, intrinsics, out, names, progress)
    seconds = time.perf_counter() - start
    for path in stale:
        path.unlink()
    removed = f"; removed {len(stale)} PNGs of an earlier render" if stale else ""
    print(
        f"wrote {len(names)} PNGs of {scene.name} at {intrinsics.width}x{intrinsics.height} to {out} "
        f"in {seconds:.1f} s{sized}{removed}"
    )
    return 0


def render_calls(count: int, intrinsics: Intrinsics) -> Tuple[int, int]:
    """How `count` views of `intrinsics` are rendered: (views per call, rows per call). Views of at most
    RENDER_GROUP_PIXELS pixels go several to a call (rows = the height); a larger view goes a strip of
    rows at a time (one view a call), so every call has one shape (one compiled program)."""
    width, height = intrinsics.width, intrinsics.height
    if width * height <= RENDER_GROUP_PIXELS:
        return max(1, min(count, RENDER_GROUP_PIXELS // (width * height))), height
    return 1, max(1, min(height, RENDER_GROUP_PIXELS // width))


def strip_intrinsics(intrinsics: Intrinsics, first_row: int, rows: int) -> Intrinsics:
    """The camera of rows [first_row, first_row + rows) of `intrinsics`'s image: the same rays (the
    principal point moved up by first_row), `rows` high."""
    return dataclasses.replace(intrinsics, height=rows, cy=intrinsics.cy - first_row)


class _Estimate:
    """Progress lines with the time left: after the first call that compiles nothing (the second), then
    at most every ESTIMATE_EVERY_S seconds; the work is counted in calls, all of one shape."""

    def __init__(self, calls: int, what: str, progress: Progress):
        self.calls, self.what, self.progress = calls, what, progress
        self.done, self.start, self.timed_from, self.last_line = 0, time.perf_counter(), None, None

    def call_done(self) -> None:
        self.done += 1
        now = time.perf_counter()
        if self.done == 1:
            self.first, self.timed_from = now - self.start, now
            return
        if self.done == self.calls or (self.last_line is not None and now - self.last_line < ESTIMATE_EVERY_S):
            return
        left = (now - self.timed_from) / (self.done - 1) * (self.calls - self.done)
        first = f" (the first, compiling, took {self.first:.1f} s)" if self.last_line is None else ""
        self.progress.say(f"{self.what}: {self.done} of {self.calls} calls done{first}; about {_duration(left)} left")
        self.last_line = now


def _duration(seconds: float) -> str:
    if seconds < 90:
        return f"{seconds:.0f} s"
    if seconds < 5400:
        return f"{seconds / 60:.0f} min"
    return f"{seconds / 3600:.1f} h"


def _write_groups(
    renderer, c2w: np.ndarray, intrinsics: Intrinsics, out: Path, names, progress: Progress, sheet=None
) -> None:
    """Renders `c2w` with `renderer(c2w, intrinsics) -> Views` in calls of one shape (`render_calls`: the
    last group padded by repeating a pose; a large view in strips of rows) and writes out/names[i];
    appends each view made small (`_sheet_cell`) to the list `sheet` when given. Memory is bounded
    by RENDER_GROUP_PIXELS however many and however large the views."""
    group, rows = render_calls(len(c2w), intrinsics)
    strips = -(-intrinsics.height // rows)
    estimate = _Estimate(-(-len(c2w) // group) * strips, f"{len(c2w)} views", progress)
    progress.phase("rendering (the first call compiles)", total=len(c2w), unit="view")
    for first in range(0, len(c2w), group):
        part = c2w[first : first + group]
        padded = jnp.asarray(np.concatenate([part, np.repeat(part[-1:], group - len(part), 0)]))
        pieces = []
        for strip in range(strips):
            views = renderer(padded, strip_intrinsics(intrinsics, strip * rows, rows))
            pieces.append(np.asarray(jax.device_get(views.rgba[..., :3])))
            estimate.call_done()
        images = np.concatenate(pieces, axis=1)[: len(part), : intrinsics.height]
        for name, image in zip(names[first : first + group], images):
            io.save_png(out / name, image)
            if sheet is not None:
                sheet.append(_sheet_cell(image))
        progress.advance(len(part))
    progress.close()


def _sheet_cell(image: np.ndarray) -> np.ndarray:
    """`image` box-filtered by an integer factor to at most SHEET_CELL pixels a side (as it is if smaller)."""
    factor = -(-max(image.shape[:2]) // SHEET_CELL)
    if factor == 1:
        return image
    h, w = (image.shape[0] // factor) * factor, (image.shape[1] // factor) * factor
    return image[:h, :w].reshape(h // factor, factor, w // factor, factor, -1).mean(axis=(1, 3))


def _render_procedural(args: argparse.Namespace, seed: int) -> int:
    """`waldo render procedural[:SEED]`: the room's training views, a sheet, transforms.json, room.json."""
    resolution = 128 if args.resolution is None else args.resolution
    args.resolution = resolution
    args.views = check_views(DEFAULT_PROCEDURAL_VIEWS if args.views is None else args.views)
    check_resolution(args.resolution)
    args.samples = 128 if args.samples is None else args.samples
    if not 1 <= args.samples <= 1024:
        raise WaldoError(f"--samples must be between 1 and 1024, got {args.samples}")
    room = make_room(seed)
    intrinsics = Intrinsics.from_fov(args.resolution, args.resolution, RoomCameraConfig().fov_x)
    try:
        c2w = np.asarray(
            training_cameras(jax.random.fold_in(jax.random.key(seed), 1), room, args.views, intrinsics), np.float32
        )
    except ValueError as e:
        raise WaldoError(str(e)) from None
    out = io.prepare_output_dir(args.out, force=args.force)
    names = [f"view_{i:03d}.png" for i in range(args.views)]
    stale = io.stale_files(out, r"view_\d{3,}\.png", names)  # --force: an earlier render's views
    progress = Progress(args.quiet)
    samples = args.views * args.resolution**2 * args.samples
    progress.say(
        f"rendering {args.views} views of procedural:{seed} at {args.resolution}x{args.resolution}, "
        f"{args.samples} samples a ray ({samples / 1e9:,.2f} G samples) ..."
    )
    start, cells = time.perf_counter(), []
    with progress:
        _write_groups(room_renderer(room, args.samples), c2w, intrinsics, out, names, progress, sheet=cells)
    seconds = time.perf_counter() - start
    visibility = np.asarray(waldo_visibility_batch(room, jnp.asarray(c2w), intrinsics))
    for path in stale:
        path.unlink()
    labels = [f"{i}: waldo {v:.0%}" for i, v in enumerate(visibility)]
    io.save_png(
        out / "contact_sheet.png",
        io.contact_sheet(
            cells,
            labels=labels,
            caption="View: Waldo visible, the share of his projected area in frame and unoccluded (exact, from the "
            "room's geometry)",
        ),
    )
    io.write_transforms(
        out / "transforms.json",
        c2w,
        intrinsics,
        names,
        extra={"waldo_procedural_seed": seed, "aabb": np.asarray(room.aabb).tolist()},
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
