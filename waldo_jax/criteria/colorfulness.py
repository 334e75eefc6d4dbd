"""Colourfulness (Hasler and Suesstrunk, "Measuring colourfulness in natural images", SPIE 2003).

M = sigma_rgyb + 0.3 * mu_rgyb on 0..255 RGB, with rg = R - G and yb = (R + G) / 2 - B:
sigma_rgyb = sqrt(var(rg) + var(yb)), mu_rgyb = sqrt(mean(rg)^2 + mean(yb)^2). In their study,
M ~ 0 is "not colourful", 33 "moderately", 59 "quite", 82 "highly" and above 109 "extremely"
colourful. A cheap, classic, no-weights image criterion (direction max); an image holding NaN
scores 0.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from waldo_jax.criteria.base import (
    Criterion,
    CriterionContext,
    CriterionSpec,
    finite_or_worst,
    register,
    sanitize_images,
)
from waldo_jax.types import Array

__all__ = ["colorfulness_image", "colorfulness"]


def colorfulness_image(image: Array) -> Array:
    """M of one image float [H, W, 3] in [0, 1] (scaled to 0..255 as in the paper); returns []."""
    rgb = 255.0 * jnp.asarray(image, jnp.float32)
    rg = rgb[..., 0] - rgb[..., 1]
    yb = 0.5 * (rgb[..., 0] + rgb[..., 1]) - rgb[..., 2]
    sigma = jnp.sqrt(jnp.var(rg) + jnp.var(yb))
    mu = jnp.sqrt(jnp.mean(rg) ** 2 + jnp.mean(yb) ** 2)
    return sigma + 0.3 * mu


def _apply(params, images: Array) -> Array:
    del params
    clean, bad = sanitize_images(images)
    return finite_or_worst(jax.vmap(colorfulness_image)(clean), bad, 0.0)


def colorfulness(context: CriterionContext) -> Criterion:
    """The `colorfulness` criterion (Hasler-Suesstrunk M, direction max, >= 0)."""
    del context
    return Criterion(
        params=(),
        name="colorfulness",
        direction="max",
        value_range=(0.0, float("inf")),
        inputs="images",
        apply=_apply,
        description=_DESCRIPTION,
        smooth_apply=_apply,
    )


_DESCRIPTION = "Hasler-Suesstrunk colourfulness M of the image (classic, no weights)"
register(CriterionSpec("colorfulness", "max", "images", _DESCRIPTION, colorfulness, smooth=True))
