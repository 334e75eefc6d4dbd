"""What every scene format shares: format names, argument and pose checks, splits and bounds.

`locate` finds a scene's format and file; `check_rigid` holds every pose to the conventions of
`waldo_jax.types` (finite, rotation orthonormal with det +1, origin within `MAX_COORDINATE`);
`camera_bounds` gives near/far that cover a box; `holdout` and `subsample` pick a split's images.
Problems with files raise `SceneFormatError(path, problem)`, bad arguments `SceneArgumentError`.
See docs/design.md, "Scenes".
"""

from __future__ import annotations

import json
import math
import os
import re
import warnings
from pathlib import Path
from typing import Any, Dict, List, Optional, Sequence, Tuple

import numpy as np

from waldo_jax.errors import SceneFormatError, WaldoError
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

_NERFSTUDIO_KEYS = ("camera_model", "applied_transform")


class SceneArgumentError(WaldoError, ValueError):
    """An argument of `load_scene` (split, downscale, background, max_images) is invalid."""


# ----------------------------------------------------------------------------------------------
# Format detection.


def read_json(path: Path) -> Dict[str, Any]:
    """Parses a JSON object, turning every failure into a `SceneFormatError` naming the file."""
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError as e:
        raise SceneFormatError(path, f"not UTF-8 text ({e.reason} at byte {e.start})") from None
    except OSError as e:
        raise SceneFormatError(path, f"cannot read file ({e.strerror or e})") from None
    try:
        data = json.loads(text)
    except json.JSONDecodeError as e:
        raise SceneFormatError(path, f"malformed JSON at line {e.lineno}, column {e.colno}: {e.msg}") from None
    if not isinstance(data, dict):
        raise SceneFormatError(path, f"expected a JSON object at the top level, got {type(data).__name__}")
    return data


def _transforms_kind(meta: Dict[str, Any]) -> str:
    """nerfstudio when the nerfstudio-only keys are present, else instant-ngp."""
    return "nerfstudio" if any(k in meta for k in _NERFSTUDIO_KEYS) else "instant-ngp"


def blender_split_of(name: str) -> Optional[str]:
    """"train" for "transforms_train.json", None for other names."""
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
            path, f"{what}: camera origin has a coordinate of {largest:.6g}, beyond the {MAX_COORDINATE:g} "
            "that float32 geometry handles (rescale the scene)")


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


def number(meta: Dict[str, Any], key: str, path: Path) -> Optional[float]:
    """meta[key] as a finite float, None when absent."""
    if key not in meta or meta[key] is None:
        return None
    value = meta[key]
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise SceneFormatError(path, f"{key!r} must be a finite number, got {value!r}")
    return float(value)


def warn_off_image_principal_point(intrinsics: Intrinsics, path: Path) -> None:
    """Warns (naming `path`) when the principal point lies outside the image.

    stacklevel 4 names the caller of `load_scene` or `read_poses_file`: keep the call depth.
    """
    cx, cy = float(intrinsics.cx), float(intrinsics.cy)
    if not (0.0 <= cx <= intrinsics.width and 0.0 <= cy <= intrinsics.height):
        warnings.warn(f"{path}: principal point (cx, cy) = ({cx:g}, {cy:g}) lies outside the "
                      f"{intrinsics.width}x{intrinsics.height} image; the cameras look far off their image centre",
                      stacklevel=4)
