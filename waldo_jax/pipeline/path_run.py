"""A camera-path experiment: source + criterion + path search -> `PathRun`, and its files.

`run_path` scores the anchor poses (the training views, as `explore` does, or the top poses of an
earlier `explore` run), runs `waldo_jax.search.path_search.search_path` (one seed, or several vmapped),
evaluates the two reference paths (the straight path between the two best anchors, and the
training trajectory: the spline through every training camera in order, at the same F frames)
under the same criterion and limits, and renders the best path's frames for the video.
`write_path_outputs` writes camera_path.json (nerfstudio), instant_ngp_path.json, poses.json,
path.mp4 and path.gif (at `gif_frame_ms`: the fps to the centisecond), path_sheet.png, scores.png,
path_plot.png (a top view down the scene's up, each path's start and end marked) and results.json (and,
for a NeRF of the room, path_truth.mp4: the NeRF beside the analytic room). Every figure names the
criterion, its direction and range.
"""

from __future__ import annotations

import dataclasses
import math
import textwrap
import time
import warnings
from pathlib import Path
from typing import Any, Callable, Dict, List, Optional, Tuple

import jax
import jax.numpy as jnp
import numpy as np

from waldo_jax import io
from waldo_jax.scenes.camera_paths import NgpFrame, instant_ngp_camera_path, nerfstudio_camera_path
from waldo_jax.search.path import PathLimits, path_c2w, straight_path
from waldo_jax.search.path_search import PathConfig, aggregate_scores, search_path, search_path_seeds
from waldo_jax.criteria import Criterion
from waldo_jax.errors import MIN_RESOLUTION, WaldoError
from waldo_jax.pipeline.experiment import (
    EPOCH_BYTES_PER_PIXEL,
    initial_scores,
    memory_bytes,
    scene_views,
    scoring_renderer,
    seed_keys,
)
from waldo_jax.pipeline.figures import criterion_caption, criterion_label, plot_frame, scene_up
from waldo_jax.pipeline.sources import Source, source_world
from waldo_jax.search.population import training_poses
from waldo_jax.cameras import camera_focus

__all__ = [
    "PathRun",
    "PathRunOptions",
    "frame_function",
    "read_explore_anchors",
    "run_path",
    "write_path_outputs",
    "paths_per_call",
    "resolve_paths_per_call",
    "evaluate_path",
    "check_nerfstudio_export",
    "path_check",
    "gif_frame_ms",
]

VIDEO_GROUP_PIXELS = 2**22  # pixels rendered per call for the video: bounds memory


def _frames(renderer, criterion: Criterion, intrinsics, c2w):
    views = scene_views(renderer, intrinsics, c2w)
    opacity = jnp.ones(c2w.shape[0], jnp.float32) if views.rgba is None else jnp.mean(views.rgba[..., 3], axis=(1, 2))
    return criterion.evaluate(views), opacity


def frame_function(source: Source, criterion: Criterion) -> jax.tree_util.Partial:
    """c2w [B, 4, 4] -> (scores [B], mean opacity [B]): `experiment.score_function` with the frames'
    opacity for the path limits. A pose criterion renders nothing (opacity 1)."""
    return jax.tree_util.Partial(_frames, scoring_renderer(source, criterion), criterion, source.intrinsics)


def paths_per_call(source: Source, config: PathConfig) -> int:
    """Paths scored per vectorised call so that one call's frames fit in memory (`EPOCH_BYTES_PER_PIXEL`)."""
    return _paths_fitting(source.intrinsics.width, source.intrinsics.height, config)


def _paths_fitting(width: int, height: int, config: PathConfig) -> int:
    per_path = config.frames * width * height * EPOCH_BYTES_PER_PIXEL
    return int(memory_bytes() // max(per_path, 1))


def _check_path_pixels(width: int, height: int, config: PathConfig, seeds: int) -> int:
    """The paths that fit one call (`paths_per_call`), refused when fewer than `seeds`."""
    fits = _paths_fitting(width, height, config)
    if fits < 1:  # not even one path: the size is the input to change
        per_path = config.frames * width * height * EPOCH_BYTES_PER_PIXEL
        side = int(max(width, height) * math.sqrt(memory_bytes() / per_path))
        raise WaldoError(
            f"--resolution {max(width, height)}: one path's {config.frames} frames of {width}x{height} take about "
            f"{per_path / 2**30:,.1f} GiB at once, more than the {memory_bytes() / 2**30:.1f} GiB at hand; pass "
            + (f"--resolution {side} or less, or fewer --frames" if side >= MIN_RESOLUTION else "fewer --frames")
        )
    if fits < seeds:
        raise WaldoError(
            f"--seeds {seeds}: one path's {config.frames} frames of {width}x{height} for every seed at once do not "
            f"fit in memory here; at most --seeds {max(fits, 1)} (or fewer --frames, a lower --resolution)"
        )
    return fits


def resolve_paths_per_call(source: Source, config: PathConfig, seeds: int) -> PathConfig:
    """`config` (resolved: `PathConfig.resolve`) with the paths `run_path` scores per vectorised call, where
    it leaves them open (None): the paths whose frames fit one call (`paths_per_call`) shared by the `seeds`
    seeds, which are vmapped, and no more than the larger of an epoch's paths and the starting paths.

    Raises:
      WaldoError: not one path's frames fit one call, or not one for every seed (naming --resolution or
        --seeds).
    """
    if config.paths_per_call is not None:
        return config
    fits = _check_path_pixels(source.intrinsics.width, source.intrinsics.height, config, seeds)
    most = max(config.paths_per_epoch, config.initial_paths)
    return dataclasses.replace(config, paths_per_call=min(fits // seeds, most))


def path_check(config: PathConfig, seeds: int) -> Callable[[int, int, int], None]:
    """`run_path`'s memory check for a source not loaded yet (`load_source(..., check=)`): called with the
    renders' size before the source renders or reads its training views."""

    def check(width: int, height: int, n_train: int) -> None:
        del n_train
        if config.paths_per_call is not None or not isinstance(seeds, int) or seeds < 1:
            return  # a given size per call, or seeds `run_path` refuses with its own message
        try:
            resolved = config.resolve()
        except ValueError:
            return  # settings `run_path` refuses with its own message
        _check_path_pixels(width, height, resolved, seeds)

    return check


def read_explore_anchors(run_dir: str) -> Tuple[np.ndarray, Optional[str]]:
    """The top poses [k, 4, 4] of an `explore` run folder (its poses.json) and the world it records
    (`scenes.PosesFile.world`; None where it records none)."""
    from waldo_jax.scenes import load_poses_file
    from waldo_jax.types import Intrinsics

    path = Path(run_dir) / "poses.json"
    if not path.is_file():
        raise WaldoError(f"--from-explore {run_dir}: no poses.json (is it the --out folder of `waldo explore`?)")
    poses = load_poses_file(path, Intrinsics.create(64, 64, 64.0))
    return poses.c2w, poses.world


def evaluate_path(frame_fn, c2w: np.ndarray, limits: PathLimits, config: PathConfig) -> Dict[str, Any]:
    """Score, per-frame scores, violation and motion figures of frames c2w [F, 4, 4]."""
    scores, opacity = _evaluate_jit(frame_fn, jnp.asarray(c2w))  # compiled: a network is ~10x slower eagerly
    scores = np.asarray(scores, np.float32)
    violation, motion = limits.violation(jnp.asarray(c2w), jnp.asarray(opacity, jnp.float32))
    return {
        "score": float(aggregate_scores(jnp.asarray(scores), config)),
        "frame_scores": scores,
        "mean": float(np.mean(scores)),
        "worst": float(np.min(scores) if config.direction == "max" else np.max(scores)),
        "violation": float(violation),
        "opacity": np.asarray(opacity, np.float32),
        **_motion_figures(motion),
    }


def _motion_figures(motion) -> Dict[str, float]:
    return {
        "travel": float(jnp.sum(motion.speed)),
        "max_speed": float(jnp.max(motion.speed)),
        "max_turn_degrees": float(jnp.max(motion.turn)),
        "max_jerk": float(jnp.max(motion.jerk)),
    }


_evaluate_jit = jax.jit(lambda frame_fn, c2w: frame_fn(c2w))


@dataclasses.dataclass
class PathRun:
    """A finished path search (host side).

    Attributes:
      source, criterion, config (resolved), limits: what ran.
      seeds: the seeds; results: a `PathResult` per seed (NumPy leaves).
      anchors: "training views" or "explore run DIR"; anchor_c2w [A, 4, 4], anchor_scores [A].
      found: per seed, `evaluate_path` of its best path.
      references: {"straight": ..., "training": ...} `evaluate_path` of the two reference paths.
      frames: float32 [F, H, W, 3] the first seed's best path rendered for the video; opacity [F];
        truth: the same frames by the analytic room (a NeRF of the room), or None.
      seconds: {"setup", "search", "render", "total"}.
    """

    source: Source
    criterion: Criterion
    config: PathConfig
    limits: PathLimits
    seeds: List[int]
    results: List[Any]
    anchors: str
    anchor_c2w: np.ndarray
    anchor_scores: np.ndarray
    found: List[Dict[str, Any]]
    references: Dict[str, Dict[str, Any]]
    frames: np.ndarray
    truth: Optional[np.ndarray]
    seconds: Dict[str, float]
    video_source: Optional[Source] = None


def _render_frames(render, c2w: np.ndarray, pixels: int) -> np.ndarray:
    group = max(1, min(len(c2w), VIDEO_GROUP_PIXELS // pixels))
    parts = []
    for first in range(0, len(c2w), group):
        part = c2w[first : first + group]
        padded = np.concatenate([part, np.repeat(part[-1:], group - len(part), 0)])
        parts.append(np.asarray(render(jnp.asarray(padded)), np.float32)[: len(part)])
    return np.concatenate(parts)


def _training_trajectory(train_c2w: np.ndarray, frames: int) -> np.ndarray:
    poses = training_poses(train_c2w, camera_focus(train_c2w))
    return np.asarray(path_c2w(poses, frames))


@dataclasses.dataclass(frozen=True)
class PathRunOptions:
    """What `run_path` starts from besides the search itself: its anchors, the video's source and the progress.

    Attributes:
      anchor_c2w: float [A, 4, 4] the anchor poses, scored by the criterion (None: the training views,
        scored as `initial` says).
      anchors: what the anchors are, in words (results.json); the training views as anchors are named
        "training views (scored on ...)" whatever this says.
      initial: what scores the training views as anchors, "images" or "renders" (`initial_scores`).
      video_source: the source rendering the video frames (another resolution); None: the searched source.
      setup_seconds: seconds spent before the call (loading the source), counted in `PathRun.seconds`.
      on_phase: called with the name of each phase as it starts (a progress display); changes nothing.
    """

    anchor_c2w: Optional[np.ndarray] = None
    anchors: str = "training views"
    initial: str = "images"
    video_source: Optional[Source] = None
    setup_seconds: float = 0.0
    on_phase: Optional[Callable[[str], None]] = None


def run_path(
    source: Source,
    criterion: Criterion,
    config: PathConfig,
    limits: PathLimits,
    seed: int = 0,
    seeds: int = 1,
    options: PathRunOptions = PathRunOptions(),
) -> PathRun:
    """Runs the path search (`seeds` seeds in one vmapped call) and renders the first seed's best path.

    Args:
      source, criterion: what renders and scores; the criterion's direction overrides config's.
      config, limits: `PathConfig` and `PathLimits`.
      seed, seeds: seeds seed, seed + 1, ... (`seed_keys`).
      options: a `PathRunOptions`: the anchors (default: the training views), the video's source,
        the setup time and a progress callback.
    """
    phase = options.on_phase or (lambda name: None)
    anchor_c2w, anchors = options.anchor_c2w, options.anchors
    start = time.perf_counter()
    config = dataclasses.replace(config, direction=criterion.direction).resolve()
    if seeds < 1:
        raise WaldoError(f"--seeds must be >= 1, got {seeds}")
    config = resolve_paths_per_call(source, config, seeds)
    frame_fn = frame_function(source, criterion)
    phase("scoring the anchors")
    if anchor_c2w is None:
        anchor_c2w = source.train_c2w
        anchor_scores, used = initial_scores(source, criterion, options.initial)
        anchors = f"training views (scored on {used})"
    else:
        anchor_scores = np.asarray(_evaluate_jit(frame_fn, jnp.asarray(anchor_c2w))[0], np.float32)
    plural = lambda n, word: f"{n} {word}" + ("s" if n != 1 else "")  # noqa: E731
    phase(f"compiling and searching ({plural(config.epochs, 'epoch')}, {plural(seeds, 'seed')})")
    try:
        if seeds == 1:
            results = [
                jax.device_get(
                    search_path(
                        jax.random.key(seed), frame_fn, anchor_c2w, anchor_scores, source.train_c2w, limits, config
                    )
                )
            ]
        else:
            out = jax.device_get(
                search_path_seeds(
                    seed_keys(seed, seeds), frame_fn, anchor_c2w, anchor_scores, source.train_c2w, limits, config
                )
            )
            results = [jax.tree.map(lambda a, i=i: a[i], out) for i in range(seeds)]
    except ValueError as e:
        raise WaldoError(str(e)) from None
    searched = time.perf_counter()
    phase("scoring the paths found and the reference paths")
    found = [evaluate_path(frame_fn, np.asarray(r.best_c2w), limits, config) for r in results]
    order = np.argsort(
        -np.where(np.isfinite(anchor_scores), (1 if config.direction == "max" else -1) * anchor_scores, -np.inf),
        kind="stable",
    )
    anchor_poses = training_poses(anchor_c2w, camera_focus(source.train_c2w))
    pick = lambda i: jax.tree.map(lambda x: x[int(i)], anchor_poses)  # noqa: E731
    straight = np.asarray(path_c2w(straight_path(pick(order[0]), pick(order[1]), config.keyframes), config.frames))
    trajectory = _training_trajectory(source.train_c2w, config.frames)
    references = {
        "straight": {**evaluate_path(frame_fn, straight, limits, config), "c2w": straight},
        "training": {**evaluate_path(frame_fn, trajectory, limits, config), "c2w": trajectory},
    }
    video = options.video_source or source
    phase(f"rendering the {config.frames} video frames")
    best = np.asarray(results[0].best_c2w)
    pixels = video.intrinsics.width * video.intrinsics.height
    rgba = _render_frames(lambda c2w: video.views(c2w).rgba, best, pixels)
    frames = rgba[..., :3]
    truth = None if video.truth is None else _render_frames(video.render_truth, best, pixels)
    done = time.perf_counter()
    seconds = {
        "setup": round(options.setup_seconds, 3),
        "search": round(searched - start, 3),
        "render": round(done - searched, 3),
        "total": round(options.setup_seconds + done - start, 3),
    }
    found[0]["video_opacity"] = rgba[..., 3].mean(axis=(1, 2))
    return PathRun(
        source=source,
        criterion=criterion,
        config=config,
        limits=limits,
        seeds=list(range(seed, seed + seeds)),
        results=results,
        anchors=anchors,
        anchor_c2w=anchor_c2w,
        anchor_scores=anchor_scores,
        found=found,
        references=references,
        frames=frames,
        truth=truth,
        seconds=seconds,
        video_source=video,
    )


# ---------------------------------------------------------------------------------------------
# Files.


def _video(path: Path, frames: np.ndarray, fps: float) -> Tuple[int, int]:
    """An MP4 (imageio-ffmpeg) or GIF of frames [F, H, W, 3], written beside `path` and renamed onto it.

    H.264 (yuv420p) needs even sides: an MP4 of odd-sided frames repeats their last row / column
    (with a warning that says so). Returns the (width, height) written.

    Raises:
      WaldoError: the encoder wrote nothing (nothing is left at `path`).
    """
    import imageio.v2 as imageio

    data = np.stack([io.to_uint8(f) for f in frames])
    height, width = data.shape[1:3]
    if path.suffix.lower() == ".mp4" and (height % 2 or width % 2):
        data = np.pad(data, ((0, 0), (0, height % 2), (0, width % 2), (0, 0)), mode="edge")
        warnings.warn(
            f"{path.name}: {width}x{height} frames padded to {data.shape[2]}x{data.shape[1]} (H.264 needs "
            "even sides; the last row / column repeated)",
            stacklevel=2,
        )
    tmp = path.with_name(f".{path.stem}.partial{path.suffix}")
    try:
        with warnings.catch_warnings():
            # imageio-ffmpeg starts ffmpeg in a subprocess, which execs at once: JAX's fork warning does not apply.
            warnings.filterwarnings("ignore", message=r"os\.fork\(\) was called")
            _write_video(imageio, tmp, list(data), fps)
        if not tmp.is_file() or tmp.stat().st_size == 0:  # ffmpeg reports encoder failures only on its stderr
            raise WaldoError(
                f"{path}: the video encoder wrote nothing for {len(data)} frames of {data.shape[2]}x{data.shape[1]}"
            )
        tmp.replace(path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return int(data.shape[2]), int(data.shape[1])


def gif_frame_ms(fps: float) -> int:
    """Milliseconds each GIF frame lasts at `fps`: 1000 / fps to the nearest centisecond (a GIF stores
    centiseconds; Python's rounding, ties to even), at least 2 cs (browsers slow 0-1 cs frames to 10 cs).

    Pillow's writer truncates milliseconds to centiseconds (15 fps: 66.7 ms -> 60 ms, 16.7 fps), so the
    rounded value is passed in whole centiseconds.
    """
    return 10 * max(2, round(100.0 / fps))


def _write_video(imageio, tmp: Path, data, fps: float) -> None:
    if tmp.suffix.lower() == ".gif":
        imageio.mimwrite(tmp, data, duration=gif_frame_ms(fps), loop=0)  # imageio's Pillow plugin: milliseconds
    else:
        imageio.mimwrite(tmp, data, fps=fps, macro_block_size=1, quality=8)


def check_nerfstudio_export(source: Source, dataparser: Optional[Tuple[np.ndarray, float]]) -> None:
    """Refuses `--nerfstudio-transforms` for a source whose nerfstudio `applied_transform` is not known.

    A checkpoint saved before waldo recorded it, whose scene file is not on this machine: the model's
    dataparser_transforms.json folds that transform in, so the export cannot undo it.
    """
    if dataparser is not None and source.info.get("nerfstudio_applied_source") == "unknown":
        raise WaldoError(
            f"--nerfstudio-transforms: {source.spec} does not record its scene's applied_transform and "
            f"its scene file {source.info.get('scene_path') or '(unnamed)'} is not here to read it from"
        )


def _score_figure(run: PathRun):
    """Per-frame scores of the found path and the two references (a bare Matplotlib `Figure`)."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=(6.4, 3.4), dpi=120)
    ax = fig.add_subplot()
    x = np.arange(run.config.frames)
    ax.plot(x, run.found[0]["frame_scores"], label=f"found ({run.config.method})", lw=2)
    ax.plot(x, run.references["straight"]["frame_scores"], label="straight (two best anchors)", ls="--")
    ax.plot(x, run.references["training"]["frame_scores"], label="training trajectory", ls=":")
    ax.set_xlabel("frame (0: start)")
    ax.set_ylabel(criterion_label(run.criterion), fontsize=8)
    ax.set_title(textwrap.fill(f"{criterion_caption(run.criterion)}; per frame on {run.source.name}", 90), fontsize=8)
    ax.legend(fontsize=7)
    return fig


def _plot_scores(path: Path, run: PathRun) -> None:
    with io.atomic_file(path) as handle:
        _score_figure(run).savefig(handle, format="png", bbox_inches="tight")


def _path_figure(run: PathRun):
    """Top view of the path, the references, the training cameras and, for the room, Waldo: looking down
    the scene's up (`plot_frame` of the training cameras), each path's start and end marked."""
    from matplotlib.figure import Figure
    from matplotlib.lines import Line2D

    frame = plot_frame(scene_up(run.source.train_c2w))
    train = frame(run.source.train_c2w[:, :3, 3])
    fig = Figure(figsize=(4.8, 5.2), dpi=120)
    ax = fig.add_subplot()
    ax.scatter(train[:, 0], train[:, 1], s=10, c="0.6", label="training cameras")
    best = np.asarray(run.results[0].best_c2w)
    for colour, (name, c2w, style) in enumerate(
        (
            (f"found ({run.config.method})", best, "-"),
            ("straight", run.references["straight"]["c2w"], "--"),
            ("training trajectory", run.references["training"]["c2w"], ":"),
        )
    ):
        o = frame(np.asarray(c2w)[:, :3, 3])
        ax.plot(o[:, 0], o[:, 1], style, color=f"C{colour}", label=name)
        ax.scatter(o[:1, 0], o[:1, 1], marker="o", s=36, color=f"C{colour}", edgecolors="k", zorder=3, gid="start")
        ax.scatter(o[-1:, 0], o[-1:, 1], marker="s", s=36, color=f"C{colour}", edgecolors="k", zorder=3, gid="end")
    o, d = frame(best[:, :3, 3]), frame(-best[:, :3, 2])
    scale = 0.06 * max(float(np.ptp(train[:, :2], axis=0).max()), 1e-6)
    ax.quiver(
        o[::2, 0],
        o[::2, 1],
        d[::2, 0],
        d[::2, 1],
        angles="xy",
        scale_units="xy",
        scale=1.0 / scale,
        width=0.004,
        color="C0",
        label="view direction (found)",
    )
    if run.source.room is not None:
        w = frame(np.asarray(run.source.room.waldo_center))
        ax.scatter([w[0]], [w[1]], marker="*", s=160, c="red", label="Waldo (the target)")
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel(frame.labels[0])
    ax.set_ylabel(frame.labels[1])
    handles, _ = ax.get_legend_handles_labels()
    handles += [
        Line2D([], [], ls="none", marker="o", color="0.8", markeredgecolor="k", label="start (frame 0)"),
        Line2D([], [], ls="none", marker="s", color="0.8", markeredgecolor="k", label=f"end (frame {len(best) - 1})"),
    ]
    ax.legend(handles=handles, fontsize=7, loc="upper center", bbox_to_anchor=(0.5, -0.1), ncol=2, frameon=False)
    ax.set_title(
        f"{run.config.method} path on {run.source.name}, top view\n(looking down the scene's up, "
        f"{frame.up_text}: the mean of the training cameras' up vectors)",
        fontsize=8,
    )
    return fig


def _plot_path(path: Path, run: PathRun) -> None:
    with io.atomic_file(path) as handle:
        _path_figure(run).savefig(handle, format="png", bbox_inches="tight")


def _summary(evaluation: Dict[str, Any]) -> Dict[str, Any]:
    keys = ("score", "mean", "worst", "violation", "travel", "max_speed", "max_turn_degrees", "max_jerk")
    out = {k: evaluation[k] for k in keys}
    out["frame_scores"] = evaluation["frame_scores"]
    return out


def _source_names(source: Source) -> Dict[str, Any]:
    """How the path's files name its SOURCE: as given, and the world its poses are in (`source_world`, which
    `waldo render --poses` compares with the source it renders; the camera path's own `world` is its frame)."""
    return {"source": source.spec, "source_world": source_world(source)}


def write_path_outputs(
    run: PathRun, out: Path, fps: float = 12.0, dataparser: Optional[Tuple[np.ndarray, float]] = None
) -> Dict[str, Any]:
    """Writes the path's files into `out` (which must exist); returns the results dictionary."""
    out = Path(out)
    best = np.asarray(run.results[0].best_c2w)
    video = run.video_source or run.source
    info = {"criterion": run.criterion.name, "method": run.config.method, **_source_names(run.source)}
    check_nerfstudio_export(run.source, dataparser)
    applied = run.source.info.get("nerfstudio_applied_transform")
    io.write_json(
        out / "camera_path.json",
        nerfstudio_camera_path(
            best,
            video.intrinsics,
            fps,
            dataparser,
            info,
            applied_transform=None if applied is None else np.asarray(applied, np.float64),
            applied_scale=float(run.source.info.get("nerfstudio_applied_scale", 1.0)),
        ),
    )
    io.write_json(
        out / "instant_ngp_path.json",
        instant_ngp_camera_path(best, video.intrinsics, fps, extra=info, frame=NgpFrame.of_info(run.source.info)),
    )
    names = [f"frame_{i:04d}" for i in range(len(best))]
    io.write_transforms(out / "poses.json", best, video.intrinsics, names, extra={"waldo_path": info})
    mp4_size = _video(out / "path.mp4", run.frames, fps)
    _video(out / "path.gif", run.frames, fps)
    if run.truth is not None:
        _video(out / "path_truth.mp4", np.concatenate([run.frames, run.truth], axis=2), fps)
    step = max(1, len(best) // 12)
    picks = list(range(0, len(best), step))
    scores = run.found[0]["frame_scores"]
    io.save_png(
        out / "path_sheet.png",
        io.contact_sheet(
            [run.frames[i] for i in picks],
            labels=[f"{i}: {scores[i]:.3g}" for i in picks],
            caption=f"Frame: score. Scores: {criterion_caption(run.criterion)}",
        ),
    )
    _plot_scores(out / "scores.png", run)
    _plot_path(out / "path_plot.png", run)

    limits = run.limits
    results = {
        "source": run.source.spec,
        "source_info": run.source.info,
        "criterion": run.criterion.name,
        "criterion_description": run.criterion.description,
        "criterion_caption": criterion_caption(run.criterion),
        "direction": run.criterion.direction,
        "method": run.config.method,
        "seeds": run.seeds,
        "config": {k: v for k, v in dataclasses.asdict(run.config).items()},
        "cost": run.config.cost(),
        "limits": {
            "max_speed_extent_per_frame": float(limits.max_speed),
            "max_turn_degrees_per_frame": float(limits.max_turn),
            "min_opacity": float(limits.min_opacity),
            "min_travel_extent": float(limits.min_travel),
            "box_low": np.asarray(limits.low),
            "box_high": np.asarray(limits.high),
            "extent": float(limits.extent),
        },
        "anchors": run.anchors,
        "anchor_scores": run.anchor_scores,
        "found": {
            **_summary(run.found[0]),
            "keyframes": {
                "origin": np.asarray(run.results[0].best_keyframes.origin),
                "target": np.asarray(run.results[0].best_keyframes.target),
                "up": np.asarray(run.results[0].best_keyframes.up),
            },
            "kept_limits": bool(run.results[0].found),
            "curve": np.asarray(run.results[0].curve),
            "video_opacity_min": (
                None if run.found[0].get("video_opacity") is None else float(np.min(run.found[0]["video_opacity"]))
            ),
        },
        "references": {k: _summary(v) for k, v in run.references.items()},
        "per_seed": [
            {"seed": s, **{k: v for k, v in _summary(f).items() if k != "frame_scores"}, "kept_limits": bool(r.found)}
            for s, r, f in zip(run.seeds, run.results, run.found)
        ],
        "seconds": run.seconds,
        "video": {
            "frame_size": [int(run.frames.shape[2]), int(run.frames.shape[1])],
            "mp4_size": list(mp4_size),
            "fps": float(fps),
            "gif_frame_ms": gif_frame_ms(fps),
        },
        "files": [
            "camera_path.json",
            "instant_ngp_path.json",
            "poses.json",
            "path.mp4",
            "path.gif",
            "path_sheet.png",
            "scores.png",
            "path_plot.png",
        ]
        + (["path_truth.mp4"] if run.truth is not None else []),
    }
    io.write_json(out / "results.json", results)
    return results
