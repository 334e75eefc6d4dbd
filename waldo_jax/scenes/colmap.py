"""COLMAP sparse models: the cameras and registered images of `cameras.{bin,txt}` and `images.{bin,txt}`.

The layout is COLMAP's (`src/colmap/scene/reconstruction_io_binary.cc`, `reconstruction_io_text.cc`;
camera models in `src/colmap/sensor/models.h`), all binary values little-endian:

  cameras.bin  uint64 count, then per camera: uint32 camera_id, int32 model_id, uint64 width,
               uint64 height, float64 params[P] (P fixed by the model);
  images.bin   uint64 count, then per image: uint32 image_id, float64 qw qx qy qz tx ty tz,
               uint32 camera_id, its name up to a NUL byte, uint64 M, M x (float64 x, y, uint64 point3D_id);
  cameras.txt  one line per camera: CAMERA_ID MODEL WIDTH HEIGHT PARAMS...;
  images.txt   two lines per image: IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME, then its 2D points
               (X Y POINT3D_ID ..., possibly an empty line). '#' lines are comments.

An image's (q, t) maps world to camera in OpenCV axes (x right, y down, z forward): x_cam = R(q) x + t,
q = (w, x, y, z); the camera centre is -R^T t. Pixel (0, 0) is the top-left corner of the top-left
pixel, as in `waldo_jax.types`, so cx, cy carry over unchanged. The 2D points and points3D are not
read; the writer writes none (and an empty points3D file, so that COLMAP opens the model).
"""

from __future__ import annotations

import math
import mmap
import os
import struct
from pathlib import Path
from typing import Dict, List, NamedTuple, Optional, Sequence, Tuple

import numpy as np

from waldo_jax.errors import SceneFormatError, read_input_file
from waldo_jax.scenes.common import input_file, one_line_errors, shown
from waldo_jax.io import write_bytes

__all__ = [
    "COLMAP_CAMERA_MODELS",
    "PINHOLE_LIKE_MODELS",
    "ColmapCamera",
    "ColmapImage",
    "find_colmap_model",
    "read_colmap_model",
    "write_colmap_model",
    "rotation_of_qvec",
    "qvec_of_rotation",
    "colmap_c2w",
    "colmap_pose",
]

# name: (model_id, number of params), from COLMAP's models.h (ids 0..17).
COLMAP_CAMERA_MODELS: Dict[str, Tuple[int, int]] = {
    "SIMPLE_PINHOLE": (0, 3),  # f, cx, cy
    "PINHOLE": (1, 4),  # fx, fy, cx, cy
    "SIMPLE_RADIAL": (2, 4),  # f, cx, cy, k
    "RADIAL": (3, 5),  # f, cx, cy, k1, k2
    "OPENCV": (4, 8),  # fx, fy, cx, cy, k1, k2, p1, p2
    "OPENCV_FISHEYE": (5, 8),
    "FULL_OPENCV": (6, 12),  # fx, fy, cx, cy, k1, k2, p1, p2, k3, k4, k5, k6
    "FOV": (7, 5),
    "SIMPLE_RADIAL_FISHEYE": (8, 4),
    "RADIAL_FISHEYE": (9, 5),
    "THIN_PRISM_FISHEYE": (10, 12),
    "RAD_TAN_THIN_PRISM_FISHEYE": (11, 16),
    "SIMPLE_DIVISION": (12, 4),  # f, cx, cy, k
    "DIVISION": (13, 5),  # fx, fy, cx, cy, k
    "SIMPLE_FISHEYE": (14, 3),
    "FISHEYE": (15, 4),
    "EUCM": (16, 6),
    "EQUIRECTANGULAR": (17, 2),
}
_MODEL_NAMES = {model_id: name for name, (model_id, _) in COLMAP_CAMERA_MODELS.items()}
# Pinholes with (or without) a lens distortion: their fx, fy, cx, cy make a pinhole camera. A fisheye,
# FOV, EUCM or spherical camera's do not.
PINHOLE_LIKE_MODELS = frozenset(
    ["SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV", "FULL_OPENCV", "SIMPLE_DIVISION", "DIVISION"]
)
_ONE_FOCAL = frozenset(
    ["SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL", "SIMPLE_DIVISION", "SIMPLE_RADIAL_FISHEYE", "RADIAL_FISHEYE"]
    + ["SIMPLE_FISHEYE"]
)
_FLOAT32_MAX = float(np.finfo(np.float32).max)
_OPENCV_TO_OPENGL = np.diag([1.0, -1.0, -1.0, 1.0])  # camera axes: y down, z forward -> y up, z backward


class ColmapCamera(NamedTuple):
    """One camera of cameras.bin/.txt: `params` in the model's order (models.h)."""

    camera_id: int
    model: str
    width: int
    height: int
    params: Tuple[float, ...]

    def pinhole(self) -> Tuple[float, float, float, float]:
        """(fx, fy, cx, cy): a one-focal model's f serves both axes."""
        p = self.params
        return (p[0], p[0], p[1], p[2]) if self.model in _ONE_FOCAL else (p[0], p[1], p[2], p[3])

    @property
    def extra_params(self) -> Tuple[float, ...]:
        """The parameters after the focal length(s) and principal point: the lens distortion."""
        return self.params[3 if self.model in _ONE_FOCAL else 4 :]


class ColmapImage(NamedTuple):
    """One registered image: world-to-camera (qvec w first, tvec), OpenCV axes."""

    image_id: int
    qvec: Tuple[float, float, float, float]
    tvec: Tuple[float, float, float]
    camera_id: int
    name: str


# ---------------------------------------------------------------------------------------------
# Poses.


def rotation_of_qvec(qvec: Sequence[float]) -> np.ndarray:
    """The [3, 3] rotation of a quaternion (w, x, y, z), normalised first (must be finite and not zero).

    Divided by its largest component before its norm, so that components past 1e154 (whose squares
    overflow float64) keep their direction instead of collapsing to the identity."""
    q = np.asarray(qvec, np.float64)
    largest = float(np.max(np.abs(q))) if q.size else 0.0
    if not (math.isfinite(largest) and largest > 0.0):
        raise ValueError(f"quaternion {list(map(float, q))} is zero or not finite")
    q = q / largest
    w, x, y, z = q / np.linalg.norm(q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def qvec_of_rotation(rotation: np.ndarray) -> np.ndarray:
    """The unit quaternion (w, x, y, z), w >= 0, of a [3, 3] rotation (largest pivot, stable near 180 deg)."""
    m = np.asarray(rotation, np.float64)
    trace = np.trace(m)
    pivots = [trace, m[0, 0], m[1, 1], m[2, 2]]
    k = int(np.argmax(pivots))
    if k == 0:
        s = 2.0 * np.sqrt(1.0 + trace)
        q = [0.25 * s, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s]
    elif k == 1:
        s = 2.0 * np.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2])
        q = [(m[2, 1] - m[1, 2]) / s, 0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s]
    elif k == 2:
        s = 2.0 * np.sqrt(1.0 - m[0, 0] + m[1, 1] - m[2, 2])
        q = [(m[0, 2] - m[2, 0]) / s, (m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s]
    else:
        s = 2.0 * np.sqrt(1.0 - m[0, 0] - m[1, 1] + m[2, 2])
        q = [(m[1, 0] - m[0, 1]) / s, (m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s]
    q = np.asarray(q) / np.linalg.norm(q)
    return -q if q[0] < 0 else q


def colmap_c2w(image: ColmapImage) -> np.ndarray:
    """The image's float64 [4, 4] camera-to-world matrix in OpenGL axes (x right, y up, z backward)."""
    rotation = rotation_of_qvec(image.qvec)  # world -> camera
    c2w = np.eye(4)
    c2w[:3, :3] = rotation.T
    c2w[:3, 3] = -rotation.T @ np.asarray(image.tvec, np.float64)
    return c2w @ _OPENCV_TO_OPENGL


def colmap_pose(c2w: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
    """(qvec [4], tvec [3]) of an OpenGL camera-to-world matrix: the inverse of `colmap_c2w`."""
    m = np.asarray(c2w, np.float64)[:3, :4] @ _OPENCV_TO_OPENGL
    rotation = m[:3, :3].T
    return qvec_of_rotation(rotation), -rotation @ m[:3, 3]


# ---------------------------------------------------------------------------------------------
# Finding a model.


def _model_ext(folder: Path) -> Optional[str]:
    """ ".bin" or ".txt" when `folder` holds images.<ext> (binary first, as COLMAP reads), else None."""
    return next((ext for ext in (".bin", ".txt") if os.path.lexists(folder / f"images{ext}")), None)


def find_colmap_model(path: str | os.PathLike) -> Optional[Tuple[Path, str]]:
    """(model folder, ".bin" or ".txt") of a COLMAP model at `path`, or None.

    `path` may be an `images.bin`/`images.txt` (or `cameras.*`) file, a model folder holding
    `images.bin` or `images.txt`, or a folder with one in `sparse/0/` or `sparse/` (looked at in
    that order; binary before text, as COLMAP reads).
    """
    path = Path(path)
    if os.path.lexists(path) and not path.is_dir():  # a FIFO or a link loop is read (and refused) by name
        stem, ext = path.stem, path.suffix
        return (path.parent, ext) if stem in ("images", "cameras") and ext in (".bin", ".txt") else None
    for folder in (path, path / "sparse" / "0", path / "sparse"):
        ext = _model_ext(folder) if folder.is_dir() else None
        if ext is not None:
            return folder, ext
    return None


# ---------------------------------------------------------------------------------------------
# Binary files.


class _Binary:
    """Little-endian reads from a memory-mapped file, refusing reads past its end (naming the file)."""

    def __init__(self, data, path: Path):
        self.data, self.path, self.pos = data, path, 0

    def take(self, fmt: str, what: str) -> tuple:
        size = struct.calcsize("<" + fmt)
        if self.pos + size > len(self.data):
            raise SceneFormatError(
                self.path, f"truncated: {what} needs {size} bytes at byte {self.pos}, the file has {len(self.data)}"
            )
        values = struct.unpack_from("<" + fmt, self.data, self.pos)
        self.pos += size
        return values

    def skip(self, size: int, what: str) -> None:
        if self.pos + size > len(self.data):
            raise SceneFormatError(
                self.path, f"truncated: {what} needs {size} bytes at byte {self.pos}, the file has {len(self.data)}"
            )
        self.pos += size

    def name(self, what: str) -> str:
        end = self.data.find(b"\0", self.pos)
        if end < 0:
            raise SceneFormatError(self.path, f"truncated: {what} has no terminating NUL byte")
        raw = bytes(self.data[self.pos : end])
        self.pos = end + 1
        try:
            return raw.decode("utf-8")
        except UnicodeDecodeError:
            raise SceneFormatError(self.path, f"{what}: the name is not UTF-8 ({raw[:40]!r})") from None


def _read_binary(path: Path, parse):
    """`parse(_Binary)` over the memory-mapped file; a file with trailing bytes is refused."""
    try:
        with open(path, "rb") as f:
            if os.fstat(f.fileno()).st_size == 0:
                raise SceneFormatError(path, "empty file (a COLMAP binary file starts with a uint64 count)")
            with mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ) as data:
                reader = _Binary(data, path)
                result = parse(reader)
                if reader.pos != len(data):
                    raise SceneFormatError(
                        path, f"{len(data) - reader.pos} bytes after the last entry (not a COLMAP {path.name}?)"
                    )
                return result
    except OSError as e:
        raise SceneFormatError(path, f"cannot read the file ({e.strerror or e})") from None


def _cameras_binary(reader: _Binary) -> Dict[int, ColmapCamera]:
    (count,) = reader.take("Q", "the camera count")
    cameras: Dict[int, ColmapCamera] = {}
    for i in range(count):
        camera_id, model_id, width, height = reader.take("IiQQ", f"camera {i}")
        if model_id not in _MODEL_NAMES:
            raise SceneFormatError(
                reader.path, f"camera {camera_id}: unknown camera model id {model_id} (COLMAP's are 0..17)"
            )
        model = _MODEL_NAMES[model_id]
        n = COLMAP_CAMERA_MODELS[model][1]
        params = reader.take("d" * n, f"camera {camera_id}'s {n} {model} parameters")
        _add_camera(cameras, ColmapCamera(camera_id, model, width, height, params), reader.path)
    return cameras


def _images_binary(reader: _Binary) -> List[ColmapImage]:
    (count,) = reader.take("Q", "the image count")
    images = []
    for i in range(count):
        image_id, qw, qx, qy, qz, tx, ty, tz, camera_id = reader.take("I7dI", f"image {i}")
        name = reader.name(f"image {image_id}")
        (points,) = reader.take("Q", f"image {image_id}'s 2D point count")
        reader.skip(24 * points, f"image {image_id}'s {points} 2D points")
        images.append(ColmapImage(image_id, (qw, qx, qy, qz), (tx, ty, tz), camera_id, name))
    return images


def _add_camera(cameras: Dict[int, ColmapCamera], camera: ColmapCamera, path: Path) -> None:
    """Adds a camera whose id is new and whose parameters are numbers float32 holds (1e308 is none)."""
    if camera.camera_id in cameras:
        raise SceneFormatError(path, f"camera id {camera.camera_id} appears twice")
    for i, value in enumerate(camera.params):
        if not (math.isfinite(value) and abs(value) <= _FLOAT32_MAX):
            raise SceneFormatError(
                path,
                f"camera {camera.camera_id}: {camera.model} parameter {i} is {value:g}, not a finite number float32 "
                f"holds (|x| <= {_FLOAT32_MAX:.4g})",
            )
    cameras[camera.camera_id] = camera


# ---------------------------------------------------------------------------------------------
# Text files.


def _lines(path: Path) -> List[str]:
    try:  # its size against the free memory first: a text file is read whole
        return read_input_file(
            path, "COLMAP text file", lambda problem: SceneFormatError(path, problem), True
        ).splitlines()
    except UnicodeDecodeError as e:
        raise SceneFormatError(path, f"cannot read the file ({e})") from None


def _numbers(tokens: Sequence[str], kind, path: Path, where: str) -> list:
    try:
        return [kind(t) for t in tokens]
    except ValueError:
        raise SceneFormatError(path, f"{where}: expected {kind.__name__} values, got {' '.join(tokens)!r}") from None


def _cameras_text(path: Path) -> Dict[int, ColmapCamera]:
    cameras: Dict[int, ColmapCamera] = {}
    for number, line in enumerate(_lines(path), 1):
        tokens = line.split()
        if not tokens or tokens[0].startswith("#"):
            continue
        where = f"line {number}"
        if len(tokens) < 4:
            raise SceneFormatError(path, f"{where}: expected CAMERA_ID MODEL WIDTH HEIGHT PARAMS..., got {line!r}")
        model = tokens[1]
        if model not in COLMAP_CAMERA_MODELS:
            raise SceneFormatError(
                path, f"{where}: unknown camera model {model!r} (COLMAP's: {', '.join(COLMAP_CAMERA_MODELS)})"
            )
        camera_id, width, height = _numbers([tokens[0], tokens[2], tokens[3]], int, path, where)
        params = _numbers(tokens[4:], float, path, where)
        n = COLMAP_CAMERA_MODELS[model][1]
        if len(params) != n:
            raise SceneFormatError(path, f"{where}: a {model} camera has {n} parameters, got {len(params)}")
        _add_camera(cameras, ColmapCamera(camera_id, model, width, height, tuple(params)), path)
    return cameras


def _image_line(tokens: Sequence[str]) -> bool:
    """True when `tokens` (a line split at most 9 times) read as IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID
    NAME: ten fields, integer ids around seven numbers."""
    if len(tokens) < 10:
        return False
    try:
        int(tokens[0]), int(tokens[8])
        [float(t) for t in tokens[1:8]]
    except ValueError:
        return False
    return True


def _points_line(line: str) -> bool:
    """True when `line` reads as an image's 2D points: (X Y POINT3D_ID) triples, the ids integers."""
    tokens = line.split()
    if len(tokens) % 3:
        return False
    try:
        [float(t) for t in tokens]
        [int(t) for t in tokens[2::3]]
    except ValueError:
        return False
    return True


def _images_text(path: Path) -> List[ColmapImage]:
    """The images of images.txt. COLMAP writes two lines per image (the second its 2D points, empty when
    it has none); a file whose blank points lines were stripped has one. Each line after an image line
    is read for what it is, a points line or the next image, so neither layout loses an image."""
    images = []
    lines = _lines(path)
    number = 0
    while number < len(lines):
        line = lines[number].strip()
        number += 1
        if not line or line.startswith("#"):
            continue
        where = f"line {number}"
        tokens = line.split(maxsplit=9)
        if not _image_line(tokens):
            if len(tokens) >= 10:
                _numbers([tokens[0], tokens[8]], int, path, where)
                _numbers(tokens[1:8], float, path, where)
            raise SceneFormatError(
                path, f"{where}: expected IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME, got {line[:80]!r}"
            )
        image_id, camera_id = int(tokens[0]), int(tokens[8])
        pose = [float(t) for t in tokens[1:8]]
        images.append(ColmapImage(image_id, tuple(pose[:4]), tuple(pose[4:]), camera_id, tokens[9]))
        if number < len(lines):
            following = lines[number].strip()
            # its 2D points: an empty line, or triples of numbers (never an image line: its name is no number)
            if not following or (_points_line(following) and not _image_line(following.split(maxsplit=9))):
                number += 1
    return images


def _unique_ids(images: List[ColmapImage], path: Path) -> List[ColmapImage]:
    """`images`, refused when two share an id (a layout read wrongly would show here, not lose images)."""
    names: Dict[int, str] = {}
    for image in images:
        if image.image_id in names:
            raise SceneFormatError(
                path,
                f"image id {image.image_id} appears twice ({shown(names[image.image_id])!r} and {shown(image.name)!r})",
            )
        names[image.image_id] = image.name
    return images


# ---------------------------------------------------------------------------------------------
# The model.


def read_colmap_model(
    folder: str | os.PathLike, ext: Optional[str] = None
) -> Tuple[Dict[int, ColmapCamera], List[ColmapImage]]:
    """Reads the cameras and registered images of a COLMAP model folder.

    Args:
      folder: the folder holding cameras.<ext> and images.<ext>.
      ext: ".bin" or ".txt"; None: images.bin if present, else images.txt.

    Returns:
      ({camera_id: ColmapCamera}, [ColmapImage] in the file's order).

    Raises:
      SceneFormatError (naming the file): a missing file, a truncated binary file or one with trailing
        bytes, a malformed text line, an unknown camera model or a wrong number of its parameters, a
        repeated camera id.
    """
    with one_line_errors():  # a file name with a newline or an escape stays on one line
        folder = Path(folder)
        ext = ext or _model_ext(folder) or ".bin"
        if ext not in (".bin", ".txt"):
            raise ValueError(f"ext must be '.bin' or '.txt', got {ext!r}")
        images_path, cameras_path = folder / f"images{ext}", folder / f"cameras{ext}"
        for path in (images_path, cameras_path):
            if not os.path.lexists(path):
                raise SceneFormatError(path, "no such file (a COLMAP model has cameras and images files side by side)")
            input_file(path, "COLMAP file")  # a FIFO would block the reader, /dev/zero never end
        if ext == ".bin":
            return _read_binary(cameras_path, _cameras_binary), _unique_ids(
                _read_binary(images_path, _images_binary), images_path
            )
        return _cameras_text(cameras_path), _unique_ids(_images_text(images_path), images_path)


def write_colmap_model(
    folder: str | os.PathLike,
    cameras: Sequence[ColmapCamera],
    images: Sequence[ColmapImage],
    binary: bool = True,
) -> Path:
    """Writes cameras, images (without 2D points) and an empty points3D file as a COLMAP model, atomically.

    Args:
      folder: the model folder (created).
      cameras: the cameras; each model's parameter count is checked.
      images: the registered images.
      binary: write .bin files, else .txt (floats as repr: exact round trips).

    Returns:
      `folder` as a Path.
    """
    folder = Path(folder)
    for camera in cameras:
        if COLMAP_CAMERA_MODELS.get(camera.model, (None, None))[1] != len(camera.params):
            raise ValueError(f"camera {camera.camera_id}: {camera.model} with {len(camera.params)} parameters")
    folder.mkdir(parents=True, exist_ok=True)
    if binary:
        parts = [struct.pack("<Q", len(cameras))]
        for c in cameras:
            model_id = COLMAP_CAMERA_MODELS[c.model][0]
            parts.append(struct.pack(f"<IiQQ{len(c.params)}d", c.camera_id, model_id, c.width, c.height, *c.params))
        files = {"cameras.bin": b"".join(parts)}
        parts = [struct.pack("<Q", len(images))]
        for im in images:
            parts.append(struct.pack("<I7dI", im.image_id, *im.qvec, *im.tvec, im.camera_id))
            parts.append(im.name.encode("utf-8") + b"\0" + struct.pack("<Q", 0))
        files["images.bin"] = b"".join(parts)
        files["points3D.bin"] = struct.pack("<Q", 0)
    else:
        cams = ["# Camera list with one line of data per camera:", "#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]"]
        for c in cameras:
            cams.append(f"{c.camera_id} {c.model} {c.width} {c.height} " + " ".join(repr(float(v)) for v in c.params))
        ims = ["# Image list with two lines of data per image:"]
        ims += ["#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME", "#   POINTS2D[] as (X, Y, POINT3D_ID)"]
        for im in images:
            pose = " ".join(repr(float(v)) for v in (*im.qvec, *im.tvec))
            ims += [f"{im.image_id} {pose} {im.camera_id} {im.name}", ""]  # no 2D points: an empty line
        files = {
            "cameras.txt": ("\n".join(cams) + "\n").encode("utf-8"),
            "images.txt": ("\n".join(ims) + "\n").encode("utf-8"),
            "points3D.txt": b"# 3D point list: none\n",
        }
    for name, data in files.items():
        write_bytes(folder / name, data)
    return folder
