"""Decoding and area-downscaling the images of a scene to float32 [N, H, W, 3] in [0, 1].

Grey images are repeated to 3 channels; 16/32-bit grey skips the 8-bit round trip. RGBA is straight
alpha: the premultiplied colour `rgb * a` and `a` are filtered, then composited on a background.
Downscaling is an area (box) filter: `PIL.Image.reduce` for integer factors that divide the size,
else `resize(BOX)` to `round(size / factor)`. See docs/design.md, "Scenes".
"""

from __future__ import annotations

import dataclasses
import math
import os
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Optional, Sequence, Tuple

import numpy as np
from PIL import Image

from waldo_jax.errors import SceneFormatError, check_memory
from waldo_jax.types import Scene

__all__ = ["IMAGE_EXTENSIONS", "downscale_scene", "fit_factor", "image_size", "load_images", "resolve_image"]

IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg", ".PNG", ".JPG", ".JPEG")
_MAX_THREADS = 8


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
        np.asarray(Image.fromarray(np.ascontiguousarray(array[..., i]), "F").resize(size, Image.BOX)) for i in range(c)
    ]
    return np.stack(channels, -1).astype(np.float32)


def fit_factor(width: int, height: int, max_pixels: int) -> int:
    """The least whole factor k >= 1 that brings a width x height image to at most `max_pixels` pixels."""
    if max_pixels < 1:
        raise ValueError(f"max_pixels must be a positive integer, got {max_pixels}")

    def fits(k: int) -> bool:
        return math.prod(_target_size(width, height, k)) <= max_pixels

    k = max(1, math.ceil(math.sqrt(width * height / max_pixels)))  # sizes round to the nearest pixel:
    while not fits(k):  # the factor that fits by area may be a little too small ...
        k += 1
    while k > 1 and fits(k - 1):  # ... or too large
        k -= 1
    return k


def downscale_scene(scene: Scene, factor: int) -> Scene:
    """`scene` with its images (and alphas) area-filtered to 1/factor of their size, the camera to match
    (`Intrinsics.downscaled`); where `factor` divides the size, as a load with `downscale` times
    `factor` would give (else one box filter after another, close to it); factor 1: `scene`."""
    factor = int(factor)
    if factor < 1:
        raise ValueError(f"the downscale factor must be a whole number >= 1, got {factor}")
    if factor == 1:
        return scene
    intrinsics = scene.intrinsics.downscaled(factor)
    size = (intrinsics.width, intrinsics.height)
    images = np.stack([_box_resize(image, size) for image in scene.images]) if scene.n_images else scene.images
    alphas = None
    if scene.alphas is not None:
        alphas = np.stack([_box_resize(a[..., None], size)[..., 0] for a in scene.alphas])
    metadata = dict(scene.metadata)
    metadata["downscale"] = float(metadata.get("downscale") or 1.0) * factor
    return dataclasses.replace(
        scene,
        images=np.clip(images, 0.0, 1.0).astype(np.float32),
        intrinsics=intrinsics,
        alphas=alphas,
        metadata=metadata,
    )


def _decode(img: Image.Image, size: Tuple[int, int], path: Path) -> Tuple[np.ndarray, Optional[np.ndarray]]:
    """An opened PIL image as (float32 [h, w, 3] colour, float32 [h, w] straight alpha or None).

    With alpha, the colour returned is premultiplied (rgb * a), filtered at `size` = (w, h). 16/32-bit
    grey outside [0, 1] (after / 65535 for integers) is refused, not clipped.
    """
    mode = img.mode
    has_alpha = mode in ("RGBA", "LA", "PA", "RGBa", "La") or (mode == "P" and "transparency" in img.info)
    if mode.startswith("I") or mode == "F":  # 16/32-bit grey: no 8-bit round trip.
        grey = np.asarray(img, np.float32)
        if mode != "F":
            grey = grey / 65535.0
        if np.all(np.isfinite(grey)) and not (grey.min() >= 0.0 and grey.max() <= 1.0):  # NaN: refused below
            scale = 1.0 if mode == "F" else 65535.0
            raise SceneFormatError(
                path,
                f"a {mode}-mode image with values in [{grey.min() * scale:g}, "
                f"{grey.max() * scale:g}], outside [0, {scale:g}]; rescale it (it is not clipped)",
            )
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


def image_size(path: Path) -> Tuple[int, int]:
    """(width, height) from an image header."""
    try:
        with Image.open(path) as img:
            return img.size
    except Exception as e:  # PIL raises many types for bad files.
        raise SceneFormatError(path, f"cannot read image ({type(e).__name__}: {e})") from None


def load_images(
    paths: Sequence[Path], factor: float, background: np.ndarray
) -> Tuple[np.ndarray, Optional[np.ndarray], Tuple[int, int]]:
    """Reads same-size images, area-downscaled by `factor`, RGBA composited on `background`.

    Returns:
      (images float32 [N, h, w, 3], alphas float32 [N, h, w] or None, (W, H) size on disk).
    """
    full = image_size(paths[0])
    size = _target_size(*full, factor)
    check_memory(
        4.0 * len(paths) * size[0] * size[1] * 3,
        f"{len(paths)} images of {size[0]}x{size[1]} (as {paths[0].parent}/{paths[0].name}, float32 RGB)",
        "load fewer (load_scene's max_images) or smaller ones (--downscale)",
    )
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
                rgb, alpha = _decode(img, size, path)
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


def resolve_image(folder: Path, file_path: str) -> Optional[Path]:
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
