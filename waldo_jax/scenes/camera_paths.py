"""Camera paths in the files other tools read, and back.

* nerfstudio (`ns-render camera-path --camera-path-filename camera_path.json`, and the viewer's "Load
  Path"): top-level `camera_type`, `render_height`, `render_width`, `fps`, `seconds`, `camera_path`
  (what `ns-render` renders: per frame {`camera_to_world`: the 4x4 OpenGL camera-to-world matrix
  flattened row by row, `fov`: vertical degrees, `aspect`: width / height}) and `keyframes` (what the
  viewer loads and edits: one keyframe per frame, {`matrix`, `fov`, `aspect`}, `default_transition_sec`
  = 1 / fps, so the viewer's spline meets every frame). nerfstudio renders in its own normalised world.
  Its saved `dataparser_transforms.json` ({"transform": D [3, 4], "scale": s}) maps the *original*
  data frame (before `applied_transform`) and s includes `applied_scale`; its nerfstudio-data (and
  colmap) dataparser gives a pose P of transforms.json the pose D A^-1 P, translation times
  s / applied_scale, where A is the file's `applied_transform` (or, with no such key and a
  colmap/sparse/0 folder, nerfstudio's legacy COLMAP one). Without D, matrices stay in the scene's own
  frame (a model trained with `--orientation-method none --center-method none --auto-scale-poses False`).
  nerfstudio's camera has fx = fy and a centred principal point.
* Instant-NGP (`testbed.load_camera_path`, `scripts/run.py --video_camera_path`, the GUI's camera
  path window): {`path`: keyframes {`R`: quaternion (x, y, z, w), `T`, `fov`: vertical degrees,
  `timestamp`, `slice`, `scale`, `dof`}, `loop`, `time`, `duration_seconds`, `spline_order`} in NGP's
  frame (`to_ngp`: y and z axes flipped, position x scale + offset, axes cycled xyz <- yzx unless
  `from_mitsuba`), with the `NgpFrame` NGP's loader derives from the scene's transforms.json
  (`ngp_frame`: `scale`, `offset`, `aabb`, `from_mitsuba`). Playback stays on our frames: one keyframe
  per frame plus a copy of the last, linear spline (order 1 passes through its keyframes; NGP's
  default, order 3, is a B-spline that does not), timed so that keyframe i sits at time i / F, where
  `run.py` renders frame i of F (`--video_n_seconds S --video_fps R` with S x R = F).

The frames themselves (`NgpFrame`, `ngp_frame`, `nerfstudio_applied`, ...) live in
`waldo_jax.scenes.tool_frames`, re-exported here. Both files carry a `waldo` block (ignored by those
tools) with what reading them back needs; `read_camera_path` reads either back into the scene's frame
(`waldo render --poses` uses it). The block (and poses.json's) names the world the path was found in
(`recorded_world`), so that a render in another can say so.
docs/cli.md ("waldo path") has the consumers' side and the measured tolerances.
"""

from __future__ import annotations

import math
from typing import Any, Dict, Optional, Sequence, Tuple

import numpy as np

from waldo_jax.errors import check_float32
from waldo_jax.scenes.colmap import rotation_of_qvec
from waldo_jax.scenes.common import numeric_array, value_text
from waldo_jax.scenes.tool_frames import (
    MITSUBA_TO_OPENGL,
    NERFSTUDIO_COLMAP_APPLIED_TRANSFORM,
    NGP_DEFAULT_OFFSET,
    NGP_DEFAULT_SCALE,
    NgpFrame,
    from_ngp,
    ngp_frame,
    nerfstudio_applied,
    nerfstudio_pose_transform,
    read_dataparser_transform,
    to_ngp,
)
from waldo_jax.types import Intrinsics

__all__ = [
    "NGP_DEFAULT_SCALE",
    "NGP_DEFAULT_OFFSET",
    "NERFSTUDIO_COLMAP_APPLIED_TRANSFORM",
    "MITSUBA_TO_OPENGL",
    "NgpFrame",
    "ngp_frame",
    "nerfstudio_applied",
    "nerfstudio_pose_transform",
    "nerfstudio_camera_path",
    "instant_ngp_camera_path",
    "run_py_video_args",
    "read_camera_path",
    "recorded_world",
    "is_camera_path",
    "to_ngp",
    "from_ngp",
    "read_dataparser_transform",
]


def _homogeneous(m: np.ndarray) -> np.ndarray:
    return np.concatenate([np.asarray(m, np.float64)[:3, :4], [[0.0, 0.0, 0.0, 1.0]]])


# ---------------------------------------------------------------------------------------------
# Quaternions (x, y, z, w), as NGP's JSON stores them.


def _quaternion_xyzw(rotation: np.ndarray) -> np.ndarray:
    """Unit quaternion (x, y, z, w) of a rotation matrix [3, 3] (largest-pivot branch)."""
    m = np.asarray(rotation, np.float64)
    trace = np.trace(m)
    if trace > 0:
        s = 2.0 * math.sqrt(trace + 1.0)
        q = [(m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s, 0.25 * s]
    else:
        i = int(np.argmax(np.diag(m)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2.0 * math.sqrt(max(1.0 + m[i, i] - m[j, j] - m[k, k], 1e-12))
        q = [0.0, 0.0, 0.0, (m[k, j] - m[j, k]) / s]
        q[i] = 0.25 * s
        q[j] = (m[j, i] + m[i, j]) / s
        q[k] = (m[k, i] + m[i, k]) / s
    q = np.asarray(q)
    return q / np.linalg.norm(q)


def _rotation_xyzw(q) -> np.ndarray:
    """The rotation of Instant-NGP's quaternion (x, y, z, w); a ValueError for a zero or non-finite one."""
    x, y, z, w = np.asarray(q, np.float64).reshape(4)
    return rotation_of_qvec([w, x, y, z])


# ---------------------------------------------------------------------------------------------
# nerfstudio.


def _vertical_fov(intrinsics: Intrinsics) -> float:
    return math.degrees(2.0 * math.atan(0.5 * intrinsics.height / float(intrinsics.fy)))


def _focal(fov_degrees: float, height: int) -> float:
    """The focal length of a vertical field of view; a NumberError (a ValueError) for a fov outside (0, 180)."""
    from waldo_jax.scenes.common import focal_from_angle  # the one check of a field of view

    return focal_from_angle(fov_degrees, height, "'fov'", degrees=True)


def nerfstudio_camera_path(
    c2w: np.ndarray,
    intrinsics: Intrinsics,
    fps: float,
    dataparser: Optional[Tuple[np.ndarray, float]] = None,
    extra: Optional[Dict[str, Any]] = None,
    applied_transform: Optional[np.ndarray] = None,
    applied_scale: float = 1.0,
) -> Dict[str, Any]:
    """nerfstudio's camera_path.json dict of frames c2w [F, 4, 4] (scene frame) rendered with `intrinsics`.

    Args:
      dataparser: (transform [4, 4], scale) of the model's dataparser_transforms.json, to write in
        nerfstudio's world; None writes the scene's own frame.
      applied_transform, applied_scale: the scene's (`nerfstudio_applied`), which that file folds in.
    """
    c2w = np.asarray(c2w, np.float64)
    waldo: Dict[str, Any] = {"world": "scene"}
    if dataparser is not None:
        transform, scale = nerfstudio_pose_transform(dataparser, applied_transform, applied_scale)
        c2w = transform @ c2w
        c2w[:, :3, 3] *= scale
        waldo = {
            "world": "nerfstudio",
            "dataparser_transform": dataparser[0][:3].tolist(),
            "dataparser_scale": float(dataparser[1]),
            "applied_transform": None if applied_transform is None else np.asarray(applied_transform)[:3].tolist(),
            "applied_scale": float(applied_scale),
            "pose_transform": transform[:3].tolist(),
            "pose_scale": scale,
        }
    waldo["note"] = (
        "nerfstudio renders with fx = fy from fov and a centred principal point; to open the path in "
        "the viewer, copy this file into the data folder's camera_paths/"
    )
    waldo.update(extra or {})
    fov, aspect = _vertical_fov(intrinsics), intrinsics.width / intrinsics.height
    flat = [np.round(m, 8).reshape(-1).tolist() for m in c2w]
    return {
        "camera_type": "perspective",
        "render_height": int(intrinsics.height),
        "render_width": int(intrinsics.width),
        "fps": float(fps),
        "seconds": len(c2w) / float(fps),
        "smoothness_value": 0.0,
        "is_cycle": False,
        "default_fov": fov,
        "default_transition_sec": 1.0 / float(fps),
        "keyframes": [
            {
                "matrix": m,
                "fov": fov,
                "aspect": aspect,
                "override_transition_enabled": False,
                "override_transition_sec": None,
            }
            for m in flat
        ],
        "camera_path": [{"camera_to_world": m, "fov": fov, "aspect": aspect} for m in flat],
        "waldo": waldo,
    }


# ---------------------------------------------------------------------------------------------
# Instant-NGP.


def run_py_video_args(frames: int, fps: float) -> Tuple[int, int]:
    """(--video_n_seconds, --video_fps) with which NGP's run.py renders exactly `frames` frames.

    run.py takes both as integers and renders their product; when `fps` is not an integer that
    divides `frames`, the only exact choice is (1, frames) (the frames are right, the video plays
    at `frames` per second: re-time it).
    """
    rounded = round(fps)
    if abs(fps - rounded) < 1e-9 and rounded > 0 and frames % rounded == 0:
        return frames // rounded, rounded
    return 1, frames


def instant_ngp_camera_path(
    c2w: np.ndarray,
    intrinsics: Intrinsics,
    fps: float,
    scale: float = NGP_DEFAULT_SCALE,
    offset=NGP_DEFAULT_OFFSET,
    extra: Optional[Dict[str, Any]] = None,
    from_mitsuba: bool = False,
    frame: Optional[NgpFrame] = None,
) -> Dict[str, Any]:
    """Instant-NGP's camera path dict of frames c2w [F, 4, 4] (scene frame).

    F + 1 keyframes (the frames and a copy of the last), `spline_order` 1, timestamps (j + 1) / fps:
    NGP's `get_pos` puts keyframe j at play time timestamp[j - 1] / timestamp[F - 1] = j / F, the
    time at which run.py starts frame j of F, and a linear spline meets its keyframes. The copy
    holds the last frame still while run.py's shutter (half a frame) is open.
    """
    frame = frame if frame is not None else NgpFrame.create(scale, offset, from_mitsuba)
    c2w = np.asarray(c2w, np.float64)
    count = len(c2w)
    fov = _vertical_fov(intrinsics)
    path = []
    for i, m in enumerate(np.concatenate([c2w, c2w[-1:]])):
        ngp = to_ngp(m, frame=frame)
        path.append(
            {
                "R": np.round(_quaternion_xyzw(ngp[:, :3]), 9).tolist(),
                "T": np.round(ngp[:, 3], 9).tolist(),
                "fov": fov,
                "timestamp": (i + 1) / float(fps),
                "slice": 0.0,
                "scale": 1.0,
                "dof": 0.0,
                "aperture_size": 0.0,
            }
        )
    seconds, rate = run_py_video_args(count, fps)
    waldo = {
        "ngp_scale": frame.scale,
        "ngp_offset": list(frame.offset),
        "ngp_from_mitsuba": frame.from_mitsuba,
        "frames": count,
        "render_width": int(intrinsics.width),
        "render_height": int(intrinsics.height),
        "run_py": [
            "--video_camera_path",
            "instant_ngp_path.json",
            "--video_n_seconds",
            str(seconds),
            "--video_fps",
            str(rate),
            "--width",
            str(int(intrinsics.width)),
            "--height",
            str(int(intrinsics.height)),
        ],
        "note": f"{count} frames + a copy of the last as keyframes; render all {count} with run.py's "
        "--video_n_seconds x --video_fps equal to that count",
    }
    waldo.update(extra or {})
    return {
        "loop": False,
        "time": 0.0,
        "duration_seconds": count / float(fps),
        "spline_order": 1,
        "path": path,
        "waldo": waldo,
    }


# ---------------------------------------------------------------------------------------------
# Reading back.


# The blocks in which waldo's files name the world their poses are in (`source_world`; the camera path's
# `world` is another thing, the frame its poses are written in): a camera path's `waldo`, the
# poses.json of `waldo path` (`waldo_path`) and of `waldo explore` (`waldo_explore`).
_SOURCE_BLOCKS = ("waldo", "waldo_path", "waldo_explore")


def recorded_world(meta: Any) -> Optional[str]:
    """The world a poses file of waldo's was written in.

    Args:
      meta: the file's parsed JSON (a camera path, or a poses.json of `waldo path` or `waldo explore`).

    Returns:
      Its `source_world` ("procedural:N" or an absolute path, as `pipeline.sources.source_world` names it),
      or None for a file that records none (another tool's, or waldo's from before it was recorded) or
      records it by a value that is not text.
    """
    if not isinstance(meta, dict):
        return None
    for key in _SOURCE_BLOCKS:
        block = meta.get(key)
        if isinstance(block, dict) and isinstance(block.get("source_world"), str) and block["source_world"]:
            return block["source_world"]
    return None


def is_camera_path(meta: Dict[str, Any]) -> bool:
    """True for a nerfstudio or an Instant-NGP camera path dict (ours or another tool's)."""
    return "camera_path" in meta or (isinstance(meta.get("path"), list) and "frames" not in meta)


def _entries(meta: Dict[str, Any], key: str) -> list:
    """meta[key], a non-empty list of objects, else a ValueError naming the key."""
    entries = meta.get(key)
    if not isinstance(entries, list) or not entries:
        raise ValueError(f"{key!r} must be a non-empty list of frames, got {value_text(entries)}")
    for i, entry in enumerate(entries):
        if not isinstance(entry, dict):
            raise ValueError(f"{key!r} entry {i} must be an object, got {value_text(entry)}")
    return entries


def _numbers(value: Any, shape: Tuple[int, ...], what: str) -> np.ndarray:
    """`value` as float64 of `shape` (numbers only: strings and booleans refused), finite, else a ValueError."""
    array = numeric_array(value)
    if array is None or array.size != int(np.prod(shape)):
        raise ValueError(f"{what} must be {int(np.prod(shape))} numbers, got {value_text(value)}")
    if not np.all(np.isfinite(array)) or np.max(np.abs(array)) > float(np.finfo(np.float32).max):
        raise ValueError(f"{what} must be finite in float32, got {value_text(value)}")
    return array.reshape(shape)


def _number(meta: Dict[str, Any], key: str, what: str, positive: bool = False) -> float:
    """meta[key], a number (not a string or a boolean) finite in float32 (> 0 there with `positive`)."""
    value = meta.get(key)
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ValueError(f"{what} {key!r} must be a number, got {value_text(value)}")
    return check_float32(value, f"{what} {key!r}", positive=positive)


def _count(meta: Dict[str, Any], key: str, what: str, low: int, high: int, default: Optional[int] = None) -> int:
    """meta[key], a whole number in [low, high] (16.0 is 16; 16.5, "16" and true are refused)."""
    if key not in meta and default is not None:
        return default
    value = meta.get(key)
    whole = isinstance(value, int) or (isinstance(value, float) and value.is_integer())
    if isinstance(value, bool) or not whole or not low <= value <= high:
        raise ValueError(f"{what} {key!r} must be a whole number between {low} and {high}, got {value_text(value)}")
    return int(value)


def _nerfstudio_back(c2w: np.ndarray, waldo: Dict[str, Any]) -> np.ndarray:
    if "pose_transform" in waldo:
        transform = _homogeneous(_numbers(waldo["pose_transform"], (3, 4), "the waldo block's 'pose_transform'"))
        scale = _number(waldo, "pose_scale", "the waldo block's", positive=True)
    else:  # written before applied transforms were undone: the dataparser transform was the pose transform
        transform, scale = read_dataparser_transform(
            {"transform": waldo.get("dataparser_transform"), "scale": waldo.get("dataparser_scale")}
        )
    if not (scale > 0 and math.isfinite(scale)) or not np.all(np.isfinite(transform)):
        raise ValueError("the waldo block's pose transform is not finite")
    c2w = c2w.copy()
    c2w[:, :3, 3] /= scale
    return np.linalg.inv(transform) @ c2w


def _ngp_back(meta: Dict[str, Any], waldo: Dict[str, Any]) -> np.ndarray:
    flag = waldo.get("ngp_from_mitsuba", False)
    if not isinstance(flag, bool):  # bool("false") is True: NGP's axes would be cycled the other way
        raise ValueError(f"the waldo block's 'ngp_from_mitsuba' must be true or false, got {value_text(flag)}")
    scale = _number(waldo, "ngp_scale", "the waldo block's", positive=True)
    offset = _numbers(waldo.get("ngp_offset"), (3,), "the waldo block's 'ngp_offset'")
    frame = NgpFrame.create(scale, offset.tolist(), flag)
    keys: Sequence[Dict[str, Any]] = _entries(meta, "path")
    # The last keyframe repeats the last frame: `frames` of them are read, a count the path must hold.
    keys = keys[: _count(waldo, "frames", "the waldo block's", 1, len(keys), default=len(keys))]
    poses = []
    for i, k in enumerate(keys):
        rotation = _rotation_xyzw(_numbers(k.get("R"), (4,), f"path keyframe {i} 'R'"))
        position = _numbers(k.get("T"), (3,), f"path keyframe {i} 'T'")
        poses.append(from_ngp(np.concatenate([rotation, position[:, None]], axis=1), frame=frame))
    return np.stack(poses)


def read_camera_path(meta: Dict[str, Any], default: Intrinsics) -> Tuple[np.ndarray, Intrinsics]:
    """(c2w float32 [F, 4, 4] in the scene's frame, intrinsics) of a camera path dict written by waldo.

    Raises:
      ValueError: a camera path without the `waldo` block (another tool's: its world frame is not
        known), or a malformed entry; the message says which.
    """
    waldo = meta.get("waldo")
    if not isinstance(waldo, dict):
        if "camera_path" in meta:
            raise ValueError(
                "a nerfstudio camera path from another tool is in nerfstudio's normalised world frame, "
                "not the scene's; pass a transforms.json-like file with frames[].transform_matrix, or "
                "a camera_path.json written by `waldo path`"
            )
        raise ValueError(
            "an Instant-NGP camera path from another tool is in NGP's frame with an unknown scale and "
            "offset; pass a transforms.json-like file, or a camera path written by `waldo path`"
        )
    from waldo_jax.errors import MAX_RESOLUTION

    world = waldo.get("world", "scene")
    if "camera_path" in meta and world not in ("scene", "nerfstudio"):  # any other word was read as "scene"
        raise ValueError(f"the waldo block's 'world' must be 'scene' or 'nerfstudio', got {value_text(world)}")
    try:
        if "camera_path" in meta:
            entries = _entries(meta, "camera_path")
            c2w = np.stack(
                [
                    _numbers(e.get("camera_to_world"), (4, 4), f"camera_path {i} 'camera_to_world'")
                    for i, e in enumerate(entries)
                ]
            )
            if world == "nerfstudio":
                c2w = _nerfstudio_back(c2w, waldo)
            width = _count(meta, "render_width", "the camera path's", 1, MAX_RESOLUTION)
            height = _count(meta, "render_height", "the camera path's", 1, MAX_RESOLUTION)
            fovs = [_number(e, "fov", f"camera_path {i}") for i, e in enumerate(entries)]
        else:
            c2w = _ngp_back(meta, waldo)
            width = _count(waldo, "render_width", "the waldo block's", 1, MAX_RESOLUTION, default=default.width)
            height = _count(waldo, "render_height", "the waldo block's", 1, MAX_RESOLUTION, default=default.height)
            fovs = [_number(e, "fov", f"path keyframe {i}") for i, e in enumerate(meta["path"][: len(c2w)])]
    except (
        KeyError,
        TypeError,
        IndexError,
        np.linalg.LinAlgError,
        OverflowError,
    ) as e:  # a backstop; a singular transform
        raise ValueError(f"malformed camera path ({type(e).__name__}: {e})") from None
    if not np.all(np.abs(c2w) <= float(np.finfo(np.float32).max)):  # before the cast warns and makes it inf
        raise ValueError("the camera path's poses, read back into the scene's frame, do not fit float32")
    kind = meta.get("camera_type", "perspective")
    if kind != "perspective":  # renders are pinhole views: another projection would be read as one
        raise ValueError(f"camera_type {kind!r}: waldo renders perspective cameras only")
    if len(set(fovs)) > 1:  # one camera renders every frame: a zoom would be read as frame 0's field of view
        raise ValueError(
            f"the frames' fields of view differ ({min(fovs):g} to {max(fovs):g} degrees): waldo renders a path "
            "with one camera; give every frame the same fov"
        )
    fov = fovs[0] if fovs else 0.0
    if len(c2w) == 0:
        raise ValueError("the camera path has no frames")
    focal = _focal(fov, height)
    return c2w.astype(np.float32), Intrinsics.create(width, height, focal, focal, 0.5 * width, 0.5 * height)
