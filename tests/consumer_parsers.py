"""How nerfstudio and Instant-NGP read the files `waldo path` exports: small re-implementations of their readers.

Each function follows one reader of the consumer's source, named in its docstring with the file and
the commit it was written from; it keeps the consumer's conventions (frame order, default arguments,
JSON keys, where it takes float32). Nothing here imports waldo_jax: a round trip through these
functions checks waldo's exports against what the consumers do, not against waldo's own reader.

Sources (read, not copied):
  NS  = nerfstudio-project/nerfstudio @ 50e0e3c70c775e89333256213363badbf074f29d (2025-07-28)
  NGP = NVlabs/instant-ngp @ abe236ee00cf90cfca6e36e65c00435d5b21f50a (2026-02-02)
  TCNN = NVlabs/tiny-cuda-nn @ 6ee3546bda615f51abe684ce9edefeb414689135 (quaternion JSON order and
         matrix layout that NGP uses: include/tiny-cuda-nn/vec_json.h, include/tiny-cuda-nn/vec.h)

Conventions: nerfstudio matrices are OpenGL camera-to-world (x right, y up, z backward), 3x4 or 4x4.
NGP matrices are its internal camera-to-world [3, 4] (x right, y down, z forward, in NGP's unit-cube
world); NGP quaternions are (x, y, z, w), viser's (the nerfstudio viewer's) (w, x, y, z).
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any, Dict, List, Sequence, Tuple

import numpy as np

NS_COMMIT = "50e0e3c70c775e89333256213363badbf074f29d"
NGP_COMMIT = "abe236ee00cf90cfca6e36e65c00435d5b21f50a"

# ---------------------------------------------------------------------------------------------
# Rotation helpers (plain maths, shared by both consumers).


def _quat_xyzw_of(rotation: np.ndarray) -> np.ndarray:
    """Unit quaternion (x, y, z, w) of a rotation matrix (Shepperd's method, largest pivot)."""
    m = np.asarray(rotation, np.float64)
    w2 = 1.0 + np.trace(m)
    diag = [1.0 + m[0, 0] - m[1, 1] - m[2, 2], 1.0 - m[0, 0] + m[1, 1] - m[2, 2], 1.0 - m[0, 0] - m[1, 1] + m[2, 2]]
    pivot = int(np.argmax([w2, *diag]))
    if pivot == 0:
        w = 0.5 * math.sqrt(w2)
        q = [(m[2, 1] - m[1, 2]) / (4 * w), (m[0, 2] - m[2, 0]) / (4 * w), (m[1, 0] - m[0, 1]) / (4 * w), w]
    elif pivot == 1:
        x = 0.5 * math.sqrt(diag[0])
        q = [x, (m[0, 1] + m[1, 0]) / (4 * x), (m[0, 2] + m[2, 0]) / (4 * x), (m[2, 1] - m[1, 2]) / (4 * x)]
    elif pivot == 2:
        y = 0.5 * math.sqrt(diag[1])
        q = [(m[0, 1] + m[1, 0]) / (4 * y), y, (m[1, 2] + m[2, 1]) / (4 * y), (m[0, 2] - m[2, 0]) / (4 * y)]
    else:
        z = 0.5 * math.sqrt(diag[2])
        q = [(m[0, 2] + m[2, 0]) / (4 * z), (m[1, 2] + m[2, 1]) / (4 * z), z, (m[1, 0] - m[0, 1]) / (4 * z)]
    q = np.asarray(q)
    return q / np.linalg.norm(q)


def _matrix_of_quat_xyzw(q: Sequence[float]) -> np.ndarray:
    """The rotation matrix of a unit quaternion (x, y, z, w) (columns = rotated axes)."""
    x, y, z, w = np.asarray(q, np.float64)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def _rotation_x(radians: float) -> np.ndarray:
    c, s = math.cos(radians), math.sin(radians)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def _homogeneous(m: np.ndarray) -> np.ndarray:
    m = np.asarray(m, np.float64)
    if m.shape[-2:] == (4, 4):
        return m.copy()
    bottom = np.broadcast_to([0.0, 0.0, 0.0, 1.0], m.shape[:-2] + (1, 4))
    return np.concatenate([m, bottom], axis=-2)


# ---------------------------------------------------------------------------------------------
# nerfstudio: the dataparsers (what world the model's cameras live in, and dataparser_transforms.json).


def ns_rotation_matrix_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The rotation taking direction a onto b (Rodrigues), as nerfstudio builds it.

    From NS nerfstudio/cameras/camera_utils.py `rotation_matrix_between`: axis a x b (for parallel
    vectors, a x e_x, or a x e_y when a has a zero x), angle acos(a . b).
    """
    a = np.asarray(a, np.float64) / np.linalg.norm(a)
    b = np.asarray(b, np.float64) / np.linalg.norm(b)
    axis = np.cross(a, b)
    if np.sum(np.abs(axis)) < 1e-6:
        other = np.array([1.0, 0.0, 0.0]) if abs(a[0]) < 1e-6 else np.array([0.0, 1.0, 0.0])
        axis = np.cross(a, other)
    axis = axis / np.linalg.norm(axis)
    k = np.array([[0.0, -axis[2], axis[1]], [axis[2], 0.0, -axis[0]], [-axis[1], axis[0], 0.0]])
    theta = math.acos(float(np.clip(np.dot(a, b), -1.0, 1.0)))
    return np.eye(3) + math.sin(theta) * k + (1.0 - math.cos(theta)) * (k @ k)


def ns_auto_orient_and_center_poses(
    poses: np.ndarray, method: str = "up", center_method: str = "poses"
) -> Tuple[np.ndarray, np.ndarray]:
    """(oriented poses [N, 3, 4], transform [3, 4]) of camera-to-world poses [N, 4, 4].

    From NS nerfstudio/cameras/camera_utils.py `auto_orient_and_center_poses`, for the orientation
    methods "up" (the mean camera y axis turned onto +z) and "none", and the centre methods "poses"
    (the mean camera origin to 0) and "none". ("pca", "vertical" and "focus" are not needed here.)
    """
    poses = np.asarray(poses, np.float64)
    origins = poses[:, :3, 3]
    if center_method == "poses":
        translation = origins.mean(axis=0)
    elif center_method == "none":
        translation = np.zeros(3)
    else:
        raise NotImplementedError(center_method)
    if method == "up":
        up = poses[:, :3, 1].mean(axis=0)
        up = up / np.linalg.norm(up)
        rotation = ns_rotation_matrix_between(up, np.array([0.0, 0.0, 1.0]))
        transform = np.concatenate([rotation, rotation @ -translation[:, None]], axis=1)
    elif method == "none":
        transform = np.concatenate([np.eye(3), -translation[:, None]], axis=1)
    else:
        raise NotImplementedError(method)
    return transform @ poses, transform


# What nerfstudio assumes was applied to COLMAP data written before `applied_transform` existed.
NS_COLMAP_DEFAULT_APPLIED_TRANSFORM = [[0.0, 1.0, 0.0, 0.0], [1.0, 0.0, 0.0, 0.0], [0.0, 0.0, -1.0, 0.0]]


def ns_nerfstudio_dataparser(
    folder: Path,
    orientation_method: str = "up",
    center_method: str = "poses",
    auto_scale_poses: bool = True,
    scale_factor: float = 1.0,
) -> Dict[str, Any]:
    """The cameras and `dataparser_transforms.json` that `ns-train` (nerfstudio-data) makes of a transforms.json.

    From NS nerfstudio/data/dataparsers/nerfstudio_dataparser.py `Nerfstudio._generate_dataparser_outputs`
    with its config defaults (orientation "up", centre "poses", auto scale, scale_factor 1): frames
    sorted by file name; poses as float32; oriented and centred over all frames (before the split);
    scaled by 1 / max |translation| times scale_factor. The saved transform is that transform times
    `applied_transform` (or, for data with a colmap/sparse/0 folder and no such key, nerfstudio's
    legacy COLMAP transform), and the saved scale is the pose scale times `applied_scale`
    (`DataparserOutputs.save_dataparser_transform` in base_dataparser.py writes both).

    Returns:
      {"file_paths": sorted, "poses": [N, 3, 4] the model's camera-to-world matrices (one per sorted
       frame), "transform": [3, 4] and "scale": what the poses got (saved-file frame -> model world),
       "dataparser_transforms": the dict nerfstudio saves as dataparser_transforms.json}.
    """
    folder = Path(folder)
    meta = json.loads((folder / "transforms.json").read_text())
    frames = sorted(meta["frames"], key=lambda f: str(folder / Path(f["file_path"])))
    poses = np.array([f["transform_matrix"] for f in frames]).astype(np.float32).astype(np.float64)
    orientation = meta.get("orientation_override", orientation_method)
    poses, transform = ns_auto_orient_and_center_poses(poses, orientation, center_method)
    scale = 1.0
    if auto_scale_poses:
        scale /= float(np.max(np.abs(poses[:, :3, 3])))
    scale *= scale_factor
    poses[:, :3, 3] *= scale
    applied = meta.get("applied_transform")
    if applied is None and (folder / "colmap" / "sparse" / "0").exists():
        applied = NS_COLMAP_DEFAULT_APPLIED_TRANSFORM
    saved = transform if applied is None else transform @ _homogeneous(np.asarray(applied, np.float64))
    saved_scale = scale * float(meta.get("applied_scale", 1.0))
    return {
        "file_paths": [f["file_path"] for f in frames],
        "poses": poses,
        "transform": transform,
        "scale": scale,
        "dataparser_transforms": {"transform": saved.tolist(), "scale": saved_scale},
    }


def ns_blender_dataparser(folder: Path, split: str = "train", scale_factor: float = 1.0) -> Dict[str, Any]:
    """The cameras and `dataparser_transforms.json` of nerfstudio's Blender dataparser (blender-data).

    From NS nerfstudio/data/dataparsers/blender_dataparser.py `Blender._generate_dataparser_outputs`:
    transforms_<split>.json in file order, translations times scale_factor (1), no orientation; the
    outputs keep base_dataparser.py's default transform (identity) and scale = scale_factor.
    """
    meta = json.loads((Path(folder) / f"transforms_{split}.json").read_text())
    poses = np.array([f["transform_matrix"] for f in meta["frames"]]).astype(np.float32).astype(np.float64)[:, :3]
    poses[:, :, 3] *= scale_factor
    transform = np.eye(4)[:3]
    return {
        "file_paths": [f["file_path"] for f in meta["frames"]],
        "poses": poses,
        "transform": transform,
        "scale": scale_factor,
        "dataparser_transforms": {"transform": transform.tolist(), "scale": scale_factor},
    }


# ---------------------------------------------------------------------------------------------
# nerfstudio: ns-render camera-path and the viewer's camera-path panel.


def ns_get_path_from_json(camera_path: Dict[str, Any]) -> Dict[str, Any]:
    """The cameras `ns-render camera-path` renders from a camera_path.json dict.

    From NS nerfstudio/cameras/camera_paths.py `get_path_from_json` (perspective cameras): each
    `camera_to_world` is 16 numbers viewed as 4x4, top 3 rows kept; fx = fy = (H / 2) / tan(fov / 2)
    with `fov` in degrees (nerfstudio/viewer_legacy/server/utils.py
    `three_js_perspective_camera_focal_length`); cx = W / 2, cy = H / 2. And from
    nerfstudio/scripts/render.py (`RenderCameraPath.main`, `_render_trajectory_video`): `seconds` is
    read from the file and the video plays at len(cameras) / seconds frames per second.
    """
    height, width = camera_path["render_height"], camera_path["render_width"]
    if camera_path.get("camera_type", "perspective") not in ("perspective",):
        raise NotImplementedError(camera_path["camera_type"])
    c2w, focal = [], []
    for camera in camera_path["camera_path"]:
        c2w.append(np.asarray(camera["camera_to_world"], np.float32).reshape(4, 4)[:3].astype(np.float64))
        focal.append((height / 2.0) / math.tan(math.radians(camera["fov"]) / 2.0))
    seconds = camera_path["seconds"]
    return {
        "c2w": np.stack(c2w),
        "fx": np.asarray(focal),
        "fy": np.asarray(focal),
        "cx": width / 2.0,
        "cy": height / 2.0,
        "width": width,
        "height": height,
        "video_fps": len(c2w) / seconds,
    }


VISER_NERFSTUDIO_SCALE_RATIO = 10.0  # NS nerfstudio/viewer/viewer.py: the viewer's scene is nerfstudio's world x 10


def ns_viewer_load_path(json_data: Dict[str, Any]) -> Dict[str, Any]:
    """The keyframes the nerfstudio viewer makes of a camera path file (its "Load Path" button).

    From NS nerfstudio/viewer/render_panel.py (`populate_render_tab`, `load_camera_path_button`):
    only `keyframes` is read, each `matrix` (16 numbers, 4x4) turned by 180 degrees about its own x
    axis into viser's camera (OpenCV axes) and its position times VISER_NERFSTUDIO_SCALE_RATIO; `fov`
    (degrees) overrides the default when it differs from `default_fov` by over 1e-3; `aspect`,
    `override_transition_enabled` / `_sec` per keyframe; `default_transition_sec` (default 0.5).
    Raises KeyError, as the viewer does, on a file without these keys.
    """
    keyframes = []
    for frame in json_data["keyframes"]:
        matrix = np.asarray(frame["matrix"], np.float64).reshape(4, 4)
        rotation = matrix[:3, :3] @ _rotation_x(math.pi)
        xyzw = _quat_xyzw_of(rotation)
        keyframes.append(
            {
                "position": matrix[:3, 3] * VISER_NERFSTUDIO_SCALE_RATIO,
                "wxyz": np.roll(xyzw, 1),
                "override_fov_enabled": abs(frame["fov"] - json_data.get("default_fov", 0.0)) > 1e-3,
                "override_fov_rad": frame["fov"] / 180.0 * math.pi,
                "aspect": frame["aspect"],
                "override_transition_enabled": frame.get("override_transition_enabled", None),
                "override_transition_sec": frame.get("override_transition_sec", None),
            }
        )
    return {
        "keyframes": keyframes,
        "default_transition_sec": json_data.get("default_transition_sec", 0.5),
        "default_fov_rad": math.radians(json_data.get("default_fov", 0.0)),
    }


def ns_viewer_keyframe_matrix(keyframe: Dict[str, Any]) -> np.ndarray:
    """The 4x4 camera-to-world (nerfstudio world) the viewer writes for one of its keyframes.

    From NS nerfstudio/viewer/render_panel.py ("Generate Command", the `keyframes` it saves): the
    keyframe's rotation turned back by 180 degrees about x, its position / VISER_NERFSTUDIO_SCALE_RATIO.
    """
    rotation = _matrix_of_quat_xyzw(np.roll(keyframe["wxyz"], -1)) @ _rotation_x(math.pi)
    out = np.eye(4)
    out[:3, :3], out[:3, 3] = rotation, keyframe["position"] / VISER_NERFSTUDIO_SCALE_RATIO
    return out


def ns_viewer_keyframe_seconds(loaded: Dict[str, Any], loop: bool = False) -> np.ndarray:
    """When the viewer's path passes each keyframe, in seconds (its spline meets every keyframe).

    From NS nerfstudio/viewer/render_panel.py `CameraPath.compute_transition_times_cumsum`: keyframe
    i > 0 adds its own transition (the override when enabled, else the default); `spline_t_from_t_sec`
    maps these times to spline knots 0, 1, 2, ... (a PCHIP through them), and the Kochanek-Bartels
    position and orientation splines pass through their control points at the knots.
    """
    total, out = 0.0, [0.0]
    for i, keyframe in enumerate(loaded["keyframes"]):
        if i == 0:
            continue
        enabled = keyframe["override_transition_enabled"] and keyframe["override_transition_sec"] is not None
        total += keyframe["override_transition_sec"] if enabled else loaded["default_transition_sec"]
        out.append(total)
    if loop:
        raise NotImplementedError("loop")
    return np.asarray(out)


# ---------------------------------------------------------------------------------------------
# Instant-NGP: the training data's frame (nerf_loader) and the camera path (camera_path, run.py).

NGP_NERF_SCALE = 0.33  # NGP src/nerf_loader.cu: NERF_SCALE, the default `scale`


def ngp_load_nerf_frame(jsons: Sequence[Dict[str, Any]]) -> Dict[str, Any]:
    """NGP's world mapping (scale, offset, from_mitsuba, aabb_scale) of the transforms JSONs it loads.

    From NGP src/nerf_loader.cu `load_nerf`: scale 0.33 and offset 0.5 to start with; then per JSON, in
    order: `normal_mts_args` or `from_mitsuba` set from_mitsuba, which sets scale 0.66 and offset
    0.25 x 0.66; `scale` sets scale; `aabb_scale`; `offset` (a number or three); `aabb`
    ([[min], [max]]) sets scale = 1 / its longest side (at least 1e-6) and offset = 0.5 - centre x scale.
    NGP keeps these in float32.
    """
    scale, offset, from_mitsuba, aabb_scale = NGP_NERF_SCALE, np.full(3, 0.5), False, 1.0
    for meta in jsons:
        if "normal_mts_args" in meta:
            from_mitsuba = True
        if "from_mitsuba" in meta:
            from_mitsuba = bool(meta["from_mitsuba"])
        if from_mitsuba:
            scale = 0.66
            offset = np.full(3, 0.25 * scale)
        if "scale" in meta:
            scale = float(meta["scale"])
        if "aabb_scale" in meta:
            aabb_scale = float(meta["aabb_scale"])
        if "offset" in meta:
            value = meta["offset"]
            offset = np.asarray(value, np.float64) if isinstance(value, list) else np.full(3, float(value))
        if "aabb" in meta:
            lo, hi = np.asarray(meta["aabb"], np.float32)
            length = max(1e-6, float(np.max(np.abs(hi - lo))))
            scale = 1.0 / length
            offset = (hi + lo) * 0.5 * -scale + 0.5
    return {
        "scale": float(np.float32(scale)),
        "offset": np.asarray(offset, np.float32).astype(np.float64),
        "from_mitsuba": from_mitsuba,
        "aabb_scale": aabb_scale,
    }


def ngp_nerf_matrix_to_ngp(matrix: np.ndarray, frame: Dict[str, Any]) -> np.ndarray:
    """A transforms.json `transform_matrix` as NGP's camera matrix [3, 4].

    From NGP include/neural-graphics-primitives/nerf_loader.h `NerfDataset::nerf_matrix_to_ngp`
    (columns: x kept, y and z negated, translation x scale + offset; then for from_mitsuba columns x
    and z negated, else the rows cycled so that row (x, y, z) <- (y, z, x)). NGP reads the JSON
    matrix m[row][col] into its column-major mat4x3 (`load_nerf`).
    """
    m = np.asarray(matrix, np.float64)[:3, :4].copy()
    m[:, 1] *= -1.0
    m[:, 2] *= -1.0
    m[:, 3] = m[:, 3] * frame["scale"] + frame["offset"]
    if frame["from_mitsuba"]:
        m[:, 0] *= -1.0
        m[:, 2] *= -1.0
        return m
    return m[[1, 2, 0]]


def ngp_matrix_to_nerf(matrix: np.ndarray, frame: Dict[str, Any]) -> np.ndarray:
    """NGP's camera matrix [3, 4] back in the transforms.json frame, as a [4, 4] matrix.

    From NGP include/neural-graphics-primitives/nerf_loader.h `NerfDataset::ngp_matrix_to_nerf`.
    """
    m = np.asarray(matrix, np.float64)[:3, :4].copy()
    if frame["from_mitsuba"]:
        m[:, 0] *= -1.0
        m[:, 2] *= -1.0
    else:
        m = m[[2, 0, 1]]
    m[:, 1] *= -1.0
    m[:, 2] *= -1.0
    m[:, 3] = (m[:, 3] - frame["offset"]) / frame["scale"]
    return _homogeneous(m)


def ngp_load_camera_path(j: Dict[str, Any]) -> Dict[str, Any]:
    """A camera path file as NGP's `CameraPath` holds it after `testbed.load_camera_path`.

    From NGP src/camera_path.cu `CameraPath::load` and `from_json` (with load_relative_to_first off,
    as `Testbed::load_camera_path` leaves it): each keyframe's `R` is a quaternion read (x, y, z, w)
    (TCNN vec_json.h `from_json(tquat)`), `T`, `slice`, `scale`, `fov`, `dof` (or `aperture_size`) and
    an optional `timestamp` (0 when absent); `loop`, `duration_seconds` (0), `spline_order` (3).
    `sanitize_keyframes`: unless every timestamp is larger than the one before it (the first larger
    than 0), they are replaced by (i + 1) / n and duration_seconds by 1.
    """
    keyframes = []
    for el in j.get("path", []):
        keyframes.append(
            {
                "R": np.asarray(el["R"], np.float64),
                "T": np.asarray(el["T"], np.float64),
                "slice": float(el["slice"]),
                "scale": float(el["scale"]),
                "fov": float(el["fov"]),
                "aperture_size": float(el["dof"] if "dof" in el else el["aperture_size"]),
                "timestamp": float(np.float32(el.get("timestamp", 0.0))),
            }
        )
    path = {
        "keyframes": keyframes,
        "loop": bool(j.get("loop", False)),
        "duration_seconds": float(j.get("duration_seconds", 0.0)),
        "spline_order": int(j.get("spline_order", 3)),
    }
    previous, valid = 0.0, True
    for keyframe in keyframes:
        if not keyframe["timestamp"] > previous:
            valid = False
            break
        previous = keyframe["timestamp"]
    if not valid:
        for i, keyframe in enumerate(keyframes):
            keyframe["timestamp"] = float(np.float32((i + 1) / len(keyframes)))
        path["duration_seconds"] = 1.0
    return path


def _kf_scale(k: Dict[str, Any], f: float) -> Dict[str, Any]:
    return {
        "R": k["R"] * f,
        "T": k["T"] * f,
        "slice": k["slice"] * f,
        "scale": k["scale"] * f,
        "fov": k["fov"] * f,
        "aperture_size": k["aperture_size"] * f,
        "timestamp": k["timestamp"],
    }


def _kf_add(a: Dict[str, Any], b: Dict[str, Any]) -> Dict[str, Any]:
    rb = -b["R"] if np.dot(b["R"], a["R"]) < 0.0 else b["R"]  # CameraKeyframe::operator+: the short way round
    return {
        "R": a["R"] + rb,
        "T": a["T"] + b["T"],
        "slice": a["slice"] + b["slice"],
        "scale": a["scale"] + b["scale"],
        "fov": a["fov"] + b["fov"],
        "aperture_size": a["aperture_size"] + b["aperture_size"],
        "timestamp": b["timestamp"],
    }


def _kf_normalize(k: Dict[str, Any]) -> Dict[str, Any]:
    return {**k, "R": k["R"] / np.linalg.norm(k["R"])}


def _ngp_get_pos(path: Dict[str, Any], playtime: float) -> Tuple[int, float]:
    """NGP src/camera_path.cu `CameraPath::get_pos` (float32 arithmetic, as NGP's)."""
    keyframes = path["keyframes"]
    if len(keyframes) == 1:
        return 0, playtime
    stamps = np.asarray([k["timestamp"] for k in keyframes], np.float32)
    duration = stamps[-1] if path["loop"] else stamps[-2]
    playtime = np.float32(playtime) * duration
    i = int(np.searchsorted(stamps, playtime, side="right"))  # std::upper_bound on timestamp
    i = min(max(i, 0), len(keyframes) - (1 if path["loop"] else 2))
    previous = np.float32(0.0) if i == 0 else stamps[i - 1]
    return i, float((playtime - previous) / (stamps[i] - previous))


def ngp_eval_camera_path(path: Dict[str, Any], playtime: float) -> Dict[str, Any]:
    """The keyframe NGP's camera takes at `playtime` in [0, 1] (`set_camera_from_time`).

    From NGP include/neural-graphics-primitives/camera_path.h `CameraPath::eval_camera_path` and
    `get_keyframe` (indices clamped, or wrapped for a loop) and src/camera_path.cu `get_pos` and
    `spline_linear`, `spline_quadratic`, `spline_cubic` (uniform B-spline weights on keyframes
    i-1..i+2, then the quaternion normalised): order 0 takes the nearest keyframe.
    """
    keyframes = path["keyframes"]
    n = len(keyframes)

    def key(i: int) -> Dict[str, Any]:
        return keyframes[(i + n) % n] if path["loop"] else keyframes[min(max(i, 0), n - 1)]

    i, t = _ngp_get_pos(path, playtime)
    order = path["spline_order"]
    if order == 0:
        return key(i + int(math.floor(t + 0.5)))
    if order == 1:
        return _kf_normalize(_kf_add(_kf_scale(key(i), 1.0 - t), _kf_scale(key(i + 1), t)))
    if order == 2:
        weights = [(1 - t) * (1 - t) * 0.5, (-2.0 * t * t + 2.0 * t + 1.0) * 0.5, t * t * 0.5]
        points = [key(i - 1), key(i), key(i + 1)]
    elif order == 3:
        weights = [
            (1 - t) ** 3 / 6.0,
            (3.0 * t**3 - 6.0 * t**2 + 4.0) / 6.0,
            (-3.0 * t**3 + 3.0 * t**2 + 3.0 * t + 1.0) / 6.0,
            t**3 / 6.0,
        ]
        points = [key(i - 1), key(i), key(i + 1), key(i + 2)]
    else:
        raise ValueError(f"Spline of order {order} is not supported.")
    total = _kf_scale(points[0], weights[0])
    for point, weight in zip(points[1:], weights[1:]):
        total = _kf_add(total, _kf_scale(point, weight))
    return _kf_normalize(total)


def ngp_keyframe_matrix(keyframe: Dict[str, Any]) -> np.ndarray:
    """NGP's camera matrix [3, 4] of a keyframe (`CameraKeyframe::m`: to_mat3(normalize(R)) and T)."""
    rotation = _matrix_of_quat_xyzw(keyframe["R"] / np.linalg.norm(keyframe["R"]))
    return np.concatenate([rotation, keyframe["T"][:, None]], axis=1)


def ngp_run_py_frame_times(video_n_seconds: int, video_fps: int) -> List[Tuple[float, float]]:
    """(start_time, end_time) of each frame `scripts/run.py --video_camera_path` renders.

    From NGP scripts/run.py: n_frames = video_n_seconds x video_fps (both integers); frame i is
    `testbed.render(..., float(i) / n_frames, float(i + 1) / n_frames, video_fps, shutter_fraction=0.5)`.
    In src/python_api.cu `Testbed::render_to_cpu`, the frame's camera starts at the path's pose at
    start_time (set at time 0 for the first frame, carried over from the previous frame's end
    otherwise) and moves, while the shutter is open, half of the way to the pose at end_time (motion blur).
    """
    if not (isinstance(video_n_seconds, int) and isinstance(video_fps, int)):
        raise TypeError("run.py takes --video_n_seconds and --video_fps as integers")
    n_frames = video_n_seconds * video_fps
    return [(float(i) / n_frames, float(i + 1) / n_frames) for i in range(n_frames)]


def ngp_fov_focal_length(fov_degrees: float, resolution: int) -> float:
    """NGP include/neural-graphics-primitives/common_device.cuh `fov_to_focal_length`; the fov axis is
    y (`Testbed::m_fov_axis = 1`), and `set_fov` gives both axes this focal length (relative to the height)."""
    return 0.5 * resolution / math.tan(0.5 * math.radians(fov_degrees))
