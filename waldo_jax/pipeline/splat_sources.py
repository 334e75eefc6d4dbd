"""3D Gaussian Splatting scenes as search sources: a `.ply`, a reference-layout folder, or a splat run.

SOURCE may be
  * a `.ply` written by the reference 3DGS code, gsplat, nerfstudio's splatfacto export or a capture
    app (`waldo_jax.splats.io.read_splat_ply`);
  * a folder as the reference code writes it (`point_cloud/iteration_N/point_cloud.ply`, the highest N,
    with `cameras.json` at its root), or a folder holding `point_cloud.ply`;
  * a splat run of `waldo train --model splat` (that layout plus `train.json`, which names the
    scene it was fitted to: its real images are then the training views, as for NeRF runs).

The pose space (the training views a search starts from) comes from, in this order: `cameras` (a
transforms.json-like file, a COLMAP model or a nerfstudio run, `--cameras`), the cameras that come
with the model (`waldo_jax.splats.cameras.find_splat_cameras`: its `cameras.json`, a nerfstudio run, a
COLMAP model), or a ring of `RING_VIEWS` views around the splats' robust bounds looking at their centre
(`ring_cameras`; said in `Source.info`).
Without real images, the training views' "images" are the splats' own renders at those poses.

The renderer is `waldo_jax.splats.render`, with `max_pairs` calibrated on the training views
(`calibrate_max_pairs`); a view that needs more pairs drops its farthest splats and is counted
(`Source.renderer_report`, written into results.json under "renderer").
"""

from __future__ import annotations

import dataclasses
import functools
import math
import warnings
from pathlib import Path
from typing import Any, Callable, Dict, Optional, Tuple

import jax
import jax.numpy as jnp
import numpy as np

from waldo_jax.io import read_json_file
from waldo_jax.cameras import look_at
from waldo_jax.criteria.base import rendered_views
from waldo_jax.errors import SceneFormatError, WaldoError, check_resolution
from waldo_jax.pipeline.sources import Source, SourceError, resize_images
from waldo_jax.scenes import load_scene, read_poses_file
from waldo_jax.scenes.common import warn_off_image_principal_point
from waldo_jax.splats.formats import find_splat_file, splat_format
from waldo_jax.splats.cameras import read_camera_source
from waldo_jax.splats.cameras_json import render_intrinsics
from waldo_jax.splats.io import SplatModel, load_splat_model
from waldo_jax.splats.model import Splats
from waldo_jax.splats.render import SplatRenderConfig, count_pairs, render_splats_on_devices
from waldo_jax.splats.upright import FORMAT_UP, Upright, UprightConfig, estimate_upright, ring_origins
from waldo_jax.splats.upright import robust_bounds as upright_robust_bounds
from waldo_jax.splats.runs import TRAIN_JSON
from waldo_jax.types import Array, Intrinsics

__all__ = [
    "is_splat_spec",
    "splat_source",
    "ring_cameras",
    "splat_upright",
    "calibrate_max_pairs",
    "calibrate_tile_chunks",
    "splat_renderer",
    "sized_splat_renderer",
    "SPLAT_RESOLUTION",
    "RING_VIEWS",
    "SPLAT_GRADIENT_COST",
    "TRAIN_JSON",
]

SPLAT_RESOLUTION = 256  # default longer side of a splat source's renders (the cameras' own size when smaller)
RING_VIEWS = 24
RING_ELEVATION_DEG = 30.0
RING_FOV_DEG = 50.0
# Renders one reverse-mode pose gradient through the splat renderer counts as in a +refine budget: the
# largest measured ratio of its time to a render and exact score's, rounded up (5.4 for saliency on the
# fitted lego_tiny splats at 64 px, 3.1 to 3.4 with colorfulness, where the render dominates; the NeRF's
# forward-mode gradient: 11.5; benchmarks/results/gradient_cost_splats_cpu.json).
SPLAT_GRADIENT_COST = 6
_PAIRS_MARGIN = 1.5  # max_pairs = this x the most pairs a training view needs (searches go closer)
_CHUNKS_MARGIN = 1.5  # tile_chunks = this x the most chunks a training view's tile needs, + 1
_PAIRS_QUANTUM = 4096


def is_splat_spec(spec: str) -> bool:
    """True when SOURCE names a splat scene: a `.ply`, `.splat`, `.spz` or `.sog` path, a file of a splat
    format by its content (`splat_format`), or a folder with `point_cloud/`, `point_cloud.ply` or one
    splat file (and no NeRF `checkpoint.ckpt`)."""
    path = Path(spec)
    if path.suffix.lower() in (".ply", ".splat", ".spz", ".sog") or splat_format(path) is not None:
        return True
    if not path.is_dir() or (path / "checkpoint.ckpt").exists():
        return False
    if (path / "point_cloud").is_dir() or (path / "point_cloud.ply").is_file():
        return True
    try:
        return find_splat_file(path) is not None
    except SceneFormatError:
        return True  # several splat files: load_splat_model says so


def robust_bounds(means: np.ndarray, valid: np.ndarray, quantile: float = 0.02) -> Tuple[np.ndarray, np.ndarray]:
    """(low, high) [3]: the `quantile` and 1 - `quantile` quantiles of the valid splats' means per axis
    (stray splats far from the scene do not move them)."""
    return upright_robust_bounds(means, valid, quantile)  # non-finite means and far strays left out


def ring_cameras(
    means: np.ndarray,
    valid: np.ndarray,
    intrinsics: Intrinsics,
    count: int = RING_VIEWS,
    up: Optional[np.ndarray] = None,
    elevation_deg: float = RING_ELEVATION_DEG,
    upright: Optional[Upright] = None,
    bounds: Optional[Tuple[np.ndarray, np.ndarray]] = None,
) -> Tuple[np.ndarray, dict]:
    """`count` cameras on a ring, looking at the centre of the splats' robust bounds.

    The ring's axis is `upright.up`, else `up`, else the direction in which the splats' means vary least
    (sign: its largest component positive; `estimate_upright` decides better). For an object (the
    default) the cameras sit `elevation_deg` above the ring's plane, far enough that the bounds' sphere
    fills the narrower field of view with a 10 % margin; for a surrounding scene (`upright.layout`
    "surround") they stand inside, `UprightConfig.inside_radius` x the bounds' radius from the centre at
    its height, looking across it.

    `bounds`: the splats' `robust_bounds` where already computed (`SplatModel.bounds`), else computed here.

    Returns:
      (c2w float32 [count, 4, 4] OpenGL, a description for `Source.info`).
    """
    low, high = robust_bounds(means, valid) if bounds is None else bounds
    centre = 0.5 * (low + high)
    radius = max(0.5 * float(np.linalg.norm(high - low)), 1e-6)
    if upright is not None:
        up = upright.up
    elif up is None:
        points = np.asarray(means, np.float64)[np.asarray(valid, bool)]
        points = points[np.all((points >= low) & (points <= high), axis=1)]
        _, vectors = np.linalg.eigh(np.cov((points - points.mean(0)).T))
        up = vectors[:, 0]
        up = up * np.sign(up[np.argmax(np.abs(up))])
    up = np.asarray(up, np.float64) / np.linalg.norm(up)
    inside = upright is not None and upright.layout == "surround"
    if inside:
        distance, elevation_deg = UprightConfig().inside_radius * radius, 0.0
    else:
        half_fov = 0.5 * min(
            2 * math.atan(0.5 * intrinsics.width / float(intrinsics.fx)),
            2 * math.atan(0.5 * intrinsics.height / float(intrinsics.fy)),
        )
        distance = 1.1 * radius / math.sin(half_fov)
    origins = ring_origins(centre, up, distance, count, elevation_deg)
    c2w = jax.vmap(look_at, in_axes=(0, None, None))(
        jnp.asarray(origins, jnp.float32), jnp.asarray(centre, jnp.float32), jnp.asarray(up, jnp.float32)
    )
    info = {
        "poses": "ring inside" if inside else "ring",
        "views": int(count),
        "centre": centre.tolist(),
        "up": up.tolist(),
        "distance": distance,
        "elevation_deg": elevation_deg,
        "bounds_quantiles": [0.02, 0.98],
        "bounds": [low.tolist(), high.tolist()],
    }
    if upright is not None:
        info["upright"] = upright.as_json()
    return np.asarray(c2w, np.float32), info


def splat_upright(
    model: SplatModel, up: Optional[np.ndarray] = None, orbit: Optional[str] = None, seed: int = 0
) -> Upright:
    """The up and layout of a splat model (`waldo_jax.splats.upright.estimate_upright` with the file
    family's axis prior; `up`/`orbit` given by `--up`/`--orbit` are kept)."""
    s = model.splats
    valid = np.asarray(s.valid)
    return estimate_upright(
        jax.random.key(seed),
        np.asarray(s.means)[valid],
        np.asarray(jax.nn.sigmoid(s.logits))[valid],
        (np.asarray(s.log_scales)[valid], np.asarray(s.quats)[valid]),
        # Every format is read in the frame of the 3DGS PLY it was made from (`waldo_jax.splats.formats`).
        format_up=FORMAT_UP["3dgs-ply"],
        up=up,
        layout=None if orbit in (None, "auto") else orbit,
    )


_count_pairs = jax.jit(count_pairs, static_argnames=("config",))


def calibrate_max_pairs(
    splats: Splats, c2w: np.ndarray, intrinsics: Intrinsics, config: SplatRenderConfig, margin: float = _PAIRS_MARGIN
) -> int:
    """`max_pairs` for views like `c2w`: `margin` x the most pairs one of them needs, rounded up to a
    multiple of `_PAIRS_QUANTUM` (the renderer's work grows with it; a view that needs more is
    counted, never silently cut). With margin 1 the views `c2w` themselves drop nothing."""
    needed = int(np.max(np.asarray(_count_pairs(splats, jnp.asarray(c2w), intrinsics, config=config))))
    return max(_PAIRS_QUANTUM, int(math.ceil(margin * needed / _PAIRS_QUANTUM)) * _PAIRS_QUANTUM)


_render_stats = jax.jit(render_splats_on_devices, static_argnames=("config",))


def calibrate_tile_chunks(
    splats: Splats, c2w: np.ndarray, intrinsics: Intrinsics, config: SplatRenderConfig, margin: float = _CHUNKS_MARGIN
) -> Tuple[Optional[int], np.ndarray, int]:
    """`tile_chunks` for views like `c2w`, from their exact renders (no tile capacity).

    A tile's depth-ordered list only counts until every pixel's transmittance falls below the stop; the
    chunks after that are work without effect (a million splats at 128 px stack thousands deep per
    tile and stop after a few hundred). The capacity is `margin` x the most chunks a tile of these views
    needed, + 1, and None when that would not be fewer chunk slots than `config` has without it.

    Returns:
      (tile_chunks or None, the exact renders rgb float32 [P, H, W, 3], the most chunks needed).
    """
    out = _render_stats(splats, jnp.asarray(c2w, jnp.float32), intrinsics, config=config)
    needed = int(np.max(np.asarray(out.stats.needed_chunks)))
    tiles_x, tiles_y = config.tiles(intrinsics)
    chunks = int(math.ceil(margin * max(needed, 1))) + 1
    saves = tiles_x * tiles_y * chunks < config.chunk_slots(intrinsics)
    return (chunks if saves else None), np.asarray(out.rgb, np.float32), needed


# ---------------------------------------------------------------------------------------------
# Renderers (module-level functions: the Partials built from them compile once per shape).


def _views(splats: Splats, background: Array, c2w: Array, intrinsics: Intrinsics, *, config: SplatRenderConfig):
    out = render_splats_on_devices(splats, c2w, intrinsics, config, background)
    return rendered_views(out.rgb, out.acc, c2w, intrinsics)


@functools.lru_cache(maxsize=None)
def _views_fn(config: SplatRenderConfig):
    """One function object per config, so that Partials of equal settings share compilations."""
    return functools.partial(_views, config=config)


def splat_renderer(splats: Splats, config: SplatRenderConfig, background=None) -> jax.tree_util.Partial:
    """The splat renderer, (c2w [P, 4, 4], intrinsics) -> `Views` (rgba: the colour and the
    accumulated opacity), a Partial; the splats are traced arguments, so it compiles once per image size.
    `config.max_pairs` and `config.tile_chunks` are capacities sized for some views
    (`calibrate_max_pairs`): `sized_splat_renderer` sizes them to others."""
    bg = jnp.asarray(config.background if background is None else background, jnp.float32)
    return jax.tree_util.Partial(_views_fn(config), splats, bg)


def sized_splat_renderer(
    splats: Splats, config: SplatRenderConfig, c2w: np.ndarray, intrinsics: Intrinsics
) -> Tuple[jax.tree_util.Partial, str]:
    """`splat_renderer` with its pairs sized to the views c2w [P, 4, 4] at `intrinsics`, and what was sized
    (`Source.sized_renderer`): no view drops a splat."""
    max_pairs = calibrate_max_pairs(splats, c2w, intrinsics, config, margin=1.0)
    note = f"{int(np.sum(np.asarray(splats.valid)))} splats, max_pairs {max_pairs}: no view dropped a splat"
    return splat_renderer(splats, dataclasses.replace(config, max_pairs=max_pairs)), note


def _report(splats: Splats, intrinsics: Intrinsics, config: SplatRenderConfig, c2w: np.ndarray) -> Dict[str, Any]:
    """What the renderer dropped over the views `c2w` of a run (for results.json)."""
    c2w = np.asarray(c2w, np.float32).reshape(-1, 4, 4)
    needed = (
        np.asarray(_count_pairs(splats, jnp.asarray(c2w), intrinsics, config=config))
        if len(c2w)
        else np.zeros(0, np.int64)
    )
    over = needed > config.max_pairs
    return {
        "renderer": "splats",
        "max_pairs": config.max_pairs,
        "views": int(len(c2w)),
        "views_over_max_pairs": int(np.sum(over)),
        "most_pairs_needed": int(needed.max(initial=0)),
        "pairs_dropped": int(np.sum(np.maximum(needed - config.max_pairs, 0))),
        "tile_size": config.tile_size,
        "chunk": config.chunk,
        "near": config.near,
        "tile_chunks": config.tile_chunks,
        "note": "a view over max_pairs drops its farthest splats' pairs (counted here; "
        "the renderer's SplatStats count the pixels that could change); with tile_chunks, each tile "
        "composites its nearest tile_chunks x chunk splats (calibrated on the training views' exact renders)",
    }


# ---------------------------------------------------------------------------------------------
# The source.


# The keys of a splat run's train.json that are read back, each with its test and what it must be.
_RECORD_KEYS = {
    "scene_path": (lambda v: isinstance(v, str), "a path"),
    "split": (lambda v: isinstance(v, str), "a split name"),
    "downscale": (
        lambda v: isinstance(v, (int, float)) and not isinstance(v, bool) and 1 <= v < math.inf,
        "a number >= 1",
    ),
    "steps": (lambda v: isinstance(v, int) and not isinstance(v, bool) and v >= 0, "a whole number >= 0"),
    "psnr_test": (lambda v: isinstance(v, (int, float)) and not isinstance(v, bool), "a number"),
    "background": (
        lambda v: (
            isinstance(v, list)
            and len(v) == 3
            and all(isinstance(c, (int, float)) and not isinstance(c, bool) and 0.0 <= c <= 1.0 for c in v)
        ),
        "3 numbers in [0, 1]",
    ),
}


def _read_train_json(folder: Path) -> Optional[dict]:
    """A splat run's train.json, None where there is none; a SourceError naming it and the key when it is no
    object or a key read back (`_RECORD_KEYS`; null is absent) holds the wrong kind of value."""
    path = folder / TRAIN_JSON
    if not path.is_file():
        return None
    record = read_json_file(path, "splat run record")
    if not isinstance(record, dict):
        raise SourceError(f"{path}: a splat run record must be a JSON object, not {type(record).__name__}")
    for key, (ok, what) in _RECORD_KEYS.items():
        if record.get(key) is not None and not ok(record[key]):
            raise SourceError(f"{path}: {key!r} must be {what}, got {record[key]!r}")
    return record


def _run_images(record: dict, names, intrinsics: Intrinsics) -> Tuple[Optional[np.ndarray], str]:
    """A splat run's real training images at `intrinsics`' size, or (None, why)."""
    scene_path = record.get("scene_path")
    if not scene_path or not Path(scene_path).exists():
        return None, f"the training scene {scene_path or '(unnamed)'} is not on this machine"
    try:
        scene = load_scene(
            scene_path,
            downscale=record.get("downscale"),
            split=record.get("split") or None,
            background=record.get("background", (1.0, 1.0, 1.0)),
        )
    except WaldoError as e:
        return None, f"cannot read the training scene again ({e})"
    by_name = {name: i for i, name in enumerate(scene.file_names)}
    missing = [name for name in names if name not in by_name]
    if missing:
        return None, f"{scene_path} no longer has the training image {missing[0]!r}"
    images = scene.images[[by_name[name] for name in names]]
    return resize_images(images, intrinsics.width, intrinsics.height), ""


# A splat below this opacity adds less than one 8-bit step to any pixel: a scene of only such splats
# renders the background alone.
MIN_VISIBLE_OPACITY = 1.0 / 255.0
# A splat whose largest log-scale is above this has a covariance (the scale squared, times the projection's
# focal / depth squared) past float32's range: the renderer finds it non-finite and leaves it out.
MAX_SHOWN_LOG_SCALE = 40.0


def _flag_transparent(spec: str, splats: Splats, info: Dict[str, Any]) -> None:
    """Warns, and flags `info["degenerate"]`, when no valid splat can show (every render would be the
    background alone): each is transparent (opacity under 1/255), or so large that its covariance overflows
    float32 (a log-scale above `MAX_SHOWN_LOG_SCALE`), or has a non-finite centre."""
    valid = np.asarray(splats.valid, bool)
    opacity = np.asarray(jax.nn.sigmoid(splats.logits), np.float32)[valid]
    log_scales = np.asarray(splats.log_scales, np.float32)[valid]
    means = np.asarray(splats.means, np.float32)[valid]
    with np.errstate(invalid="ignore"):
        opaque = opacity >= MIN_VISIBLE_OPACITY
        sized = np.all(np.isfinite(log_scales), -1) & (np.max(log_scales, -1, initial=-np.inf) <= MAX_SHOWN_LOG_SCALE)
    placed = np.all(np.isfinite(means), -1)
    if np.any(opaque & sized & placed):
        return
    count = int(valid.sum())
    if not opaque.any():
        highest = f"{float(opacity.max()):.2g}" if opacity.size else "none"
        why = f"all {count} splats are transparent (highest opacity {highest}, under 1/255)"
    else:
        why = (
            f"none of the {count} splats can show: {int((~opaque).sum())} are transparent (opacity under 1/255), "
            f"{int((opaque & ~sized).sum())} opaque ones have a scale past exp({MAX_SHOWN_LOG_SCALE:g}) (their "
            f"covariance overflows float32), {int((opaque & sized & ~placed).sum())} a non-finite centre"
        )
    why += ": every render is the background alone"
    info["degenerate"] = why
    warnings.warn(f"{spec}: {why}", stacklevel=3)


# Fewer float32 steps than this across the splats' extent, at their distance from the origin, place them
# visibly coarsely: a 0.2-unit model 10^4 units out has about 200 steps across it.
MIN_POSITION_STEPS = 1000


def _steps(count: float) -> str:
    return f"{count:.0f} steps" if count >= 1.5 else "one step" if count >= 0.5 else "under one step"


def _flag_coarse_positions(spec: str, splats: Splats, info: Dict[str, Any]) -> None:
    """Warns, and flags `info["coarse_positions"]`, when the splats lie so far from the origin, for their
    extent, that float32 (in which they are read and rendered) holds fewer than `MIN_POSITION_STEPS`
    positions across them: a model saved at +10^6 in float64 rendered as a distorted slab, at +10^7 as a
    streak, with no word."""
    valid = np.asarray(splats.valid, bool)
    means = np.asarray(splats.means, np.float32)[valid]
    means = means[np.all(np.isfinite(means), -1)]
    if len(means) < 2:
        return
    low, high = np.quantile(means, [0.02, 0.98], axis=0)
    extent = float(np.max(high - low))
    distance = float(np.max(np.abs(np.concatenate([low, high]))))
    step = float(np.spacing(np.float32(distance)))
    if step * MIN_POSITION_STEPS <= extent:
        return
    why = (
        f"its splats lie {distance:.3g} from the origin, where float32 (in which they are read and rendered) "
        f"steps by {step:.2g}: their extent {extent:.3g} is {_steps(extent / step)}, so they are placed coarsely "
        "(move the model near the origin, in float64, before saving it)"
    )
    info["coarse_positions"] = why
    warnings.warn(f"{spec}: {why}", stacklevel=3)


def splat_source(
    spec: str,
    resolution: Optional[int] = None,
    cameras: Optional[str] = None,
    config: Optional[SplatRenderConfig] = None,
    images: bool = True,
    up: Optional[np.ndarray] = None,
    orbit: Optional[str] = None,
    check: Optional[Callable[[int, int, int], None]] = None,
):
    """A splat scene (`.ply`, reference-layout folder or splat run) as a `Source`.

    Args:
      spec: the SOURCE string.
      resolution: longer side of the renders (default: the cameras' own, at most SPLAT_RESOLUTION).
      cameras: a transforms.json-like poses file, a COLMAP model (folder, images.bin/.txt) or a
        nerfstudio run (folder, config.yml) giving the training poses (and intrinsics), or None.
      config: renderer settings (default `SplatRenderConfig()`; `max_pairs` calibrated here).
      images: read (or, without photos, render) the training views' images; False leaves them None.
      up: the scene's up [3] for a ring of views (`--up`; default: `splat_upright` decides).
      orbit: "object", "surround" or "auto"/None (`--orbit`): orbit the splats or stand inside them.
      check: `load_source`'s, called with the renders' size and the views' count before any render.

    Raises:
      WaldoError (SceneFormatError, SourceError, ...): the file or folder cannot be read, or `up`/`orbit`
        are given for a scene whose cameras fix its poses.
    """
    path = Path(spec)
    if not path.exists():
        raise SourceError(f"SOURCE {spec!r}: no such splat file or folder")
    model: SplatModel = load_splat_model(path)
    splats = jax.device_put(model.splats)
    config = SplatRenderConfig() if config is None else config
    folder = model.ply_path.parent if model.iteration is None else model.ply_path.parent.parent.parent
    record = _read_train_json(folder) if path.is_dir() else None
    means, valid = np.asarray(splats.means), np.asarray(splats.valid)
    info: Dict[str, Any] = {
        "splat_file": str(model.ply_path.resolve()),
        "splats": int(valid.sum()),
        "sh_degree": splats.sh_degree,
        "iteration": model.iteration,
        "model": model.source,
    }
    if record is None and model.ply_path.parent != folder:  # a fit's .ply given alone, inside its folder
        try:
            fitted = _read_train_json(folder)  # its train.json names the scene whose world its poses are in
        except WaldoError:
            fitted = None
        if fitted and fitted.get("scene_path"):
            info["fit_scene_path"] = fitted["scene_path"]  # for `source_world` only
    _flag_transparent(spec, splats, info)
    _flag_coarse_positions(spec, splats, info)
    if getattr(model, "degenerate", None) and "degenerate" not in info:  # a scene of one point (warned on load)
        info["degenerate"] = model.degenerate
    names: Tuple[str, ...]
    if resolution is not None:
        check_resolution(resolution)
    if (up is not None or orbit not in (None, "auto")) and (cameras is not None or model.cameras is not None):
        given = "--cameras" if cameras is not None else "its own cameras"
        raise SourceError(
            f"--up/--orbit place a ring of views around a scene without cameras; {spec} has {given}, "
            "which fix its training views"
        )
    # --cameras: a COLMAP model or a nerfstudio run (`read_camera_source`), else a poses file.
    other = read_camera_source(cameras) if cameras is not None else None
    if other is not None:
        c2w, names = other[0].c2w, other[0].names
        intrinsics = other[0].shared_intrinsics or other[0].intrinsics[0]
        info["poses"] = f"--cameras {cameras}: {other[1]}"
        warn_off_image_principal_point(intrinsics, Path(cameras), stacklevel=2)  # as a poses file's reader does
    elif cameras is not None:
        default = Intrinsics.from_fov(SPLAT_RESOLUTION, SPLAT_RESOLUTION, math.radians(RING_FOV_DEG))
        c2w, intrinsics, files = read_poses_file(cameras, default)
        names = tuple(f or f"pose_{i:04d}" for i, f in enumerate(files))
        info["poses"] = f"--cameras {cameras}"
    elif model.cameras is not None:
        c2w, names = model.cameras.c2w, model.cameras.names
        intrinsics = model.cameras.shared_intrinsics or model.cameras.intrinsics[0]
        # `model.source` ends "with N cameras from <where>" (`find_splat_cameras`' description).
        warn_off_image_principal_point(intrinsics, Path(model.source.rpartition(" cameras from ")[2]), stacklevel=2)
        info["poses"] = model.source.rpartition(" cameras from ")[2] + (
            "" if model.cameras.shared_intrinsics else " (cameras of several sizes: the first camera's intrinsics)"
        )
    else:
        intrinsics = Intrinsics.from_fov(SPLAT_RESOLUTION, SPLAT_RESOLUTION, math.radians(RING_FOV_DEG))
        c2w, ring = ring_cameras(means, valid, intrinsics, upright=splat_upright(model, up, orbit), bounds=model.bounds)
        names = tuple(f"ring_{i:02d}" for i in range(len(c2w)))
        info["poses"] = ring["poses"]
        info["ring"] = ring
    side = min(max(intrinsics.width, intrinsics.height), SPLAT_RESOLUTION) if resolution is None else resolution
    intrinsics = render_intrinsics(intrinsics, int(side), Path(cameras or spec), "the views' camera")
    if check is not None:
        check(intrinsics.width, intrinsics.height, len(c2w))
    background = np.asarray(record.get("background", config.background) if record else config.background, np.float32)
    config = SplatRenderConfig(**{**config.__dict__, "background": tuple(float(v) for v in background)})
    max_pairs = calibrate_max_pairs(splats, c2w, intrinsics, config)
    config = SplatRenderConfig(**{**config.__dict__, "max_pairs": max_pairs})
    tile_chunks, exact_renders, needed_chunks = calibrate_tile_chunks(splats, c2w, intrinsics, config)
    config = SplatRenderConfig(**{**config.__dict__, "tile_chunks": tile_chunks})
    info["renderer"] = {
        "max_pairs": max_pairs,
        "calibrated_on": f"the training views (x{_PAIRS_MARGIN:g})",
        "tile_chunks": tile_chunks,
        "tile_chunks_calibration": f"the training views' exact renders needed at most {needed_chunks} chunks "
        f"per tile before every pixel stopped; x{_CHUNKS_MARGIN:g} + 1"
        + ("" if tile_chunks is not None else ": no fewer than every chunk, so no capacity"),
        "tile_size": config.tile_size,
        "chunk": config.chunk,
        "near": config.near,
        "background": list(config.background),
    }
    train_images, note = None, "not loaded (images=False)"
    if record is not None:
        info.update(
            {
                "run_dir": str(folder.resolve()),
                "scene_path": record.get("scene_path"),
                "psnr_test": record.get("psnr_test"),
                "train_steps": record.get("steps"),
            }
        )
        if images:
            train_images, note = _run_images(record, names, intrinsics)
    if images and train_images is None:
        # No photos come with a splat file: its training views are its own renders there.
        train_images = exact_renders
        info["train_images"] = "renders at the training poses" + (f" ({note})" if record is not None else "")
        note = ""
    name = folder.name if path.is_dir() else path.stem
    return Source(
        spec=str(spec),
        kind="splats",
        name=name,
        train_c2w=np.asarray(c2w, np.float32),
        intrinsics=intrinsics,
        renderer=splat_renderer(splats, config),
        train_images=train_images,
        train_names=tuple(names),
        info=info,
        train_images_note=note,
        renderer_report=functools.partial(_report, splats, intrinsics, config),
        gradient="reverse",
        gradient_cost=SPLAT_GRADIENT_COST,
        sized_renderer=functools.partial(sized_splat_renderer, splats, config),
    )
