"""LLFF scenes: `poses_bounds.npy` with `images/` or `images_K/` folders.

LLFF pose columns [down, right, backward] become OpenGL [right, up, backward]; the world is neither
recentred nor rescaled. `downscale` is relative to the full-size images of hwf (default
`LLFF_DEFAULT_FACTOR` = 8, NeRF's): a factor F reads `images_F`, else the folder with the largest
K < F box-filtered by F / K (never upsampled). The box covers every camera frustum between its own
near and far bound. See docs/design.md, "Scenes".
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any, Dict, List, Optional, Tuple

import numpy as np

from waldo_jax.errors import NumberError, SceneFormatError, check_float32
from waldo_jax.scenes.common import (
    SPLITS,
    check_holdout_split,
    check_rigid,
    check_split,
    holdout,
    input_file,
    natural_key,
    relative,
    shown,
    subsample,
)
from waldo_jax.scenes.images import image_size, is_image_name, load_images
from waldo_jax.types import Intrinsics

__all__ = ["LLFF_NEAR_MARGIN", "LLFF_FAR_MARGIN", "LLFF_DEFAULT_FACTOR", "load_llff"]

LLFF_NEAR_MARGIN = 0.9
LLFF_FAR_MARGIN = 1.0
LLFF_DEFAULT_FACTOR = 8


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


def _read_poses_bounds(path: Path) -> np.ndarray:
    """poses_bounds.npy as float64 [N, 17] (a 3x5 pose, near, far per row), checked finite and non-empty."""
    input_file(path, "poses file (.npy)")
    try:
        with open(path, "rb") as f:
            magic = f.read(6)
    except OSError as e:
        raise SceneFormatError(shown(path), f"cannot read .npy array ({e.strerror or e})") from None
    if magic != b"\x93NUMPY" and magic[:2] != b"PK":  # NumPy would say "pickled (object) data" of any other bytes
        raise SceneFormatError(shown(path), f"not a .npy array (it starts {magic!r}, not NumPy's b'\\x93NUMPY')")
    try:
        table = np.load(path, allow_pickle=False)
    except Exception as e:  # numpy raises ValueError/OSError/EOFError... for bad files.
        raise SceneFormatError(shown(path), f"cannot read .npy array ({type(e).__name__}: {e})") from None
    if not isinstance(table, np.ndarray):  # np.load reads what the content is: an .npz archive, say
        if hasattr(table, "close"):
            table.close()
        raise SceneFormatError(
            shown(path), f"not a .npy array: the file holds a {type(table).__name__} (an .npz archive?), not an array"
        )
    if table.ndim != 2 or table.shape[1] != 17 or table.shape[0] == 0:
        raise SceneFormatError(
            path, f"expected shape [N, 17] with N >= 1 (3x5 pose + near, far), got {list(table.shape)}"
        )
    if not np.issubdtype(table.dtype, np.floating) or not np.all(np.isfinite(table)):
        raise SceneFormatError(path, "poses_bounds must be finite floating-point numbers")
    return table.astype(np.float64)


def _shared_hwf(path: Path, poses: np.ndarray) -> Tuple[float, float, float]:
    """The one camera's (full height, full width, focal) from the poses' [h, w, f] column [N, 3, 5]."""
    hwf = poses[:, :, 4]
    if np.any(np.abs(hwf - hwf[0]) > 1e-6 * np.abs(hwf[0])):
        raise SceneFormatError(path, "the [h, w, f] column differs between poses: several cameras are not supported")
    full_h, full_w, focal = hwf[0]
    try:
        for value, what in ((full_h, "h"), (full_w, "w"), (focal, "f")):
            check_float32(value, f"[h, w, f] {what}", positive=True)
    except NumberError as e:
        raise SceneFormatError(path, str(e)) from None
    if min(full_h, full_w) < 1:
        raise SceneFormatError(path, f"[h, w, f] = {hwf[0].tolist()}: image sides must be at least 1 pixel")
    return full_h, full_w, focal


def _llff_c2w(path: Path, poses: np.ndarray) -> np.ndarray:
    """OpenGL camera-to-world float64 [N, 4, 4] from LLFF's [down, right, backward] poses [N, 3, 5]."""
    llff_rot = poses[:, :, :3]
    rotation = np.stack([llff_rot[:, :, 1], -llff_rot[:, :, 0], llff_rot[:, :, 2]], -1)
    c2w_all = np.zeros((len(poses), 4, 4))
    c2w_all[:, :3, :3] = rotation
    c2w_all[:, :3, 3] = poses[:, :, 3]
    c2w_all[:, 3, 3] = 1.0
    for i, m in enumerate(c2w_all):
        check_rigid(m, path, f"pose {i}")
    return c2w_all


def _image_folder(folder: Path, factor: Optional[float]) -> Tuple[Path, float]:
    """(the images/ or images_K/ folder to read, the downscale wanted of the full-size images)."""
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
    return folders[source_k], wanted


def _image_paths(image_dir: Path, path: Path, count: int) -> List[Path]:
    """The folder's images in natural order, one per pose (`count`)."""
    # Extensions in any case (.png, .Png, .PNG); an image name that is no regular file (a FIFO, a folder,
    # a link loop) is refused by name, not left out of the count.
    image_paths = sorted(
        (input_file(p, "scene image file") for p in image_dir.iterdir() if is_image_name(p)),
        key=lambda p: natural_key(p.name),
    )
    if len(image_paths) != count:
        raise SceneFormatError(image_dir, f"holds {len(image_paths)} images but {path.name} has {count} poses")
    return image_paths


def _frustums_aabb(c2w_all: np.ndarray, bounds: np.ndarray, full_w: float, full_h: float, focal: float) -> np.ndarray:
    """Scene box float32 [2, 3]: all camera frustums between each camera's own near and far bound."""
    half_w, half_h = 0.5 * full_w / focal, 0.5 * full_h / focal
    corners_cam = np.array([[sx * half_w, sy * half_h, -1.0] for sx in (-1, 1) for sy in (-1, 1)])  # [4, 3]
    depths = bounds[:, :, None, None] * corners_cam[None, None]  # [N, 2, 4, 3]
    world = np.einsum("nij,nkcj->nkci", c2w_all[:, :3, :3], depths) + c2w_all[:, None, None, :3, 3]
    world = world.reshape(-1, 3)
    return np.stack([world.min(0), world.max(0)]).astype(np.float32)


def load_llff(
    folder: Path,
    path: Path,
    split: Optional[str],
    factor: Optional[float],
    background: np.ndarray,
    max_images: Optional[int],
) -> Dict[str, Any]:
    """LLFF poses_bounds.npy with images/ or images_K/ folders."""
    check_split(split, SPLITS)
    split = split or "all"
    check_holdout_split(split, "llff", path)
    table = _read_poses_bounds(path)
    poses = table[:, :15].reshape(-1, 3, 5)
    bounds = table[:, 15:17]  # [N, 2] per-camera near, far.
    full_h, full_w, focal = _shared_hwf(path, poses)
    if np.any(bounds[:, 0] <= 0) or np.any(bounds[:, 1] <= bounds[:, 0]):
        raise SceneFormatError(path, "near/far bounds must satisfy 0 < near < far for every pose")
    # LLFF columns are [down, right, backward]; OpenGL wants [right, up, backward].
    c2w_all = _llff_c2w(path, poses)

    image_dir, wanted = _image_folder(folder, factor)
    image_paths = _image_paths(image_dir, path, len(poses))
    index = subsample(holdout(len(poses), split), max_images)
    chosen = [image_paths[i] for i in index]
    if not chosen:
        raise SceneFormatError(path, f"split {split!r} is empty ({len(poses)} images in all)")
    disk_w, disk_h = image_size(chosen[0])
    if abs(disk_w / disk_h - full_w / full_h) > 0.01 * full_w / full_h:
        raise SceneFormatError(
            image_dir, f"images are {disk_w}x{disk_h}, another aspect ratio than the {full_w:g}x{full_h:g} of hwf"
        )
    residual = wanted * disk_w / full_w  # further factor applied to the folder's images.
    images, alphas, full = load_images(chosen, max(1.0, residual), background)
    height, width = images.shape[1:3]
    intrinsics = Intrinsics.create(int(round(full_w)), int(round(full_h)), focal).scaled(width, height)
    aabb = _frustums_aabb(c2w_all, bounds, full_w, full_h, focal)
    return dict(
        images=images,
        alphas=alphas,
        original_size=(int(round(full_w)), int(round(full_h))),
        intrinsics=intrinsics,
        c2w=c2w_all[index],
        aabb=aabb,
        near=float(LLFF_NEAR_MARGIN * bounds[:, 0].min()),
        far=float(LLFF_FAR_MARGIN * bounds[:, 1].max()),
        file_names=tuple(relative(p, folder) for p in chosen),
        split=split,
        skipped_missing=0,
        applied_transform=None,
        metadata={
            "scene_file": relative(path, folder),
            "image_folder": image_dir.name,
            "image_folder_size": [int(full[0]), int(full[1])],
            "bounds_min": bounds.min(0).tolist(),
            "bounds_max": bounds.max(0).tolist(),
        },
    )
