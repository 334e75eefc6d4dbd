"""The artefact guard and criterion combinations.

The paper names empty views as a failure mode (a camera looking into free space renders the
background, which a criterion may like); a ray's accumulated opacity is ~0 where it met nothing, so:
  * `opacity` (renders, max, [0, 1]): the view's mean accumulated opacity (photographs: 1);
  * `constrained(primary, guard, threshold)`: the primary where the guard passes, its worst score
    elsewhere (`--criterion saliency --guard opacity:0.9`);
  * `weighted(parts, weights)`: the weighted mean of the parts' scores, each mapped onto [0, 1]
    (`--criterion weighted:saliency=0.7,iqa_cnn=0.3`); `build_criterion` parses such specs, and
    `spec_names` reads the criteria one names without building them.
Parts may score poses (the room's oracles): pose criteria alone combine into a pose criterion
(`--criterion waldo_oracle --guard waldo_visible:0.9`), pose and view criteria into a "posed" one that
scores renders with their poses. A combination of parts with smooth stand-ins has one.
The definitions, and the inputs and parameters of a combination: see docs/design.md, section
"Criteria > Guards and combinations".
"""

from __future__ import annotations

import dataclasses
import math
from typing import Callable, Optional, Sequence, Tuple

import jax
import jax.numpy as jnp
import numpy as np

from waldo_jax.criteria.base import (
    Criterion,
    CriterionContext,
    CriterionError,
    CriterionSpec,
    Views,
    check_registered,
    combined_inputs,
    criterion_args,
    finite_or_worst,
    make_criterion,
    register,
    views_of_args,
    worst_score,
)
from waldo_jax.errors import NumberError, check_float32
from waldo_jax.types import Array

__all__ = ["opacity", "mean_opacity", "constrained", "weighted", "build_criterion", "parse_guard", "spec_names"]


def mean_opacity(rgba: Array) -> Array:
    """Mean accumulated opacity [P] of renders rgba [P, H, W, 4]; 0 for a render holding NaN."""
    alpha = rgba[..., 3]
    bad = ~jnp.all(jnp.isfinite(rgba), axis=(1, 2, 3))
    return finite_or_worst(jnp.mean(jnp.clip(alpha, 0.0, 1.0), axis=(1, 2)), bad, 0.0)


def _opacity_apply(params, rgba: Array) -> Array:
    del params
    return mean_opacity(rgba)


_OPACITY_DESCRIPTION = "mean accumulated opacity of the render (empty views score ~0; photographs 1)"


def opacity(context: Optional[CriterionContext] = None) -> Criterion:
    """The `opacity` criterion: mean accumulated opacity of the render, direction max, in [0, 1]."""
    del context
    return Criterion(
        params=(),
        name="opacity",
        direction="max",
        value_range=(0.0, 1.0),
        inputs="renders",
        apply=_opacity_apply,
        description=_OPACITY_DESCRIPTION,
        smooth_apply=_opacity_apply,
    )


register(CriterionSpec("opacity", "max", "renders", _OPACITY_DESCRIPTION, opacity, smooth=True))


@dataclasses.dataclass(frozen=True)
class _Part:
    """The static side of a criterion inside a combination (hashable: it is part of a jit cache key)."""

    apply: Callable
    smooth_apply: Optional[Callable]
    inputs: str
    direction: str
    value_range: Tuple[float, float]

    @classmethod
    def of(cls, criterion: Criterion) -> "_Part":
        return cls(
            criterion.apply, criterion.smooth_apply, criterion.inputs, criterion.direction, tuple(criterion.value_range)
        )

    def scores(self, params, views: Views, smooth: bool = False) -> Array:
        apply = self.smooth_apply if smooth else self.apply
        return apply(params, *criterion_args(self.inputs, views))

    def normalised(self, params, views: Views, smooth: bool = False) -> Array:
        low, high = self.value_range
        unit = (self.scores(params, views, smooth) - low) / (high - low)
        return jnp.clip(unit if self.direction == "max" else 1.0 - unit, 0.0, 1.0)


def _inputs(parts: Sequence[_Part]) -> str:
    """The combination's inputs (`base.combined_inputs` of its parts')."""
    return combined_inputs(p.inputs for p in parts)


def _smooth_apply(apply, parts: Sequence[_Part]):
    """`apply`'s smooth stand-in when every part has one, else None."""
    return dataclasses.replace(apply, smooth=True) if all(p.smooth_apply is not None for p in parts) else None


@dataclasses.dataclass(frozen=True)
class _ConstrainedApply:
    primary: _Part
    guard: _Part
    worst: float
    inputs: str
    smooth: bool = False

    def __call__(self, params, *args) -> Array:
        primary_params, guard_params, threshold = params
        views = views_of_args(self.inputs, args)
        score = self.primary.scores(primary_params, views, self.smooth)
        guard = self.guard.scores(guard_params, views, self.smooth)
        if self.smooth:  # a sigmoid of 5 % of the guard's range (or of 1 where it is unbounded) for the step
            low, high = self.guard.value_range
            width = 0.05 * ((high - low) if math.isfinite(high - low) else 1.0)
            margin = (guard - threshold) if self.guard.direction == "max" else (threshold - guard)
            passes = jax.nn.sigmoid(margin / width)
            return self.worst + passes * (score - self.worst)
        passes = guard >= threshold if self.guard.direction == "max" else guard <= threshold
        return finite_or_worst(jnp.where(passes, score, self.worst), jnp.zeros(score.shape, bool), self.worst)


def constrained(primary: Criterion, guard: Criterion, threshold: float) -> Criterion:
    """`primary` where `guard` passes `threshold`, else the primary's worst score.

    Either may score poses (the room's oracles): a combination of pose criteria scores poses, one of
    pose and view criteria scores renders with their poses (inputs "posed").

    Args:
      primary: the criterion to optimise.
      guard: the criterion that must pass, e.g. `opacity` or `waldo_visible`.
      threshold: a "max" guard passes at or above it, a "min" guard at or below it.

    Returns:
      A criterion named "PRIMARY|GUARD>=THRESHOLD" (or "<=") with the primary's direction and range.
      It has a smooth stand-in when both have one: their stand-ins, the step at the threshold a
      sigmoid 5 % of the guard's range wide.
    """
    parts = (_Part.of(primary), _Part.of(guard))
    try:
        worst = worst_score(primary.direction, primary.value_range)
    except ValueError:
        raise CriterionError(
            f"criterion {primary.name!r} has no finite worst score to give a view that fails "
            f"the guard (value range {primary.value_range})"
        ) from None
    relation = ">=" if guard.direction == "max" else "<="
    low, high = guard.value_range
    # A threshold at or past the guard's good end fails every view; at or past its bad end it passes all.
    fails_all = threshold > high if guard.direction == "max" else threshold < low
    passes_all = threshold <= low if guard.direction == "max" else threshold >= high
    if fails_all or passes_all:
        raise CriterionError(
            f"--guard {guard.name}:{threshold:g}: {guard.name} lies in [{low:g}, {high:g}], so the threshold "
            f"{'fails' if fails_all else 'passes'} every view; choose one inside that range"
        )
    name = f"{primary.name}|{guard.name}{relation}{threshold:g}"
    params = (primary.params, guard.params, jnp.float32(threshold))
    apply = _ConstrainedApply(parts[0], parts[1], worst, _inputs(parts))
    return Criterion(
        params=params,
        name=name,
        direction=primary.direction,
        value_range=primary.value_range,
        inputs=_inputs(parts),
        apply=apply,
        smooth_apply=_smooth_apply(apply, parts),
        description=f"{primary.description}; the worst score where {guard.name} {relation} {threshold:g} fails",
    )


@dataclasses.dataclass(frozen=True)
class _WeightedApply:
    parts: Tuple[_Part, ...]
    inputs: str
    smooth: bool = False

    def __call__(self, params, *args) -> Array:
        part_params, weights = params
        views = views_of_args(self.inputs, args)
        units = jnp.stack([p.normalised(q, views, self.smooth) for p, q in zip(self.parts, part_params)])  # [K, P]
        return jnp.sum(weights[:, None] * units, axis=0)


def weighted(criteria: Sequence[Criterion], weights: Sequence[float]) -> Criterion:
    """The weighted mean of criteria normalised to [0, 1] by their value ranges (1 = good end).

    Pose criteria (the room's oracles) may take part, alone or beside view criteria (see `constrained`).
    It has a smooth stand-in when every part has one (the weighted mean of their stand-ins).

    Raises:
      CriterionError: no criteria, a length mismatch, a negative or all-zero weight, or a criterion
        whose value range is not finite at both ends (it cannot be normalised).
    """
    if not criteria or len(criteria) != len(weights):
        raise CriterionError(
            f"weighted needs one weight per criterion, got {len(criteria)} criteria and {len(weights)} weights"
        )
    w = np.asarray(weights, np.float64)
    if np.any(w < 0) or not np.all(np.isfinite(w)) or not np.max(w) > 0:
        raise CriterionError(f"weighted: weights must be finite, >= 0 and not all 0, got {list(weights)}")
    w = w / np.max(w)  # weights near float64's largest would sum to infinity (and normalise to 0)
    for c in criteria:
        low, high = c.value_range
        if not (np.isfinite(low) and np.isfinite(high) and high > low):
            raise CriterionError(
                f"criterion {c.name!r} cannot be weighted: its value range {c.value_range} is not finite at both ends"
            )
    parts = tuple(_Part.of(c) for c in criteria)
    name = "weighted:" + ",".join(f"{c.name}={x:g}" for c, x in zip(criteria, weights))
    params = (tuple(c.params for c in criteria), jnp.asarray(w / w.sum(), jnp.float32))
    apply = _WeightedApply(parts, _inputs(parts))
    return Criterion(
        params=params,
        name=name,
        direction="max",
        value_range=(0.0, 1.0),
        inputs=_inputs(parts),
        apply=apply,
        smooth_apply=_smooth_apply(apply, parts),
        description="weighted mean of " + ", ".join(c.name for c in criteria) + " normalised to [0, 1]",
    )


def parse_guard(spec: str) -> Tuple[str, float]:
    """`NAME:THRESHOLD` -> (name, threshold), with a clear error."""
    name, sep, value = spec.rpartition(":")
    try:
        threshold = float(value)
    except ValueError:
        threshold = None
    if not sep or not name or threshold is None or not np.isfinite(threshold):
        raise CriterionError(f"bad --guard {spec!r}: expected NAME:THRESHOLD, e.g. opacity:0.9")
    try:
        threshold = check_float32(threshold, f"the threshold of --guard {spec!r}")  # scores are float32
    except NumberError as e:
        raise CriterionError(str(e)) from None
    return name, threshold


def _weighted_items(spec: str) -> Tuple[Tuple[str, float], ...]:
    """`weighted:NAME=W,...` -> ((name, weight), ...), with a clear error for a malformed spec."""
    items = []
    rest = spec[len("weighted:") :]
    for item in rest.split(",") if rest.strip() else []:
        if not item.strip():  # a stray comma: a criterion left out by mistake, not a spec to guess at
            raise CriterionError(f"bad criterion {spec!r}: an empty item between commas (expected NAME=WEIGHT,...)")
        name, _, value = item.partition("=")
        name = name.strip()
        try:
            weight = float(value)
        except ValueError:
            raise CriterionError(
                f"bad weight {value!r} for {name!r} in {spec!r}: expected NAME=WEIGHT for every criterion"
            ) from None
        if name in (n for n, _ in items):
            raise CriterionError(f"{spec!r} names {name!r} twice: give each criterion once, with its weight")
        check_registered(name)
        items.append((name, weight))
    if len(items) < 2:
        raise CriterionError(
            f"bad criterion {spec!r}: weighted needs at least two criteria, "
            "weighted:NAME=WEIGHT,NAME=WEIGHT (for one, name it alone)"
        )
    return tuple(items)


def _parse_weighted(spec: str, context: CriterionContext) -> Criterion:
    items = _weighted_items(spec)
    return weighted([build_criterion(name, context) for name, _ in items], [weight for _, weight in items])


def spec_names(spec: str, guards: Sequence[str] = ()) -> Tuple[str, ...]:
    """The registered criteria a `build_criterion` spec and its guards name, without building any.

    Checks what needs nothing but the text (the syntax, the names, a repeated name), so that a
    command can refuse a bad spec before it loads a scene; what needs the criteria themselves (a
    guard's range, weights files) `build_criterion` checks.

    Raises:
      CriterionError: as `build_criterion` would for the same text.
    """
    spec = spec.strip()
    names = [name for name, _ in _weighted_items(spec)] if spec.startswith("weighted:") else [spec]
    names += [parse_guard(guard)[0] for guard in guards]
    for name in names:
        check_registered(name)
    return tuple(names)


def build_criterion(spec: str, context: Optional[CriterionContext] = None, guards: Sequence[str] = ()) -> Criterion:
    """The criterion the command line names.

    Args:
      spec: a registered name (`saliency`), or `weighted:NAME=W,NAME=W,...`.
      context: what building needs (room, weights folder, target image).
      guards: `NAME:THRESHOLD` strings, applied in order with `constrained`.

    Raises:
      CriterionError: an unknown name or a malformed spec (the message says which).
    """
    context = context or CriterionContext()
    spec = spec.strip()
    criterion = _parse_weighted(spec, context) if spec.startswith("weighted:") else make_criterion(spec, context)
    for guard_spec in guards:
        name, threshold = parse_guard(guard_spec)
        criterion = constrained(criterion, make_criterion(name, context), threshold)
    return criterion
