"""Oracle criteria of the procedural Waldo room: exact answers from the analytic geometry, no render.

  * `waldo_oracle`: the share of the image covered by the visible part of Waldo
    (`waldo_jax.procedural.waldo_coverage`), the exact counterpart of the paper's BASNet criterion;
  * `waldo_visible`: the fraction of Waldo's projected area that is visible
    (`waldo_jax.procedural.waldo_visibility`), whatever his size in the image.

Both take the room as their params and score camera poses (`inputs == "poses"`). Why these two, and
what a search has to trade: see docs/design.md, section "Criteria > Oracles".
"""

from __future__ import annotations

import jax

from waldo_jax.criteria.base import Criterion, CriterionContext, CriterionError, CriterionSpec, register
from waldo_jax.procedural import waldo_coverage, waldo_visibility

__all__ = ["SOFTNESS", "waldo_oracle", "waldo_visible"]


# The smooth stand-ins' sigmoid width at the image borders, as a fraction of the image width.
SOFTNESS = 0.05


def _coverage(room, c2w, intrinsics, softness=0.0):
    return jax.vmap(lambda c: waldo_coverage(room, c, intrinsics, softness=softness))(c2w)


def _visible(room, c2w, intrinsics, softness=0.0):
    return jax.vmap(lambda c: waldo_visibility(room, c, intrinsics, softness=softness))(c2w)


def _smooth_coverage(room, c2w, intrinsics):
    return _coverage(room, c2w, intrinsics, SOFTNESS)


def _smooth_visible(room, c2w, intrinsics):
    return _visible(room, c2w, intrinsics, SOFTNESS)


def _need_room(name: str, context: CriterionContext):
    if context.room is None:
        where = f" (source: {context.source})" if context.source else ""
        raise CriterionError(
            f"criterion {name!r} needs the procedural Waldo room{where}: use SOURCE procedural[:SEED] "
            "or a run trained on it")
    return context.room


def waldo_oracle(context: CriterionContext) -> Criterion:
    """The `waldo_oracle` criterion (visible-Waldo share of the image, direction max, in [0, 1])."""
    return Criterion(params=_need_room("waldo_oracle", context), name="waldo_oracle", direction="max",
                     value_range=(0.0, 1.0), inputs="poses", apply=_coverage, description=_ORACLE,
                     smooth_apply=_smooth_coverage)


def waldo_visible(context: CriterionContext) -> Criterion:
    """The `waldo_visible` criterion (visible fraction of Waldo, direction max, in [0, 1])."""
    return Criterion(params=_need_room("waldo_visible", context), name="waldo_visible", direction="max",
                     value_range=(0.0, 1.0), inputs="poses", apply=_visible, description=_VISIBLE,
                     smooth_apply=_smooth_visible)


_ORACLE = "share of the image showing un-occluded Waldo (exact, procedural room)"
_VISIBLE = "fraction of Waldo in frame and not occluded (exact, procedural room)"
register(CriterionSpec("waldo_oracle", "max", "poses", _ORACLE, waldo_oracle, smooth=True))
register(CriterionSpec("waldo_visible", "max", "poses", _VISIBLE, waldo_visible, smooth=True))
