"""Photo composition in [1, 5] from a saliency map (a documented stand-in for SAMP-Net).

The paper scores composition with SAMP-Net (Zhang et al., BMVC 2021), whose weights cannot be had
here; `composition` scores the classic composition rules on the CSNet saliency map S [H, W] instead:
the rule of thirds (salient centroid near a power point), balance (centroid near the centre),
left-right symmetry and subject emphasis (share of salient pixels in [0.05, 0.5]), as
composition = 1 + 4 * (0.4 thirds + 0.2 balance + 0.1 symmetry + 0.3 emphasis). Its numbers are not
comparable to the paper's; it is deterministic, documented and cheap. NaN images score 1 (the worst).
`composition_terms` and `composition_from_map` score one map; `composition` is the criterion.

Each term's formula, the references and why these weights: see docs/design.md, section
"Criteria > Composition".
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
from waldo_jax.criteria.csnet import SOFTNESS, load_params, saliency_maps
from waldo_jax.types import Array

__all__ = ["WEIGHTS", "composition_terms", "composition_from_map", "composition"]

WEIGHTS = {"thirds": 0.4, "balance": 0.2, "symmetry": 0.1, "emphasis": 0.3}
_THIRDS_SIGMA = 0.15
_BALANCE_SIGMA = 0.25
_AREA_RANGE = (0.05, 0.5)


def composition_terms(saliency: Array, softness: float = 0.0) -> dict:
    """The four rule scores of one saliency map [H, W] in [0, 1], each [] in [0, 1].

    softness > 0 counts the salient area (of `emphasis`) with a sigmoid of that width instead of the
    step at 0.5: the differentiable stand-in of the smooth score.
    """
    saliency = jnp.clip(jnp.asarray(saliency, jnp.float32), 0.0, 1.0)
    height, width = saliency.shape
    ys = (jnp.arange(height, dtype=jnp.float32) + 0.5) / height  # [H]
    xs = (jnp.arange(width, dtype=jnp.float32) + 0.5) / width  # [W]
    mass = jnp.sum(saliency)
    has_mass = mass > 1e-6
    safe_mass = jnp.where(has_mass, mass, 1.0)
    cx = jnp.where(has_mass, jnp.sum(saliency * xs[None, :]) / safe_mass, 0.5)
    cy = jnp.where(has_mass, jnp.sum(saliency * ys[:, None]) / safe_mass, 0.5)

    power = jnp.array([1.0 / 3.0, 2.0 / 3.0], jnp.float32)
    d2 = jnp.min((cx - power[:, None]) ** 2 + (cy - power[None, :]) ** 2)
    thirds = jnp.exp(-d2 / (2 * _THIRDS_SIGMA**2))
    balance = jnp.exp(-((cx - 0.5) ** 2 + (cy - 0.5) ** 2) / (2 * _BALANCE_SIGMA**2))
    mirror_gap = jnp.sum(jnp.abs(saliency - saliency[:, ::-1]))
    symmetry = jnp.where(has_mass, 1.0 - mirror_gap / (2.0 * safe_mass), 0.0)

    if softness > 0.0:
        area = jnp.mean(jax.nn.sigmoid((saliency - 0.5) / softness))
    else:
        area = jnp.mean((saliency > 0.5).astype(jnp.float32))
    low, high = _AREA_RANGE
    emphasis = jnp.where(area < low, area / low, jnp.clip(1.0 - (area - high) / high, 0.0, 1.0))
    return {"thirds": thirds, "balance": balance, "symmetry": jnp.clip(symmetry, 0.0, 1.0), "emphasis": emphasis}


def composition_from_map(saliency: Array, softness: float = 0.0) -> Array:
    """The composition score [] in [1, 5] of one saliency map [H, W] (see docs/design.md, "Criteria");
    softness as `composition_terms`."""
    terms = composition_terms(saliency, softness)
    return 1.0 + 4.0 * sum(WEIGHTS[name] * terms[name] for name in WEIGHTS)


def _apply(params, images: Array, softness: float = 0.0) -> Array:
    clean, bad = sanitize_images(images)
    scores = jax.vmap(lambda m: composition_from_map(m, softness))(saliency_maps(params, clean))
    return finite_or_worst(scores, bad, 1.0)


def _smooth_apply(params, images: Array) -> Array:
    return _apply(params, images, SOFTNESS)


_DESCRIPTION = "photo composition in [1, 5] from the CSNet saliency map: thirds, balance, symmetry, emphasis"


def composition(context: CriterionContext) -> Criterion:
    """The `composition` criterion (direction max, [1, 5]); loads CSNet from `context.weights_dir`."""
    return Criterion(
        params=load_params(context.weights_dir),
        name="composition",
        direction="max",
        value_range=(1.0, 5.0),
        inputs="images",
        apply=_apply,
        description=_DESCRIPTION,
        smooth_apply=_smooth_apply,
    )


register(CriterionSpec("composition", "max", "images", _DESCRIPTION, composition, smooth=True, reads=("weights_dir",)))
