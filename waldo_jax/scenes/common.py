"""What every scene format shares: format names, argument and pose checks, splits and bounds.

`locate` finds a scene's format and file; `check_rigid` holds every pose to the conventions of
`waldo_jax.types` (finite, rotation orthonormal with det +1, origin within `MAX_COORDINATE`);
`camera_bounds` gives near/far that cover a box; `holdout` and `subsample` pick a split's images.
`number` reads a file's number for float32 use, `focal_from_angle` turns a field of view into a
focal length, and `intrinsics_problem` says what makes a camera unusable (every loader, poses file
and checkpoint asks it). Problems with files raise `SceneFormatError(path, problem)`, bad arguments
`SceneArgumentError`.
See docs/design.md, "Scenes".
"""

from __future__ import annotations

import math
import os
import re
import warnings
from pathlib import Path
from typing import Any, Dict, List, Optional, Sequence, Tuple

import numpy as np

from waldo_jax.io import read_json_file
from waldo_jax.errors import MAX_RESOLUTION, MIN_RESOLUTION, NumberError, SceneFormatError, WaldoError, check_float32
from waldo_jax.types import Intrinsics

__all__ = [
    "FORMATS",
    "SPLITS",
    "BLENDER_SPLITS",
    "RIGID_TOL",
    "MAX_COORDINATE",
    "TEST_EVERY",
    "MIN_NEAR_FRACTION",
    "SceneArgumentError",
    "read_json",
    "blender_split_of",
    "locate",
    "detect_format",
    "check_rigid",
    "check_origin",
    "camera_bounds",
    "check_split",
    "holdout",
    "subsample",
    "natural_key",
    "relative",
    "number",
    "focal_from_angle",
    "intrinsics_problem",
    "extent_problem",
    "MIN_FIELD_OF_VIEW",
    "MAX_FIELD_OF_VIEW",
    "MAX_RAY_SLOPE",
    "warn_off_image_principal_point",
]

FORMATS = ("instant-ngp", "nerfstudio", "blender", "llff")
SPLITS = ("all", "train", "val", "test")
BLENDER_SPLITS = ("train", "val", "test")

RIGID_TOL = 1e-3  # max |R^T R - I| and |bottom row - (0,0,0,1)| of a pose.
# Largest |coordinate| of a camera origin or scene box: geometry runs in float32, where squared
# distances of larger coordinates lose all precision (and 1e20 overflows). Rescale such scenes.
MAX_COORDINATE = 1e6
TEST_EVERY = 8  # hold-out stride of formats without splits (NeRF's `llffhold`).
MIN_NEAR_FRACTION = 0.02
# A pinhole camera's field of view (degrees, per axis, from its focal length and image side): near 180
# the focal length is ~0 and every ray leaves the image plane sideways (renders come out blank); near
# 0 every pixel sees the same ray.
MIN_FIELD_OF_VIEW, MAX_FIELD_OF_VIEW = 1e-3, 179.0
# Largest |x - c| / f of a pixel (x) from a principal point (c): the squared ray direction must stay
# finite in float32. An off-image principal point below it is legal (and warned about).
MAX_RAY_SLOPE = 1e6

_NERFSTUDIO_KEYS = ("camera_model", "applied_transform")


class SceneArgumentError(WaldoError, ValueError):
    """An argument of `load_scene` (split, downscale, background, max_images) is invalid."""


# ----------------------------------------------------------------------------------------------
# Format detection.


def read_json(path: Path) -> Dict[str, Any]:
    """Parses a JSON object, turning every failure into a `SceneFormatError` naming the file."""
    data = read_json_file(path, "JSON file", lambda problem: SceneFormatError(path, problem))
    if not isinstance(data, dict):
        raise SceneFormatError(path, f"expected a JSON object at the top level, got {type(data).__name__}")
    return data


def _transforms_kind(meta: Dict[str, Any]) -> str:
    """nerfstudio when the nerfstudio-only keys are present, else instant-ngp."""
    return "nerfstudio" if any(k in meta for k in _NERFSTUDIO_KEYS) else "instant-ngp"


def blender_split_of(name: str) -> Optional[str]:
    """ "train" for "transforms_train.json", None for other names."""
    m = re.fullmatch(r"transforms_(train|val|test)\.json", name)
    return m.group(1) if m else None


def locate(path: str | os.PathLike) -> Tuple[Path, str, Path, Optional[Dict[str, Any]]]:
    """Resolves a folder or scene file to (folder, format, scene file, parsed JSON or None)."""
    path = Path(path).expanduser()
    if not path.exists():
        if os.path.islink(path):  # exists() follows links: a loop or a dangling link is not "missing"
            raise SceneFormatError(path, "a symbolic link that leads nowhere (a loop or a missing target)")
        raise SceneFormatError(path, "no such file or folder")
    if path.is_dir():
        folder = path
        transforms = folder / "transforms.json"
        if transforms.is_file():
            meta = read_json(transforms)
            return folder, _transforms_kind(meta), transforms, meta
        for split in BLENDER_SPLITS:
            candidate = folder / f"transforms_{split}.json"
            if candidate.is_file():
                return folder, "blender", candidate, None
        poses = folder / "poses_bounds.npy"
        if poses.is_file():
            return folder, "llff", poses, None
        raise SceneFormatError(
            folder,
            "unknown scene format: the folder holds none of transforms.json, "
            "transforms_{train,val,test}.json, poses_bounds.npy",
        )
    folder = path.parent
    if path.name == "poses_bounds.npy":
        return folder, "llff", path, None
    if blender_split_of(path.name):
        return folder, "blender", path, None
    if path.suffix.lower() == ".json":
        meta = read_json(path)
        if "frames" in meta:
            return folder, _transforms_kind(meta), path, meta
        raise SceneFormatError(path, "unknown scene format: a JSON file without 'frames'")
    raise SceneFormatError(
        path,
        "unknown scene format: expected a scene folder, transforms.json, "
        "transforms_{train,val,test}.json or poses_bounds.npy",
    )


def detect_format(path: str | os.PathLike) -> str:
    """Names the format of a scene folder or scene file.

    Args:
      path: a scene folder, or its `transforms.json`, `transforms_<split>.json` or `poses_bounds.npy`.

    Returns:
      One of `FORMATS`: "instant-ngp", "nerfstudio", "blender" or "llff".

    Raises:
      SceneFormatError: the path is missing, unreadable, or in no known format.
    """
    return locate(path)[1]


# ----------------------------------------------------------------------------------------------
# Poses and bounds.


def check_rigid(m: np.ndarray, path: Path, what: str) -> np.ndarray:
    """Checks finiteness, orthonormal rotation with det +1 and a (0, 0, 0, 1) bottom row."""
    if not np.all(np.isfinite(m)):
        raise SceneFormatError(path, f"{what}: pose has non-finite values (NaN or inf)")
    rotation = m[:3, :3]
    ortho_err = float(np.max(np.abs(rotation.T @ rotation - np.eye(3))))
    det = float(np.linalg.det(rotation))
    if ortho_err > RIGID_TOL or det < 0:
        raise SceneFormatError(
            path,
            f"{what}: pose is not rigid (rotation part not orthonormal with det +1: "
            f"max |R^T R - I| = {ortho_err:.3g}, det = {det:.4g})",
        )
    if m.shape == (4, 4) and float(np.max(np.abs(m[3] - (0.0, 0.0, 0.0, 1.0)))) > RIGID_TOL:
        raise SceneFormatError(path, f"{what}: pose bottom row is {m[3].tolist()}, expected [0, 0, 0, 1]")
    check_origin(m, path, what)
    return m


def check_origin(m: np.ndarray, path: Path, what: str) -> None:
    """Refuses a camera origin with a coordinate beyond `MAX_COORDINATE`."""
    largest = float(np.max(np.abs(m[:3, 3])))
    if largest > MAX_COORDINATE:
        raise SceneFormatError(
            path,
            f"{what}: camera origin has a coordinate of {largest:.6g}, beyond the {MAX_COORDINATE:g} "
            "that float32 geometry handles (rescale the scene)",
        )


def camera_bounds(
    c2w: np.ndarray, aabb: np.ndarray, min_near_fraction: float = MIN_NEAR_FRACTION
) -> Tuple[float, float]:
    """Ray-distance bounds that cover a box from every camera.

    Args:
      c2w: [N, 4, 4] (or [N, 3, 4]) camera-to-world matrices.
      aabb: [2, 3] box (min corner, max corner), world units.
      min_near_fraction: near is at least this fraction of far (cameras inside the box).

    Returns:
      (near, far): near = smallest camera-to-box distance (clamped as above); far = largest
      camera-to-box-corner distance. World units.
    """
    origins = np.asarray(c2w, np.float64)[:, :3, 3]
    lo, hi = np.asarray(aabb, np.float64)
    corners = np.stack(np.meshgrid(*zip(lo, hi), indexing="ij"), -1).reshape(-1, 3)  # [8, 3]
    far = float(np.linalg.norm(origins[:, None, :] - corners[None], axis=-1).max())
    outside = np.maximum(np.maximum(lo - origins, origins - hi), 0.0)  # [N, 3]
    near = float(np.linalg.norm(outside, axis=-1).min())
    return max(near, min_near_fraction * far), far


# ----------------------------------------------------------------------------------------------
# Splits, file names, numbers, warnings.


def check_split(split: Any, allowed: Sequence[str]) -> None:
    """Raises `SceneArgumentError` unless `split` is None or one of `allowed`."""
    if split is not None and split not in allowed:
        raise SceneArgumentError(f"unknown split {split!r}: expected one of {', '.join(allowed)} (or None)")


def holdout(n: int, split: str) -> np.ndarray:
    """Indices of `split` among n sorted images: test = every TEST_EVERY-th, train = the rest."""
    index = np.arange(n)
    if split == "test":
        return index[index % TEST_EVERY == 0]
    if split == "train":
        return index[index % TEST_EVERY != 0]
    return index


def subsample(index: np.ndarray, max_images: Optional[int]) -> np.ndarray:
    """At most `max_images` of `index`, evenly spaced (first and last kept)."""
    if max_images is None or len(index) <= max_images:
        return index
    pick = np.unique(np.round(np.linspace(0, len(index) - 1, max_images)).astype(int))
    return index[pick]


def natural_key(text: str) -> List[Any]:
    """Sort key that orders "r_2" before "r_10"."""
    return [int(t) if t.isdigit() else t for t in re.split(r"(\d+)", text)]


def relative(path: Path, folder: Path) -> str:
    """`path` relative to `folder`, POSIX style."""
    return Path(os.path.relpath(path, folder)).as_posix()


def number(meta: Dict[str, Any], key: str, path: Path, positive: bool = False) -> Optional[float]:
    """meta[key] as a float that stays finite in float32 (and > 0 there if `positive`), None when absent."""
    if key not in meta or meta[key] is None:
        return None
    value = meta[key]
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise SceneFormatError(path, f"{key!r} must be a finite number, got {value!r}")
    try:
        return check_float32(value, repr(key), positive=positive)
    except NumberError as e:
        raise SceneFormatError(path, str(e)) from None


def focal_from_angle(angle: float, size: float, what: str, degrees: bool = False) -> float:
    """The focal length (pixels) of a field of view `angle` across `size` pixels: 0.5 size / tan(angle / 2).

    Raises:
      NumberError (a ValueError): the angle is not finite or not in (0, 180) degrees (0 divides by
        zero; 180 and beyond give a zero or negative focal length), or the focal length does not fit
        float32; the message names `what`.
    """
    limit = 180.0 if degrees else math.pi
    angle = check_float32(angle, what)
    if not 0 < angle < limit:
        raise NumberError(
            f"{what} must be a field of view between 0 and {limit:.6g} {'degrees' if degrees else 'radians'} "
            f"(exclusive), got {angle:g}"
        )
    radians = math.radians(angle) if degrees else angle
    return check_float32(0.5 * size / math.tan(0.5 * radians), f"the focal length of {what} = {angle:g}", positive=True)


def extent_problem(aabb: Any, near: Any, far: Any) -> Optional[str]:
    """What makes a scene box or ray bounds unusable, or None: a box [2, 3] that is not finite, lies
    beyond `MAX_COORDINATE` or is empty or flipped on an axis (its sides are divided by); near / far
    that are not 0 < near < far in float32 (far - near is divided by)."""
    try:
        box = np.asarray(aabb, np.float64).reshape(2, 3)
        near, far = float(near), float(far)
    except (TypeError, ValueError, OverflowError):
        return f"scene box {aabb!r} / near {near!r} / far {far!r} are not numbers of the right shape"
    if not (np.all(np.isfinite(box)) and np.max(np.abs(box)) <= MAX_COORDINATE):
        return f"scene box {_box_text(box)} is not finite or lies beyond {MAX_COORDINATE:g} (rescale the scene)"
    if not np.all(box[0].astype(np.float32) < box[1].astype(np.float32)):
        return f"scene box {_box_text(box)} is empty or flipped: its minimum corner must lie below its maximum"
    usable = math.isfinite(near) and math.isfinite(far) and 0 < near < far <= float(np.finfo(np.float32).max)
    if not (usable and 0 < np.float32(near) < np.float32(far)):
        return f"near/far bounds {near:g} / {far:g} do not satisfy 0 < near < far (in float32)"
    return None


def _box_text(box: np.ndarray) -> str:
    """[[x, y, z], [x, y, z]] with 6 significant digits."""
    return "[" + ", ".join("[" + ", ".join(f"{v:.6g}" for v in corner) + "]" for corner in box) + "]"


def intrinsics_problem(
    intrinsics: Intrinsics, sides: Optional[Tuple[int, int]] = (MIN_RESOLUTION, MAX_RESOLUTION)
) -> Optional[str]:
    """What makes a camera unusable, or None: image sides outside `sides` (None: any size >= 1), focal
    lengths that are not positive and finite in float32 or give a field of view outside
    [MIN_FIELD_OF_VIEW, MAX_FIELD_OF_VIEW], a principal point that is not finite or lies beyond
    MAX_RAY_SLOPE focal lengths, non-finite distortion. Reads the float32 values that render."""
    width, height = int(intrinsics.width), int(intrinsics.height)
    low, high = sides or (1, None)
    if min(width, height) < low or (high is not None and max(width, height) > high):
        limits = f"between {low} and {high}" if high is not None else f"at least {low}"
        return f"camera of {width}x{height} pixels: sides must lie {limits}"
    values = {k: float(np.asarray(getattr(intrinsics, k), np.float32)) for k in ("fx", "fy", "cx", "cy")}
    for key, size in (("fx", width), ("fy", height)):
        f = values[key]
        if not (math.isfinite(f) and f > 0):
            return f"focal length {key} = {f:g} px: must be a positive finite number"
        fov = math.degrees(2.0 * math.atan(0.5 * size / f))
        if not MIN_FIELD_OF_VIEW <= fov <= MAX_FIELD_OF_VIEW:
            return (
                f"focal length {key} = {f:g} px gives a {fov:.4g} degree field of view across {size} pixels; "
                f"a pinhole camera needs {MIN_FIELD_OF_VIEW:g} to {MAX_FIELD_OF_VIEW:g}"
            )
    for key, size, f in (("cx", width, values["fx"]), ("cy", height, values["fy"])):
        c = values[key]
        if not math.isfinite(c) or max(abs(c), abs(size - c)) / f > MAX_RAY_SLOPE:
            return (
                f"principal point {key} = {c:g} px: must be finite and within {MAX_RAY_SLOPE:g} focal lengths of "
                f"the image"
            )
    if not np.all(np.isfinite(np.asarray(intrinsics.distortion, np.float32))):
        return "distortion coefficients (k1, k2, p1, p2) must be finite float32 numbers"
    return None


def warn_off_image_principal_point(intrinsics: Intrinsics, path: Path) -> None:
    """Warns (naming `path`) when the principal point lies outside the image.

    stacklevel 4 names the caller of `load_scene` or `read_poses_file`: keep the call depth.
    """
    cx, cy = float(intrinsics.cx), float(intrinsics.cy)
    if not (0.0 <= cx <= intrinsics.width and 0.0 <= cy <= intrinsics.height):
        warnings.warn(
            f"{path}: principal point (cx, cy) = ({cx:g}, {cy:g}) lies outside the "
            f"{intrinsics.width}x{intrinsics.height} image; the cameras look far off their image centre",
            stacklevel=4,
        )
