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

import contextlib
import errno
import functools
import math
import os
import re
import warnings
from pathlib import Path, PurePosixPath
from typing import Any, Dict, Iterator, List, Optional, Sequence, Tuple

import numpy as np

from waldo_jax.io import read_json_file
from waldo_jax.errors import (
    MAX_RESOLUTION,
    MIN_RESOLUTION,
    NumberError,
    SceneFormatError,
    WaldoError,
    check_float32,
    check_input_file,
)
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
    "shown",
    "input_file",
    "file_name_problem",
    "numeric_array",
    "field",
    "value_text",
    "check_holdout_split",
    "distortion_problem",
    "blender_split_of",
    "locate",
    "detect_format",
    "check_rigid",
    "rigid_problem",
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
    "one_line_errors",
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
# Files a scene names, and the typed fields of its JSON.


def shown(text: Any) -> str:
    """`text` (a path or a name) with each character that would break one line of output (a newline, an
    ANSI escape, any other control character) written as its Python escape (``\\n``, ``\\x1b``)."""
    text = str(os.fspath(text)) if isinstance(text, os.PathLike) else str(text)
    if text.isprintable():
        return text
    return "".join(c if c.isprintable() else repr(c)[1:-1] for c in text)


@contextlib.contextmanager
def one_line_errors() -> Iterator[None]:
    """Makes every `WaldoError` raised in its body one printable line (`shown`): a file name that holds a
    newline or an escape sequence must not split or forge the error line. A `with` block, not a wrapper,
    so that the warnings of the body keep their stack level."""
    try:
        yield
    except WaldoError as e:
        if str(e).isprintable():
            raise
        if isinstance(e, SceneFormatError):
            raise SceneFormatError(shown(e.path), shown(e.problem)) from None
        try:
            escaped = type(e)(shown(str(e)))
        except TypeError:
            escaped = WaldoError(shown(str(e)))
        raise escaped from None


def input_file(path: str | os.PathLike, what: str) -> Path:
    """`path` if it is a readable regular file (or a link to one), else a `SceneFormatError` that names it
    (`shown`) and says what it is: missing, a dangling link, a directory, a FIFO or device, a link loop.
    Called before anything opens a file a scene names: a FIFO blocks a reader, /dev/zero never ends."""
    path = Path(path)
    if os.path.islink(path) and not os.path.exists(path) and os.path.lexists(path):
        try:
            os.stat(path)
        except FileNotFoundError:  # a loop raises ELOOP instead, which `check_input_file` names
            raise SceneFormatError(
                shown(path), f"a symbolic link to a missing file, where a {what} was expected"
            ) from None
        except OSError:
            pass
    try:
        return check_input_file(path, what)
    except WaldoError as e:
        text, prefix = str(e), f"{path}: "
        raise SceneFormatError(shown(path), text[len(prefix) :] if text.startswith(prefix) else text) from None


def file_name_problem(name: str) -> Optional[str]:
    """What keeps a path field (a frame's `file_path`, `ply_file_path`) from naming a file, or None: it is
    empty, holds a control character (a newline, an escape: no file name does), or its last part names a
    folder ("/", ".", "..", a trailing slash)."""
    if not name:
        return "is empty: it names no file"
    if not name.isprintable():
        return f"'{shown(name)}' holds control characters (a newline, an escape, ...): it is no file name"
    if name.endswith("/") or PurePosixPath(name).name in ("", ".", ".."):
        return f"'{shown(name)}' names a folder, not a file"
    return None


def numeric_array(value: Any) -> Optional[np.ndarray]:
    """`value` as float64 if it is a number or nested lists of numbers (JSON's), else None: strings and
    booleans are refused, not converted ("1" and true are no matrix entries), as are ragged lists."""

    def numeric(v: Any, depth: int) -> bool:
        if isinstance(v, (list, tuple)):
            return depth < 8 and all(numeric(x, depth + 1) for x in v)
        if isinstance(v, np.ndarray):
            return v.dtype.kind in "iuf"
        return isinstance(v, (int, float, np.integer, np.floating)) and not isinstance(v, (bool, np.bool_))

    if not numeric(value, 0):
        return None
    try:
        return np.asarray(value, np.float64)
    except (TypeError, ValueError, OverflowError):  # ragged, or an integer past float64
        return None


_FIELD_KINDS = {"string": "a string", "number": "a number", "flag": "true or false", "list": "a list"}
_FIELD_KINDS.update(object="an object", matrix="a matrix of numbers")


def field(meta: Any, key: str, path: Path, kind: str, where: str = "", positive: bool = False, default: Any = None):
    """`meta[key]` checked to be of `kind`, else a `SceneFormatError` naming `path`, `where` and the key;
    `default` when the key is absent (a number's null is absent too).

    Kinds: "string" (a str), "number" (a float that stays finite in float32, > 0 there with `positive`;
    not a bool), "flag" (a bool), "list", "object" (a dict), "matrix" (float64 array of nested lists of
    numbers, see `numeric_array`; its shape is the caller's to check).
    """
    if kind not in _FIELD_KINDS:
        raise ValueError(f"unknown field kind {kind!r}")
    if not isinstance(meta, dict) or key not in meta or (kind == "number" and meta[key] is None):
        return default
    value = meta[key]
    label = f"{where}: {key!r}" if where else repr(key)
    if kind == "number":
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise SceneFormatError(path, f"{label} must be a finite number, got {value_text(value)}")
        try:
            return check_float32(value, label, positive=positive)
        except NumberError as e:
            raise SceneFormatError(path, str(e)) from None
    if kind == "matrix":
        array = numeric_array(value)
        if array is None:
            raise SceneFormatError(path, f"{label} must be a matrix of numbers, got {value_text(value)}")
        return array
    types = {"string": str, "flag": bool, "list": list, "object": dict}[kind]
    if not isinstance(value, types):
        raise SceneFormatError(path, f"{label} must be {_FIELD_KINDS[kind]}, got {value_text(value)}")
    return value


def value_text(value: Any) -> str:
    """A JSON value for a message: its type and (shortened, escaped) repr."""
    text = shown(repr(value))
    return f"{type(value).__name__} {text if len(text) <= 60 else text[:57] + '...'}"


def check_holdout_split(split: str, fmt: str, path: Path) -> None:
    """Refuses split "val" for a format that holds out only a test split (every `TEST_EVERY`-th image):
    its "val" would be every image, the held-out ones included."""
    if split == "val":
        raise SceneArgumentError(
            f"{shown(path)}: split 'val' does not exist in {fmt} scenes: they hold out every {TEST_EVERY}th "
            "image as 'test' (splits: all, train, test)"
        )


# ----------------------------------------------------------------------------------------------
# Format detection.


def read_json(path: Path) -> Dict[str, Any]:
    """Parses a JSON object, turning every failure into a `SceneFormatError` naming the file (a FIFO, a
    device or a directory is refused before it is opened)."""
    input_file(path, "JSON file")
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
    if not os.path.lexists(path):
        raise SceneFormatError(shown(path), "no such file or folder")
    if os.path.islink(path) and not os.path.exists(path):  # not "missing": say what the link does
        raise SceneFormatError(shown(path), f"a symbolic link that leads nowhere ({_dead_link(path)})")
    if not path.is_dir():
        return _locate_file(path)
    folder = path
    # A scene file that is there but no regular file (a FIFO, a device, a link loop, a folder) is named as
    # such, not passed over as missing.
    transforms = folder / "transforms.json"
    if os.path.lexists(transforms):
        meta = read_json(input_file(transforms, "scene file"))
        return folder, _transforms_kind(meta), transforms, meta
    for split in BLENDER_SPLITS:
        candidate = folder / f"transforms_{split}.json"
        if os.path.lexists(candidate):
            return folder, "blender", input_file(candidate, "scene file"), None
    poses = folder / "poses_bounds.npy"
    if os.path.lexists(poses):
        return folder, "llff", input_file(poses, "scene file"), None
    raise SceneFormatError(
        shown(folder),
        "unknown scene format: the folder holds none of transforms.json, "
        "transforms_{train,val,test}.json, poses_bounds.npy",
    )


def _dead_link(path: Path) -> str:
    """Why a symbolic link leads nowhere: a loop, or a missing target."""
    try:
        os.stat(path)
    except OSError as e:
        if e.errno == errno.ELOOP:
            return "a symbolic link loop"
    return f"its target {shown(os.readlink(path))} is missing"


def _locate_file(path: Path) -> Tuple[Path, str, Path, Optional[Dict[str, Any]]]:
    """`locate` of a scene file given by its own path."""
    folder = path.parent
    input_file(path, "scene file")
    if path.name == "poses_bounds.npy":
        return folder, "llff", path, None
    if blender_split_of(path.name):
        return folder, "blender", path, None
    if path.suffix.lower() == ".json":
        meta = read_json(path)
        if "frames" in meta:
            return folder, _transforms_kind(meta), path, meta
        raise SceneFormatError(shown(path), "unknown scene format: a JSON file without 'frames'")
    raise SceneFormatError(
        shown(path),
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
    with one_line_errors():  # a file name with a newline or an escape stays on one line
        return locate(path)[1]


# ----------------------------------------------------------------------------------------------
# Poses and bounds.


def check_rigid(m: np.ndarray, path: Path, what: str) -> np.ndarray:
    """Checks finiteness, orthonormal rotation with det +1, a (0, 0, 0, 1) bottom row (a 4x4) and an origin
    within `MAX_COORDINATE` (`rigid_problem`'s rule), else a `SceneFormatError` naming `path` and `what`."""
    found = rigid_problem(np.asarray(m)[None], far_remedy="rescale the scene")
    if found is not None:
        raise SceneFormatError(path, f"{what}: {found[1]}")
    return m


def rigid_problem(m: np.ndarray, far_remedy: str = "") -> Optional[Tuple[int, str]]:
    """Whether every pose of m is a camera-to-world waldo takes: finite, its rotation orthonormal within
    `RIGID_TOL` with det +1, a 4x4's bottom row (0, 0, 0, 1), its origin's coordinates within
    `MAX_COORDINATE`. All N are checked at once (a results.json or a poses file of 10^5 poses), one rule
    after the other.

    Args:
      m: poses [N, 4, 4] or [N, 3, 4].
      far_remedy: what to do about an origin too far, in brackets after its message ("rescale the scene"
        where the poses are a scene's own; none for poses read to render a scene or for a results.json).

    Returns:
      None where all pass; else (index, why in words) of the first pose that fails the earliest rule any
      pose fails (of poses [far origin, NaN], the NaN one).
    """
    m = np.asarray(m, np.float64)
    if not len(m):
        return None
    with np.errstate(all="ignore"):
        finite = np.all(np.isfinite(m), axis=(1, 2))
        if not finite.all():
            return int(np.argmin(finite)), "pose has non-finite values (NaN or inf)"
        rotation = m[:, :3, :3]
        ortho = np.max(np.abs(np.swapaxes(rotation, 1, 2) @ rotation - np.eye(3)), axis=(1, 2))
        det = np.linalg.det(rotation)
        bad = (ortho > RIGID_TOL) | (det < 0)
        if bad.any():
            i = int(np.argmax(bad))
            return i, (
                "pose is not rigid (rotation part not orthonormal with det +1: "
                f"max |R^T R - I| = {ortho[i]:.3g}, det = {det[i]:.4g})"
            )
        if m.shape[1] == 4:
            row = np.max(np.abs(m[:, 3] - (0.0, 0.0, 0.0, 1.0)), axis=1)
            if (row > RIGID_TOL).any():
                i = int(np.argmax(row > RIGID_TOL))
                return i, f"pose bottom row is {m[i, 3].tolist()}, expected [0, 0, 0, 1]"
        far = np.max(np.abs(m[:, :3, 3]), axis=1)
        if (far > MAX_COORDINATE).any():
            i = int(np.argmax(far > MAX_COORDINATE))
            return i, (
                f"camera origin has a coordinate of {far[i]:.6g}, beyond the {MAX_COORDINATE:g} "
                "that float32 geometry handles" + (f" ({far_remedy})" if far_remedy else "")
            )
    return None


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
    return field(meta, key, path, "number", positive=positive)


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
    return distortion_problem(intrinsics)


# The distorted pixel positions a camera's lens is checked on: a grid of this many points per side,
# corners and edges included.
_DISTORTION_GRID = 9
# How far (pixels) a ray's pixel, distorted back, may land from the pixel it was cast through.
MAX_UNDISTORT_ERROR_PX = 0.5


def _distort64(xy: np.ndarray, d: np.ndarray) -> np.ndarray:
    """`waldo_jax.cameras.distort` in float64 NumPy: normalised coordinates [..., 2]."""
    k1, k2, p1, p2 = d
    x, y = xy[..., 0], xy[..., 1]
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k1 + k2 * r2)
    xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
    yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
    return np.stack([xd, yd], -1)


def _radial_peak(k1: float, k2: float) -> float:
    """The undistorted radius r where r (1 + k1 r^2 + k2 r^4) first stops growing (its derivative
    1 + 3 k1 r^2 + 5 k2 r^4 reaches 0), or infinity when it grows for every r."""
    roots = np.roots([5.0 * k2, 3.0 * k1, 1.0]) if k2 != 0.0 else np.roots([3.0 * k1, 1.0])
    squares = [float(r.real) for r in np.atleast_1d(roots) if abs(r.imag) <= 1e-12 * abs(r) and r.real > 0]
    return math.sqrt(min(squares)) if squares else math.inf


@functools.lru_cache(maxsize=1)
def _undistort_points():
    """`waldo_jax.cameras.undistort` over a batch of points, jitted once: the rays a render casts."""
    import jax

    from waldo_jax.cameras import undistort

    return jax.jit(jax.vmap(undistort, in_axes=(0, None)))


def distortion_problem(intrinsics: Intrinsics) -> Optional[str]:
    """What makes a camera's lens distortion (k1, k2, p1, p2) unusable over its image, or None.

    The distortion must map the undistorted rays onto the whole image one to one: the radial part
    r (1 + k1 r^2 + k2 r^4) must still grow where it reaches the image's farthest corner (k1 = -5 folds
    the image back on itself), the Jacobian of the whole map must keep its sign, and the rays a render
    casts (`waldo_jax.cameras.undistort`, float32 Newton steps) must be finite and land within
    `MAX_UNDISTORT_ERROR_PX` of their pixels (k1 = 1e30 overflows float32 there: every ray NaN).
    """
    d = np.asarray(intrinsics.distortion, np.float64).reshape(-1)
    if d.shape != (4,) or not np.any(d != 0.0):
        return None
    named = "distortion " + ", ".join(f"{k} = {v:g}" for k, v in zip(("k1", "k2", "p1", "p2"), d) if v != 0.0)
    fx, fy, cx, cy = (float(np.asarray(getattr(intrinsics, k), np.float32)) for k in ("fx", "fy", "cx", "cy"))
    width, height = int(intrinsics.width), int(intrinsics.height)
    u = (np.linspace(0.0, width, _DISTORTION_GRID) - cx) / fx
    v = (np.linspace(0.0, height, _DISTORTION_GRID) - cy) / fy
    distorted = np.stack(np.meshgrid(u, v, indexing="xy"), -1).reshape(-1, 2)  # [G * G, 2]
    with np.errstate(all="ignore"):
        radius = float(np.max(np.hypot(distorted[:, 0], distorted[:, 1])))
        peak = _radial_peak(float(d[0]), float(d[1]))
        reach = peak * (1.0 + d[0] * peak**2 + d[1] * peak**4) if math.isfinite(peak) else math.inf
        if not reach > radius:
            return (
                f"{named} folds the image: the distorted radius stops growing at {reach:.4g} focal lengths, short of "
                f"the {radius:.4g} the {width}x{height} image reaches (a lens maps each ray to one pixel)"
            )
        undistorted = np.asarray(
            _undistort_points()(distorted.astype(np.float32), d.astype(np.float32)), np.float64
        )  # [G * G, 2]
        if not np.all(np.isfinite(undistorted)):
            return f"{named} gives non-finite rays over the {width}x{height} image (its inverse overflows float32)"
        miss = float(np.max(np.abs(_distort64(undistorted, d) - distorted) * (fx, fy)))
        beyond = float(np.max(np.hypot(undistorted[:, 0], undistorted[:, 1]))) >= peak
        step = 1e-6 * (1.0 + np.abs(undistorted))
        jx = (_distort64(undistorted + step * (1, 0), d) - _distort64(undistorted - step * (1, 0), d)) / (
            2 * step[:, :1]
        )
        jy = (_distort64(undistorted + step * (0, 1), d) - _distort64(undistorted - step * (0, 1), d)) / (
            2 * step[:, 1:]
        )
        folded = not np.all(jx[:, 0] * jy[:, 1] - jx[:, 1] * jy[:, 0] > 0)
    if not (miss <= MAX_UNDISTORT_ERROR_PX) or beyond or folded:
        return f"{named} cannot be inverted over the {width}x{height} image: " + (
            "it folds the image (its Jacobian changes sign)"
            if folded or beyond
            else f"rays miss their pixels by up to {miss:.3g} px"
        )
    return None


def warn_off_image_principal_point(intrinsics: Intrinsics, path: Path, stacklevel: int = 4) -> None:
    """Warns (naming `path`) when the principal point lies outside the image.

    `stacklevel` 4 names the caller of `load_scene` (5 that of `read_poses_file` / `load_poses_file`): keep
    the call depths.
    """
    cx, cy = float(intrinsics.cx), float(intrinsics.cy)
    if not (0.0 <= cx <= intrinsics.width and 0.0 <= cy <= intrinsics.height):
        warnings.warn(
            f"{path}: principal point (cx, cy) = ({cx:g}, {cy:g}) lies outside the "
            f"{intrinsics.width}x{intrinsics.height} image; the cameras look far off their image centre",
            stacklevel=stacklevel,
        )
