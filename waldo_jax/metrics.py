"""Image metrics shared by training, fitting, the demo and the benchmarks: PSNR of images in [0, 1]."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

__all__ = ["MSE_FLOOR", "psnr_from_mse", "image_psnr", "masked_psnr"]

# The smallest MSE a PSNR is computed from (120 dB): identical images give a finite number.
MSE_FLOOR = 1e-12


def psnr_from_mse(mse):
    """PSNR (dB) of images in [0, 1] from their mean squared error: a JAX array (also under jit) or NumPy."""
    xp = jnp if isinstance(mse, jax.Array) else np
    return -10.0 * xp.log10(xp.maximum(mse, MSE_FLOOR))


def image_psnr(rendered, truth) -> np.ndarray:
    """PSNR (dB) [P] of each of the images rendered [P, H, W, C] against truth [P, H, W, C] (host arrays,
    compared in float64)."""
    mse = np.mean((np.asarray(rendered, np.float64) - np.asarray(truth, np.float64)) ** 2, axis=(1, 2, 3))
    return psnr_from_mse(mse)


def masked_psnr(rendered, truth, mask, threshold: float = 0.5) -> np.ndarray:
    """PSNR (dB) [P] of images rendered [P, H, W, C] against truth over the pixels where mask [P, H, W] >
    `threshold` (host arrays, float64); NaN for an image with no such pixel."""
    rendered, truth = np.asarray(rendered, np.float64), np.asarray(truth, np.float64)
    inside = np.asarray(mask) > threshold  # [P, H, W]
    error = np.sum((rendered - truth) ** 2, axis=-1)  # [P, H, W]
    count = inside.sum(axis=(1, 2))
    mse = np.where(count > 0, np.sum(np.where(inside, error, 0.0), axis=(1, 2)) / np.maximum(count, 1), np.nan)
    return np.where(count > 0, psnr_from_mse(np.where(count > 0, mse, 1.0) / rendered.shape[-1]), np.nan)
