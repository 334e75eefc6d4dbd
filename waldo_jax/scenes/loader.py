"""`load_scene`: detects a scene's format, runs its loader, checks the result and builds a `Scene`."""

from __future__ import annotations

import math
import os
import warnings
from pathlib import Path
from typing import Any, Dict, Optional, Sequence

import numpy as np

from waldo_jax.errors import SceneFormatError
from waldo_jax.scenes.common import (
    SPLITS,
    SceneArgumentError,
    check_split,
    extent_problem,
    intrinsics_problem,
    locate,
    one_line_errors,
    shown,
    warn_off_image_principal_point,
)
from waldo_jax.scenes.llff import load_llff
from waldo_jax.scenes.transforms import load_blender, load_transforms
from waldo_jax.types import Scene

__all__ = ["load_scene"]

# Cameras whose origins all lie within this fraction of the scene box's diagonal lie at one point.
ONE_POINT_FRACTION = 1e-6


def _check_downscale(downscale: Any) -> Optional[float]:
    """`downscale` as a float >= 1, or None."""
    if downscale is None:
        return None
    try:
        factor = float(downscale)
    except (TypeError, ValueError, OverflowError):
        raise SceneArgumentError(f"downscale (--downscale) must be a number >= 1, got {downscale!r}") from None
    if not math.isfinite(factor) or factor < 1.0:
        raise SceneArgumentError(f"downscale (--downscale) must be a number >= 1 (no upsampling), got {downscale!r}")
    return factor


def _check_background(background: Any) -> np.ndarray:
    """`background` as float32 [3] finite RGB (one number is repeated)."""
    try:
        bg = np.asarray(background, np.float32).reshape(-1)
    except (TypeError, ValueError, OverflowError):
        bg = np.zeros(0, np.float32)
    if bg.shape == (1,):
        bg = np.repeat(bg, 3)
    if bg.shape != (3,) or not np.all(np.isfinite(bg)) or not np.all((bg >= 0) & (bg <= 1)):
        raise SceneArgumentError(f"background must be 3 numbers in [0, 1] (an RGB colour), got {background!r}")
    return bg


def _check_max_images(max_images: Any) -> Optional[int]:
    """`max_images` as a positive int, or None."""
    if max_images is None:
        return None
    if isinstance(max_images, bool) or not isinstance(max_images, (int, np.integer)) or max_images < 1:
        raise SceneArgumentError(f"max_images must be a positive integer or None, got {max_images!r}")
    return int(max_images)


def _check_extent(parts: Dict[str, Any], path: Path) -> None:
    """Refuses a scene box, near/far or camera that is not finite, lies beyond `MAX_COORDINATE`, is
    empty or flipped (the box's sides and far - near are divided by), or that rounds to 0 in float32."""
    problem = extent_problem(parts["aabb"], parts["near"], parts["far"])
    if problem:
        raise SceneFormatError(path, problem)
    problem = intrinsics_problem(parts["intrinsics"], sides=None)
    if problem:
        raise SceneFormatError(path, f"camera: {problem}")


def _warn_about_cameras(parts: Dict[str, Any], path: Path) -> None:
    """Warns about cameras that load but surely are a mistake: repeated poses, an off-image principal point."""
    c2w = np.asarray(parts["c2w"], np.float64)
    if len(c2w) > 1:
        scale = max(float(np.max(np.abs(np.asarray(parts["aabb"])))), 1e-6)
        distinct = np.unique(np.round(c2w[:, :3, :] / np.array([1.0, 1.0, 1.0, scale]) * 1e6), axis=0)
        origins = c2w[:, :3, 3]
        spread = float(np.max(np.max(origins, 0) - np.min(origins, 0)))
        box = np.asarray(parts["aabb"], np.float64).reshape(2, 3)
        diagonal = float(np.linalg.norm(box[1] - box[0]))
        if len(distinct) < len(c2w):
            warnings.warn(
                f"{shown(path)}: {len(c2w) - len(distinct)} of {len(c2w)} cameras repeat another camera's pose "
                f"({len(distinct)} distinct); views from one pose give a NeRF no parallax",
                stacklevel=3,
            )
        elif spread <= ONE_POINT_FRACTION * diagonal:
            warnings.warn(
                f"{shown(path)}: all {len(c2w)} cameras lie at one point (within {spread:.3g} of each other, in a "
                f"scene box {diagonal:.3g} across): views from one point (a panorama) give a NeRF no parallax, so "
                "its depth is a guess",
                stacklevel=3,
            )
    warn_off_image_principal_point(parts["intrinsics"], path)


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
        relative to the full-size images, see `waldo_jax.scenes.llff`).
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
    with one_line_errors():  # a file name with a newline or an escape stays on one line
        factor = _check_downscale(downscale)
        bg = _check_background(background)
        max_images = _check_max_images(max_images)
        check_split(split, SPLITS)
        folder, fmt, scene_file, meta = locate(path)
        if fmt in ("instant-ngp", "nerfstudio"):
            parts = load_transforms(folder, fmt, scene_file, meta, split, factor, bg, max_images)
        elif fmt == "blender":
            parts = load_blender(folder, scene_file, split, factor, bg, max_images)
        else:
            parts = load_llff(folder, scene_file, split, factor, bg, max_images)
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
