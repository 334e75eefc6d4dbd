"""Oracle criteria of the procedural Waldo room: exact answers from the analytic geometry, no render.

  * `waldo_oracle`: the share of the image covered by the visible part of Waldo
    (`waldo_jax.procedural.waldo_coverage`), the exact counterpart of the paper's BASNet criterion;
  * `waldo_visible`: the fraction of Waldo's projected area that is visible
    (`waldo_jax.procedural.waldo_visibility`), whatever his size in the image;
  * `waldo_found`: "Waldo found, as large as possible": 1 + his image share when at least
    `FOUND_VISIBILITY` (90 %) of him is visible, else his visible fraction (< 1), so every found view
    beats every view that is not, and below the bar a search climbs towards it.

All take the room as their params and score camera poses (`inputs == "poses"`). Why these two, and
what a search has to trade: see docs/design.md, section "Criteria > Oracles".
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from waldo_jax.criteria.base import Criterion, CriterionContext, CriterionError, CriterionSpec, register
from waldo_jax.procedural import FOUND_VISIBILITY, waldo_coverage, waldo_view, waldo_visibility
from waldo_jax.types import Array

__all__ = ["SOFTNESS", "FOUND_SOFTNESS", "found_score", "waldo_found", "waldo_oracle", "waldo_visible"]


# The smooth stand-ins' sigmoid width at the image borders, as a fraction of the image width.
SOFTNESS = 0.05
# The width of `waldo_found`'s smooth step at FOUND_VISIBILITY, in visibility units: sharp enough that
# the stand-in is within 0.01 of the exact score 0.1 away from the bar, wide enough to pull a view
# just below it upwards.
FOUND_SOFTNESS = 0.02


def _coverage(room, c2w, intrinsics, softness=0.0):
    return jax.vmap(lambda c: waldo_coverage(room, c, intrinsics, softness=softness))(c2w)


def _visible(room, c2w, intrinsics, softness=0.0):
    return jax.vmap(lambda c: waldo_visibility(room, c, intrinsics, softness=softness))(c2w)


def _smooth_coverage(room, c2w, intrinsics):
    return _coverage(room, c2w, intrinsics, SOFTNESS)


def _smooth_visible(room, c2w, intrinsics):
    return _visible(room, c2w, intrinsics, SOFTNESS)


def found_score(visibility: Array, coverage: Array, width: float = 0.0) -> Array:
    """`waldo_found`'s score from Waldo's visible fraction and image share (any matching shapes).

    1 + coverage where visibility >= FOUND_VISIBILITY, else visibility; width > 0 replaces the step
    by a sigmoid of that width (the smooth stand-in). In [0, 2]: a score >= 1 means found.
    """
    if width > 0.0:
        found = jax.nn.sigmoid((visibility - FOUND_VISIBILITY) / width)
    else:
        found = (visibility >= FOUND_VISIBILITY).astype(jnp.float32)
    return visibility + found * (1.0 + coverage - visibility)


def _found(room, c2w, intrinsics, softness=0.0, width=0.0):
    visibility, coverage = jax.vmap(lambda c: waldo_view(room, c, intrinsics, softness=softness))(c2w)
    return found_score(visibility, coverage, width)


def _smooth_found(room, c2w, intrinsics):
    return _found(room, c2w, intrinsics, SOFTNESS, FOUND_SOFTNESS)


def _need_room(name: str, context: CriterionContext):
    if context.room is None:
        where = f" (source: {context.source})" if context.source else ""
        raise CriterionError(
            f"criterion {name!r} needs the procedural Waldo room{where}: use SOURCE procedural[:SEED] "
            "or a run trained on it"
        )
    return context.room


def waldo_oracle(context: CriterionContext) -> Criterion:
    """The `waldo_oracle` criterion (visible-Waldo share of the image, direction max, in [0, 1])."""
    return Criterion(
        params=_need_room("waldo_oracle", context),
        name="waldo_oracle",
        direction="max",
        value_range=(0.0, 1.0),
        inputs="poses",
        apply=_coverage,
        description=_ORACLE,
        smooth_apply=_smooth_coverage,
    )


def waldo_visible(context: CriterionContext) -> Criterion:
    """The `waldo_visible` criterion (visible fraction of Waldo, direction max, in [0, 1])."""
    return Criterion(
        params=_need_room("waldo_visible", context),
        name="waldo_visible",
        direction="max",
        value_range=(0.0, 1.0),
        inputs="poses",
        apply=_visible,
        description=_VISIBLE,
        smooth_apply=_smooth_visible,
    )


def waldo_found(context: CriterionContext) -> Criterion:
    """The `waldo_found` criterion (direction max, in [0, 2]; >= 1: at least 90 % of Waldo visible).

    Exact from the room's geometry: 1 + the share of the image showing visible Waldo where at least
    `FOUND_VISIBILITY` of him is in frame and unoccluded, else that visible fraction. Its smooth
    stand-in softens the frame's borders (`SOFTNESS`) and the step at the bar (`FOUND_SOFTNESS`).
    """
    return Criterion(
        params=_need_room("waldo_found", context),
        name="waldo_found",
        direction="max",
        value_range=(0.0, 2.0),
        inputs="poses",
        apply=_found,
        description=_FOUND,
        smooth_apply=_smooth_found,
    )


_ORACLE = "share of the image showing un-occluded Waldo (exact, procedural room)"
_VISIBLE = "fraction of Waldo in frame and not occluded (exact, procedural room)"
_FOUND = (
    "Waldo found: 1 + the share of the image showing him where >= 90 % of him is visible, else that "
    "visible fraction (exact, procedural room)"
)
register(CriterionSpec("waldo_found", "max", "poses", _FOUND, waldo_found, smooth=True))
register(CriterionSpec("waldo_oracle", "max", "poses", _ORACLE, waldo_oracle, smooth=True))
register(CriterionSpec("waldo_visible", "max", "poses", _VISIBLE, waldo_visible, smooth=True))
