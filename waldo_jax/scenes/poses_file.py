"""Cameras to render, without images: a transforms.json-like poses file (see `read_poses_file`)."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any, Dict, List, NamedTuple, Optional, Tuple

import numpy as np

from waldo_jax.io import read_json_file
from waldo_jax.scenes.camera_paths import is_camera_path, read_camera_path, recorded_world
from waldo_jax.errors import (
    MAX_RESOLUTION,
    MIN_RESOLUTION,
    NumberError,
    SceneFormatError,
)
from waldo_jax.scenes.common import (
    field,
    focal_from_angle,
    input_file,
    intrinsics_problem,
    number,
    numeric_array,
    one_line_errors,
    rigid_problem,
    warn_off_image_principal_point,
)
from waldo_jax.types import Intrinsics

__all__ = ["PosesFile", "load_poses_file", "read_poses_file"]


def _poses_file_c2w(matrix: Any, path: Path, what: str) -> np.ndarray:
    """A [4, 4] matrix of numbers from a poses file's entry (16 numbers or [3, 4] accepted); whether it is a
    camera-to-world is `_rigid_poses`' to check, for all of them at once."""
    m = numeric_array(matrix)  # strings and booleans are refused, not converted
    if m is None:
        raise SceneFormatError(path, f"{what} is not a matrix of numbers")
    if m.shape == (16,):
        m = m.reshape(4, 4)
    if m.shape == (3, 4):
        m = np.concatenate([m, [[0.0, 0.0, 0.0, 1.0]]])
    if m.shape != (4, 4):
        raise SceneFormatError(path, f"{what} has shape {list(m.shape)}, expected 4x4")
    return m


def _rigid_poses(poses: List[np.ndarray], path: Path, what: str) -> np.ndarray:
    """The poses stacked, float32 [N, 4, 4], once each is a camera by a scene's rule (`rigid_problem`: finite,
    rigid, the bottom row (0, 0, 0, 1), which had been dropped unread, the origin within MAX_COORDINATE),
    checked for all N at once (a file may hold 10^5); else a `SceneFormatError` naming the pose (`what`
    holds its index as {i})."""
    stacked = np.stack(poses)
    found = rigid_problem(stacked)
    if found is not None:
        raise SceneFormatError(path, f"{what.format(i=found[0])}: {found[1]}")
    return stacked.astype(np.float32)


_FRAME_CAMERA_KEYS = ("w", "h", "fl_x", "fl_y", "cx", "cy", "camera_angle_x", "camera_angle_y", "k1", "k2", "p1", "p2")


def _poses_file_intrinsics(meta: Dict[str, Any], path: Path, default: Intrinsics) -> Intrinsics:
    """Intrinsics of a poses file, or `default` when it has no focal length."""
    w, h = number(meta, "w", path, positive=True), number(meta, "h", path, positive=True)
    for key, side in (("w", w), ("h", h)):
        if side is not None and side != int(side):  # 16.5 had rendered at 16 without a word
            raise SceneFormatError(path, f"{key!r} must be a whole number of pixels, got {side:g}")
    fl_x, fl_y = number(meta, "fl_x", path, positive=True), number(meta, "fl_y", path, positive=True)
    angle_x, angle_y = number(meta, "camera_angle_x", path), number(meta, "camera_angle_y", path)
    if fl_x is None and fl_y is None and angle_x is None and angle_y is None:
        other = [k for k in ("w", "h", "cx", "cy", "k1", "k2", "p1", "p2") if meta.get(k) is not None]
        if other:  # they were dropped for the default camera without a word
            raise SceneFormatError(
                path,
                f"camera keys {', '.join(other)} without a focal length: give 'fl_x' (or 'camera_angle_x'), "
                "or leave the camera out to render with the source's",
            )
        return default
    if w is None or h is None:
        # A focal length without an image size: assume the default camera's size (and aspect).
        w = w or (h * default.width / default.height if h else float(default.width))
        h = h or (w * default.height / default.width)
    if not (MIN_RESOLUTION <= min(w, h) and max(w, h) <= MAX_RESOLUTION):
        raise SceneFormatError(
            path,
            f"camera of {w:g}x{h:g} pixels: sides must lie between {MIN_RESOLUTION} and "
            f"{MAX_RESOLUTION} (--resolution R renders at another size)",
        )
    try:
        if fl_x is None and angle_x is not None:
            fl_x = focal_from_angle(angle_x, w, "'camera_angle_x'")
        if fl_y is None and angle_y is not None:
            fl_y = focal_from_angle(angle_y, h, "'camera_angle_y'")
    except NumberError as e:
        raise SceneFormatError(path, str(e)) from None
    fl_x = fl_x if fl_x is not None else fl_y
    fl_y = fl_y if fl_y is not None else fl_x
    distortion = [number(meta, k, path) or 0.0 for k in ("k1", "k2", "p1", "p2")]
    intrinsics = Intrinsics.create(
        int(round(w)), int(round(h)), fl_x, fl_y, number(meta, "cx", path), number(meta, "cy", path), distortion
    )
    _check_camera(intrinsics, path)
    warn_off_image_principal_point(intrinsics, path, stacklevel=5)  # the caller of read/load_poses_file
    return intrinsics


def _check_camera(intrinsics: Intrinsics, path: Path) -> None:
    """Refuses a camera a render cannot use (`intrinsics_problem`), naming the file."""
    problem = intrinsics_problem(intrinsics)
    if problem:
        raise SceneFormatError(path, problem if problem.startswith("camera of") else f"camera: {problem}")


def _check_count(count: int, max_poses: Optional[int], path: Path) -> None:
    """Refuses more poses than the caller renders, from the list's length, before each is checked (10^6
    frames took 30 s and 2 GB to be validated and then refused by the count)."""
    if max_poses is not None and count > max_poses:
        raise SceneFormatError(path, f"{count} poses; at most {max_poses} are read at once (split the file)")


class PosesFile(NamedTuple):
    """A poses file's cameras (`load_poses_file`).

    Attributes:
      c2w: float32 [N, 4, 4] camera-to-world poses.
      intrinsics: the camera rendering every pose.
      file_names: frame i's `file_path`, or None when it has none.
      world: the world the file's poses were written in, as waldo records it (`recorded_world`:
        "procedural:N" or an absolute path), or None where the file records none.
    """

    c2w: np.ndarray
    intrinsics: Intrinsics
    file_names: List[Optional[str]]
    world: Optional[str]


def read_poses_file(
    path: str | os.PathLike, default_intrinsics: Intrinsics, max_poses: Optional[int] = None
) -> Tuple[np.ndarray, Intrinsics, List[Optional[str]]]:
    """(c2w, intrinsics, file_names) of a poses file: `load_poses_file` without the recorded world."""
    c2w, intrinsics, names, _ = _load(path, default_intrinsics, max_poses)
    return c2w, intrinsics, names


def load_poses_file(
    path: str | os.PathLike, default_intrinsics: Intrinsics, max_poses: Optional[int] = None
) -> PosesFile:
    """Reads the cameras of a transforms.json-like poses file (no images are needed or read).

    The file is a JSON object with `frames[].transform_matrix` (instant-ngp / nerfstudio / Blender
    transforms: OpenGL camera-to-world, in the file's own world frame, used as they are). A matrix may
    be 4x4 (its bottom row (0, 0, 0, 1)), 3x4 (that row is added) or 16 numbers; it must be finite and
    rigid (rotation orthonormal within `scenes.common.RIGID_TOL`, det +1, `check_rigid`). Intrinsics come
    from the file when it has a focal length
    (`fl_x`/`fl_y` or `camera_angle_x`/`camera_angle_y`, with `w`/`h`, `cx`/`cy`, `k1 k2 p1 p2`; a
    missing size is taken from `default_intrinsics`), else they are `default_intrinsics`. Camera paths
    written by `waldo path` (nerfstudio `camera_path.json`, Instant-NGP paths; `waldo_jax.scenes.camera_paths`)
    are read back into the scene's frame; other tools' camera paths are refused: their world frame
    (nerfstudio's normalised one, NGP's scaled one) is not known.

    Args:
      path: the JSON file.
      default_intrinsics: the camera to use when the file has no focal length (e.g. a checkpoint's).
      max_poses: refuse a file of more poses than this (counted before any pose is checked), or None.

    Returns:
      `PosesFile` (c2w float32 [N, 4, 4], intrinsics, file_names, world), the file parsed once.

    Raises:
      SceneFormatError: the file is missing, unreadable, not JSON, has no (or an empty) `frames`
        list, a frame without a valid `transform_matrix`, invalid intrinsics, or is a camera path.
        The message names the file (and the frame).
    """
    return _load(path, default_intrinsics, max_poses)


def _load(path: str | os.PathLike, default_intrinsics: Intrinsics, max_poses: Optional[int]) -> PosesFile:
    """`load_poses_file`'s work, one call below both public readers (a warning's stacklevel names their caller)."""
    with one_line_errors():  # a file name with a newline or an escape stays on one line
        path = Path(path)
        if not os.path.lexists(path):
            raise SceneFormatError(path, "no such poses file")
        input_file(path, "poses file")
        meta = read_json_file(path, "poses file", lambda problem: SceneFormatError(path, problem))
        if not isinstance(meta, dict):
            raise SceneFormatError(path, "expected a JSON object with a 'frames' list")
        if isinstance(meta.get("frames"), list):
            frames = meta["frames"]
            if not frames:
                raise SceneFormatError(path, "'frames' is empty")
            _check_count(len(frames), max_poses, path)
            poses, names = [], []
            for i, frame in enumerate(frames):
                if not isinstance(frame, dict) or "transform_matrix" not in frame:
                    raise SceneFormatError(path, f"frame {i} has no 'transform_matrix'")
                own = [k for k in _FRAME_CAMERA_KEYS if k in frame and frame[k] != meta.get(k)]
                if own:  # one camera renders every frame: a frame's own would be ignored
                    raise SceneFormatError(
                        path,
                        f"frame {i} has its own camera ({', '.join(own)}): a poses file gives one camera for "
                        "all frames, at its top level",
                    )
                poses.append(_poses_file_c2w(frame["transform_matrix"], path, f"frame {i} transform_matrix"))
                names.append(field(frame, "file_path", path, "string", where=f"frame {i}"))
            c2w = _rigid_poses(poses, path, "frame {i} transform_matrix")
            return PosesFile(c2w, _poses_file_intrinsics(meta, path, default_intrinsics), names, recorded_world(meta))
        if is_camera_path(meta):
            entries = meta.get("camera_path", meta.get("path"))
            count = len(entries) if isinstance(entries, list) else 0
            waldo = meta.get("waldo")
            frames = waldo.get("frames") if isinstance(waldo, dict) and "camera_path" not in meta else None
            if isinstance(frames, int) and not isinstance(frames, bool):  # an NGP path repeats its last frame
                count = min(count, frames)
            _check_count(count, max_poses, path)
            try:
                c2w, intrinsics = read_camera_path(meta, default_intrinsics)
            except ValueError as e:
                raise SceneFormatError(path, str(e)) from None
            _check_camera(intrinsics, path)
            poses = [_poses_file_c2w(m, path, f"camera path frame {i}") for i, m in enumerate(c2w)]
            c2w = _rigid_poses(poses, path, "camera path frame {i}")
            return PosesFile(c2w, intrinsics, [None] * len(poses), recorded_world(meta))
        raise SceneFormatError(path, "no 'frames' list with transform_matrix entries (transforms.json format)")
