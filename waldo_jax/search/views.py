"""Views as shots: the scene's frame, the distance between two views, and the k best *different* shots.

A search returns "the best views"; ten near-copies of one view are one shot, not ten. Two views are
measured around the scene's frame (`SceneFrame`: its focus f, its up u and the training cameras' median
distance r to f). With camera centres o and viewing directions v (unit, OpenGL: -c2w[:3, 2]):

    centre angle     = angle between o_a - f and o_b - f          (seen from the focus)
    direction angle  = angle between v_a and v_b
    distance term    = |ln(|o_a - f| / |o_b - f|)| radians, in degrees (x1.42 in distance = 20 degrees)
    separation(a, b) = max of the three, in degrees

Two views are different shots when their separation is at least `min_separation` (default 20
degrees). `distinct_top_k` picks the best view, drops every view within `min_separation` of it, and
repeats: the k best views pairwise at least `min_separation` apart, from the views already scored (no
extra renders); with `min_separation` 0 it is the paper's top-k. `distinct_count` counts the shots
among a given set (greedy in rank order). Choices and limits: docs/design.md, "Search > Different shots".
"""

from __future__ import annotations

import math
from typing import Optional, Tuple

import flax.struct
import jax
import jax.numpy as jnp
import numpy as np

from waldo_jax.cameras import camera_focus, scene_up
from waldo_jax.types import Array

__all__ = [
    "DEFAULT_MIN_SEPARATION",
    "SceneFrame",
    "scene_frame",
    "frame_axes",
    "view_separation",
    "separation_to",
    "distinct_top_k",
    "distinct_count",
]

# Degrees between two views for them to count as different shots (`--min-separation`).
DEFAULT_MIN_SEPARATION = 20.0
_DEGREES = 180.0 / math.pi


@flax.struct.dataclass
class SceneFrame:
    """Where views are measured from: the scene's focus, its up and the training cameras' distance.

    Attributes:
      focus: float32 [3], the point views are seen around (the training cameras' focus, where their
        optical axes meet, unless given).
      up: float32 [3], the scene's up (unit; the mean of the training cameras' up vectors unless given).
      radius: float32 [], the median distance of the training cameras to `focus` (> 0): the unit of
        distances (distance bands, mutation scales) and the floor of a camera's distance to the focus
        (`_FOCUS_FLOOR` of it), so that a camera on the focus still has a direction.
    """

    focus: Array
    up: Array
    radius: Array


# A camera closer to the focus than this fraction of the radius is measured as if this far away.
_FOCUS_FLOOR = 1e-3


def scene_frame(c2w: np.ndarray, focus: Optional[np.ndarray] = None, up: Optional[np.ndarray] = None) -> SceneFrame:
    """The frame of a scene from its training cameras (host, NumPy).

    Args:
      c2w: float [N, 4, 4] (or [N, 3, 4]) training camera-to-world matrices.
      focus: [3] the focus (default `cameras.camera_focus(c2w)`).
      up: [3] the up direction (default `cameras.scene_up(c2w)`); normalised here.

    Returns:
      `SceneFrame` of float32 arrays.

    Raises:
      ValueError: a focus or up that is not 3 finite numbers, or a zero up.
    """
    c2w = np.asarray(c2w, np.float64)
    focus = camera_focus(c2w) if focus is None else np.asarray(focus, np.float64).reshape(-1)
    up = scene_up(c2w) if up is None else np.asarray(up, np.float64).reshape(-1)
    for name, value in (("focus", focus), ("up", up)):
        if value.shape != (3,) or not np.all(np.isfinite(value)):
            raise ValueError(f"the scene frame's {name} must be 3 finite numbers, got {value!r}")
    norm = float(np.linalg.norm(up))
    if norm < 1e-9:
        raise ValueError(f"the scene frame's up must not be zero, got {up!r}")
    distances = np.linalg.norm(c2w[:, :3, 3] - focus, axis=-1)
    finite = distances[np.isfinite(distances)]
    radius = float(np.median(finite)) if len(finite) else 1.0
    radius = radius if radius > 1e-9 else 1.0
    return SceneFrame(
        focus=jnp.asarray(focus, jnp.float32), up=jnp.asarray(up / norm, jnp.float32), radius=jnp.float32(radius)
    )


def frame_axes(frame: SceneFrame) -> Tuple[Array, Array, Array]:
    """(east, north, up) [3] each: a right-handed orthonormal frame whose third axis is the scene's up.

    `east` (azimuth 0) is the world axis least aligned with up (the first on ties), made orthogonal to
    it; `north` (azimuth +90 degrees) = up x east.
    """
    up = frame.up / jnp.linalg.norm(frame.up)
    axis = jnp.eye(3, dtype=up.dtype)[jnp.argmin(jnp.abs(up))]
    east = axis - jnp.dot(axis, up) * up
    east = east / jnp.linalg.norm(east)
    return east, jnp.cross(up, east), up


def _angle(a: Array, b: Array) -> Array:
    """Degrees between vectors a and b [..., 3] (atan2: accurate near 0 and 180; 0 if one is zero)."""
    cross = jnp.linalg.norm(jnp.cross(a, b), axis=-1)
    return jnp.arctan2(cross, jnp.sum(a * b, axis=-1)) * _DEGREES


def _centre_and_direction(c2w: Array, frame: SceneFrame) -> Tuple[Array, Array, Array]:
    """Offsets from the focus [..., 3], their floored lengths [...] and viewing directions [..., 3]."""
    offset = c2w[..., :3, 3] - frame.focus
    distance = jnp.maximum(jnp.linalg.norm(offset, axis=-1), _FOCUS_FLOOR * frame.radius)
    return offset, distance, -c2w[..., :3, 2]


def view_separation(c2w_a: Array, c2w_b: Array, frame: SceneFrame) -> Array:
    """Separation in degrees of two views c2w [4, 4] (or [3, 4]): the module docstring's max of the
    centre angle, the direction angle and the distance term. Symmetric, 0 for a view and itself; NaN
    when a pose is not finite."""
    offset_a, distance_a, direction_a = _centre_and_direction(c2w_a, frame)
    offset_b, distance_b, direction_b = _centre_and_direction(c2w_b, frame)
    centre = _angle(offset_a, offset_b)
    direction = _angle(direction_a, direction_b)
    zoom = jnp.abs(jnp.log(distance_a) - jnp.log(distance_b)) * _DEGREES
    # jnp.maximum propagates NaN, so a non-finite pose is never taken for a copy of another.
    return jnp.maximum(jnp.maximum(centre, direction), zoom)


def separation_to(c2w: Array, others: Array, frame: SceneFrame) -> Array:
    """Separations [C] in degrees of one view c2w [4, 4] from each of others [C, 4, 4]."""
    return jax.vmap(view_separation, in_axes=(None, 0, None))(c2w, others, frame)


def distinct_top_k(fitness: Array, c2w: Array, frame: SceneFrame, k: int, min_separation: float) -> Tuple[Array, Array]:
    """The k best views pairwise at least `min_separation` degrees apart, best first (greedy).

    Repeats k times: take the view of highest fitness still eligible (ties: the lowest index, as
    `lax.top_k`), then make ineligible every view less than `min_separation` from it. Jit-able with k
    and min_separation static; O(k C) work. With min_separation <= 0 it returns `lax.top_k` itself
    (the paper's top-k, bit for bit).

    Args:
      fitness: [C] signed scores, higher is better; -inf (or NaN) is never taken.
      c2w: [C, 4, 4] the views.
      frame: the `SceneFrame` they are measured in.
      k: how many (static), at most C.
      min_separation: degrees (static).

    Returns:
      indices: int32 [k], best first.
      ok: bool [k], False where fewer than k distinct usable views exist (the index is then meaningless).
    """
    fitness = jnp.where(jnp.isnan(fitness), -jnp.inf, fitness)
    if min_separation <= 0.0:
        values, indices = jax.lax.top_k(fitness, k)
        return indices.astype(jnp.int32), jnp.isfinite(values)
    slots = jnp.arange(fitness.shape[0], dtype=jnp.int32)

    def pick(eligible, _):
        masked = jnp.where(eligible, fitness, -jnp.inf)
        best = jnp.argmax(masked).astype(jnp.int32)
        ok = jnp.isfinite(masked[best])
        near = separation_to(c2w[best], c2w, frame) < min_separation  # NaN: not near
        eligible = eligible & ~(ok & near) & (slots != best)
        return eligible, (best, ok)

    _, (indices, ok) = jax.lax.scan(pick, jnp.isfinite(fitness), None, length=k)
    return indices, ok


def distinct_count(c2w: Array, ok: Array, frame: SceneFrame, min_separation: float) -> Array:
    """How many different shots a ranked set of views holds: int32 [].

    Greedy in rank order (as `distinct_top_k` restricted to the set): view i counts when it is at
    least `min_separation` degrees from every earlier view that counted.

    Args:
      c2w: [k, 4, 4] the views, best first (e.g. the paper's top-k).
      ok: bool [k], which entries are real.
      frame: the `SceneFrame`.
      min_separation: degrees (static); <= 0 counts every real view.
    """
    k = c2w.shape[0]
    fitness = jnp.where(ok, -jnp.arange(k, dtype=jnp.float32), -jnp.inf)  # rank order
    _, picked = distinct_top_k(fitness, c2w, frame, k, min_separation)
    return jnp.sum(picked, dtype=jnp.int32)
