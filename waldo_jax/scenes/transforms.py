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
    check_rigid,
    check_split,
    focal_from_angle,
    holdout,
    natural_key,
    number,
    read_json,
    relative,
    subsample,
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
    """Validates one camera-to-world matrix: [4, 4], finite, rigid. Returns it as float64."""
    try:
        m = np.asarray(matrix, dtype=np.float64)
    except (TypeError, ValueError, OverflowError):
        raise SceneFormatError(path, f"{what}: transform_matrix is not a 4x4 matrix of numbers") from None
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
    frames = meta.get("frames")
    if frames is None:
        raise SceneFormatError(path, "no 'frames' list")
    if not isinstance(frames, list):
        raise SceneFormatError(path, f"'frames' must be a list, got {type(frames).__name__}")
    if not frames:
        raise SceneFormatError(path, "no frames: 'frames' is empty")
    for i, frame in enumerate(frames):
        if not isinstance(frame, dict):
            raise SceneFormatError(path, f"frame {i} is not an object")
        for key in ("file_path", "transform_matrix"):
            if key not in frame:
                raise SceneFormatError(path, f"frame {i} has no '{key}'")
        if not isinstance(frame["file_path"], str) or not frame["file_path"]:
            raise SceneFormatError(path, f"frame {i}: 'file_path' must be a non-empty string")
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
        image = resolve_image(folder, frame["file_path"])
        if image is None:
            missing.append(frame["file_path"])
        else:
            found.append((frame, image))
    if not found:
        first = folder / missing[0]
        raise SceneFormatError(
            path,
            f"none of the {len(frames)} image files listed exist (first: {first}"
            + (", a directory)" if first.is_dir() else ")"),
        )
    if missing:
        directories = [m for m in missing if (folder / m).is_dir()]
        what = f"; {folder / directories[0]} is a directory" if directories else ""
        warnings.warn(
            f"{path}: skipped {len(missing)} of {len(frames)} frames whose image file is missing (first: "
            f"{missing[0]}{what})",
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
            f"{path}: {sum(shared.values())} of {len(found)} frames share {len(shared)} image files (first: {first}, "
            f"named by {shared[first]} frames): each is one photo for several poses",
            stacklevel=5,
        )


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
    frames = _read_frames(meta, path)
    camera = _camera_meta(meta, frames, path)
    metadata: Dict[str, Any] = {"scene_file": relative(path, folder)}
    if fmt == "nerfstudio":
        model = meta.get("camera_model", "OPENCV")
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
        ply_name = meta.get("ply_file_path", "sparse_pc.ply")
        ply = folder / ply_name if isinstance(ply_name, str) else None
        if ply is not None and ply.is_file():
            points = read_ply_points(ply)
            if len(points) == 0:
                raise SceneFormatError(ply, "PLY file has no vertices")
            lo, hi = np.percentile(points, PLY_PERCENTILES, axis=0)
            aabb = _pad_box(lo, hi, PLY_PAD)
            spread = float(np.linalg.norm(hi - lo))
            if not spread > 1e-6 * max(1.0, float(np.linalg.norm(lo))):  # all at one spot: no box to march
                raise SceneFormatError(
                    ply,
                    f"its {len(points)} points lie at one spot ({np.round(lo, 6).tolist()}), so they give "
                    f"{path.name} no scene box; remove the file (the cameras then bound the scene) or add points",
                )
            metadata.update(aabb_source=relative(ply, folder), ply_points=int(len(points)))
        else:
            origins = np.concatenate([c2w_all[:, :3, 3], camera_focus(c2w_all)[None]])
            aabb = _pad_box(origins.min(0), origins.max(0), ORIGIN_PAD)
            metadata["aabb_source"] = "camera origins and focus"
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
        files = [f for f in files if f.is_file()]
    elif not files[0].is_file():
        present = [s for s in BLENDER_SPLITS if (folder / f"transforms_{s}.json").is_file()]
        raise SceneFormatError(files[0], f"no such file: this Blender scene has splits {', '.join(present)}")
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
