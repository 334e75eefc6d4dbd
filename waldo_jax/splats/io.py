"""Reading and writing 3D Gaussian Splatting scenes in the reference layout (Kerbl et al., SIGGRAPH 2023).

The reference code (graphdeco-inria/gaussian-splatting) saves a trained model as a folder:

  <model>/point_cloud/iteration_<N>/point_cloud.ply    the splats, one per PLY vertex;
  <model>/cameras.json                                  the cameras they were fitted to.

The PLY is binary little-endian, one `vertex` element of float properties
`x y z nx ny nz f_dc_0..2 f_rest_0..M-1 opacity scale_0..2 rot_0..3`: raw parameters before their
activations (logit opacity, log scales, quaternion w first and not unit), the normals zeros (gsplat's
exporter leaves them out). `f_rest` holds the SH coefficients 1..K-1 channel-major: all red ones, then
all green, then all blue, M = 3 (K - 1). `cameras.json` is a list of {id, img_name, width, height,
position, rotation, fy, fx}: the camera centre and the camera-to-world rotation in OpenCV axes (x right,
y down, z forward), a pinhole with its principal point at the image centre. We hold OpenGL c2w
(`waldo_jax.types`): the same matrix with its y and z columns negated.

Names: N splats, K SH coefficients per channel ((degree + 1)^2), M = 3 (K - 1) `f_rest` properties.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import re
import warnings
from pathlib import Path
from typing import Any, List, Optional, Sequence, Tuple

import numpy as np

from waldo_jax.errors import MIN_RESOLUTION, SceneFormatError, WaldoError, check_input_file
from waldo_jax.io import atomic_file, write_json
from waldo_jax.scenes.common import check_rigid
from waldo_jax.scenes.ply import PlyElement, PlyHeader, read_ply_header
from waldo_jax.splats.formats import find_splat_file, read_splat_file, splat_format
from waldo_jax.splats.model import MAX_SH_DEGREE, Splats, make_splats, sh_coefficients
from waldo_jax.types import Intrinsics

__all__ = [
    "SplatCameras",
    "SplatModel",
    "splat_ply_properties",
    "read_splat_ply",
    "write_splat_ply",
    "read_cameras_json",
    "write_cameras_json",
    "load_splat_model",
    "write_splat_model",
]

SH_C0 = 0.28209479177387814  # the degree-0 SH basis, 1 / (2 sqrt(pi)): colour = SH_C0 * f_dc + 0.5
# Focal lengths in pixels: below this, float32 projections lose all precision (and a tiny float64
# value flushes to 0); no camera of an image of MIN_RESOLUTION px or more has one (its FoV is 179.98 deg).
MIN_FOCAL = 1e-3

# The reference writes the photos' own size into cameras.json (5K and more for some captures); renders
# are made at --resolution (`Intrinsics.with_max_side`), so only sizes no camera has are refused.
MAX_CAMERA_SIDE = 65536
_FLOAT32_MAX = float(np.finfo(np.float32).max)
_XYZ = ("x", "y", "z")
_DC = ("f_dc_0", "f_dc_1", "f_dc_2")
_SCALES = ("scale_0", "scale_1", "scale_2")
_ROTS = ("rot_0", "rot_1", "rot_2", "rot_3")
_RGB = ("red", "green", "blue")
_FLOAT_TYPES = ("float", "float32", "double", "float64")
_REST = re.compile(r"f_rest_(\d+)")
_ITERATION = re.compile(r"iteration_(\d+)")
_CAMERA_KEYS = ("width", "height", "position", "rotation", "fx", "fy")


def splat_ply_properties(sh_degree: int, normals: bool = True) -> List[str]:
    """The reference PLY's vertex properties in their order, for SH `sh_degree` (0..3)."""
    rest = 3 * (sh_coefficients(sh_degree) - 1)
    return (
        list(_XYZ)
        + (["nx", "ny", "nz"] if normals else [])
        + list(_DC)
        + [f"f_rest_{i}" for i in range(rest)]
        + ["opacity"]
        + list(_SCALES)
        + list(_ROTS)
    )


# ---------------------------------------------------------------------------------------------
# The splat PLY.


def _splat_layout(path: Path, header: PlyHeader, vertex: PlyElement) -> Tuple[List[str], int, bool]:
    """Checks the vertex properties; returns (properties to read, M, colours from red/green/blue)."""
    types = dict(vertex.properties)
    if "packed_position" in types or header.element("chunk") is not None:
        raise SceneFormatError(
            path,
            "a compressed splat PLY (SuperSplat / gsplat 'ply_compressed'): not the reference layout, "
            "read it with load_splat_model or waldo_jax.splats.formats.read_compressed_ply",
        )
    rest = {int(m.group(1)): name for name in types if (m := _REST.fullmatch(name))}
    splat_only = set(_DC) | {"opacity"} | set(_SCALES) | set(_ROTS)
    if all(k in types for k in _XYZ) and not rest and not splat_only & set(types):
        raise SceneFormatError(
            path,
            f"a point cloud, not a splat scene (its vertices have {' '.join(types)}; "
            "a splat PLY's have f_dc_0..2, opacity, scale_0..2, rot_0..3)",
        )
    if vertex.has_lists:
        lists = [p for p, t in vertex.properties if t == "list"]
        raise SceneFormatError(
            path, f"the vertex element has list properties ({', '.join(lists)}): not supported in a splat PLY"
        )
    # nerfstudio's `ply_color_mode="rgb"` export writes red/green/blue in place of f_dc.
    from_rgb = not any(k in types for k in _DC) and all(k in types for k in _RGB)
    wanted = list(_XYZ) + ([] if from_rgb else list(_DC)) + ["opacity"] + list(_SCALES) + list(_ROTS)
    missing = [k for k in wanted if k not in types]
    if missing:
        raise SceneFormatError(
            path,
            f"missing splat properties {', '.join(missing)} (a splat PLY's vertices have "
            "x y z f_dc_0..2 f_rest_* opacity scale_0..2 rot_0..3)",
        )
    if header.format != "binary_little_endian":
        raise SceneFormatError(
            path,
            f"{header.format} PLY is not supported: convert it to binary_little_endian (the reference 3DGS layout)",
        )
    m = len(rest)
    gaps = [f"f_rest_{i}" for i in range(m) if i not in rest]
    if gaps:
        raise SceneFormatError(path, f"f_rest_* properties are not numbered 0..{m - 1}: missing {', '.join(gaps[:4])}")
    k = m // 3 + 1
    if m % 3 or math.isqrt(k) ** 2 != k or math.isqrt(k) - 1 > MAX_SH_DEGREE:
        raise SceneFormatError(
            path,
            f"{m} f_rest_* properties are no SH degree 0..{MAX_SH_DEGREE} (expected 0, 9, 24 "
            "or 45: 3 ((degree + 1)^2 - 1))",
        )
    wanted += [rest[i] for i in range(m)]
    wrong = [f"{p} is {types[p]}" for p in wanted if types[p] not in _FLOAT_TYPES]
    if wrong:
        raise SceneFormatError(path, f"splat properties must be float or double: {', '.join(wrong[:4])}")
    if from_rgb:
        wanted += list(_RGB)
    return wanted, m, from_rgb


def _check_values(path: Path, columns: dict, n: int) -> None:
    """Refuses non-finite values (naming the properties and rows) and zero quaternions (naming a row)."""
    bad_rows = np.zeros(n, bool)
    counts = []
    for name, values in columns.items():
        bad = ~np.isfinite(values)
        if bad.any():
            bad_rows |= bad
            counts.append(f"{name} ({int(bad.sum())} rows)")
    if counts:
        more = f" and {len(counts) - 6} more properties" if len(counts) > 6 else ""
        raise SceneFormatError(
            path,
            f"non-finite values (NaN, infinity, or beyond float32) in {int(bad_rows.sum())} "
            f"of {n} splats: {', '.join(counts[:6])}{more}",
        )
    quats = np.stack([columns[k] for k in _ROTS], -1)
    with np.errstate(over="ignore", under="ignore"):
        zero = np.flatnonzero(np.sum(quats * quats, -1) < np.finfo(np.float32).tiny)
    if len(zero):
        more = f" (and {len(zero) - 1} more rows)" if len(zero) > 1 else ""
        raise SceneFormatError(path, f"a zero quaternion (rot_0..3 all 0, no rotation) in row {int(zero[0])}{more}")


def read_splat_ply(path: str | os.PathLike) -> Splats:
    """Reads a 3D Gaussian Splatting PLY in the reference layout.

    Properties are found by name, in any order; other properties (normals, extras) are ignored;
    float64 properties are cast to float32. The SH degree (0..3) follows from the number of
    `f_rest_*` properties; nerfstudio's colour-only export (red/green/blue, no f_dc) gives
    f_dc = (rgb - 0.5) / SH_C0.

    Args:
      path: the .ply file.

    Returns:
      `Splats` with the file's raw values (log-scales, logits, quaternions w first as stored), all
      rows valid; sh[:, 0] = f_dc_0..2 and sh[:, k, c] = f_rest_{c (K - 1) + k - 1} for k >= 1.

    Raises:
      DataNotFoundError: no such file.
      SceneFormatError: (naming the file) not a PLY; an ASCII or big-endian PLY; a point cloud; a
        compressed PLY; missing, non-float or list properties; f_rest_* of no SH degree; zero
        splats; data shorter than the header promises; non-finite values; a zero quaternion.
    """
    path = check_input_file(path, "splat PLY file")
    try:
        with open(path, "rb") as f:
            header = read_ply_header(f, path)
            vertex = header.element("vertex")
            if vertex is None:
                raise SceneFormatError(path, "the PLY file has no 'vertex' element")
            wanted, m, from_rgb = _splat_layout(path, header, vertex)
            n = vertex.count
            if n == 0:
                raise SceneFormatError(path, "no splats (element vertex 0)")
            try:
                offset = header.offset_of("vertex")
            except ValueError as e:
                raise SceneFormatError(path, str(e)) from None
            dtype = vertex.dtype("<")
            expected = n * dtype.itemsize
            available = os.fstat(f.fileno()).st_size - offset
            if available < expected:
                raise SceneFormatError(
                    path,
                    f"truncated: {n} splats of {dtype.itemsize} bytes need {expected} bytes "
                    f"of data, the file holds {max(available, 0)}",
                )
            f.seek(offset)
            data = np.fromfile(f, dtype=dtype, count=n)
    except OSError as e:
        raise SceneFormatError(path, f"cannot read file ({e.strerror or e})") from None
    if len(data) != n:  # the file shrank while being read
        raise SceneFormatError(path, f"truncated: {n} splats expected, {len(data)} read")
    with np.errstate(over="ignore"):  # float64 beyond float32 becomes inf, refused below
        columns = {k: data[k].astype(np.float32) for k in wanted}
    if from_rgb:  # integer colours span their type's range (uchar 0..255), float ones 0..1
        for name, dc in zip(_RGB, _DC):
            kind = data.dtype[name]
            top = float(np.iinfo(kind).max) if kind.kind in "iu" else 1.0
            columns[dc] = ((columns.pop(name) / top - 0.5) / SH_C0).astype(np.float32)
    _check_values(path, columns, n)
    k = m // 3 + 1
    rest = np.stack([columns[f"f_rest_{i}"] for i in range(m)], -1) if m else np.zeros((n, 0), np.float32)
    sh = np.concatenate(
        [
            np.stack([columns[c] for c in _DC], -1)[:, None, :],  # [N, 1, 3]
            rest.reshape(n, 3, k - 1).transpose(0, 2, 1),
        ],
        axis=1,
    )  # [N, K, 3]
    return make_splats(
        means=np.stack([columns[c] for c in _XYZ], -1),
        log_scales=np.stack([columns[c] for c in _SCALES], -1),
        quats=np.stack([columns[c] for c in _ROTS], -1),
        logits=columns["opacity"],
        sh=sh,
    )


def write_splat_ply(path: str | os.PathLike, splats: Splats, normals: bool = True) -> Path:
    """Writes the valid rows of `splats` as a reference 3DGS PLY, atomically.

    The layout is the reference `save_ply`'s: binary_little_endian 1.0, `element vertex N`, float32
    properties `x y z nx ny nz f_dc_0..2 f_rest_0..M-1 opacity scale_0..2 rot_0..3` (normals zero;
    left out with `normals=False`, as gsplat writes), raw values, f_rest channel-major.

    Args:
      path: the .ply file (its folder is created).
      splats: the splats; rows with `valid` False are left out.
      normals: write the zero normals nx ny nz, as the reference does.

    Returns:
      `path` as a Path.

    Raises:
      WaldoError: no valid rows, or valid rows with non-finite values or a zero quaternion (which
        `read_splat_ply` would refuse): mark them invalid first.
    """
    path = Path(path)
    valid = np.asarray(splats.valid, bool)
    rows = np.flatnonzero(valid)
    if len(rows) == 0:
        raise WaldoError(f"{path}: no valid splats to write")
    sh = np.asarray(splats.sh, np.float32)[rows]  # [N, K, 3]
    n, k = sh.shape[:2]
    columns = [np.asarray(splats.means, np.float32)[rows]]
    columns += [np.zeros((n, 3), np.float32)] if normals else []
    columns += [
        sh[:, 0, :],
        sh[:, 1:, :].transpose(0, 2, 1).reshape(n, 3 * (k - 1)),
        np.asarray(splats.logits, np.float32)[rows, None],
        np.asarray(splats.log_scales, np.float32)[rows],
        np.asarray(splats.quats, np.float32)[rows],
    ]
    table = np.ascontiguousarray(np.concatenate(columns, axis=1), "<f4")  # [N, properties]
    quats = table[:, -4:]
    with np.errstate(over="ignore", under="ignore"):
        bad = ~np.all(np.isfinite(table), axis=1) | (np.sum(quats * quats, -1) < np.finfo(np.float32).tiny)
    if bad.any():
        raise WaldoError(
            f"{path}: {int(bad.sum())} valid splats have non-finite values or a zero quaternion (first: "
            f"row {int(rows[np.argmax(bad)])}); mark them invalid before writing"
        )
    names = splat_ply_properties(splats.sh_degree, normals)
    header = "".join(
        ["ply\n", "format binary_little_endian 1.0\n", f"element vertex {n}\n"]
        + [f"property float {name}\n" for name in names]
        + ["end_header\n"]
    )
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_file(path) as f:
        f.write(header.encode("ascii"))
        f.write(memoryview(table).cast("B"))
    return path


# ---------------------------------------------------------------------------------------------
# cameras.json.


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
    except (TypeError, ValueError):
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
        if (
            isinstance(v, bool)
            or not isinstance(v, (int, float))
            or not math.isfinite(v)
            or not MIN_FOCAL <= v < _FLOAT32_MAX
        ):
            raise SceneFormatError(
                path, f"{what}: {key} must be a finite focal length of at least {MIN_FOCAL:g} pixels, got {v!r}"
            )
        focal.append(float(v))
    return Intrinsics.create(sides[0], sides[1], focal[0], focal[1])


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
    try:
        entries = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError) as e:
        raise SceneFormatError(path, f"cannot read the cameras file ({e})") from None
    except json.JSONDecodeError as e:
        raise SceneFormatError(path, f"malformed JSON at line {e.lineno}, column {e.colno}: {e.msg}") from None
    except RecursionError:
        raise SceneFormatError(path, "JSON nested too deeply") from None
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


# ---------------------------------------------------------------------------------------------
# Model folders.


@dataclasses.dataclass(frozen=True, eq=False)
class SplatModel:
    """A splat scene loaded by `load_splat_model`.

    Attributes:
      splats: the splats.
      cameras: the cameras that come with it (`waldo_jax.splats.cameras.find_splat_cameras`), or None.
      ply_path: the PLY read.
      iteration: N of `point_cloud/iteration_N/`, or None outside that layout.
      source: where the scene came from, in words.
    """

    splats: Splats
    cameras: Optional[SplatCameras]
    ply_path: Path
    iteration: Optional[int]
    source: str


def _iteration_of(ply: Path) -> Optional[int]:
    """N when `ply` lies in `point_cloud/iteration_N/`, else None."""
    m = _ITERATION.fullmatch(ply.parent.name)
    return int(m.group(1)) if m and ply.parent.parent.name == "point_cloud" else None


def _cameras_beside(ply: Path) -> Optional[Path]:
    """cameras.json beside `ply`, else at the model root of the reference layout, else None."""
    candidates = [ply.parent / "cameras.json"]
    if _iteration_of(ply) is not None:
        candidates.append(ply.parent.parent.parent / "cameras.json")
    return next((c for c in candidates if c.is_file()), None)


def _find_ply(folder: Path) -> Tuple[Path, Optional[int]]:
    """The PLY of a model folder: the highest point_cloud/iteration_N/point_cloud.ply, else point_cloud.ply."""
    iterations = folder / "point_cloud" if (folder / "point_cloud").is_dir() else None
    if iterations is None and folder.name == "point_cloud":
        iterations = folder
    if iterations is not None:
        found = {
            int(m.group(1)): d / "point_cloud.ply"
            for d in iterations.iterdir()
            if (m := _ITERATION.fullmatch(d.name)) and (d / "point_cloud.ply").is_file()
        }
        if found:
            return found[max(found)], max(found)
    if (folder / "point_cloud.ply").is_file():
        return folder / "point_cloud.ply", _iteration_of(folder / "point_cloud.ply")
    other = find_splat_file(folder)  # a .splat, .spz, .sog, compressed PLY or SOG meta.json
    if other is not None:
        return other, None
    holds = "; its point_cloud/ holds no iteration_<N>/point_cloud.ply" if iterations is not None else ""
    raise SceneFormatError(
        folder,
        "no splat scene here: looked for point_cloud/iteration_<N>/point_cloud.ply (the "
        f"reference 3DGS layout), one file of another splat format and point_cloud.ply{holds}",
    )


def load_splat_model(path: str | os.PathLike) -> SplatModel:
    """Loads a splat scene from a PLY file or a model folder.

    Accepts a `.ply` file (with the cameras.json beside it, or at the model root when the file lies
    in `point_cloud/iteration_N/`); a folder in the reference layout (`point_cloud/iteration_N/
    point_cloud.ply`, the highest N taken numerically, `cameras.json` at the root); its
    `point_cloud/` folder; or a folder holding `point_cloud.ply` directly. A scene without a
    camera file has `cameras` None (cameras.json, else a nerfstudio run, else a COLMAP model:
    `waldo_jax.splats.cameras.find_splat_cameras`).
    A file (or a folder's one file) of another splat format in
    `waldo_jax.splats.formats.FORMATS` (.splat, .spz, SOG, compressed PLY) loads too, `source` naming it.

    Raises:
      SceneFormatError: no such path, a folder in no such layout (listing what was looked for), or
        a malformed PLY or camera file (see `read_splat_ply`, `find_splat_cameras`).
    """
    path = Path(path).expanduser()
    if not path.exists():
        raise SceneFormatError(
            path,
            "no such file or folder"
            if not os.path.islink(path)
            else "a symbolic link that leads nowhere (a loop or a missing target)",
        )
    if path.is_dir():
        ply, iteration = _find_ply(path)
    else:
        ply, iteration = path, _iteration_of(path)
    fmt = splat_format(ply)
    if fmt is None and ply.suffix.lower() == ".ply":
        fmt = "ply"  # a malformed PLY: read_splat_ply says what is wrong with it
    splat_file = None if fmt == "ply" else read_splat_file(ply)  # unknown: an error listing the formats
    splats = read_splat_ply(ply) if splat_file is None else splat_file.splats
    from waldo_jax.splats.cameras import find_splat_cameras  # here: that module imports this one

    found = find_splat_cameras(ply)  # cameras.json, a nerfstudio run, a COLMAP model
    cameras = None if found is None else found[0]
    if iteration is not None:
        source = f"3DGS model {ply.parent.parent.parent}, iteration {iteration}"
    else:
        source = f"splat PLY {ply}" if splat_file is None else f"{splat_file.details}: {ply}"
    if found is not None:
        source += f", with {len(cameras)} cameras from {found[1]}"
    return SplatModel(splats, cameras, ply, iteration, source)


def write_splat_model(
    folder: str | os.PathLike,
    splats: Splats,
    iteration: int,
    cameras: Optional[SplatCameras] = None,
    normals: bool = True,
) -> Path:
    """Writes a model folder in the reference layout.

    Writes `<folder>/point_cloud/iteration_<iteration>/point_cloud.ply` (see `write_splat_ply`) and,
    when `cameras` is given, `<folder>/cameras.json` (see `write_cameras_json`).

    Returns:
      The path of the PLY written.
    """
    if isinstance(iteration, bool) or not isinstance(iteration, (int, np.integer)) or iteration < 0:
        raise ValueError(f"iteration must be a non-negative integer, got {iteration!r}")
    folder = Path(folder)
    ply = write_splat_ply(folder / "point_cloud" / f"iteration_{int(iteration)}" / "point_cloud.ply", splats, normals)
    if cameras is not None:
        write_cameras_json(folder / "cameras.json", cameras.c2w, cameras.intrinsics, cameras.names)
    return ply
