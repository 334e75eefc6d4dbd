"""Natural-scene statistics (NSS) shared by the BRISQUE and NIQE image-quality models.

A. Mittal, A. K. Moorthy and A. C. Bovik, "No-Reference Image Quality Assessment in the Spatial
Domain", IEEE Trans. Image Processing 21(12), 2012 (BRISQUE); A. Mittal, R. Soundararajan and
A. C. Bovik, "Making a 'Completely Blind' Image Quality Analyzer", IEEE Signal Processing Letters
20(3), 2013 (NIQE). Both describe an image by how its locally normalised luminance departs from the
statistics of pristine photographs; `quality_scores` is how both criteria score a batch.

Names (the papers' symbols):
  I            grey image [H, W] on the 0..255 scale;
  w            7x7 Gaussian window, standard deviation 7/6 px, normalised to sum 1; borders replicate;
  mu, sigma    local mean sum_k w_k I_{x+k} and standard deviation sqrt(sum_k w_k (I_{x+k} - mu)^2);
  I_hat        MSCN ("mean-subtracted contrast-normalised") coefficients (I - mu) / (sigma + C), C = 1;
  alpha        shape of a generalised Gaussian (GGD) or of an asymmetric one (AGGD), chosen on the
               grid 0.2, 0.201, ..., 10 (9801 values) of both reference implementations;
  sigma_l, sigma_r   root mean squares of the negative and of the positive samples (AGGD);
  beta_l, beta_r     AGGD scales sigma_{l,r} sqrt(Gamma(1/alpha) / Gamma(3/alpha));
  eta          AGGD mean (beta_r - beta_l) Gamma(2/alpha) / Gamma(1/alpha).

The shape fits are moment matching by table look-up (an argmin over the grid, so they jit); the
pairwise products I_hat(i, j) I_hat(i + di, j + dj) take the four orientations of `PAIR_SHIFTS`. All
float32: a flat region gives exactly zero coefficients, and a degenerate fit (no negative or no
positive sample, NaN in MATLAB) stays finite and is flagged by `AGGDFit.valid`. The formulas and the
numerics: docs/design.md, "Criteria".
"""

from __future__ import annotations

import math
from typing import Callable, NamedTuple, Tuple

import jax
import jax.numpy as jnp
import numpy as np

from waldo_jax.criteria.base import finite_or_worst, sanitize_images, worst_score
from waldo_jax.types import Array

__all__ = [
    "SHAPE_GRID",
    "PAIR_SHIFTS",
    "FLAT_LEVEL",
    "MSCN_C",
    "gaussian_window",
    "mscn",
    "AGGDFit",
    "aggd_fit",
    "ggd_fit",
    "pairwise_products",
    "map_images",
    "quality_scores",
]

SHAPE_GRID = 0.2 + 0.001 * np.arange(9801)  # float64 [9801]: 0.2, 0.201, ..., 10.0
PAIR_SHIFTS: Tuple[Tuple[int, int], ...] = ((0, 1), (1, 0), (1, 1), (-1, 1))  # (di, dj): H, V, D1, D2
MSCN_C = 1.0  # on the 0..255 scale (OpenCV's 1/255 on its 0..1 scale is the same)
FLAT_LEVEL = 1e-4  # grey levels: |I - mu| below this is float rounding, set to 0


def _lgamma(x: np.ndarray) -> np.ndarray:
    return np.array([math.lgamma(v) for v in np.ravel(x)]).reshape(np.shape(x))


_LG1, _LG2, _LG3 = (_lgamma(k / SHAPE_GRID) for k in (1.0, 2.0, 3.0))
# Gamma(2/a)^2 / (Gamma(1/a) Gamma(3/a)), increasing in a from 0.063 to 0.741 on the grid.
_R_AGGD = np.exp(2.0 * _LG2 - _LG1 - _LG3)
_RHO_GGD = 1.0 / _R_AGGD  # Gamma(1/a) Gamma(3/a) / Gamma(2/a)^2, decreasing
_SCALE_FACTOR = np.exp(0.5 * (_LG1 - _LG3))  # beta = sigma * sqrt(Gamma(1/a) / Gamma(3/a))
_MEAN_FACTOR = np.exp(_LG2 - _LG1)  # Gamma(2/a) / Gamma(1/a)


def gaussian_window(size: int = 7, std: float = 7.0 / 6.0) -> np.ndarray:
    """The normalised 1-D Gaussian [size] whose outer product is MATLAB's fspecial('gaussian') / OpenCV's."""
    x = np.arange(size, dtype=np.float64) - (size - 1) / 2.0
    g = np.exp(-0.5 * (x / std) ** 2)
    return g / g.sum()


def mscn(grey: Array, c: float = MSCN_C) -> Tuple[Array, Array]:
    """MSCN coefficients of one grey image, and its local standard deviation.

    Args:
      grey: float [H, W] on the 0..255 scale.
      c: the stabilising constant C in (I - mu) / (sigma + C).

    Returns:
      (I_hat [H, W], sigma [H, W]), float32; 7x7 Gaussian window of std 7/6 with replicated borders.
    """
    grey = jnp.asarray(grey, jnp.float32)
    height, width = grey.shape
    g = gaussian_window()
    half = len(g) // 2
    padded = jnp.pad(grey, half, mode="edge")  # [H + 6, W + 6]
    first = jnp.zeros_like(grey)  # sum_k w_k (I_{x+k} - I_x) = mu - I
    second = jnp.zeros_like(grey)  # sum_k w_k (I_{x+k} - I_x)^2
    for i in range(len(g)):
        for j in range(len(g)):
            delta = padded[i : i + height, j : j + width] - grey  # exact for grey levels: no cancellation
            weight = np.float32(g[i] * g[j])
            first = first + weight * delta
            second = second + weight * delta * delta
    variance = jnp.maximum(second - first * first, 0.0)  # sum_k w_k (I_{x+k} - mu)^2
    sigma = jnp.sqrt(variance)
    centred = jnp.where(jnp.abs(first) < FLAT_LEVEL, 0.0, -first)  # I - mu
    return centred / (sigma + c), sigma


def _sums(x: Array) -> Array:
    """Sums [K] of the K stacked arrays x [K, ...], the last axis first (small float32 summation error)."""
    x = jnp.asarray(x, jnp.float32)
    x = x.reshape(x.shape[0], -1, x.shape[-1]) if x.ndim > 2 else x.reshape(x.shape[0], 1, -1)
    return jnp.sum(jnp.sum(x, axis=-1), axis=-1)


def _nearest_on_grid(table: np.ndarray, value: Array) -> Array:
    """Index [] of the entry of `table` [9801] nearest to `value` (the references' argmin)."""
    return jnp.argmin(jnp.abs(jnp.asarray(table, jnp.float32) - value))


class AGGDFit(NamedTuple):
    """An asymmetric generalised Gaussian fitted by moment matching (all float32 [], `valid` bool [])."""

    alpha: Array  # shape, on SHAPE_GRID
    sigma_l: Array  # root mean square of the negative samples
    sigma_r: Array  # root mean square of the positive samples
    beta_l: Array  # left scale
    beta_r: Array  # right scale
    eta: Array  # mean
    valid: Array  # both sides had samples (a MATLAB fit would otherwise give NaN)


def aggd_fit(x: Array) -> AGGDFit:
    """AGGD fit of the samples `x` (any shape, e.g. an MSCN image or a pairwise-product image).

    Zeros count in the moments E[|x|], E[x^2] but on neither side, as in both references.
    """
    x = jnp.asarray(x, jnp.float32)
    n = np.float32(x.size)
    square = x * x
    neg, pos = x < 0, x > 0
    zero = jnp.zeros_like(x)
    # One stacked reduction for the six moments (compiles far faster than six separate ones).
    sums = _sums(
        jnp.stack(
            [
                neg.astype(jnp.float32),
                pos.astype(jnp.float32),
                jnp.where(neg, square, zero),
                jnp.where(pos, square, zero),
                jnp.abs(x),
                square,
            ]
        )
    )  # [6]
    count_l, count_r = sums[0], sums[1]
    sigma_l = jnp.sqrt(sums[2] / jnp.maximum(count_l, 1.0))
    sigma_r = jnp.sqrt(sums[3] / jnp.maximum(count_r, 1.0))
    mean_abs, mean_square = sums[4] / n, sums[5] / n
    r_hat = jnp.where(mean_square > 0, mean_abs * mean_abs / jnp.where(mean_square > 0, mean_square, 1.0), 0.0)
    # (g^3 + 1)(g + 1) / (g^2 + 1)^2 with g = sigma_l / sigma_r, written homogeneously so that an empty
    # side (g = 0 or inf) needs no special case; 1 (symmetric) when both sides are empty.
    num = (sigma_l**3 + sigma_r**3) * (sigma_l + sigma_r)
    den = (sigma_l**2 + sigma_r**2) ** 2
    r_hat_norm = r_hat * jnp.where(den > 0, num / jnp.where(den > 0, den, 1.0), 1.0)
    index = _nearest_on_grid(_R_AGGD, r_hat_norm)
    scale = jnp.asarray(_SCALE_FACTOR, jnp.float32)[index]
    beta_l, beta_r = sigma_l * scale, sigma_r * scale
    eta = (beta_r - beta_l) * jnp.asarray(_MEAN_FACTOR, jnp.float32)[index]
    alpha = jnp.asarray(SHAPE_GRID, jnp.float32)[index]
    return AGGDFit(alpha, sigma_l, sigma_r, beta_l, beta_r, eta, (count_l > 0) & (count_r > 0))


def ggd_fit(x: Array) -> Tuple[Array, Array]:
    """Symmetric GGD fit of the samples `x` (any shape): (alpha [], sigma^2 = E[x^2] []).

    The original BRISQUE MATLAB fit (estimateggdparam). The OpenCV BRISQUE model and the NIQE model
    were trained with the AGGD fit of the MSCN image instead (`aggd_fit`), which agrees with this one
    up to the grid step when the samples are symmetric.
    """
    x = jnp.asarray(x, jnp.float32)
    mean_square, mean_abs = _sums(jnp.stack([x * x, jnp.abs(x)])) / np.float32(x.size)
    rho = mean_square / jnp.maximum(mean_abs * mean_abs, jnp.finfo(jnp.float32).tiny)
    index = _nearest_on_grid(_RHO_GGD, rho)
    return jnp.asarray(SHAPE_GRID, jnp.float32)[index], mean_square


def pairwise_products(x: Array, border: str) -> Array:
    """Products x(i, j) x(i + di, j + dj) for the four `PAIR_SHIFTS`, [4, H, W].

    Args:
      x: MSCN coefficients [H, W].
      border: "circular" (indices wrap, MATLAB's circshift, as NIQE does per patch) or "zero" (a
        neighbour outside the image counts as 0, as OpenCV's BRISQUE does).
    """
    x = jnp.asarray(x, jnp.float32)
    height, width = x.shape
    if border == "circular":
        return jnp.stack([x * jnp.roll(x, (-di, -dj), axis=(0, 1)) for di, dj in PAIR_SHIFTS])
    if border == "zero":
        padded = jnp.pad(x, 1)
        return jnp.stack([x * padded[1 + di : 1 + di + height, 1 + dj : 1 + dj + width] for di, dj in PAIR_SHIFTS])
    raise ValueError(f"border must be 'circular' or 'zero', got {border!r}")


def map_images(score: Callable[[Array], Array], images: Array, chunk: int) -> Array:
    """`score` (of one image) over images [P, ...]: vmapped over chunks of `chunk`, scanned over chunks.

    The batch is padded with zero images to a whole number of chunks (one compiled body, bounded
    memory); the padding's scores are dropped. Returns [P].
    """
    count = images.shape[0]
    chunk = max(1, min(chunk, count))
    pad = (-count) % chunk
    if pad:
        images = jnp.concatenate([images, jnp.zeros((pad,) + images.shape[1:], images.dtype)])
    chunks = images.reshape((-1, chunk) + images.shape[1:])  # [P / chunk, chunk, ...]
    return jax.lax.map(jax.vmap(score), chunks).reshape(-1)[:count]


def quality_scores(
    score: Callable[[Array], Array], images: Array, chunk: int, value_range: Tuple[float, float]
) -> Array:
    """Criterion scores [P] of a lower-is-better quality model (BRISQUE, NIQE) over images [P, H, W, 3].

    The images are sanitised (`sanitize_images`), scored with `map_images` and clipped to
    `value_range`; images that held NaN/inf, and non-finite scores, get the worst score `value_range[1]`.

    Args:
      score: the model's score [] of one image float32 [H, W, 3] in [0, 1].
      images: float32 [P, H, W, 3].
      chunk: images vmapped at once (see `map_images`).
      value_range: (best, worst) finite bounds the scores are clipped to.

    Returns:
      float32 [P].
    """
    clean, bad = sanitize_images(images)
    scores = jnp.clip(map_images(score, clean, chunk), *value_range)
    return finite_or_worst(scores, bad, worst_score("min", value_range))
