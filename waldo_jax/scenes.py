"""Loading posed image sets from disk: instant-ngp, nerfstudio, Blender and LLFF scenes.

`load_scene(path)` detects the format, reads images and cameras, and returns a host-side `Scene`
(see `waldo_jax.types`). Every loader ends in the same conventions:

  * `c2w` is [N, 4, 4] float32 in the OpenGL convention of `types.py` (columns: right, up, backward,
    origin). instant-ngp, nerfstudio and Blender files already store OpenGL camera-to-world
    matrices, so they are used as they are, in the file's own world coordinates: instant-ngp's
    `scale`/`offset` and axis cycling are *not* applied (they only enter `aabb`, see below), and
    nerfstudio's `applied_transform` is recorded in `Scene.applied_transform`, not re-applied. LLFF
    poses are [down, right, backward] columns and are converted to [right, up, backward]; the LLFF
    world is neither recentred nor rescaled.
  * Every matrix must be rigid: 4x4, finite, rotation orthonormal within `RIGID_TOL` with det +1,
    bottom row (0, 0, 0, 1). The shipped nerfstudio scenes (face, garden) are rigid to 1e-14, so no
    scale is tolerated inside a pose.
  * Images are float32 [N, H, W, 3] in [0, 1]. Grey images are repeated to 3 channels. Downscaling
    is an area (box) filter: `PIL.Image.reduce` for integer factors that divide the size, else
    `resize(BOX)` to `round(size / factor)`; intrinsics follow with `Intrinsics.scaled`.
  * RGBA images are *straight* (un-premultiplied) alpha, as PNG specifies. lego_tiny was made by
    box-filtering premultiplied colour and then dividing by alpha again: its semi-transparent edge
    pixels carry the object's full colour (mean rgb 0.49 at mean alpha 0.24, against 0.45 inside the
    object; a third of edge pixels have rgb > alpha, impossible for premultiplied data). So the
    composite is `rgb * a + (1 - a) * background`; downscaling filters the premultiplied colour
    `rgb * a` and `a`, then composites. `Scene.alphas` keeps `a` so training can re-composite.

Scene extents (`aabb` [2, 3] float32, `near`, `far`) per format:
  * instant-ngp: the box NGP itself marches in. NGP maps a world point p to `cycle(p * scale +
    offset)` (defaults 0.33 and 0.5; `cycle` is its x->y->z axis rotation) and uses the cube
    `0.5 +- aabb_scale / 2`. That cube is symmetric, so the cycling drops out and the world box is
    `(0.5 +- aabb_scale / 2 - offset) / scale` per axis (fox, aabb_scale 4: +-6.06).
  * nerfstudio: the 1st-99th percentile box of `sparse_pc.ply` (or `ply_file_path`), padded by
    `PLY_PAD` of its size per side. The ply is already in the transforms' world: for face all of its
    points lie in front of every camera as the poses stand, and only 8% do after applying
    `applied_transform` once more. Without a ply: the box of the camera origins and their common
    focus point (`camera_focus`), padded by `ORIGIN_PAD`.
  * Blender: [-1.5, 1.5]^3, near 2, far 6 (the NeRF synthetic convention).
  * LLFF: the box of all camera frustums between each camera's own near and far bound; near is
    `LLFF_NEAR_MARGIN` (0.9) x the smallest near bound, far the largest far bound.
  * instant-ngp and nerfstudio take near/far from `camera_bounds(c2w, aabb)`: far is the largest
    camera-to-box-corner distance, near the smallest camera-to-box distance, at least
    `MIN_NEAR_FRACTION` of far (cameras usually sit inside the box).

Splits: Blender reads `transforms_<split>.json` (default "train"; "all" = every split file present).
Formats without splits use the NeRF/LLFF hold-out: sorted images with index i % 8 == 0 are "test",
the rest "train"; the default there is "all". Frames are sorted by file name (natural order) for
instant-ngp and nerfstudio, kept in file order for Blender, sorted file names for LLFF. Frames whose
image file is missing are skipped (one warning with the count, `Scene.skipped_missing`) before the
split is taken.

LLFF resolution: `poses_bounds.npy` holds [h, w, f] of the full-size images, and `downscale` is
relative to that size. `images_K` holds images downscaled K times (`images` = full size). A
requested factor F uses `images_F` if present, else the folder with the largest K < F, box-filtered
by a further F / K; with no such folder it is an error (no upsampling). The default (None) is
`LLFF_DEFAULT_FACTOR` = 8, NeRF's LLFF resolution: `images_8` when present, else the images_K with
the largest K, else `images`. The actual factor is derived from the loaded size against hwf.

Every problem with the files raises `SceneFormatError(path, problem)`; bad arguments raise
`SceneArgumentError` (a `WaldoError` and a `ValueError`).
"""

from __future__ import annotations

import json
import math
import os
import re
import warnings
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any, Dict, List, Optional, Sequence, Tuple

import numpy as np
from PIL import Image

from waldo_jax.cameras import camera_focus
from waldo_jax.errors import MAX_RESOLUTION, MIN_RESOLUTION, SceneFormatError, WaldoError, check_input_file
from waldo_jax.types import Intrinsics, Scene

__all__ = [
    "FORMATS",
    "SPLITS",
    "SceneArgumentError",
    "camera_bounds",
    "camera_focus",
    "detect_format",
    "load_scene",
    "read_ply_points",
    "read_poses_file",
]

FORMATS = ("instant-ngp", "nerfstudio", "blender", "llff")
SPLITS = ("all", "train", "val", "test")
BLENDER_SPLITS = ("train", "val", "test")

RIGID_TOL = 1e-3  # max |R^T R - I| and |bottom row - (0,0,0,1)| of a pose.
# Largest |coordinate| of a camera origin or scene box: geometry runs in float32, where squared
# distances of larger coordinates lose all precision (and 1e20 overflows). Rescale such scenes.
MAX_COORDINATE = 1e6
TEST_EVERY = 8  # hold-out stride of formats without splits (NeRF's `llffhold`).
BLENDER_AABB = ((-1.5, -1.5, -1.5), (1.5, 1.5, 1.5))
BLENDER_NEAR, BLENDER_FAR = 2.0, 6.0
NGP_DEFAULT_SCALE = 0.33
NGP_DEFAULT_OFFSET = 0.5
PLY_PERCENTILES = (1.0, 99.0)
PLY_PAD = 0.1  # fraction of the percentile box size added on each side.
ORIGIN_PAD = 0.25  # fraction of the camera box size added on each side (no point cloud).
MIN_NEAR_FRACTION = 0.02
LLFF_NEAR_MARGIN = 0.9
LLFF_FAR_MARGIN = 1.0
LLFF_DEFAULT_FACTOR = 8
IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg", ".PNG", ".JPG", ".JPEG")

_NERFSTUDIO_MODELS = {"OPENCV", "PINHOLE", "SIMPLE_PINHOLE"}
_NERFSTUDIO_KEYS = ("camera_model", "applied_transform")
_INTRINSIC_KEYS = (
    "w", "h", "fl_x", "fl_y", "cx", "cy", "camera_angle_x", "camera_angle_y",
    "k1", "k2", "k3", "k4", "p1", "p2",
)
_MAX_THREADS = 8


class SceneArgumentError(WaldoError, ValueError):
    """An argument of `load_scene` (split, downscale, background, max_images) is invalid."""


# ----------------------------------------------------------------------------------------------
# Format detection.


def _read_json(path: Path) -> Dict[str, Any]:
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


def _blender_split_of(name: str) -> Optional[str]:
    """"train" for "transforms_train.json", None for other names."""
    m = re.fullmatch(r"transforms_(train|val|test)\.json", name)
    return m.group(1) if m else None


def _locate(path: str | os.PathLike) -> Tuple[Path, str, Path, Optional[Dict[str, Any]]]:
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
            meta = _read_json(transforms)
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
    if _blender_split_of(path.name):
        return folder, "blender", path, None
    if path.suffix.lower() == ".json":
        meta = _read_json(path)
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
    return _locate(path)[1]


# ----------------------------------------------------------------------------------------------
# Poses.


def _check_c2w(matrix: Any, path: Path, what: str) -> np.ndarray:
    """Validates one camera-to-world matrix: [4, 4], finite, rigid. Returns it as float64."""
    try:
        m = np.asarray(matrix, dtype=np.float64)
    except (TypeError, ValueError):
        raise SceneFormatError(path, f"{what}: transform_matrix is not a 4x4 matrix of numbers") from None
    if m.shape != (4, 4):
        raise SceneFormatError(path, f"{what}: transform_matrix has shape {list(m.shape)}, expected 4x4")
    return _check_rigid(m, path, what)


def _check_rigid(m: np.ndarray, path: Path, what: str) -> np.ndarray:
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
    _check_origin(m, path, what)
    return m


def _check_origin(m: np.ndarray, path: Path, what: str) -> None:
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


def _pad_box(lo: np.ndarray, hi: np.ndarray, fraction: float) -> np.ndarray:
    """[2, 3] float32 box grown by `fraction` of its size per side (at least 1e-3 of its diagonal)."""
    size = hi - lo
    pad = fraction * np.maximum(size, 1e-3 * max(float(np.linalg.norm(size)), 1e-6))
    return np.stack([lo - pad, hi + pad]).astype(np.float32)


# ----------------------------------------------------------------------------------------------
# Point clouds.

_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}


def read_ply_points(path: str | os.PathLike) -> np.ndarray:
    """Reads the x, y, z vertex coordinates of an ASCII or binary PLY file.

    Supports vertex elements of scalar properties (list properties, e.g. faces, may follow the
    vertices but not precede them in a binary file).

    Args:
      path: the .ply file.

    Returns:
      float32 [P, 3] vertex positions.

    Raises:
      SceneFormatError: the file is not a PLY point cloud this reader understands.
    """
    path = Path(path)
    try:
        raw = path.read_bytes()
    except OSError as e:
        raise SceneFormatError(path, f"cannot read file ({e.strerror or e})") from None
    end = raw.find(b"end_header")
    if not raw.startswith(b"ply") or end < 0:
        raise SceneFormatError(path, "not a PLY file (no 'ply' magic or no 'end_header')")
    body_start = raw.index(b"\n", end) + 1 if b"\n" in raw[end:] else len(raw)
    header = raw[:end].decode("ascii", errors="replace").splitlines()
    fmt = None
    elements: List[Tuple[str, int, List[Tuple[str, str]]]] = []  # (name, count, [(prop, type)])
    for line in header[1:]:
        words = line.split()
        if not words or words[0] in ("comment", "obj_info"):
            continue
        if words[0] == "format" and len(words) >= 2:
            fmt = words[1]
        elif words[0] == "element" and len(words) == 3:
            try:
                elements.append((words[1], int(words[2]), []))
            except ValueError:
                raise SceneFormatError(path, f"bad PLY header line {line!r}") from None
        elif words[0] == "property" and elements:
            ptype = "list" if words[1] == "list" else words[1]
            elements[-1][2].append((words[-1], ptype))
    if fmt not in ("ascii", "binary_little_endian", "binary_big_endian"):
        raise SceneFormatError(path, f"unsupported PLY format {fmt!r}")
    names = [e[0] for e in elements]
    if "vertex" not in names:
        raise SceneFormatError(path, "PLY file has no 'vertex' element")
    v_index = names.index("vertex")
    _, count, props = elements[v_index]
    prop_names = [p for p, _ in props]
    if not all(k in prop_names for k in "xyz"):
        raise SceneFormatError(path, f"PLY vertices lack x, y, z properties (have {prop_names})")
    if any(t == "list" for _, t in props):
        raise SceneFormatError(path, "PLY vertex element has list properties: not supported")
    try:
        if fmt == "ascii":
            lines = raw[body_start:].decode("ascii").split("\n")
            skip = sum(e[1] for e in elements[:v_index])
            rows = [ln.split() for ln in lines[skip : skip + count]]
            table = np.array([[float(r[prop_names.index(k)]) for k in "xyz"] for r in rows], np.float64)
            if len(table) != count:
                raise ValueError(f"{len(table)} vertex lines, header says {count}")
        else:
            order = "<" if fmt == "binary_little_endian" else ">"
            offset = body_start
            for name, n, eprops in elements[:v_index]:
                if any(t == "list" for _, t in eprops):
                    raise ValueError(f"element {name!r} with list properties precedes the vertices")
                offset += n * sum(np.dtype(_PLY_TYPES[t]).itemsize for _, t in eprops)
            dtype = np.dtype([(p, order + _PLY_TYPES[t]) for p, t in props])
            data = np.frombuffer(raw, dtype=dtype, count=count, offset=offset)
            table = np.stack([data[k].astype(np.float64) for k in "xyz"], -1)
    except (ValueError, IndexError, KeyError, UnicodeDecodeError, TypeError) as e:
        raise SceneFormatError(path, f"malformed PLY vertex data ({e})") from None
    table = table.reshape(-1, 3)
    if not np.all(np.isfinite(table)):
        raise SceneFormatError(path, "PLY vertices have non-finite coordinates")
    return table.astype(np.float32)


# ----------------------------------------------------------------------------------------------
# Images.


def _target_size(width: int, height: int, factor: float) -> Tuple[int, int]:
    """Size after downscaling by `factor`, rounded as `Intrinsics.downscaled` rounds."""
    return max(1, int(round(width / factor))), max(1, int(round(height / factor)))


def _box_resize(array: np.ndarray, size: Tuple[int, int]) -> np.ndarray:
    """Area-filters a float [H, W, C] array to `size` = (w, h)."""
    h, w, c = array.shape
    tw, th = size
    if (tw, th) == (w, h):
        return array
    if w % tw == 0 and h % th == 0:
        ky, kx = h // th, w // tw
        return array.reshape(th, ky, tw, kx, c).mean(axis=(1, 3), dtype=np.float32)
    channels = [
        np.asarray(Image.fromarray(np.ascontiguousarray(array[..., i]), "F").resize(size, Image.BOX))
        for i in range(c)
    ]
    return np.stack(channels, -1).astype(np.float32)


def _decode(img: Image.Image, size: Tuple[int, int]) -> Tuple[np.ndarray, Optional[np.ndarray]]:
    """An opened PIL image as (float32 [h, w, 3] colour, float32 [h, w] straight alpha or None).

    With alpha, the colour returned is premultiplied (rgb * a), filtered at `size` = (w, h).
    """
    mode = img.mode
    has_alpha = mode in ("RGBA", "LA", "PA", "RGBa", "La") or (mode == "P" and "transparency" in img.info)
    if mode.startswith("I") or mode == "F":  # 16/32-bit grey: no 8-bit round trip.
        grey = np.asarray(img, np.float32)
        if mode != "F":
            grey = grey / 65535.0
        rgb = np.repeat(np.clip(grey, 0.0, 1.0)[..., None], 3, -1)
        return _box_resize(rgb, size), None
    if has_alpha:
        rgba = np.asarray(img.convert("RGBA"), np.float32) * (1.0 / 255.0)
        alpha = rgba[..., 3:]
        stacked = np.concatenate([rgba[..., :3] * alpha, alpha], -1)
        stacked = _box_resize(stacked, size)
        return stacked[..., :3], stacked[..., 3]
    if mode != "RGB":
        img = img.convert("RGB")
    w, h = img.size
    factor_x, factor_y = w / size[0], h / size[1]
    if size != (w, h):
        if factor_x == factor_y and factor_x.is_integer() and w % size[0] == 0 and h % size[1] == 0:
            img = img.reduce(int(factor_x))
        else:
            img = img.resize(size, Image.BOX)
    rgb = np.asarray(img, np.float32)
    rgb *= 1.0 / 255.0
    return rgb, None


def _image_size(path: Path) -> Tuple[int, int]:
    """(width, height) from an image header."""
    try:
        with Image.open(path) as img:
            return img.size
    except Exception as e:  # PIL raises many types for bad files.
        raise SceneFormatError(path, f"cannot read image ({type(e).__name__}: {e})") from None


def _load_images(
    paths: Sequence[Path], factor: float, background: np.ndarray
) -> Tuple[np.ndarray, Optional[np.ndarray], Tuple[int, int]]:
    """Reads same-size images, area-downscaled by `factor`, RGBA composited on `background`.

    Returns:
      (images float32 [N, h, w, 3], alphas float32 [N, h, w] or None, (W, H) size on disk).
    """
    full = _image_size(paths[0])
    size = _target_size(*full, factor)
    images = np.empty((len(paths), size[1], size[0], 3), np.float32)

    def read(i: int) -> Optional[np.ndarray]:
        path = paths[i]
        try:
            with Image.open(path) as img:
                if img.size != full:
                    raise SceneFormatError(
                        path,
                        f"image is {img.size[0]}x{img.size[1]} but {paths[0].name} is "
                        f"{full[0]}x{full[1]}: all images of a scene must have the same size",
                    )
                img.load()
                rgb, alpha = _decode(img, size)
        except SceneFormatError:
            raise
        except Exception as e:  # corrupt or truncated files raise OSError, SyntaxError, ValueError...
            raise SceneFormatError(path, f"cannot read image ({type(e).__name__}: {e})") from None
        if not np.all(np.isfinite(rgb)) or (alpha is not None and not np.all(np.isfinite(alpha))):
            raise SceneFormatError(path, "the image has NaN or infinite values")
        if alpha is not None:
            rgb = rgb + (1.0 - alpha[..., None]) * background
        images[i] = rgb
        return alpha

    workers = max(1, min(_MAX_THREADS, os.cpu_count() or 1, len(paths)))
    with ThreadPoolExecutor(workers) as pool:
        alpha_list = list(pool.map(read, range(len(paths))))
    alphas = None
    if any(a is not None for a in alpha_list):
        alphas = np.ones(images.shape[:3], np.float32)
        for i, a in enumerate(alpha_list):
            if a is not None:
                alphas[i] = a
    np.clip(images, 0.0, 1.0, out=images)
    return images, alphas, full


def _resolve_image(folder: Path, file_path: str) -> Optional[Path]:
    """The image a frame's `file_path` names, trying common extensions when it has none."""
    candidate = folder / file_path
    if candidate.is_file():
        return candidate
    if not candidate.suffix or candidate.suffix.lower() not in (".png", ".jpg", ".jpeg", ".exr"):
        for ext in IMAGE_EXTENSIONS:
            with_ext = candidate.with_name(candidate.name + ext)
            if with_ext.is_file():
                return with_ext
    return None


def _natural_key(text: str) -> List[Any]:
    """Sort key that orders "r_2" before "r_10"."""
    return [int(t) if t.isdigit() else t for t in re.split(r"(\d+)", text)]


def _relative(path: Path, folder: Path) -> str:
    """`path` relative to `folder`, POSIX style."""
    return Path(os.path.relpath(path, folder)).as_posix()


# ----------------------------------------------------------------------------------------------
# Arguments, splits, intrinsics.


def _check_downscale(downscale: Any) -> Optional[float]:
    if downscale is None:
        return None
    try:
        factor = float(downscale)
    except (TypeError, ValueError):
        raise SceneArgumentError(f"downscale must be a number >= 1, got {downscale!r}") from None
    if not math.isfinite(factor) or factor < 1.0:
        raise SceneArgumentError(f"downscale must be a number >= 1 (no upsampling), got {downscale!r}")
    return factor


def _check_background(background: Any) -> np.ndarray:
    try:
        bg = np.asarray(background, np.float32).reshape(-1)
    except (TypeError, ValueError):
        bg = np.zeros(0, np.float32)
    if bg.shape == (1,):
        bg = np.repeat(bg, 3)
    if bg.shape != (3,) or not np.all(np.isfinite(bg)):
        raise SceneArgumentError(f"background must be 3 finite numbers (an RGB colour), got {background!r}")
    return bg


def _check_split(split: Any, allowed: Sequence[str]) -> None:
    if split is not None and split not in allowed:
        raise SceneArgumentError(f"unknown split {split!r}: expected one of {', '.join(allowed)} (or None)")


def _holdout(n: int, split: str) -> np.ndarray:
    """Indices of `split` among n sorted images: test = every TEST_EVERY-th, train = the rest."""
    index = np.arange(n)
    if split == "test":
        return index[index % TEST_EVERY == 0]
    if split == "train":
        return index[index % TEST_EVERY != 0]
    return index


def _subsample(index: np.ndarray, max_images: Optional[int]) -> np.ndarray:
    """At most `max_images` of `index`, evenly spaced (first and last kept)."""
    if max_images is None or len(index) <= max_images:
        return index
    pick = np.unique(np.round(np.linspace(0, len(index) - 1, max_images)).astype(int))
    return index[pick]


def _check_max_images(max_images: Any) -> Optional[int]:
    if max_images is None:
        return None
    if isinstance(max_images, bool) or not isinstance(max_images, (int, np.integer)) or max_images < 1:
        raise SceneArgumentError(f"max_images must be a positive integer or None, got {max_images!r}")
    return int(max_images)


def _number(meta: Dict[str, Any], key: str, path: Path) -> Optional[float]:
    """meta[key] as a finite float, None when absent."""
    if key not in meta or meta[key] is None:
        return None
    value = meta[key]
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise SceneFormatError(path, f"{key!r} must be a finite number, got {value!r}")
    return float(value)


def _camera_meta(meta: Dict[str, Any], frames: List[Dict[str, Any]], path: Path) -> Dict[str, Any]:
    """The single camera of a transforms file: top-level keys overridden by per-frame keys.

    Per-frame intrinsics are accepted only when every frame has the same values.
    """
    top = {k: meta[k] for k in _INTRINSIC_KEYS if k in meta}
    if not any(k in f for f in frames for k in _INTRINSIC_KEYS):
        return top
    first = None
    for i, frame in enumerate(frames):
        merged = {**top, **{k: frame[k] for k in _INTRINSIC_KEYS if k in frame}}
        if first is None:
            first = merged
        elif merged != first:
            diff = sorted(k for k in set(first) | set(merged) if first.get(k) != merged.get(k))
            shown = ", ".join(f"{k}: {first.get(k)!r} vs {merged.get(k)!r}" for k in diff[:3])
            raise SceneFormatError(
                path,
                f"per-frame intrinsics differ between frame 0 and frame {i} ({shown}): "
                "scenes with several cameras are not supported",
            )
    return first


def _json_intrinsics(camera: Dict[str, Any], image_size: Tuple[int, int], path: Path) -> Intrinsics:
    """Intrinsics of a transforms file at the size of its images on disk."""
    width, height = image_size
    w = _number(camera, "w", path) or float(width)
    h = _number(camera, "h", path) or float(height)
    fl_x = _number(camera, "fl_x", path)
    fl_y = _number(camera, "fl_y", path)
    angle_x = _number(camera, "camera_angle_x", path)
    angle_y = _number(camera, "camera_angle_y", path)
    if fl_x is None and angle_x is not None:
        fl_x = 0.5 * w / math.tan(0.5 * angle_x)
    if fl_y is None and angle_y is not None:
        fl_y = 0.5 * h / math.tan(0.5 * angle_y)
    if fl_x is None:
        fl_x = fl_y
    if fl_x is None:
        raise SceneFormatError(path, "no focal length: need 'fl_x' or 'camera_angle_x'")
    if fl_x <= 0 or (fl_y is not None and fl_y <= 0):
        raise SceneFormatError(path, f"focal length must be positive, got fl_x={fl_x}, fl_y={fl_y}")
    for key in ("k3", "k4"):
        if (_number(camera, key, path) or 0.0) != 0.0:
            raise SceneFormatError(path, f"distortion coefficient {key} is not supported (only k1, k2, p1, p2)")
    distortion = [_number(camera, k, path) or 0.0 for k in ("k1", "k2", "p1", "p2")]
    intrinsics = Intrinsics.create(
        int(round(w)), int(round(h)), fl_x, fl_y, _number(camera, "cx", path), _number(camera, "cy", path), distortion
    )
    if (intrinsics.width, intrinsics.height) != (width, height):
        if abs(width / height - w / h) > 0.01 * (w / h):
            raise SceneFormatError(
                path, f"images are {width}x{height} but the file describes {w:g}x{h:g} (another aspect ratio)"
            )
        intrinsics = intrinsics.scaled(width, height)
    return intrinsics


def _read_frames(meta: Dict[str, Any], path: Path) -> List[Dict[str, Any]]:
    """The validated frames list: non-empty, each with `file_path` and a rigid `transform_matrix`."""
    frames = meta.get("frames")
    if frames is None:
        raise SceneFormatError(path, "no 'frames' list")
    if not isinstance(frames, list):
        raise SceneFormatError(path, f"'frames' must be a list, got {type(frames).__name__}")
    if not frames:
        raise SceneFormatError(path, "no frames: 'frames' is empty")
    for i, frame in enumerate(frames):
        if not isinstance(frame, dict):
            raise SceneFormatError(path, f"frame {i} is not an object")
        for key in ("file_path", "transform_matrix"):
            if key not in frame:
                raise SceneFormatError(path, f"frame {i} has no '{key}'")
        if not isinstance(frame["file_path"], str) or not frame["file_path"]:
            raise SceneFormatError(path, f"frame {i}: 'file_path' must be a non-empty string")
        frame["_c2w"] = _check_c2w(frame["transform_matrix"], path, f"frame {i}")
        frame["_index"] = i
    return frames


def _existing_frames(
    frames: List[Dict[str, Any]], folder: Path, path: Path
) -> Tuple[List[Tuple[Dict[str, Any], Path]], int]:
    """Frames whose image exists (with its path) and the number skipped, warning once."""
    found = []
    missing = []
    for frame in frames:
        image = _resolve_image(folder, frame["file_path"])
        if image is None:
            missing.append(frame["file_path"])
        else:
            found.append((frame, image))
    if not found:
        raise SceneFormatError(
            path, f"none of the {len(frames)} image files listed exist (first: {folder / missing[0]})"
        )
    if missing:
        warnings.warn(
            f"{path}: skipped {len(missing)} of {len(frames)} frames whose image file is missing "
            f"(first: {missing[0]})",
            stacklevel=4,
        )
    return found, len(missing)


# ----------------------------------------------------------------------------------------------
# Format loaders. Each returns the keyword arguments of `Scene` it knows.


def _load_transforms(
    folder: Path, fmt: str, path: Path, meta: Dict[str, Any], split: Optional[str],
    factor: Optional[float], background: np.ndarray, max_images: Optional[int],
) -> Dict[str, Any]:
    """instant-ngp and nerfstudio transforms.json: OpenGL c2w, one camera."""
    _check_split(split, SPLITS)
    split = split or "all"
    frames = _read_frames(meta, path)
    camera = _camera_meta(meta, frames, path)
    metadata: Dict[str, Any] = {"scene_file": _relative(path, folder)}
    applied = None
    if fmt == "nerfstudio":
        model = meta.get("camera_model", "OPENCV")
        if model not in _NERFSTUDIO_MODELS:
            raise SceneFormatError(
                path, f"unsupported camera_model {model!r} (supported: {', '.join(sorted(_NERFSTUDIO_MODELS))})"
            )
        metadata["camera_model"] = model
        if "applied_transform" in meta:
            try:
                applied = np.asarray(meta["applied_transform"], np.float64)
            except (TypeError, ValueError):
                applied = np.zeros(0)
            if applied.shape != (3, 4) or not np.all(np.isfinite(applied)):
                raise SceneFormatError(path, "'applied_transform' must be a finite 3x4 matrix")
            applied = applied.astype(np.float32)
    found, skipped = _existing_frames(frames, folder, path)
    found.sort(key=lambda fi: _natural_key(fi[0]["file_path"]))
    index = _subsample(_holdout(len(found), split), max_images)
    chosen = [found[i] for i in index]
    if not chosen:
        raise SceneFormatError(path, f"split {split!r} is empty ({len(found)} images in all)")
    images, alphas, full = _load_images([p for _, p in chosen], factor or 1.0, background)
    intrinsics = _json_intrinsics(camera, full, path)
    intrinsics = intrinsics.scaled(images.shape[2], images.shape[1])
    c2w_all = np.stack([f["_c2w"] for f, _ in found])

    if fmt == "instant-ngp":
        aabb_scale = _number(meta, "aabb_scale", path)
        aabb_scale = 1.0 if aabb_scale is None else aabb_scale
        scale = _number(meta, "scale", path)
        scale = NGP_DEFAULT_SCALE if scale is None else scale
        if aabb_scale <= 0 or scale <= 0:
            raise SceneFormatError(path, f"'aabb_scale' and 'scale' must be positive, got {aabb_scale:g} and {scale:g}")
        offset = meta.get("offset", NGP_DEFAULT_OFFSET)
        try:
            offset_vec = np.broadcast_to(np.asarray(offset, np.float64), (3,))
        except (TypeError, ValueError):
            raise SceneFormatError(path, f"'offset' must be a number or 3 numbers, got {offset!r}") from None
        ngp_lo, ngp_hi = 0.5 - 0.5 * aabb_scale, 0.5 + 0.5 * aabb_scale
        corners = (np.stack([np.full(3, ngp_lo), np.full(3, ngp_hi)]) - offset_vec) / scale
        aabb = np.stack([corners.min(0), corners.max(0)]).astype(np.float32)
        metadata.update(aabb_scale=aabb_scale, scale=scale, offset=offset_vec.tolist(),
                        ngp_aabb=[[ngp_lo] * 3, [ngp_hi] * 3])
    else:
        ply_name = meta.get("ply_file_path", "sparse_pc.ply")
        ply = folder / ply_name if isinstance(ply_name, str) else None
        if ply is not None and ply.is_file():
            points = read_ply_points(ply)
            if len(points) == 0:
                raise SceneFormatError(ply, "PLY file has no vertices")
            lo, hi = np.percentile(points, PLY_PERCENTILES, axis=0)
            aabb = _pad_box(lo, hi, PLY_PAD)
            metadata.update(aabb_source=_relative(ply, folder), ply_points=int(len(points)))
        else:
            origins = np.concatenate([c2w_all[:, :3, 3], camera_focus(c2w_all)[None]])
            aabb = _pad_box(origins.min(0), origins.max(0), ORIGIN_PAD)
            metadata["aabb_source"] = "camera origins and focus"
    near, far = camera_bounds(c2w_all, aabb)
    metadata["distortion"] = [float(v) for v in np.asarray(intrinsics.distortion)]
    return dict(
        images=images, alphas=alphas, original_size=full, intrinsics=intrinsics,
        c2w=np.stack([f["_c2w"] for f, _ in chosen]), aabb=aabb, near=near, far=far,
        file_names=tuple(_relative(p, folder) for _, p in chosen), split=split,
        skipped_missing=skipped, applied_transform=applied, metadata=metadata,
    )


def _load_blender(
    folder: Path, path: Path, split: Optional[str], factor: Optional[float],
    background: np.ndarray, max_images: Optional[int],
) -> Dict[str, Any]:
    """Blender transforms_{train,val,test}.json: camera_angle_x, RGBA PNGs."""
    _check_split(split, SPLITS)
    split = split or _blender_split_of(path.name) or "train"
    names = BLENDER_SPLITS if split == "all" else (split,)
    files = [folder / f"transforms_{s}.json" for s in names]
    if split == "all":
        files = [f for f in files if f.is_file()]
    elif not files[0].is_file():
        present = [s for s in BLENDER_SPLITS if (folder / f"transforms_{s}.json").is_file()]
        raise SceneFormatError(files[0], f"no such file: this Blender scene has splits {', '.join(present)}")
    frames: List[Dict[str, Any]] = []
    camera = None
    for file in files:
        meta = _read_json(file)
        file_frames = _read_frames(meta, file)
        this_camera = _camera_meta(meta, file_frames, file)
        if camera is not None and this_camera != camera:
            raise SceneFormatError(file, f"camera differs from {files[0].name}: {this_camera} vs {camera}")
        camera = this_camera
        frames.extend(file_frames)
    found, skipped = _existing_frames(frames, folder, files[0] if len(files) == 1 else folder)
    chosen = [found[i] for i in _subsample(np.arange(len(found)), max_images)]
    images, alphas, full = _load_images([p for _, p in chosen], factor or 1.0, background)
    intrinsics = _json_intrinsics(camera, full, files[0]).scaled(images.shape[2], images.shape[1])
    return dict(
        images=images, alphas=alphas, original_size=full, intrinsics=intrinsics,
        c2w=np.stack([f["_c2w"] for f, _ in chosen]), aabb=np.asarray(BLENDER_AABB, np.float32),
        near=BLENDER_NEAR, far=BLENDER_FAR, file_names=tuple(_relative(p, folder) for _, p in chosen),
        split=split, skipped_missing=skipped, applied_transform=None,
        metadata={"scene_file": [_relative(f, folder) for f in files]},
    )


def _llff_folders(folder: Path) -> Dict[int, Path]:
    """{K: images_K folder}, with K = 1 for `images/`."""
    found = {}
    for child in folder.iterdir():
        m = re.fullmatch(r"images(?:_(\d+))?", child.name)
        if m and child.is_dir():
            k = int(m.group(1) or 1)
            if k >= 1:
                found[k] = child
    return found


def _load_llff(
    folder: Path, path: Path, split: Optional[str], factor: Optional[float],
    background: np.ndarray, max_images: Optional[int],
) -> Dict[str, Any]:
    """LLFF poses_bounds.npy with images/ or images_K/ folders."""
    _check_split(split, SPLITS)
    split = split or "all"
    try:
        table = np.load(path, allow_pickle=False)
    except Exception as e:  # numpy raises ValueError/OSError/EOFError... for bad files.
        raise SceneFormatError(path, f"cannot read .npy array ({type(e).__name__}: {e})") from None
    if table.ndim != 2 or table.shape[1] != 17 or table.shape[0] == 0:
        raise SceneFormatError(
            path, f"expected shape [N, 17] with N >= 1 (3x5 pose + near, far), got {list(table.shape)}"
        )
    if not np.issubdtype(table.dtype, np.floating) or not np.all(np.isfinite(table)):
        raise SceneFormatError(path, "poses_bounds must be finite floating-point numbers")
    table = table.astype(np.float64)
    poses = table[:, :15].reshape(-1, 3, 5)
    bounds = table[:, 15:17]  # [N, 2] per-camera near, far.
    hwf = poses[:, :, 4]
    if np.any(np.abs(hwf - hwf[0]) > 1e-6 * np.abs(hwf[0])):
        raise SceneFormatError(path, "the [h, w, f] column differs between poses: several cameras are not supported")
    full_h, full_w, focal = hwf[0]
    if min(full_h, full_w, focal) <= 0:
        raise SceneFormatError(path, f"[h, w, f] must be positive, got {hwf[0].tolist()}")
    if np.any(bounds[:, 0] <= 0) or np.any(bounds[:, 1] <= bounds[:, 0]):
        raise SceneFormatError(path, "near/far bounds must satisfy 0 < near < far for every pose")
    # LLFF columns are [down, right, backward]; OpenGL wants [right, up, backward].
    llff_rot = poses[:, :, :3]
    rotation = np.stack([llff_rot[:, :, 1], -llff_rot[:, :, 0], llff_rot[:, :, 2]], -1)
    c2w_all = np.zeros((len(poses), 4, 4))
    c2w_all[:, :3, :3] = rotation
    c2w_all[:, :3, 3] = poses[:, :, 3]
    c2w_all[:, 3, 3] = 1.0
    for i, m in enumerate(c2w_all):
        _check_rigid(m, path, f"pose {i}")

    folders = _llff_folders(folder)
    if not folders:
        raise SceneFormatError(folder, "LLFF scene has no images/ or images_K/ folder")
    wanted = float(LLFF_DEFAULT_FACTOR) if factor is None else factor
    if factor is None and LLFF_DEFAULT_FACTOR not in folders:
        source_k = max(folders)
        wanted = float(source_k)
    else:
        exact = [k for k in folders if abs(k - wanted) < 1e-9]
        below = [k for k in folders if k < wanted]
        if not exact and not below:
            raise SceneFormatError(
                folder,
                f"downscale {wanted:g} needs images/ or images_K with K <= {wanted:g}; "
                f"available: {', '.join(folders[k].name for k in sorted(folders))}",
            )
        source_k = exact[0] if exact else max(below)
    image_dir = folders[source_k]
    image_paths = sorted(
        (p for p in image_dir.iterdir() if p.suffix in IMAGE_EXTENSIONS and p.is_file()),
        key=lambda p: _natural_key(p.name),
    )
    if len(image_paths) != len(poses):
        raise SceneFormatError(
            image_dir, f"holds {len(image_paths)} images but {path.name} has {len(poses)} poses"
        )
    index = _subsample(_holdout(len(poses), split), max_images)
    chosen = [image_paths[i] for i in index]
    if not chosen:
        raise SceneFormatError(path, f"split {split!r} is empty ({len(poses)} images in all)")
    disk_w, disk_h = _image_size(chosen[0])
    if abs(disk_w / disk_h - full_w / full_h) > 0.01 * full_w / full_h:
        raise SceneFormatError(
            image_dir, f"images are {disk_w}x{disk_h}, another aspect ratio than the {full_w:g}x{full_h:g} of hwf"
        )
    residual = wanted * disk_w / full_w  # further factor applied to the folder's images.
    images, alphas, full = _load_images(chosen, max(1.0, residual), background)
    height, width = images.shape[1:3]
    intrinsics = Intrinsics.create(int(round(full_w)), int(round(full_h)), focal).scaled(width, height)

    # Scene box: all camera frustums between each camera's own near and far bound.
    half_w, half_h = 0.5 * full_w / focal, 0.5 * full_h / focal
    corners_cam = np.array([[sx * half_w, sy * half_h, -1.0] for sx in (-1, 1) for sy in (-1, 1)])  # [4, 3]
    depths = bounds[:, :, None, None] * corners_cam[None, None]  # [N, 2, 4, 3]
    world = np.einsum("nij,nkcj->nkci", c2w_all[:, :3, :3], depths) + c2w_all[:, None, None, :3, 3]
    world = world.reshape(-1, 3)
    aabb = np.stack([world.min(0), world.max(0)]).astype(np.float32)
    return dict(
        images=images, alphas=alphas, original_size=(int(round(full_w)), int(round(full_h))),
        intrinsics=intrinsics, c2w=c2w_all[index], aabb=aabb, near=float(LLFF_NEAR_MARGIN * bounds[:, 0].min()),
        far=float(LLFF_FAR_MARGIN * bounds[:, 1].max()),
        file_names=tuple(_relative(p, folder) for p in chosen), split=split, skipped_missing=0,
        applied_transform=None,
        metadata={
            "scene_file": _relative(path, folder),
            "image_folder": image_dir.name,
            "image_folder_size": [int(full[0]), int(full[1])],
            "bounds_min": bounds.min(0).tolist(),
            "bounds_max": bounds.max(0).tolist(),
        },
    )


# ----------------------------------------------------------------------------------------------
# Poses files (cameras to render, without images).


def _poses_file_c2w(matrix: Any, path: Path, what: str) -> np.ndarray:
    """A validated [4, 4] camera-to-world matrix of a poses file (16 numbers or [3, 4] accepted)."""
    try:
        m = np.asarray(matrix, np.float64)
    except (TypeError, ValueError):
        raise SceneFormatError(path, f"{what} is not a matrix of numbers") from None
    if m.shape == (16,):
        m = m.reshape(4, 4)
    if m.shape == (3, 4):
        m = np.concatenate([m, [[0.0, 0.0, 0.0, 1.0]]])
    if m.shape != (4, 4):
        raise SceneFormatError(path, f"{what} has shape {list(m.shape)}, expected 4x4")
    if not np.all(np.isfinite(m)):
        raise SceneFormatError(path, f"{what} has non-finite values")
    rotation = m[:3, :3]
    if np.max(np.abs(rotation.T @ rotation - np.eye(3))) > RIGID_TOL or np.linalg.det(rotation) < 0:
        raise SceneFormatError(path, f"{what} is not a rigid camera-to-world matrix")
    _check_origin(m, path, what)
    return m


def _poses_file_intrinsics(meta: Dict[str, Any], path: Path, default: Intrinsics) -> Intrinsics:
    """Intrinsics of a poses file, or `default` when it has no focal length."""
    w, h = _number(meta, "w", path), _number(meta, "h", path)
    fl_x, fl_y = _number(meta, "fl_x", path), _number(meta, "fl_y", path)
    angle_x, angle_y = _number(meta, "camera_angle_x", path), _number(meta, "camera_angle_y", path)
    if fl_x is None and fl_y is None and angle_x is None and angle_y is None:
        return default
    if w is None or h is None:
        # A focal length without an image size: assume the default camera's size (and aspect).
        w = w or (h * default.width / default.height if h else float(default.width))
        h = h or (w * default.height / default.width)
    if fl_x is None and angle_x is not None:
        fl_x = 0.5 * w / math.tan(0.5 * angle_x)
    if fl_y is None and angle_y is not None:
        fl_y = 0.5 * h / math.tan(0.5 * angle_y)
    fl_x = fl_x if fl_x is not None else fl_y
    fl_y = fl_y if fl_y is not None else fl_x
    if not (fl_x > 0 and fl_y > 0 and w >= 1 and h >= 1):
        raise SceneFormatError(path, f"invalid camera (fl_x={fl_x}, fl_y={fl_y}, w={w}, h={h})")
    if not (MIN_RESOLUTION <= min(w, h) and max(w, h) <= MAX_RESOLUTION):
        raise SceneFormatError(path, f"camera of {w:g}x{h:g} pixels: sides must lie between {MIN_RESOLUTION} and "
                               f"{MAX_RESOLUTION} (--resolution R renders at another size)")
    distortion = [_number(meta, k, path) or 0.0 for k in ("k1", "k2", "p1", "p2")]
    intrinsics = Intrinsics.create(int(round(w)), int(round(h)), fl_x, fl_y, _number(meta, "cx", path),
                                   _number(meta, "cy", path), distortion)
    _warn_off_image_principal_point(intrinsics, path)
    return intrinsics


def read_poses_file(
    path: str | os.PathLike, default_intrinsics: Intrinsics
) -> Tuple[np.ndarray, Intrinsics, List[Optional[str]]]:
    """Reads the cameras of a transforms.json-like poses file (no images are needed or read).

    The file is a JSON object with `frames[].transform_matrix` (instant-ngp / nerfstudio / Blender
    transforms: OpenGL camera-to-world, in the file's own world frame, used as they are). A matrix may
    be 4x4, 3x4 (the (0, 0, 0, 1) row is added) or 16 numbers; it must be finite and rigid (rotation
    orthonormal within `RIGID_TOL`, det +1). Intrinsics come from the file when it has a focal length
    (`fl_x`/`fl_y` or `camera_angle_x`/`camera_angle_y`, with `w`/`h`, `cx`/`cy`, `k1 k2 p1 p2`; a
    missing size is taken from `default_intrinsics`), else they are `default_intrinsics`. nerfstudio
    viewer camera paths (`camera_path`) are refused: they live in nerfstudio's normalised world, which
    `load_scene` does not reproduce.

    Args:
      path: the JSON file.
      default_intrinsics: the camera to use when the file has no focal length (e.g. a checkpoint's).

    Returns:
      (c2w float32 [N, 4, 4], intrinsics, file_names): `file_names[i]` is frame i's `file_path`, or
      None when it has none.

    Raises:
      SceneFormatError: the file is missing, unreadable, not JSON, has no (or an empty) `frames`
        list, a frame without a valid `transform_matrix`, invalid intrinsics, or is a camera path.
        The message names the file (and the frame).
    """
    path = Path(path)
    if not os.path.lexists(path):
        raise SceneFormatError(path, "no such poses file")
    check_input_file(path, "poses file")
    try:
        meta = json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise SceneFormatError(path, "no such poses file") from None
    except (OSError, UnicodeDecodeError) as e:
        raise SceneFormatError(path, f"cannot read poses file ({e})") from None
    except json.JSONDecodeError as e:
        raise SceneFormatError(path, f"malformed JSON at line {e.lineno}, column {e.colno}: {e.msg}") from None
    if not isinstance(meta, dict):
        raise SceneFormatError(path, "expected a JSON object with a 'frames' list")
    if isinstance(meta.get("frames"), list):
        frames = meta["frames"]
        if not frames:
            raise SceneFormatError(path, "'frames' is empty")
        poses, names = [], []
        for i, frame in enumerate(frames):
            if not isinstance(frame, dict) or "transform_matrix" not in frame:
                raise SceneFormatError(path, f"frame {i} has no 'transform_matrix'")
            poses.append(_poses_file_c2w(frame["transform_matrix"], path, f"frame {i} transform_matrix"))
            name = frame.get("file_path")
            names.append(None if name is None else str(name))
        return np.stack(poses).astype(np.float32), _poses_file_intrinsics(meta, path, default_intrinsics), names
    if "camera_path" in meta:
        # nerfstudio's viewer writes camera paths in its own normalised world (after its dataparser's
        # orientation and scale), not in the frame of the scene's transforms.json.
        raise SceneFormatError(
            path, "a nerfstudio camera path is in nerfstudio's normalised world frame, not the scene's; "
            "pass a transforms.json-like file with frames[].transform_matrix in the scene's own frame")
    raise SceneFormatError(path, "no 'frames' list with transform_matrix entries (transforms.json format)")


# ----------------------------------------------------------------------------------------------
# Entry point.


def _check_extent(parts: Dict[str, Any], path: Path) -> None:
    """Refuses a scene box or near/far that is not finite or lies beyond `MAX_COORDINATE`."""
    aabb = np.asarray(parts["aabb"], np.float64)
    near, far = float(parts["near"]), float(parts["far"])
    if not (np.all(np.isfinite(aabb)) and np.max(np.abs(aabb)) <= MAX_COORDINATE):
        raise SceneFormatError(path, f"scene box {aabb.tolist()} is not finite or lies beyond {MAX_COORDINATE:g} "
                               "(rescale the scene)")
    if not (math.isfinite(near) and math.isfinite(far) and 0 < near < far):
        raise SceneFormatError(path, f"near/far bounds {near:g} / {far:g} do not satisfy 0 < near < far")


def _warn_about_cameras(parts: Dict[str, Any], path: Path) -> None:
    """Warns about cameras that load but surely are a mistake: repeated poses, an off-image principal point."""
    c2w = np.asarray(parts["c2w"], np.float64)
    if len(c2w) > 1:
        scale = max(float(np.max(np.abs(np.asarray(parts["aabb"])))), 1e-6)
        distinct = np.unique(np.round(c2w[:, :3, :] / np.array([1.0, 1.0, 1.0, scale]) * 1e6), axis=0)
        if len(distinct) < len(c2w):
            warnings.warn(f"{path}: {len(c2w) - len(distinct)} of {len(c2w)} cameras repeat another camera's pose "
                          f"({len(distinct)} distinct); views from one pose give a NeRF no parallax", stacklevel=3)
    _warn_off_image_principal_point(parts["intrinsics"], path)


def _warn_off_image_principal_point(intrinsics: Intrinsics, path: Path) -> None:
    cx, cy = float(intrinsics.cx), float(intrinsics.cy)
    if not (0.0 <= cx <= intrinsics.width and 0.0 <= cy <= intrinsics.height):
        warnings.warn(f"{path}: principal point (cx, cy) = ({cx:g}, {cy:g}) lies outside the "
                      f"{intrinsics.width}x{intrinsics.height} image; the cameras look far off their image centre",
                      stacklevel=4)


def load_scene(
    path: str | os.PathLike,
    downscale: Optional[float] = None,
    split: Optional[str] = None,
    background: Sequence[float] = (1.0, 1.0, 1.0),
    max_images: Optional[int] = None,
) -> Scene:
    """Loads a posed image set (instant-ngp, nerfstudio, Blender or LLFF) into a `Scene`.

    Args:
      path: a scene folder, or its `transforms.json`, `transforms_<split>.json` or
        `poses_bounds.npy`.
      downscale: area-downscale factor >= 1 (int or float). None: the images as stored (LLFF: 8,
        relative to the full-size images, see the module docstring).
      split: "all", "train", "val" or "test". None: "train" for Blender (or the split of the file
        passed), "all" otherwise. Formats without splits hold out every 8th sorted image as "test".
      background: RGB colour in [0, 1] that RGBA images are composited on.
      max_images: keep at most this many images of the split, evenly spaced.

    Returns:
      A `Scene`: images float32 [N, H, W, 3], c2w float32 [N, 4, 4] (OpenGL), intrinsics at the loaded
      size, aabb float32 [2, 3], near/far, file names relative to the scene folder, metadata
      (`downscale` and `original_size` [W, H] of the images it is relative to, which for LLFF are
      the full-size images of hwf; plus format facts).

    Raises:
      SceneFormatError: a file is missing, malformed or inconsistent (the message names it).
      SceneArgumentError: an argument is invalid.
    """
    factor = _check_downscale(downscale)
    bg = _check_background(background)
    max_images = _check_max_images(max_images)
    _check_split(split, SPLITS)
    folder, fmt, scene_file, meta = _locate(path)
    if fmt in ("instant-ngp", "nerfstudio"):
        parts = _load_transforms(folder, fmt, scene_file, meta, split, factor, bg, max_images)
    elif fmt == "blender":
        parts = _load_blender(folder, scene_file, split, factor, bg, max_images)
    else:
        parts = _load_llff(folder, scene_file, split, factor, bg, max_images)
    images = parts["images"]
    _check_extent(parts, scene_file)
    _warn_about_cameras(parts, scene_file)
    # The size `downscale` is relative to: the stored images (LLFF: the full-size images of hwf).
    original_w, original_h = parts["original_size"]
    metadata = dict(parts["metadata"])
    metadata.update(
        original_size=[int(original_w), int(original_h)],
        downscale=float(original_w / images.shape[2]),
    )
    return Scene(
        images=images,
        c2w=np.asarray(parts["c2w"], np.float32),
        intrinsics=parts["intrinsics"],
        aabb=np.asarray(parts["aabb"], np.float32),
        near=float(parts["near"]),
        far=float(parts["far"]),
        file_names=parts["file_names"],
        format=fmt,
        name=folder.resolve().name,
        split=parts["split"],
        path=str(folder),
        skipped_missing=int(parts["skipped_missing"]),
        alphas=parts["alphas"],
        background=bg if parts["alphas"] is not None else None,
        applied_transform=parts["applied_transform"],
        metadata=metadata,
    )
