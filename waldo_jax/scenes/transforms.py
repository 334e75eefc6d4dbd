"""instant-ngp, nerfstudio and Blender scenes: `transforms.json` and `transforms_<split>.json`.

All three store OpenGL camera-to-world matrices, used as they are in the file's own world, except
instant-ngp's `from_mitsuba` files, whose camera axes are Mitsuba's (turned into OpenGL's here).
instant-ngp's `scale`, `offset`, `aabb` and `from_mitsuba` enter the box and the exports as NGP's
loader reads them (`tool_frames.ngp_frame`); nerfstudio's `applied_transform` (or its COLMAP default)
and `applied_scale` are recorded (`tool_frames.nerfstudio_applied`), not re-applied. Boxes:
instant-ngp the cube NGP marches in, mapped back to the world; nerfstudio the padded 1st-99th
percentile box of its point cloud (else of the camera origins and focus); Blender [-1.5, 1.5]^3 with
near 2, far 6. See docs/design.md, "Scenes".
"""

from __future__ import annotations

import os
import warnings
from pathlib import Path
from typing import Any, Dict, List, Optional, Tuple

import numpy as np

from waldo_jax.cameras import camera_focus
from waldo_jax.errors import NumberError, SceneFormatError
from waldo_jax.scenes.common import (
    BLENDER_SPLITS,
    SPLITS,
    blender_split_of,
    camera_bounds,
    check_holdout_split,
    check_rigid,
    check_split,
    field,
    file_name_problem,
    focal_from_angle,
    holdout,
    input_file,
    natural_key,
    number,
    numeric_array,
    read_json,
    relative,
    shown,
    subsample,
    value_text,
)
from waldo_jax.scenes.tool_frames import MITSUBA_TO_OPENGL, NgpFrame, nerfstudio_applied, ngp_frame
from waldo_jax.scenes.images import load_images, resolve_image
from waldo_jax.scenes.ply import read_ply_points
from waldo_jax.types import Intrinsics

__all__ = [
    "BLENDER_AABB",
    "BLENDER_NEAR",
    "BLENDER_FAR",
    "NGP_DEFAULT_SCALE",
    "NGP_DEFAULT_OFFSET",
    "PLY_PERCENTILES",
    "PLY_PAD",
    "ORIGIN_PAD",
    "load_transforms",
    "load_blender",
]

BLENDER_AABB = ((-1.5, -1.5, -1.5), (1.5, 1.5, 1.5))
BLENDER_NEAR, BLENDER_FAR = 2.0, 6.0
NGP_DEFAULT_SCALE = 0.33
NGP_DEFAULT_OFFSET = 0.5
PLY_PERCENTILES = (1.0, 99.0)
PLY_PAD = 0.1  # fraction of the percentile box size added on each side.
ORIGIN_PAD = 0.25  # fraction of the camera box size added on each side (no point cloud).
# A point cloud whose box has a side below this fraction of its longest lies on a line or a plane: its box
# has no volume to march in.
MIN_BOX_SIDE_RATIO = 1e-3
# Each side of the box that replaces such a point cloud's is at least this fraction of its longest (the
# cameras too may lie in one plane).
FALLBACK_BOX_SIDE_RATIO = 0.1
# The side of the box of a scene without a point cloud whose cameras all lie at one point (world units:
# such cameras give no scale).
ONE_POINT_CUBE = 2.0

_NERFSTUDIO_MODELS = {"OPENCV", "PINHOLE", "SIMPLE_PINHOLE"}
_INTRINSIC_KEYS = (
    "w",
    "h",
    "fl_x",
    "fl_y",
    "cx",
    "cy",
    "camera_angle_x",
    "camera_angle_y",
    "k1",
    "k2",
    "k3",
    "k4",
    "p1",
    "p2",
)


# ----------------------------------------------------------------------------------------------
# One camera, frames and their images.


def _check_c2w(matrix: Any, path: Path, what: str) -> np.ndarray:
    """Validates one camera-to-world matrix: [4, 4] numbers (no strings or booleans), finite, rigid.
    Returns it as float64."""
    m = numeric_array(matrix)
    if m is None:
        raise SceneFormatError(path, f"{what}: transform_matrix is not a 4x4 matrix of numbers")
    if m.shape != (4, 4):
        raise SceneFormatError(path, f"{what}: transform_matrix has shape {list(m.shape)}, expected 4x4")
    return check_rigid(m, path, what)


def _pad_box(lo: np.ndarray, hi: np.ndarray, fraction: float) -> np.ndarray:
    """[2, 3] float32 box grown by `fraction` of its size per side (at least 1e-3 of its diagonal)."""
    size = hi - lo
    pad = fraction * np.maximum(size, 1e-3 * max(float(np.linalg.norm(size)), 1e-6))
    return np.stack([lo - pad, hi + pad]).astype(np.float32)


def _camera_meta(meta: Dict[str, Any], frames: List[Dict[str, Any]], path: Path) -> Dict[str, Any]:
    """The single camera of a transforms file: top-level keys overridden by per-frame keys.

    Per-frame intrinsics are accepted only when every frame has the same values.
    """
    top = {k: meta[k] for k in _INTRINSIC_KEYS if k in meta}
    for i, frame in enumerate([meta, *frames]):  # every intrinsic is a number (or null), named where it is
        for key in _INTRINSIC_KEYS:  # found; its range is checked once merged (`_json_intrinsics`)
            value = frame.get(key)
            if value is not None and (isinstance(value, bool) or not isinstance(value, (int, float))):
                where = f"frame {i - 1}: " if i else ""
                raise SceneFormatError(path, f"{where}{key!r} must be a finite number, got {value_text(value)}")
    if not any(k in f for f in frames for k in _INTRINSIC_KEYS):
        return top
    first = None
    for i, frame in enumerate(frames):
        merged = {**top, **{k: frame[k] for k in _INTRINSIC_KEYS if k in frame}}
        if first is None:
            first = merged
        elif merged != first:
            diff = sorted(k for k in set(first) | set(merged) if first.get(k) != merged.get(k))
            shown = ", ".join(f"{k}: {first.get(k)!r} vs {merged.get(k)!r}" for k in diff[:3])
            raise SceneFormatError(
                path,
                f"per-frame intrinsics differ between frame 0 and frame {i} ({shown}): "
                "scenes with several cameras are not supported",
            )
    return first


def _json_intrinsics(camera: Dict[str, Any], image_size: Tuple[int, int], path: Path) -> Intrinsics:
    """Intrinsics of a transforms file at the size of its images on disk."""
    width, height = image_size
    w = number(camera, "w", path, positive=True) or float(width)
    h = number(camera, "h", path, positive=True) or float(height)
    if min(w, h) < 1:
        raise SceneFormatError(path, f"'w' x 'h' = {w:g}x{h:g}: image sides must be at least 1 pixel")
    fl_x = number(camera, "fl_x", path, positive=True)
    fl_y = number(camera, "fl_y", path, positive=True)
    angle_x = number(camera, "camera_angle_x", path)
    angle_y = number(camera, "camera_angle_y", path)
    try:
        if fl_x is None and angle_x is not None:
            fl_x = focal_from_angle(angle_x, w, "'camera_angle_x'")
        if fl_y is None and angle_y is not None:
            fl_y = focal_from_angle(angle_y, h, "'camera_angle_y'")
    except NumberError as e:
        raise SceneFormatError(path, str(e)) from None
    if fl_x is None:
        fl_x = fl_y
    if fl_x is None:
        raise SceneFormatError(path, "no focal length: need 'fl_x' or 'camera_angle_x'")
    if fl_x <= 0 or (fl_y is not None and fl_y <= 0):
        raise SceneFormatError(path, f"focal length must be positive, got fl_x={fl_x}, fl_y={fl_y}")
    for key in ("k3", "k4"):
        if (number(camera, key, path) or 0.0) != 0.0:
            raise SceneFormatError(path, f"distortion coefficient {key} is not supported (only k1, k2, p1, p2)")
    distortion = [number(camera, k, path) or 0.0 for k in ("k1", "k2", "p1", "p2")]
    intrinsics = Intrinsics.create(
        int(round(w)), int(round(h)), fl_x, fl_y, number(camera, "cx", path), number(camera, "cy", path), distortion
    )
    if (intrinsics.width, intrinsics.height) != (width, height):
        if abs(width / height - w / h) > 0.01 * (w / h):
            raise SceneFormatError(
                path, f"images are {width}x{height} but the file describes {w:g}x{h:g} (another aspect ratio)"
            )
        intrinsics = intrinsics.scaled(width, height)
    return intrinsics


def _read_frames(meta: Dict[str, Any], path: Path) -> List[Dict[str, Any]]:
    """The validated frames list: non-empty, each with `file_path` and a rigid `transform_matrix`."""
    frames = field(meta, "frames", path, "list")
    if frames is None:
        raise SceneFormatError(path, "no 'frames' list")
    if not frames:
        raise SceneFormatError(path, "no frames: 'frames' is empty")
    for i, frame in enumerate(frames):
        if not isinstance(frame, dict):
            raise SceneFormatError(path, f"frame {i} is not an object")
        for key in ("file_path", "transform_matrix"):
            if key not in frame:
                raise SceneFormatError(path, f"frame {i} has no '{key}'")
        name = field(frame, "file_path", path, "string", where=f"frame {i}")
        problem = file_name_problem(name)
        if problem:
            raise SceneFormatError(path, f"frame {i}: 'file_path' {problem}")
        frame["_c2w"] = _check_c2w(frame["transform_matrix"], path, f"frame {i}")
        frame["_index"] = i
    return frames


def _existing_frames(
    frames: List[Dict[str, Any]], folder: Path, path: Path
) -> Tuple[List[Tuple[Dict[str, Any], Path]], int]:
    """Frames whose image exists (with its path) and the number skipped, warning once."""
    found = []
    missing = []
    for frame in frames:
        image = resolve_image(folder, frame["file_path"])  # refuses a folder, a FIFO, a link loop by name
        if image is None:
            missing.append(frame["file_path"])
        else:
            found.append((frame, image))
    if not found:
        raise SceneFormatError(
            path, f"none of the {len(frames)} image files listed exist (first: {shown(folder / missing[0])})"
        )
    if missing:
        warnings.warn(
            f"{shown(path)}: skipped {len(missing)} of {len(frames)} frames whose image file is missing (first: "
            f"{shown(missing[0])})",
            stacklevel=4,
        )
    _warn_shared_images(found, path)
    return found, len(missing)


def _warn_shared_images(found: List[Tuple[Dict[str, Any], Path]], path: Path) -> None:
    """Warns once when frames name the same image file: one photo then trains, or judges, several poses."""
    users: Dict[Path, int] = {}
    for _, image in found:
        key = image.resolve()
        users[key] = users.get(key, 0) + 1
    shared = {image: n for image, n in users.items() if n > 1}
    if shared:
        first = next(iter(shared))
        warnings.warn(
            f"{shown(path)}: {sum(shared.values())} of {len(found)} frames share {len(shared)} image files "
            f"(first: {shown(first)}, named by {shared[first]} frames): each is one photo for several poses",
            stacklevel=5,
        )


def _camera_box(c2w_all: np.ndarray) -> Tuple[np.ndarray, str]:
    """(box, its source) of the camera origins and their focus, padded by `ORIGIN_PAD`; cameras that all
    lie at one point (a panorama) span no box: a cube of side `ONE_POINT_CUBE` around them instead (the
    loader warns that they give no parallax)."""
    origins = np.concatenate([c2w_all[:, :3, 3], camera_focus(c2w_all)[None]])
    lo, hi = origins.min(0), origins.max(0)
    if float(np.max(hi - lo)) <= 1e-6 * max(1.0, float(np.max(np.abs(origins)))):
        centre = 0.5 * (lo + hi)
        half = 0.5 * ONE_POINT_CUBE
        box = np.stack([centre - half, centre + half]).astype(np.float32)
        return box, f"a cube of side {ONE_POINT_CUBE:g} around the cameras (they all lie at one point)"
    return _pad_box(lo, hi, ORIGIN_PAD), "camera origins and focus"


def _nerfstudio_box(
    meta: Dict[str, Any], folder: Path, path: Path, c2w_all: np.ndarray
) -> Tuple[np.ndarray, Dict[str, Any]]:
    """(box, metadata) of a nerfstudio scene: the padded percentile box of its point cloud
    (`ply_file_path`, else `sparse_pc.ply` where there is one), else the cameras' (`_camera_box`).

    A `ply_file_path` that names no file warns and falls back to the cameras; a folder, a FIFO or a link
    loop is refused. Points on a line or a plane give a box without thickness: it warns and takes the
    union with the cameras' box (every side at least `FALLBACK_BOX_SIDE_RATIO` of the longest).
    """
    named = "ply_file_path" in meta
    name = field(meta, "ply_file_path", path, "string", default="sparse_pc.ply")
    problem = file_name_problem(name)
    if problem:
        raise SceneFormatError(path, f"'ply_file_path' {problem}")
    ply = folder / name
    if not os.path.lexists(ply):
        box, source = _camera_box(c2w_all)
        if named:
            warnings.warn(
                f"{shown(path)}: 'ply_file_path' names {shown(ply)}, which does not exist; the scene box comes from "
                f"the {source}",
                stacklevel=4,
            )
        return box, {"aabb_source": source}
    points = read_ply_points(input_file(ply, "point cloud (PLY file)"))
    if len(points) == 0:
        raise SceneFormatError(shown(ply), "PLY file has no vertices")
    lo, hi = np.percentile(points, PLY_PERCENTILES, axis=0)
    spread = float(np.linalg.norm(hi - lo))
    if not spread > 1e-6 * max(1.0, float(np.linalg.norm(lo))):  # all at one spot: no box to march
        raise SceneFormatError(
            shown(ply),
            f"its {len(points)} points lie at one spot ({np.round(lo, 6).tolist()}), so they give "
            f"{shown(path.name)} no scene box; remove the file (the cameras then bound the scene) or add points",
        )
    source = relative(ply, folder)
    metadata = {"aabb_source": source, "ply_points": int(len(points))}
    sides = hi - lo
    if float(sides.min()) < MIN_BOX_SIDE_RATIO * float(sides.max()):  # on a line or a plane
        camera_box, camera_source = _camera_box(c2w_all)
        lo, hi = np.minimum(lo, camera_box[0]), np.maximum(hi, camera_box[1])
        grow = np.maximum(FALLBACK_BOX_SIDE_RATIO * float(np.max(hi - lo)) - (hi - lo), 0.0)
        lo, hi = lo - 0.5 * grow, hi + 0.5 * grow
        axes = "".join(a for a, side in zip("xyz", sides) if side < MIN_BOX_SIDE_RATIO * float(sides.max()))
        warnings.warn(
            f"{shown(ply)}: its {len(points)} points lie on a line or a plane (the box of their 1st-99th "
            f"percentiles is {float(sides.min()):.3g} thick along {axes}, {float(sides.max()):.3g} long); the scene "
            f"box joins the {camera_source}",
            stacklevel=4,
        )
        metadata["aabb_source"] = f"{source} and {camera_source} (its points lie on a line or a plane)"
    return _pad_box(lo, hi, PLY_PAD), metadata


# ----------------------------------------------------------------------------------------------
# Format loaders. Each returns the keyword arguments of `Scene` it knows.


def load_transforms(
    folder: Path,
    fmt: str,
    path: Path,
    meta: Dict[str, Any],
    split: Optional[str],
    factor: Optional[float],
    background: np.ndarray,
    max_images: Optional[int],
) -> Dict[str, Any]:
    """instant-ngp and nerfstudio transforms.json: OpenGL c2w, one camera."""
    check_split(split, SPLITS)
    split = split or "all"
    check_holdout_split(split, fmt, path)
    frames = _read_frames(meta, path)
    camera = _camera_meta(meta, frames, path)
    metadata: Dict[str, Any] = {"scene_file": relative(path, folder)}
    if fmt == "nerfstudio":
        model = field(meta, "camera_model", path, "string", default="OPENCV")
        if model not in _NERFSTUDIO_MODELS:
            raise SceneFormatError(
                path, f"unsupported camera_model {model!r} (supported: {', '.join(sorted(_NERFSTUDIO_MODELS))})"
            )
        metadata["camera_model"] = model
    try:  # what a nerfstudio model of this file folds into its dataparser_transforms.json
        applied, applied_scale, applied_source = nerfstudio_applied(meta, folder)
    except ValueError as e:
        raise SceneFormatError(path, str(e)) from None
    metadata["nerfstudio_applied"] = {
        "transform": None if applied is None else applied.tolist(),
        "scale": applied_scale,
        "source": applied_source,
    }
    applied = None if applied is None else applied.astype(np.float32)
    ngp = NgpFrame()
    if fmt == "instant-ngp":
        try:
            ngp = ngp_frame(meta)
        except ValueError as e:
            raise SceneFormatError(path, str(e)) from None
        if ngp.from_mitsuba:  # Mitsuba's camera axes (x left, y up, z forward) -> OpenGL's
            for frame in frames:
                frame["_c2w"] = frame["_c2w"] @ MITSUBA_TO_OPENGL
    found, skipped = _existing_frames(frames, folder, path)
    found.sort(key=lambda fi: natural_key(fi[0]["file_path"]))
    index = subsample(holdout(len(found), split), max_images)
    chosen = [found[i] for i in index]
    if not chosen:
        raise SceneFormatError(path, f"split {split!r} is empty ({len(found)} images in all)")
    images, alphas, full = load_images([p for _, p in chosen], factor or 1.0, background)
    intrinsics = _json_intrinsics(camera, full, path)
    intrinsics = intrinsics.scaled(images.shape[2], images.shape[1])
    c2w_all = np.stack([f["_c2w"] for f, _ in found])

    if fmt == "instant-ngp":
        aabb_scale = number(meta, "aabb_scale", path)
        aabb_scale = 1.0 if aabb_scale is None else aabb_scale
        if aabb_scale <= 0:
            raise SceneFormatError(
                path, f"'aabb_scale' and 'scale' must be positive, got {aabb_scale:g} and {ngp.scale:g}"
            )
        # NGP marches in the cube 0.5 +- aabb_scale / 2 of its frame; the cube is symmetric under NGP's
        # axis cycle, so its world box is (cube - offset) / scale per axis.
        offset_vec = np.asarray(ngp.offset, np.float64)
        ngp_lo, ngp_hi = 0.5 - 0.5 * aabb_scale, 0.5 + 0.5 * aabb_scale
        corners = (np.stack([np.full(3, ngp_lo), np.full(3, ngp_hi)]) - offset_vec) / ngp.scale
        aabb = np.stack([corners.min(0), corners.max(0)]).astype(np.float32)
        metadata.update(
            aabb_scale=aabb_scale,
            scale=ngp.scale,
            offset=offset_vec.tolist(),
            from_mitsuba=ngp.from_mitsuba,
            ngp_aabb=[[ngp_lo] * 3, [ngp_hi] * 3],
        )
    else:
        aabb, box_metadata = _nerfstudio_box(meta, folder, path, c2w_all)
        metadata.update(box_metadata)
    near, far = camera_bounds(c2w_all, aabb)
    metadata["distortion"] = [float(v) for v in np.asarray(intrinsics.distortion)]
    return dict(
        images=images,
        alphas=alphas,
        original_size=full,
        intrinsics=intrinsics,
        c2w=np.stack([f["_c2w"] for f, _ in chosen]),
        aabb=aabb,
        near=near,
        far=far,
        file_names=tuple(relative(p, folder) for _, p in chosen),
        split=split,
        skipped_missing=skipped,
        applied_transform=applied,
        metadata=metadata,
    )


def load_blender(
    folder: Path,
    path: Path,
    split: Optional[str],
    factor: Optional[float],
    background: np.ndarray,
    max_images: Optional[int],
) -> Dict[str, Any]:
    """Blender transforms_{train,val,test}.json: camera_angle_x, RGBA PNGs."""
    check_split(split, SPLITS)
    split = split or blender_split_of(path.name) or "train"
    names = BLENDER_SPLITS if split == "all" else (split,)
    files = [folder / f"transforms_{s}.json" for s in names]
    if split == "all":
        files = [f for f in files if os.path.lexists(f)]
    elif not os.path.lexists(files[0]):
        present = [s for s in BLENDER_SPLITS if os.path.lexists(folder / f"transforms_{s}.json")]
        raise SceneFormatError(files[0], f"no such file: this Blender scene has splits {', '.join(present)}")
    for file in files:  # a split file that is a FIFO, a folder or a link loop is named as such
        input_file(file, "Blender split file")
    frames: List[Dict[str, Any]] = []
    camera = None
    for file in files:
        meta = read_json(file)
        file_frames = _read_frames(meta, file)
        this_camera = _camera_meta(meta, file_frames, file)
        if camera is not None and this_camera != camera:
            raise SceneFormatError(file, f"camera differs from {files[0].name}: {this_camera} vs {camera}")
        camera = this_camera
        frames.extend(file_frames)
    found, skipped = _existing_frames(frames, folder, files[0] if len(files) == 1 else folder)
    chosen = [found[i] for i in subsample(np.arange(len(found)), max_images)]
    images, alphas, full = load_images([p for _, p in chosen], factor or 1.0, background)
    intrinsics = _json_intrinsics(camera, full, files[0]).scaled(images.shape[2], images.shape[1])
    return dict(
        images=images,
        alphas=alphas,
        original_size=full,
        intrinsics=intrinsics,
        c2w=np.stack([f["_c2w"] for f, _ in chosen]),
        aabb=np.asarray(BLENDER_AABB, np.float32),
        near=BLENDER_NEAR,
        far=BLENDER_FAR,
        file_names=tuple(relative(p, folder) for _, p in chosen),
        split=split,
        skipped_missing=skipped,
        applied_transform=None,
        metadata={"scene_file": [relative(f, folder) for f in files]},
    )
