"""Where a splat scene's cameras come from: cameras.json, a nerfstudio splatfacto run, a COLMAP model.

`find_splat_cameras(ply_or_folder)` looks, in this order, for
  1. `cameras.json` beside the PLY, or at the model root of the reference layout
     (`<model>/point_cloud/iteration_N/point_cloud.ply`): `waldo_jax.splats.io.read_cameras_json`;
  2. a nerfstudio run (`outputs/<name>/<method>/<timestamp>/`, holding `config.yml` and
     `dataparser_transforms.json`): the PLY's folder, the one above it, or the one run in a folder
     below the PLY's (`*/` or `outputs/*/*/*/`);
  3. a COLMAP sparse model (`sparse/0/`, `sparse/` or the folder itself: `images.bin` or `images.txt`)
     in the PLY's folder, or at the model root of the reference layout.

Frames. A reference 3DGS model lives in its COLMAP model's world: COLMAP cameras are used as they
are. `ns-export gaussian-splat` writes splatfacto's means as trained, in nerfstudio's dataparser frame.
The run's data holds the cameras in the data's own frame (`transforms.json`: OpenGL c2w P); the
model's pose is T P with its translation times s, (T, s) being `dataparser_transforms.json` with the
data's `applied_transform` folded back out (`tool_frames.nerfstudio_pose_transform`): a point p goes to
s (T [p; 1]), a rotation R to T[:3, :3] R. A run of nerfstudio's colmap dataparser reads its COLMAP
model (`colmap_path` under the data), whose world the saved transform maps directly.

Every camera is a pinhole (fx, fy, cx, cy; the principal point as the file gives it, off-centre
allowed): a lens distortion is dropped with a warning, a fisheye or spherical camera refused.
"""

from __future__ import annotations

import math
import os
import warnings
from pathlib import Path
from typing import Any, Dict, List, Optional, Tuple

import numpy as np
import yaml

from waldo_jax.errors import MIN_RESOLUTION, SceneFormatError, WaldoError, check_input_file, read_input_file
from waldo_jax.scenes.colmap import (
    PINHOLE_LIKE_MODELS,
    ColmapCamera,
    colmap_c2w,
    find_colmap_model,
    read_colmap_model,
)
from waldo_jax.scenes.common import check_rigid, intrinsics_problem, natural_key, number, read_json
from waldo_jax.scenes.tool_frames import nerfstudio_applied, nerfstudio_pose_transform, read_dataparser_transform
from waldo_jax.splats.cameras_json import (
    MAX_CAMERA_SIDE,
    SplatCameras,
    cameras_beside,
    check_camera_aspect,
    iteration_of,
    read_cameras_json,
)
from waldo_jax.types import Intrinsics

__all__ = [
    "NERFSTUDIO_RUN_FILES",
    "find_splat_cameras",
    "read_camera_source",
    "read_colmap_cameras",
    "read_nerfstudio_cameras",
]

NERFSTUDIO_RUN_FILES = ("config.yml", "dataparser_transforms.json")
# A nerfstudio config.yml is a few KiB (its dataclasses written out); PyYAML takes about 400 times a file's
# size in memory and 8 MB of nested lists took 147 s to read: past this it is refused unread.
CONFIG_MAX_BYTES = 4 * 2**20
# nerfstudio camera models (transforms.json `camera_model`) that are pinholes, with or without distortion.
_NERFSTUDIO_PINHOLES = ("SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV", "FULL_OPENCV")
_DISTORTION_KEYS = ("k1", "k2", "k3", "k4", "p1", "p2")


def _pinhole(width: Any, height: Any, focal: Tuple[Any, Any, Any, Any], path: Path, what: str) -> Intrinsics:
    """A validated pinhole of (width, height, (fx, fy, cx, cy)), else a SceneFormatError naming `what`."""
    try:
        values = [float(v) for v in focal]
        sides = [int(width), int(height)]
    except (TypeError, ValueError, OverflowError):
        raise SceneFormatError(path, f"{what}: size and focal lengths must be numbers") from None
    if not all(math.isfinite(v) for v in values) or min(sides) < 1:
        raise SceneFormatError(path, f"{what}: non-finite focal length or principal point, or an empty image")
    if max(sides) > MAX_CAMERA_SIDE:
        raise SceneFormatError(path, f"{what}: image of {sides[0]}x{sides[1]} pixels (at most {MAX_CAMERA_SIDE})")
    intrinsics = Intrinsics.create(sides[0], sides[1], *values)
    check_camera_aspect(intrinsics, path, what)
    problem = intrinsics_problem(intrinsics, (MIN_RESOLUTION, MAX_CAMERA_SIDE))
    if problem:
        raise SceneFormatError(path, f"{what}: {problem}")
    return intrinsics


# ---------------------------------------------------------------------------------------------
# COLMAP.


def read_colmap_cameras(path: str | os.PathLike) -> SplatCameras:
    """The registered images of a COLMAP sparse model as `SplatCameras`, sorted by image name.

    Args:
      path: a model folder (or one holding `sparse/0/` or `sparse/`), or its images.bin/.txt file.

    Returns:
      `SplatCameras`: OpenGL c2w (the world-to-camera (q, t) inverted, y and z axes negated); each
      image's camera as a pinhole with the file's fx, fy, cx, cy (distortion dropped, with a warning);
      names as the file gives them.

    Raises:
      SceneFormatError (naming the file): no model there, a malformed file (see `read_colmap_model`),
        no registered images, an image of a missing camera, a fisheye or spherical camera, a zero or
        non-finite quaternion, a camera a render cannot use.
    """
    path = Path(path)
    found = find_colmap_model(path)
    if found is None:
        raise SceneFormatError(
            path, "no COLMAP model here: looked for images.bin or images.txt in it, in sparse/0/ and in sparse/"
        )
    folder, ext = found
    cameras, images = read_colmap_model(folder, ext)
    images_path, cameras_path = folder / f"images{ext}", folder / f"cameras{ext}"
    if not images:
        raise SceneFormatError(images_path, "no registered images")
    pinholes: Dict[int, Intrinsics] = {}
    distorted: List[ColmapCamera] = []
    poses, intrinsics, names = [], [], []
    for image in sorted(images, key=lambda im: natural_key(im.name)):
        what = f"image {image.image_id} ({image.name!r})"
        camera = cameras.get(image.camera_id)
        if camera is None:
            raise SceneFormatError(images_path, f"{what}: camera {image.camera_id} is not in {cameras_path.name}")
        if image.camera_id not in pinholes:
            if camera.model not in PINHOLE_LIKE_MODELS:
                raise SceneFormatError(
                    cameras_path,
                    f"camera {camera.camera_id} is a {camera.model} camera: only pinhole-like models are read "
                    f"({', '.join(sorted(PINHOLE_LIKE_MODELS))}); undistort the images first "
                    "(colmap image_undistorter)",
                )
            pinholes[image.camera_id] = _pinhole(
                camera.width, camera.height, camera.pinhole(), cameras_path, f"camera {camera.camera_id}"
            )
            if any(v != 0.0 for v in camera.extra_params):
                distorted.append(camera)
        qvec = np.asarray(image.qvec, np.float64)
        if not np.all(np.isfinite(qvec)) or not np.all(np.isfinite(image.tvec)) or np.max(np.abs(qvec)) == 0.0:
            raise SceneFormatError(images_path, f"{what}: zero or non-finite quaternion or translation")
        poses.append(check_rigid(colmap_c2w(image), images_path, what))
        intrinsics.append(pinholes[image.camera_id])
        names.append(image.name)
    if distorted:
        models = sorted({c.model for c in distorted})
        warnings.warn(
            f"{cameras_path}: the lens distortion of {len(distorted)} camera(s) ({', '.join(models)}) is "
            "ignored: the splats are rendered through a pinhole with their fx, fy, cx, cy",
            stacklevel=2,
        )
    return SplatCameras(np.stack(poses).astype(np.float32), tuple(intrinsics), tuple(names))


# ---------------------------------------------------------------------------------------------
# nerfstudio runs.


class _ConfigLoader(yaml.SafeLoader):
    """A SafeLoader that builds every tagged node (nerfstudio's `!!python/object:...` dataclasses) as
    plain data: objects as dicts, `pathlib` paths as Paths. No tag is executed or imported."""


def _untagged(loader: _ConfigLoader, node: yaml.Node) -> Any:
    if isinstance(node, yaml.MappingNode):
        value = loader.construct_mapping(node, deep=True)
        args = value.get("args") if "pathlib" in node.tag else None
        return _path_of(args) if isinstance(args, list) else value
    if isinstance(node, yaml.SequenceNode):
        items = loader.construct_sequence(node, deep=True)
        return _path_of(items) if "pathlib" in node.tag else items
    return loader.construct_scalar(node)


def _path_of(parts: list) -> Any:
    """Path(*parts) of a pickled pathlib path (`!!python/object/apply:pathlib.PosixPath [parts]`)."""
    return Path(*parts) if all(isinstance(p, str) for p in parts) else parts


_ConfigLoader.add_constructor(None, _untagged)


def _get(tree: Any, *keys: str) -> Any:
    for key in keys:
        tree = tree.get(key) if isinstance(tree, dict) else None
    return tree


def _read_run_config(path: Path) -> Dict[str, Any]:
    """config.yml as nested dicts (tags ignored), else a SceneFormatError naming it."""
    try:  # its size against the free memory first: it is read whole
        text = read_input_file(
            path, "nerfstudio config", lambda problem: SceneFormatError(path, problem), True, CONFIG_MAX_BYTES
        )
    except UnicodeDecodeError as e:
        raise SceneFormatError(path, f"cannot read the file ({e})") from None
    try:
        config = yaml.load(text, Loader=_ConfigLoader)  # noqa: S506 (a SafeLoader: no tag runs code)
    except (yaml.YAMLError, RecursionError) as e:
        raise SceneFormatError(path, f"not a readable YAML file ({' '.join(str(e).split())[:200]})") from None
    if not isinstance(config, dict):
        raise SceneFormatError(path, "expected nerfstudio's config (a YAML mapping)")
    return config


def _data_path(config: Dict[str, Any], path: Path) -> Path:
    """The run's data: pipeline.datamanager.data (ns-train --data), else its dataparser's, else `data`."""
    datamanager = _get(config, "pipeline", "datamanager")
    values = [_get(datamanager, "data"), _get(datamanager, "dataparser", "data"), config.get("data")]
    paths = [Path(v) for v in values if isinstance(v, (str, Path))]
    chosen = next((p for p in paths if p != Path(".")), paths[0] if paths else None)
    if chosen is None:
        raise SceneFormatError(path, "names no data (pipeline.datamanager.dataparser.data)")
    return chosen


class NerfstudioDataMissing(SceneFormatError):
    """A nerfstudio run whose config names a data folder that is not here (its cameras live there)."""


def _locate_data(data: Path, run: Path, config: Dict[str, Any], path: Path, found) -> Path:
    """`data` where `found(candidate)` holds: as written when absolute; else under the folder ns-train
    ran in (the run is <output_dir>/<experiment>/<method>/<timestamp>), the run's other ancestors, the
    current folder."""
    if data.is_absolute():
        candidates = [data]
    else:
        ancestors = list(run.resolve().parents)
        output_dir = config.get("output_dir")
        depth = len(Path(output_dir).parts) if isinstance(output_dir, (str, Path)) else 1
        if not Path(output_dir or ".").is_absolute() and 2 + depth < len(ancestors):
            ancestors.insert(0, ancestors[2 + depth])  # the folder ns-train ran in, if the run was not moved
        candidates = [a / data for a in ancestors] + [Path.cwd() / data]
    for candidate in candidates:
        if found(candidate):
            return candidate
    shown = ", ".join(str(c) for c in dict.fromkeys(candidates[:3]))
    raise NerfstudioDataMissing(
        path,
        f"names the data {data}, which is not here (looked at {shown}{', ...' if len(candidates) > 3 else ''}): "
        "put the data back where the run was trained, or pass the cameras with --cameras",
    )


def _nerfstudio_frames(transforms: Path) -> SplatCameras:
    """The cameras of a nerfstudio transforms.json in its own frame, sorted by file path (as nerfstudio)."""
    meta = read_json(transforms)
    frames = meta.get("frames")
    if not isinstance(frames, list) or not frames:
        raise SceneFormatError(transforms, "no 'frames' list (nerfstudio transforms.json)")
    model = meta.get("camera_model", "OPENCV")
    if model not in _NERFSTUDIO_PINHOLES:
        raise SceneFormatError(
            transforms, f"camera_model {model!r} is not a pinhole ({', '.join(_NERFSTUDIO_PINHOLES)} are read)"
        )
    entries = []
    distorted = 0
    for i, frame in enumerate(frames):
        what = f"frame {i}"
        if not isinstance(frame, dict) or not isinstance(frame.get("file_path"), str):
            raise SceneFormatError(transforms, f"{what} has no 'file_path'")
        camera = {**meta, **frame}
        missing = [k for k in ("w", "h", "fl_x") if number(camera, k, transforms) is None]
        if missing:
            raise SceneFormatError(transforms, f"{what}: no {', '.join(missing)} (nor at the top level)")
        fl_x = number(camera, "fl_x", transforms, positive=True)
        fl_y = number(camera, "fl_y", transforms, positive=True) or fl_x
        w, h = number(camera, "w", transforms), number(camera, "h", transforms)
        cx, cy = number(camera, "cx", transforms), number(camera, "cy", transforms)
        focal = (fl_x, fl_y, w / 2 if cx is None else cx, h / 2 if cy is None else cy)
        intrinsics = _pinhole(w, h, focal, transforms, what)
        distorted += any(number(camera, k, transforms) for k in _DISTORTION_KEYS)
        try:
            c2w = np.asarray(frame.get("transform_matrix"), np.float64)
        except (TypeError, ValueError, OverflowError):
            c2w = np.zeros(0)
        if c2w.shape == (3, 4):
            c2w = np.concatenate([c2w, [[0.0, 0.0, 0.0, 1.0]]])
        if c2w.shape != (4, 4):
            raise SceneFormatError(transforms, f"{what}: transform_matrix is not a 3x4 or 4x4 matrix of numbers")
        entries.append((frame["file_path"], check_rigid(c2w, transforms, what), intrinsics))
    if distorted:
        warnings.warn(
            f"{transforms}: the lens distortion of {distorted} frame(s) is ignored: the splats are rendered "
            "through a pinhole with their fl_x, fl_y, cx, cy",
            stacklevel=3,
        )
    entries.sort(key=lambda e: e[0])
    return SplatCameras(np.stack([e[1] for e in entries]), tuple(e[2] for e in entries), tuple(e[0] for e in entries))


def read_nerfstudio_cameras(run: str | os.PathLike) -> Tuple[SplatCameras, str]:
    """The training cameras of a nerfstudio run (splatfacto), in its model's frame (where `ns-export
    gaussian-splat` writes the splats).

    Args:
      run: the run folder (`outputs/<name>/<method>/<timestamp>/`) or its config.yml.

    Returns:
      (cameras, a description): OpenGL c2w float32 [N, 4, 4] moved by the dataparser transform;
      pinholes from the data's transforms.json (or COLMAP model), distortion dropped with a warning.

    Raises:
      SceneFormatError (naming the file): a missing or unreadable config.yml or
        dataparser_transforms.json, a config naming data that is not found, malformed cameras.
    """
    run = Path(run)
    if run.name == "config.yml":
        run = run.parent
    config_path, transform_path = (run / name for name in NERFSTUDIO_RUN_FILES)
    for path in (config_path, transform_path):
        try:
            check_input_file(path, "file")
        except WaldoError as e:  # nothing there, or a folder, a FIFO, a link loop: said as such
            problem = str(e).removeprefix(f"{path}: ")
            raise SceneFormatError(
                path, f"{problem} (a nerfstudio run holds config.yml and dataparser_transforms.json)"
            ) from None
    config = _read_run_config(config_path)
    try:
        dataparser = read_dataparser_transform(read_json(transform_path))
    except ValueError as e:
        raise SceneFormatError(transform_path, str(e)) from None
    data = _data_path(config, config_path)
    colmap_path = _get(config, "pipeline", "datamanager", "dataparser", "colmap_path")
    if isinstance(colmap_path, (str, Path)):  # nerfstudio's colmap dataparser: the saved transform maps COLMAP's world
        data = _locate_data(data, run, config, config_path, lambda d: find_colmap_model(d / colmap_path) is not None)
        cameras = read_colmap_cameras(data / colmap_path)
        transform, scale = dataparser
        source = f"{data / colmap_path}"
    else:
        data = _locate_data(data, run, config, config_path, _has_transforms)
        transforms = data if data.suffix == ".json" else data / "transforms.json"
        cameras = _nerfstudio_frames(transforms)
        try:
            applied, applied_scale, _ = nerfstudio_applied(read_json(transforms), data)
        except ValueError as e:
            raise SceneFormatError(transforms, str(e)) from None
        transform, scale = nerfstudio_pose_transform(dataparser, applied, applied_scale)
        source = f"{transforms}"
    c2w = transform @ np.asarray(cameras.c2w, np.float64)  # [N, 4, 4]
    c2w[:, :3, 3] *= scale
    for i, m in enumerate(c2w):
        check_rigid(m, transform_path, f"camera {i} ({cameras.names[i]!r}) moved by the dataparser transform")
    moved = SplatCameras(c2w.astype(np.float32), cameras.intrinsics, cameras.names)
    return moved, f"nerfstudio run {run} ({source}, moved into the splats' frame by {transform_path.name})"


def _has_transforms(data: Path) -> bool:
    """True when `data` is a nerfstudio data folder with transforms.json, or such a JSON file itself."""
    return (data / "transforms.json").is_file() or (data.suffix == ".json" and data.is_file())


def _is_run(folder: Path) -> bool:
    return all((folder / name).is_file() for name in NERFSTUDIO_RUN_FILES)


def _nerfstudio_run_near(base: Path) -> Optional[Path]:
    """The nerfstudio run at `base` or above it, else the only one below it (a warning when several)."""
    for folder in (base, base.parent):
        if _is_run(folder):
            return folder
    below = sorted(
        {c.parent for pattern in ("*/config.yml", "outputs/*/*/*/config.yml") for c in base.glob(pattern)},
        key=str,
    )
    below = [run for run in below if _is_run(run)]
    if len(below) > 1:
        warnings.warn(
            f"{base}: {len(below)} nerfstudio runs below (first: {below[0]}, {below[1]}): none is used for "
            "the cameras; name one with --cameras",
            stacklevel=3,
        )
    return below[0] if len(below) == 1 else None


# ---------------------------------------------------------------------------------------------
# The lookup.


def read_camera_source(path: str | os.PathLike) -> Optional[Tuple[SplatCameras, str]]:
    """The cameras of a COLMAP model (folder, `images.bin`/`.txt`) or a nerfstudio run (folder,
    config.yml) at `path`, with a description; None when `path` is neither (a poses file, say).

    Raises:
      SceneFormatError: `path` is a folder holding part of a run (one of its two files) or of a COLMAP
        model (its cameras or points without images.bin / images.txt), named by what it lacks; or what
        `read_nerfstudio_cameras` and `read_colmap_cameras` raise.
    """
    path = Path(path)
    if path.name == "config.yml" or (path.is_dir() and _is_run(path)):
        return read_nerfstudio_cameras(path)
    found = find_colmap_model(path)
    if found is not None:
        folder, ext = found
        return read_colmap_cameras(path), f"COLMAP model {folder} (images{ext})"
    if path.is_dir() and any(os.path.lexists(path / name) for name in NERFSTUDIO_RUN_FILES):
        return read_nerfstudio_cameras(path)  # part of a run: refused by the file it lacks (or cannot read)
    held = [name for name in _COLMAP_OTHERS if (path / name).exists()] if path.is_dir() else []
    if held:
        raise SceneFormatError(
            path,
            f"a COLMAP model without images.bin or images.txt, which hold its poses (it holds {', '.join(held)})",
        )
    return None


# A COLMAP model's files besides images.bin / images.txt, which hold its poses.
_COLMAP_OTHERS = ("cameras.bin", "cameras.txt", "points3D.bin", "points3D.txt")


def find_splat_cameras(ply_or_folder: str | os.PathLike) -> Optional[Tuple[SplatCameras, str]]:
    """The cameras that come with a splat scene, and where they came from in words; None without any.

    Looks, in this order, for `cameras.json` (beside the PLY, or at the reference layout's model
    root), a nerfstudio run (the PLY's folder, the one above, or the only run below it), a COLMAP
    sparse model (`sparse/0/`, `sparse/` or the folder itself, in the PLY's folder or the model root).
    The first found is read; a malformed one raises rather than falling through, except a nerfstudio
    run whose data folder is gone (a warning: the search then starts from a ring of views).

    Args:
      ply_or_folder: the splats' PLY, or the folder holding the scene.

    Returns:
      (SplatCameras in the splats' frame, a description such as "cameras.json"), or None.

    Raises:
      SceneFormatError (naming the file): a malformed camera file (see `read_cameras_json`,
        `read_nerfstudio_cameras`, `read_colmap_cameras`).
    """
    path = Path(ply_or_folder)
    base = path if path.is_dir() else path.parent
    json_path = base / "cameras.json" if path.is_dir() else cameras_beside(path)
    if json_path is not None and os.path.lexists(json_path):  # a FIFO or folder there: read_cameras_json says so
        return read_cameras_json(json_path), json_path.name
    run = _nerfstudio_run_near(base)
    if run is not None:
        try:
            return read_nerfstudio_cameras(run)
        except NerfstudioDataMissing as error:
            # Found by looking around, not asked for: the splats still load, from a ring of views.
            warnings.warn(f"{error}; its cameras are not read", stacklevel=2)
    folders = [base]
    if not path.is_dir() and iteration_of(path) is not None:
        folders.append(path.parent.parent.parent)
    for folder in folders:
        found = find_colmap_model(folder)
        if found is not None:
            return read_colmap_cameras(found[0] / f"images{found[1]}"), f"COLMAP model {found[0]} (images{found[1]})"
    return None
