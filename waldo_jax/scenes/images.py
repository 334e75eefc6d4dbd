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
import warnings
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Optional, Sequence, Tuple

import numpy as np
from PIL import Image

from waldo_jax import errors
from waldo_jax.errors import SceneFormatError, check_memory
from waldo_jax.scenes.common import input_file, shown
from waldo_jax.types import Scene

__all__ = [
    "IMAGE_EXTENSIONS",
    "downscale_scene",
    "fit_factor",
    "image_size",
    "is_image_name",
    "load_images",
    "resolve_image",
]

IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg", ".PNG", ".JPG", ".JPEG")
_ALPHA_MODES = ("RGBA", "LA", "PA", "RGBa", "La")


def is_image_name(path: Path) -> bool:
    """True for a name that ends in an image extension, in any case (.png, .Png, .JPG ...)."""
    return path.suffix.lower() in (".png", ".jpg", ".jpeg")


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
    has_alpha = mode in _ALPHA_MODES or (mode == "P" and "transparency" in img.info)
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
    return _header(path)[0]


# The EXIF tag of the orientation a viewer shows an image in (1: as stored).
_EXIF_ORIENTATION = 0x0112


def _header(path: Path) -> Tuple[Tuple[int, int], str, bool, int]:
    """((width, height), PIL mode, has alpha, EXIF orientation (1: as stored)) from an image header, nothing
    decoded; a file that is no regular file (a FIFO, a device) is refused before it is opened, and so is
    one of several frames (an animation, a multi-page file: which frame is the view?), as `waldo score`
    refuses it."""
    input_file(path, "scene image file")
    try:
        with Image.open(path) as img:
            alpha = img.mode in _ALPHA_MODES or (img.mode == "P" and "transparency" in img.info)
            frames = 2 if getattr(img, "is_animated", False) else 1  # Pillow looks no further than frame 2
            try:
                orientation = int(img.getexif().get(_EXIF_ORIENTATION, 1) or 1)
            except Exception:  # a damaged EXIF block: the pixels are read as stored anyway
                orientation = 1
            size, mode = img.size, img.mode
    except Exception as e:  # PIL raises many types for bad files.
        raise SceneFormatError(shown(path), f"cannot read image ({type(e).__name__}: {e})") from None
    if frames > 1:
        raise SceneFormatError(
            shown(path),
            "an image of several frames (an animation or a multi-page file); a scene's views are still images: "
            "save the frame you mean as a PNG",
        )
    return size, mode, alpha, orientation


def _decode_bytes(width: int, height: int, mode: str, alpha: bool) -> int:
    """Bytes one full-size decode of `_decode` holds at its peak: per pixel, straight alpha holds uint8
    RGBA, float32 RGBA, the premultiplied float32 RGB and the float32 stack filtered (48 bytes); 16/32-bit
    grey float32 grey twice and RGB (20, 28 with the filter's copy); 8-bit colour PIL's 4 bytes, a
    converted copy, uint8 and float32 RGB (23, 24)."""
    per_pixel = 48 if alpha else 28 if (mode.startswith("I") or mode == "F") else 24
    return per_pixel * width * height


def load_images(
    paths: Sequence[Path], factor: float, background: np.ndarray
) -> Tuple[np.ndarray, Optional[np.ndarray], Tuple[int, int]]:
    """Reads same-size images, area-downscaled by `factor`, RGBA composited on `background`.

    Before any is decoded, every header is read (sizes must agree) and the memory is checked: the images
    kept (float32 RGB, and alpha where there is one) plus each reader thread's full-size decode
    (`_decode_bytes`); threads are fewer where that memory is short.

    Returns:
      (images float32 [N, h, w, 3], alphas float32 [N, h, w] or None, (W, H) size on disk).
    """
    headers = [_header(path) for path in paths]
    full = headers[0][0]
    turned = [path for path, header in zip(paths, headers) if header[3] != 1]
    if turned:  # read as stored: a scene's poses are made from the stored pixels, as its intrinsics are
        warnings.warn(
            f"{len(turned)} of the {len(paths)} images (first: {shown(turned[0])}, EXIF orientation "
            f"{headers[list(paths).index(turned[0])][3]}) are shown turned by image viewers; they are read as "
            "stored, without the turn (their poses and sizes must describe the stored pixels)",
            stacklevel=2,
        )
    for path, (path_size, _, _, _) in zip(paths, headers):
        if path_size != full:
            raise SceneFormatError(
                shown(path),
                f"image is {path_size[0]}x{path_size[1]} but {shown(paths[0].name)} is "
                f"{full[0]}x{full[1]}: all images of a scene must have the same size",
            )
    size = _target_size(*full, factor)
    any_alpha = any(alpha for _, _, alpha, _ in headers)
    kept = 4 * len(paths) * size[0] * size[1] * (4 if any_alpha else 3)
    decode = max(_decode_bytes(*full, mode, alpha) for _, mode, alpha, _ in headers)
    workers = max(1, min(_MAX_THREADS, os.cpu_count() or 1, len(paths)))
    available = errors.host_memory_bytes()
    if available:  # as many decodes at once as fit beside the images kept (at least one)
        workers = max(1, min(workers, (available - kept) // max(decode, 1)))
    mode = headers[0][1]
    check_memory(
        kept + workers * decode,
        f"{len(paths)} images of {size[0]}x{size[1]} (as {shown(paths[0].parent)}/{shown(paths[0].name)}, float32 "
        f"RGB{'A' if any_alpha else ''}) decoded from {full[0]}x{full[1]} {mode}, {workers} at a time",
        "load fewer (load_scene's max_images) or smaller ones (--downscale)",
    )
    images = np.empty((len(paths), size[1], size[0], 3), np.float32)

    def read(i: int) -> Optional[np.ndarray]:
        path = paths[i]
        try:
            with Image.open(path) as img:
                if img.size != full:  # changed since its header was read
                    raise SceneFormatError(
                        shown(path), f"image is {img.size[0]}x{img.size[1]}, not {full[0]}x{full[1]}"
                    )
                img.load()
                rgb, alpha = _decode(img, size, path)
        except SceneFormatError:
            raise
        except Exception as e:  # corrupt or truncated files raise OSError, SyntaxError, ValueError...
            raise SceneFormatError(shown(path), f"cannot read image ({type(e).__name__}: {e})") from None
        if rgb.shape != (size[1], size[0], 3) or (alpha is not None and alpha.shape != (size[1], size[0])):
            raise SceneFormatError(shown(path), f"decoded to an array of shape {list(rgb.shape)}, not an image")
        if not np.all(np.isfinite(rgb)) or (alpha is not None and not np.all(np.isfinite(alpha))):
            raise SceneFormatError(shown(path), "the image has NaN or infinite values")
        if alpha is not None:
            rgb = rgb + (1.0 - alpha[..., None]) * background
        images[i] = rgb
        return alpha

    with ThreadPoolExecutor(workers) as pool:
        alpha_list = list(pool.map(read, range(len(paths))))
    alphas = None
    if any(a is not None for a in alpha_list):
        alphas = np.ones(images.shape[:3], np.float32)
        for i, a in enumerate(alpha_list):
            if a is not None:
                alphas[i] = a
    np.clip(images, 0.0, 1.0, out=images)
    _warn_nothing_to_learn(paths, images, alphas)
    return images, alphas, full


def _warn_nothing_to_learn(paths: Sequence[Path], images: np.ndarray, alphas: Optional[np.ndarray]) -> None:
    """Warns when the images show nothing a field could learn: every pixel transparent (alpha under 1/255:
    what is seen is the background alone), or every image one colour (all black, say). Such a scene
    trained to 6.7 dB with no word, as splats that cannot show are warned of."""
    where = f"{shown(paths[0].parent)}"
    if alphas is not None and float(alphas.max(initial=0.0)) < 1.0 / 255.0:
        warnings.warn(
            f"{where}: all {len(paths)} images are transparent (highest alpha {float(alphas.max()):.2g}, under "
            "1/255): they show the background alone, so a field trained on them learns nothing else",
            stacklevel=3,
        )
    elif images.size and float(np.ptp(images)) == 0.0:
        colour = ", ".join(f"{v:.3g}" for v in images.reshape(-1, 3)[0])
        warnings.warn(
            f"{where}: all {len(paths)} images are one colour ({colour}): a field trained on them learns nothing "
            "of the scene",
            stacklevel=3,
        )


def resolve_image(folder: Path, file_path: str) -> Optional[Path]:
    """The image a frame's `file_path` names (trying common extensions when it has none), None when
    nothing is there; a folder, a FIFO, a device or a link loop there is refused by name."""
    candidate = folder / file_path
    tried = [candidate]
    if not candidate.suffix or candidate.suffix.lower() not in (".png", ".jpg", ".jpeg", ".exr"):
        tried += [candidate.with_name(candidate.name + ext) for ext in IMAGE_EXTENSIONS]
    present = [path for path in tried if os.path.lexists(path)]
    if not present:
        return None
    # "images/0001" may be a folder beside "images/0001.png": the file is the image.
    files = [path for path in present if os.path.isfile(path)]
    return input_file(files[0] if files else present[0], "scene image file")
