"""Exact oracles from the room's geometry: how much of Waldo a camera sees (`waldo_visibility`), how
much of its image he covers (`waldo_coverage`), both from one pass (`waldo_view`), by casting segments
against the primitives. `FOUND_VISIBILITY` is what "Waldo found" means: at least 90 % of him in frame
and unoccluded (the paper's "a view in which Waldo is fully visible").
"""

from __future__ import annotations

import functools
from typing import Tuple

import jax
import jax.numpy as jnp
import numpy as np

from waldo_jax.cameras import project_points
from waldo_jax.procedural.room import FAR, KIND_BOX, KIND_SPHERE, WaldoRoom
from waldo_jax.types import Array, Intrinsics

__all__ = [
    "FOUND_VISIBILITY",
    "waldo_visibility",
    "waldo_coverage",
    "waldo_view",
    "waldo_visibility_batch",
    "waldo_surface_seen",
    "waldo_samples_seen",
]

# A view shows Waldo "whole" (found) when at least this fraction of him is in frame and unoccluded: the
# sampled surface and the frame's pixel grid make 100 % a knife edge, and 90 % is a hat brim or a heel.
FOUND_VISIBILITY = 0.9


def _segment_hits(kind: Array, center: Array, size: Array, start: Array, end: Array) -> Array:
    """Whether the open segment start -> end [3] crosses the solid primitive (exact)."""
    v = end - start
    safe_v = jnp.where(jnp.abs(v) > 1e-12, v, 1e-12)

    def slab(lo, hi):
        t0, t1 = (lo - start) / safe_v, (hi - start) / safe_v
        return jnp.minimum(t0, t1), jnp.maximum(t0, t1)

    # Box: intersection of three slabs.
    near, far = slab(center - size, center + size)
    box_in, box_out = jnp.max(near), jnp.min(far)

    # Quadratic a s^2 + b s + c = 0 for the sphere and the cylinder's mantle.
    def quadratic(a, half_b, c):
        disc = half_b * half_b - a * c
        safe_a = jnp.where(jnp.abs(a) > 1e-12, a, 1.0)
        root = jnp.sqrt(jnp.maximum(disc, 0.0))
        lo, hi = (-half_b - root) / safe_a, (-half_b + root) / safe_a
        degenerate = jnp.abs(a) <= 1e-12  # no motion in the quadratic's plane: inside or not, always
        lo = jnp.where(degenerate, jnp.where(c < 0.0, -FAR, FAR), jnp.where(disc > 0.0, lo, FAR))
        hi = jnp.where(degenerate, jnp.where(c < 0.0, FAR, -FAR), jnp.where(disc > 0.0, hi, -FAR))
        return lo, hi

    d = start - center
    r = size[0]
    sph_in, sph_out = quadratic(jnp.dot(v, v), jnp.dot(v, d), jnp.dot(d, d) - r * r)
    cyl_in, cyl_out = quadratic(v[0] ** 2 + v[2] ** 2, v[0] * d[0] + v[2] * d[2], d[0] ** 2 + d[2] ** 2 - r * r)
    y_near, y_far = slab(center[1] - size[1], center[1] + size[1])
    cyl_in, cyl_out = jnp.maximum(cyl_in, y_near[1]), jnp.minimum(cyl_out, y_far[1])

    t_in = jnp.select([kind == KIND_BOX, kind == KIND_SPHERE], [box_in, sph_in], cyl_in)
    t_out = jnp.select([kind == KIND_BOX, kind == KIND_SPHERE], [box_out, sph_out], cyl_out)
    return (t_in < t_out) & (t_out > 0.0) & (t_in < 1.0)


def _samples_seen(
    room: WaldoRoom, c2w: Array, intrinsics: Intrinsics, near: float, softness: float = 0.0
) -> Tuple[Array, Array]:
    """Per surface sample of Waldo: (seen [M] in [0, 1], solid angle [M] in steradians, 0 where it faces
    away). seen is 1 in frame and unoccluded, 0 else; softness > 0 replaces the in-frame step by a
    product of sigmoids of the distance (in pixels) to the four image borders, of width softness * image
    width; occlusion stays exact."""
    c2w = jnp.asarray(c2w, jnp.float32)
    camera = c2w[:3, 3]
    to_camera = camera - room.waldo_points  # [M, 3]
    dist2 = jnp.sum(to_camera**2, axis=-1)
    cos = jnp.sum(room.waldo_normals * to_camera, axis=-1) / jnp.sqrt(dist2 + 1e-12)
    weight = room.waldo_areas * jnp.maximum(cos, 0.0) / jnp.maximum(dist2, 1e-6)  # [M] solid angles

    uv, depth = project_points(c2w, intrinsics, room.waldo_points)
    if softness > 0.0:
        width = softness * intrinsics.width
        margins = jnp.stack([uv[:, 0], intrinsics.width - uv[:, 0], uv[:, 1], intrinsics.height - uv[:, 1]], -1)
        in_frame = (depth > near) * jnp.prod(jax.nn.sigmoid(margins / width), axis=-1)
    else:
        in_frame = (
            (depth > near)
            & (uv[:, 0] >= 0)
            & (uv[:, 0] <= intrinsics.width)
            & (uv[:, 1] >= 0)
            & (uv[:, 1] <= intrinsics.height)
        ).astype(jnp.float32)

    starts = room.waldo_points + 1e-4 * room.waldo_normals  # off the surface, so its own solid is not hit
    hits = jax.vmap(
        lambda s: jax.vmap(_segment_hits, in_axes=(0, 0, 0, None, None))(room.kind, room.center, room.size, s, camera)
    )(starts)  # [M, K]
    return jnp.where(jnp.any(hits, axis=-1), 0.0, in_frame), weight


def _waldo_solid_angles(
    room: WaldoRoom, c2w: Array, intrinsics: Intrinsics, near: float, softness: float = 0.0
) -> Tuple[Array, Array]:
    """(seen, facing): Waldo's solid angle (steradians) that the camera sees, and that faces it
    (`_samples_seen` summed)."""
    seen, weight = _samples_seen(room, c2w, intrinsics, near, softness)
    return jnp.sum(seen * weight), jnp.sum(weight)


# Eager calls of the batched oracles pad their cameras to a multiple of this many (copies of the last,
# cropped away), so that the populations of different sizes a run asks about (candidate cameras, training
# views, best views) share a few compiled programs instead of one each; each camera's value is its own.
POSE_BUCKET = 128


def in_buckets(jitted, room: WaldoRoom, c2w, *args):
    """`jitted(room, c2w, *args)` with a concrete c2w [P, 4, 4] padded to a multiple of `POSE_BUCKET` poses
    and the result's pose axis cropped to P (padded and cropped on the host: no program per size), as a
    NumPy array; traced arguments (inside a jit or a transformation) are passed as they are."""
    if any(isinstance(leaf, jax.core.Tracer) for leaf in jax.tree.leaves((room, c2w, args))):
        return jitted(room, c2w, *args)
    c2w = np.asarray(c2w, np.float32)
    count = c2w.shape[0]
    pad = (-count) % POSE_BUCKET if count else 0
    padded = np.concatenate([c2w, np.repeat(c2w[-1:], pad, axis=0)]) if pad else c2w
    return np.asarray(jitted(room, padded, *args))[:count]


@jax.jit
def _samples_seen_batch(room: WaldoRoom, c2w: Array, intrinsics: Intrinsics) -> Array:
    seen = jax.vmap(lambda c: _samples_seen(room, c, intrinsics, 0.05))(jnp.asarray(c2w, jnp.float32))
    return (seen[0] > 0.0) & (seen[1] > 0.0)


def waldo_samples_seen(room: WaldoRoom, c2w: Array, intrinsics: Intrinsics) -> Array:
    """bool [P, M]: which of Waldo's M surface samples each camera c2w [P, 4, 4] sees (facing it, in frame,
    unoccluded; exact), as `waldo_surface_seen` counts them."""
    return in_buckets(_samples_seen_batch, room, c2w, intrinsics)


@jax.jit
def waldo_surface_seen(room: WaldoRoom, c2w: Array, intrinsics: Intrinsics) -> Array:
    """The share of Waldo's surface area that at least one of the cameras c2w [P, 4, 4] sees (facing it,
    in frame, unoccluded; exact): what a field trained on those views can know of him. In [0, 1]."""
    by_any = jnp.any(waldo_samples_seen(room, c2w, intrinsics), axis=0)  # [M]
    return jnp.sum(jnp.where(by_any, room.waldo_areas, 0.0)) / jnp.sum(room.waldo_areas)


@functools.partial(jax.jit, static_argnames="softness")
def waldo_visibility(
    room: WaldoRoom, c2w: Array, intrinsics: Intrinsics, near: float = 0.05, softness: float = 0.0
) -> Array:
    """The oracle: the fraction of Waldo's projected area that is in frame and not occluded.

    Waldo's surface is represented by regular area-weighted samples. A sample counts towards the
    projected area when it faces the camera, with weight area * cos(angle) / distance^2 (its solid
    angle, so proportional to its projected pixels); it counts as seen when, in addition, it
    projects inside the image in front of the camera (beyond `near`) and the segment from it to the
    camera centre crosses no solid (walls, floor, clutter, crates, or Waldo's other parts).

    Args:
      room: the room.
      c2w: [4, 4] or [3, 4] camera-to-world matrix of one camera.
      intrinsics: its intrinsics (distortion included).
      near: minimum depth in front of the camera.
      softness: 0 for the exact oracle; > 0 for its smooth stand-in (a sigmoid of that width, as a
        fraction of the image width, at the image borders: see `_waldo_solid_angles`).

    Returns:
      visibility [] in [0, 1]: 0 when Waldo is behind the camera, out of frame or hidden; 1 when
      all of Waldo is in frame with nothing in between.

    Jitted (softness static), so a call from the host is one compiled program, not a hundred
    op-by-op ones; inside another jit, vmap or grad it is inlined as before.
    """
    seen, facing = _waldo_solid_angles(room, c2w, intrinsics, near, softness)
    return jnp.where(facing > 0.0, seen / jnp.maximum(facing, 1e-30), 0.0)


@functools.partial(jax.jit, static_argnames="softness")
def waldo_coverage(
    room: WaldoRoom, c2w: Array, intrinsics: Intrinsics, near: float = 0.05, softness: float = 0.0
) -> Array:
    """The share of the image covered by the visible part of Waldo (his "visible pixels" / all pixels).

    The seen solid angle of `waldo_visibility` times the pixels per steradian at the image centre
    (fx * fy), over the image's pixel count. It is largest when Waldo is close, unoccluded and
    whole in frame: moving closer enlarges him until the frame starts to cut him. Like the paper's
    salient-pixel criterion, but exact. softness as `waldo_visibility`.

    Returns:
      coverage [] in [0, 1] (clipped; the small-angle pixel estimate can overshoot near the border).
      Jitted as `waldo_visibility`.
    """
    seen, _ = _waldo_solid_angles(room, c2w, intrinsics, near, softness)
    pixels = seen * intrinsics.fx * intrinsics.fy
    return jnp.clip(pixels / (intrinsics.width * intrinsics.height), 0.0, 1.0)


@functools.partial(jax.jit, static_argnames="softness")
def waldo_view(
    room: WaldoRoom, c2w: Array, intrinsics: Intrinsics, near: float = 0.05, softness: float = 0.0
) -> Tuple[Array, Array]:
    """(`waldo_visibility`, `waldo_coverage`) of one camera from one pass over Waldo's samples.

    Returns:
      (visibility [] in [0, 1], coverage [] in [0, 1]), as the two functions return them (softness
      likewise). Jitted as `waldo_visibility`.
    """
    seen, facing = _waldo_solid_angles(room, c2w, intrinsics, near, softness)
    visibility = jnp.where(facing > 0.0, seen / jnp.maximum(facing, 1e-30), 0.0)
    coverage = jnp.clip(seen * intrinsics.fx * intrinsics.fy / (intrinsics.width * intrinsics.height), 0.0, 1.0)
    return visibility, coverage


@jax.jit
def _visibility_batch(room: WaldoRoom, c2w: Array, intrinsics: Intrinsics) -> Array:
    return jax.vmap(waldo_visibility, in_axes=(None, 0, None))(room, c2w, intrinsics)


def waldo_visibility_batch(room: WaldoRoom, c2w: Array, intrinsics: Intrinsics) -> Array:
    """`waldo_visibility` for a population of cameras c2w [P, 4, 4]; returns [P]."""
    return in_buckets(_visibility_batch, room, c2w, intrinsics)
