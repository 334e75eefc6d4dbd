"""Camera paths in the files other tools read, and back.

* nerfstudio (`ns-render camera-path --camera-path-filename camera_path.json`): top-level
  `camera_type`, `render_height`, `render_width`, `fps`, `seconds` and `camera_path`, a list of
  {`camera_to_world`: the 4x4 OpenGL camera-to-world matrix flattened row by row, `fov`: vertical
  field of view in degrees, `aspect`: width / height}. nerfstudio renders in its own normalised
  world (its dataparser orients, centres and scales the poses and saves that as
  `dataparser_transforms.json`: {"transform": 3x4, "scale": s}); given that file, the matrices are
  written in nerfstudio's world (c2w' = T c2w, then its translation times s), else in the scene's
  own frame (what nerfstudio uses when trained with `--orientation-method none --center-method none
  --auto-scale-poses False`). nerfstudio's camera has fx = fy and a centred principal point.
* Instant-NGP (`testbed.load_camera_path`, the GUI's camera path window): {`path`: keyframes
  {`R`: quaternion (x, y, z, w), `T`: position, `fov`: vertical degrees, `timestamp`, `slice`,
  `scale`, `dof`, `aperture_size`}, `loop`, `time`, `duration_seconds`, `spline_order`} in NGP's
  internal frame (`to_ngp`: y and z axes flipped, position x scale + offset, axes cycled xyz <- yzx,
  with the scene's transforms.json `scale` / `offset`, defaults 0.33 / 0.5). Every frame is written as
  a keyframe, so NGP's own spline between them stays on our path.

Both files carry a `waldo` block (ignored by those tools) with what reading them back needs: the
world the matrices are in and the NGP scale / offset. `read_camera_path` reads either back into the
scene's frame; `waldo_jax.scenes.read_poses_file` (and so `waldo render --poses`) uses it.
"""

from __future__ import annotations

import math
from typing import Any, Dict, Optional, Tuple

import numpy as np

from waldo_jax.types import Intrinsics

__all__ = ["NGP_DEFAULT_SCALE", "NGP_DEFAULT_OFFSET", "nerfstudio_camera_path", "instant_ngp_camera_path",
           "read_camera_path", "is_camera_path", "to_ngp", "from_ngp", "read_dataparser_transform"]

NGP_DEFAULT_SCALE = 0.33
NGP_DEFAULT_OFFSET = (0.5, 0.5, 0.5)
_CYCLE = [1, 2, 0]  # NGP's rows: x <- y, y <- z, z <- x


def _vertical_fov(intrinsics: Intrinsics) -> float:
    return math.degrees(2.0 * math.atan(0.5 * intrinsics.height / float(intrinsics.fy)))


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
    x, y, z, w = np.asarray(q, np.float64) / np.linalg.norm(q)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def to_ngp(c2w: np.ndarray, scale: float = NGP_DEFAULT_SCALE, offset=NGP_DEFAULT_OFFSET) -> np.ndarray:
    """Instant-NGP's camera matrix [3, 4] of an OpenGL camera-to-world matrix in the transforms.json frame."""
    m = np.array(c2w, np.float64)[:3, :4]
    m[:, 1:3] *= -1.0
    m[:, 3] = m[:, 3] * scale + np.asarray(offset, np.float64)
    return m[_CYCLE]


def from_ngp(matrix: np.ndarray, scale: float = NGP_DEFAULT_SCALE, offset=NGP_DEFAULT_OFFSET) -> np.ndarray:
    """The inverse of `to_ngp`: a [4, 4] OpenGL camera-to-world matrix in the transforms.json frame."""
    m = np.empty((3, 4))
    m[_CYCLE] = np.asarray(matrix, np.float64)[:3, :4]
    m[:, 3] = (m[:, 3] - np.asarray(offset, np.float64)) / scale
    m[:, 1:3] *= -1.0
    return np.concatenate([m, [[0.0, 0.0, 0.0, 1.0]]])


def read_dataparser_transform(meta: Dict[str, Any]) -> Tuple[np.ndarray, float]:
    """(transform [4, 4], scale) of a nerfstudio `dataparser_transforms.json` dict; ValueError when malformed."""
    try:
        transform = np.asarray(meta["transform"], np.float64)
        scale = float(meta["scale"])
    except (KeyError, TypeError, ValueError):
        raise ValueError("expected nerfstudio's dataparser_transforms.json: {\"transform\": 3x4, \"scale\": s}") from None
    if transform.shape == (3, 4):
        transform = np.concatenate([transform, [[0.0, 0.0, 0.0, 1.0]]])
    if transform.shape != (4, 4) or not np.all(np.isfinite(transform)) or not (scale > 0 and math.isfinite(scale)):
        raise ValueError(f"dataparser transform must be a finite 3x4 matrix with a positive scale, got shape "
                         f"{list(transform.shape)} and scale {scale}")
    return transform, scale


def nerfstudio_camera_path(c2w: np.ndarray, intrinsics: Intrinsics, fps: float,
                           dataparser: Optional[Tuple[np.ndarray, float]] = None,
                           extra: Optional[Dict[str, Any]] = None) -> Dict[str, Any]:
    """nerfstudio's camera_path.json dict of frames c2w [F, 4, 4] (scene frame) rendered with `intrinsics`.

    `dataparser`: (transform [4, 4], scale) of the nerfstudio model's dataparser_transforms.json, to
    write in nerfstudio's world; None writes the scene's own frame.
    """
    c2w = np.asarray(c2w, np.float64)
    if dataparser is not None:
        transform, scale = dataparser
        c2w = transform @ c2w
        c2w[:, :3, 3] *= scale
    fov, aspect = _vertical_fov(intrinsics), intrinsics.width / intrinsics.height
    waldo = {"world": "scene" if dataparser is None else "nerfstudio",
             "dataparser_transform": None if dataparser is None else dataparser[0][:3].tolist(),
             "dataparser_scale": None if dataparser is None else dataparser[1],
             "note": "nerfstudio renders with fx = fy from fov and a centred principal point"}
    waldo.update(extra or {})
    return {"camera_type": "perspective", "render_height": int(intrinsics.height),
            "render_width": int(intrinsics.width), "fps": float(fps), "seconds": len(c2w) / float(fps),
            "smoothness_value": 0.0, "is_cycle": False, "keyframes": [],
            "camera_path": [{"camera_to_world": np.round(m, 8).reshape(-1).tolist(), "fov": fov, "aspect": aspect}
                            for m in c2w],
            "waldo": waldo}


def instant_ngp_camera_path(c2w: np.ndarray, intrinsics: Intrinsics, fps: float, scale: float = NGP_DEFAULT_SCALE,
                            offset=NGP_DEFAULT_OFFSET, extra: Optional[Dict[str, Any]] = None) -> Dict[str, Any]:
    """Instant-NGP's camera path dict of frames c2w [F, 4, 4] (transforms.json frame), one keyframe per frame."""
    c2w = np.asarray(c2w, np.float64)
    seconds = len(c2w) / float(fps)
    fov = _vertical_fov(intrinsics)
    path = []
    for i, m in enumerate(c2w):
        ngp = to_ngp(m, scale, offset)
        path.append({"R": np.round(_quaternion_xyzw(ngp[:, :3]), 8).tolist(), "T": np.round(ngp[:, 3], 8).tolist(),
                     "fov": fov, "timestamp": seconds * (i + 1) / len(c2w), "slice": 0.0, "scale": 1.0,
                     "dof": 0.0, "aperture_size": 0.0})
    waldo = {"ngp_scale": float(scale), "ngp_offset": [float(v) for v in np.broadcast_to(offset, (3,))],
             "render_width": int(intrinsics.width), "render_height": int(intrinsics.height)}
    waldo.update(extra or {})
    return {"loop": False, "time": 0.0, "duration_seconds": seconds, "spline_order": 3, "path": path,
            "waldo": waldo}


def is_camera_path(meta: Dict[str, Any]) -> bool:
    """True for a nerfstudio or an Instant-NGP camera path dict (ours or another tool's)."""
    return "camera_path" in meta or (isinstance(meta.get("path"), list) and "frames" not in meta)


def _focal(fov_degrees: float, height: int) -> float:
    return 0.5 * height / math.tan(0.5 * math.radians(fov_degrees))


def read_camera_path(meta: Dict[str, Any], default: Intrinsics) -> Tuple[np.ndarray, Intrinsics]:
    """(c2w float32 [F, 4, 4] in the scene's frame, intrinsics) of a camera path dict written by waldo.

    Raises:
      ValueError: a camera path without the `waldo` block (another tool's: its world frame is not
        known), or a malformed entry; the message says which.
    """
    waldo = meta.get("waldo")
    if not isinstance(waldo, dict):
        if "camera_path" in meta:
            raise ValueError("a nerfstudio camera path from another tool is in nerfstudio's normalised world frame, "
                             "not the scene's; pass a transforms.json-like file with frames[].transform_matrix, or "
                             "a camera_path.json written by `waldo path`")
        raise ValueError("an Instant-NGP camera path from another tool is in NGP's frame with an unknown scale and "
                         "offset; pass a transforms.json-like file, or a camera path written by `waldo path`")
    try:
        if "camera_path" in meta:
            c2w = np.stack([np.asarray(e["camera_to_world"], np.float64).reshape(4, 4) for e in meta["camera_path"]])
            if waldo.get("world") == "nerfstudio":
                transform, scale = read_dataparser_transform({"transform": waldo["dataparser_transform"],
                                                              "scale": waldo["dataparser_scale"]})
                c2w[:, :3, 3] /= scale
                c2w = np.linalg.inv(transform) @ c2w
            width, height = int(meta["render_width"]), int(meta["render_height"])
            fov = float(meta["camera_path"][0]["fov"])
        else:
            scale, offset = float(waldo["ngp_scale"]), waldo["ngp_offset"]
            c2w = np.stack([from_ngp(np.concatenate([_rotation_xyzw(k["R"]), np.asarray(k["T"], np.float64)[:, None]],
                                                    axis=1), scale, offset) for k in meta["path"]])
            width = int(waldo.get("render_width", default.width))
            height = int(waldo.get("render_height", default.height))
            fov = float(meta["path"][0]["fov"])
    except (KeyError, TypeError, ValueError, IndexError) as e:
        raise ValueError(f"malformed camera path ({type(e).__name__}: {e})") from None
    if len(c2w) == 0:
        raise ValueError("the camera path has no frames")
    focal = _focal(fov, height)
    return c2w.astype(np.float32), Intrinsics.create(width, height, focal, focal, 0.5 * width, 0.5 * height)
