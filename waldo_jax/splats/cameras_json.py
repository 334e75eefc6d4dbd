"""The reference 3DGS `cameras.json`, read and written, and where it lies beside a model.

`cameras.json` is a list of {id, img_name, width, height, position, rotation, fy, fx}: the camera
centre and the camera-to-world rotation in OpenCV axes (x right, y down, z forward), a pinhole with its
principal point at the image centre. We hold OpenGL c2w (`waldo_jax.types`): the same matrix with its y
and z columns negated. The reference layout puts it at the model root, beside
`point_cloud/iteration_<N>/point_cloud.ply`.
"""

from __future__ import annotations

import dataclasses
import math
import os
import re
import warnings
from pathlib import Path
from typing import Any, Optional, Sequence, Tuple

import numpy as np

from waldo_jax.errors import MAX_RESOLUTION, MIN_RESOLUTION, SceneFormatError, check_input_file, is_finite_number
from waldo_jax.io import read_json_file, write_json
from waldo_jax.scenes.common import check_rigid, value_text
from waldo_jax.types import Intrinsics

__all__ = [
    "SplatCameras",
    "read_cameras_json",
    "write_cameras_json",
    "iteration_of",
    "cameras_beside",
    "check_camera_aspect",
    "render_intrinsics",
]

# Focal lengths in pixels: below this, float32 projections lose all precision (and a tiny float64
# value flushes to 0); no camera of an image of MIN_RESOLUTION px or more has one (its FoV is 179.98 deg).
MIN_FOCAL = 1e-3

# The reference writes the photos' own size into cameras.json (5K and more for some captures); renders
# are made at --resolution (`Intrinsics.with_max_side`), so only sizes no camera has are refused.
MAX_CAMERA_SIDE = 65536
_FLOAT32_MAX = float(np.finfo(np.float32).max)
_ITERATION = re.compile(r"iteration_(\d+)")
_CAMERA_KEYS = ("width", "height", "position", "rotation", "fx", "fy")


@dataclasses.dataclass(frozen=True, eq=False)
class SplatCameras:
    """The cameras of a reference `cameras.json` (or a COLMAP model, a nerfstudio run:
    `waldo_jax.splats.cameras`), in waldo_jax's conventions.

    Attributes:
      c2w: float32 [N, 4, 4] camera-to-world matrices, OpenGL axes (x right, y up, z backward).
      intrinsics: N pinhole cameras; from cameras.json with the principal point at the image centre
        (cx = width / 2), from the other layouts where their files put it.
      names: N image names (cameras.json's `img_name`, usually without extension; the image names or
        file paths of the other layouts).
    """

    c2w: np.ndarray
    intrinsics: Tuple[Intrinsics, ...]
    names: Tuple[str, ...]

    def __len__(self) -> int:
        return int(self.c2w.shape[0])

    @property
    def shared_intrinsics(self) -> Optional[Intrinsics]:
        """The one camera all N share (size and focal lengths), else None."""
        first = self.intrinsics[0].to_dict()
        return self.intrinsics[0] if all(i.to_dict() == first for i in self.intrinsics[1:]) else None


def _numbers(value: Any, shape: Tuple[int, ...]) -> Optional[np.ndarray]:
    """`value` as float64 of `shape` when it is nested lists of JSON numbers, else None."""
    try:
        array = np.array(value, dtype=object)
    except (TypeError, ValueError, OverflowError):
        return None
    if array.shape != shape or not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in array.flat):
        return None
    return array.astype(np.float64)


def _camera_intrinsics(cam: dict, path: Path, what: str) -> Intrinsics:
    """The validated pinhole of one cameras.json entry."""
    sides = []
    for key in ("width", "height"):
        v = cam[key]
        if (
            isinstance(v, bool)
            or not isinstance(v, (int, float))
            or not float(v).is_integer()
            or not MIN_RESOLUTION <= v <= MAX_CAMERA_SIDE
        ):
            raise SceneFormatError(
                path,
                f"{what}: {key} must be a whole number of pixels between {MIN_RESOLUTION} and "
                f"{MAX_CAMERA_SIDE}, got {v!r}",
            )
        sides.append(int(v))
    focal = []
    for key in ("fx", "fy"):
        v = cam[key]
        if not is_finite_number(v) or not MIN_FOCAL <= v < _FLOAT32_MAX:
            raise SceneFormatError(
                path,
                f"{what}: {key} must be a finite focal length of at least {MIN_FOCAL:g} pixels, got {value_text(v)}",
            )
        focal.append(float(v))
    return check_camera_aspect(Intrinsics.create(sides[0], sides[1], focal[0], focal[1]), path, what)


def check_camera_aspect(intrinsics: Intrinsics, path: Path, what: str) -> Intrinsics:
    """`intrinsics` when some render size keeps both its sides in [MIN_RESOLUTION, MAX_RESOLUTION] (renders
    are the camera scaled to a longer side of at most MAX_RESOLUTION); else a SceneFormatError naming the
    file and the camera (8 x 65536 pixels is 1 pixel wide at any render size)."""
    short, long = sorted((intrinsics.width, intrinsics.height))
    if short * MAX_RESOLUTION < MIN_RESOLUTION * long:
        raise SceneFormatError(
            path,
            f"{what}: an image of {intrinsics.width}x{intrinsics.height} pixels (aspect {long / short:.4g}:1): "
            f"renders, at most {MAX_RESOLUTION} px on the longer side, would be under {MIN_RESOLUTION} px on the "
            f"shorter (at most {MAX_RESOLUTION // MIN_RESOLUTION}:1 is rendered)",
        )
    return intrinsics


def render_intrinsics(intrinsics: Intrinsics, side: int, path: Path, what: str) -> Intrinsics:
    """The camera scaled to a longer side of `side` pixels (`Intrinsics.with_max_side`); a SceneFormatError
    naming `path` and the camera `what` when its shorter side then falls below MIN_RESOLUTION (the render size
    the file's camera gives, not one to clamp silently)."""
    scaled = intrinsics.with_max_side(int(side))
    short, long = sorted((intrinsics.width, intrinsics.height))
    if min(scaled.width, scaled.height) < MIN_RESOLUTION:
        raise SceneFormatError(
            path,
            f"{what}: an image of {intrinsics.width}x{intrinsics.height} pixels renders at {scaled.width}x"
            f"{scaled.height} for a longer side of {side}, under {MIN_RESOLUTION} px on the shorter side: pass a "
            f"larger --resolution (at least {math.ceil(MIN_RESOLUTION * long / short)})",
        )
    return scaled


def read_cameras_json(path: str | os.PathLike) -> SplatCameras:
    """Reads a reference 3DGS `cameras.json` (written by its `camera_to_JSON`).

    Each entry's `rotation` (3x3, rows as written) and `position` form the camera-to-world matrix in
    OpenCV axes; its y and z columns are negated to give our OpenGL c2w. The principal point is the
    image centre (the reference renders a centred pinhole). `id` is not used: the cameras keep the
    file's order.

    Args:
      path: the JSON file.

    Returns:
      `SplatCameras` (c2w float32 [N, 4, 4] OpenGL, N `Intrinsics`, N names).

    Raises:
      DataNotFoundError: no such file.
      SceneFormatError: (naming the file and the camera index) not JSON, not a non-empty list of
        objects, a missing key, a size outside [MIN_RESOLUTION, MAX_CAMERA_SIDE], a focal length not
        finite or below MIN_FOCAL, a non-finite or non-rigid pose, an origin beyond MAX_COORDINATE.
    """
    path = check_input_file(path, "cameras file")
    entries = read_json_file(path, "cameras file", lambda problem: SceneFormatError(path, problem))
    if not isinstance(entries, list) or not entries:
        raise SceneFormatError(path, "expected a non-empty JSON list of cameras (3DGS cameras.json)")
    poses, intrinsics, names = [], [], []
    for i, cam in enumerate(entries):
        what = f"camera {i}"
        if not isinstance(cam, dict):
            raise SceneFormatError(path, f"{what} is not a JSON object")
        if isinstance(cam.get("img_name"), str):
            what += f" ({cam['img_name']!r})"
        missing = [k for k in _CAMERA_KEYS if k not in cam]
        if missing:
            raise SceneFormatError(path, f"{what} lacks {', '.join(missing)}")
        intrinsics.append(_camera_intrinsics(cam, path, what))
        position, rotation = _numbers(cam["position"], (3,)), _numbers(cam["rotation"], (3, 3))
        if position is None or rotation is None:
            key = "position" if position is None else "rotation"
            raise SceneFormatError(path, f"{what}: {key} must be {'3' if position is None else '3x3'} numbers")
        c2w = np.eye(4)
        c2w[:3, :3], c2w[:3, 3] = rotation, position
        check_rigid(c2w, path, what)
        c2w[:3, 1:3] *= -1.0  # OpenCV (y down, z forward) -> OpenGL (y up, z backward)
        poses.append(c2w)
        names.append(str(cam.get("img_name", i)))
    return SplatCameras(np.stack(poses).astype(np.float32), tuple(intrinsics), tuple(names))


def write_cameras_json(path: str | os.PathLike, c2w, intrinsics, names: Sequence[str]) -> Path:
    """Writes cameras as a reference 3DGS `cameras.json`, atomically.

    The format holds a centred pinhole only: a principal point off the image centre or a distortion
    is dropped, with a warning.

    Args:
      path: the JSON file (its folder is created).
      c2w: [N, 4, 4] or [N, 3, 4] camera-to-world matrices, OpenGL axes.
      intrinsics: one `Intrinsics` for all cameras, or N of them.
      names: N image names (`img_name`).

    Returns:
      `path` as a Path.

    Raises:
      ValueError: the numbers of matrices, intrinsics and names differ.
      SceneFormatError: a pose is not finite and rigid (naming the camera).
    """
    path = Path(path)
    c2w = np.asarray(c2w, np.float64)
    if c2w.ndim != 3 or c2w.shape[1:] not in ((4, 4), (3, 4)):
        raise ValueError(f"c2w must be [N, 4, 4] or [N, 3, 4], got shape {c2w.shape}")
    n = len(c2w)
    intrinsics = [intrinsics] * n if isinstance(intrinsics, Intrinsics) else list(intrinsics)
    names = list(names)
    if len(intrinsics) != n or len(names) != n or n == 0:
        raise ValueError(
            f"{n} cameras need as many names and intrinsics (or one), got {len(names)} names and "
            f"{len(intrinsics)} intrinsics"
        )
    entries, dropped = [], []
    for i, (m, camera, name) in enumerate(zip(c2w, intrinsics, names)):
        check_rigid(m, path, f"camera {i}")
        d = camera.to_dict()
        if abs(d["cx"] - d["width"] / 2) > 1e-3 or abs(d["cy"] - d["height"] / 2) > 1e-3 or camera.has_distortion:
            dropped.append(i)
        rotation = m[:3, :3] * np.array([1.0, -1.0, -1.0])  # OpenGL -> OpenCV: negate the y and z columns
        entries.append(
            {
                "id": i,
                "img_name": str(name),
                "width": d["width"],
                "height": d["height"],
                "position": m[:3, 3].tolist(),
                "rotation": rotation.tolist(),
                "fy": d["fy"],
                "fx": d["fx"],
            }
        )
    if dropped:
        warnings.warn(
            f"{path}: cameras.json holds a centred pinhole only; the principal point or distortion of "
            f"{len(dropped)} cameras (first: camera {dropped[0]}) is dropped",
            stacklevel=2,
        )
    path.parent.mkdir(parents=True, exist_ok=True)
    write_json(path, entries)
    return path


def iteration_of(ply: Path) -> Optional[int]:
    """N when `ply` lies in `point_cloud/iteration_N/`, else None."""
    m = _ITERATION.fullmatch(ply.parent.name)
    return int(m.group(1)) if m and ply.parent.parent.name == "point_cloud" else None


def cameras_beside(ply: Path) -> Optional[Path]:
    """cameras.json beside `ply`, else at the model root of the reference layout, else None."""
    candidates = [ply.parent / "cameras.json"]
    if iteration_of(ply) is not None:
        candidates.append(ply.parent.parent.parent / "cameras.json")
    # Anything there by that name, a FIFO or a folder included: `read_cameras_json` refuses those by name.
    return next((c for c in candidates if os.path.lexists(c)), None)
