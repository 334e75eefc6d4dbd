"""A camera path: K keyframe poses joined by a smooth curve and sampled at F frames, and its motion.

A path is a `Pose` with [K, 3] fields (origin, look-at point, up per keyframe). `sample_path` joins
the origins and the look-at points with a uniform Catmull-Rom spline (it passes through every
keyframe; the end tangents point along the first and last chords) and the up vectors with SLERP
per segment; each frame's rotation then follows from `look_at`. Frames are spaced evenly along
the path, by the arc length of the origin and of the look-at point together (the curve is sampled
`DENSITY` times per frame and inverted by interpolation), so a camera does not rush through a long
segment and crawl through a short one. Everything has fixed shapes: jit and vmap over paths.

`path_motion` measures the sampled frames: speed (origin displacement per frame, in units of the
scene extent), angular speed (degrees per frame) and jerk (third difference of the origin per
frame, in extent units). `PathLimits.violation` turns them, the scene box and the frames' opacity
into one number that is 0 exactly when the path keeps every limit.
"""

from __future__ import annotations

import functools
from typing import Tuple

import flax.struct
import jax
import jax.numpy as jnp

from waldo_jax.cameras import pose_to_c2w, rotation_angle
from waldo_jax.types import Array, Pose

__all__ = [
    "DENSITY",
    "catmull_rom",
    "slerp_unit",
    "sample_path",
    "path_c2w",
    "straight_path",
    "PathLimits",
    "path_motion",
    "Motion",
]

# Dense curve samples per output frame for the arc-length parametrisation.
DENSITY = 8


@jax.jit
def catmull_rom(points: Array, u: Array) -> Array:
    """Uniform Catmull-Rom spline through points [K, D] (K >= 2) at parameters u [...] in [0, K - 1].

    The ends use reflected phantom points (2 p0 - p1, 2 p_K-1 - p_K-2): the spline leaves the first
    keyframe along the first chord and reaches the last along the last one.
    """
    first = 2.0 * points[0] - points[1]
    last = 2.0 * points[-1] - points[-2]
    padded = jnp.concatenate([first[None], points, last[None]], axis=0)  # [K + 2, D]
    segment = jnp.clip(jnp.floor(u), 0, points.shape[0] - 2).astype(jnp.int32)
    t = (u - segment)[..., None]
    p0, p1, p2, p3 = (padded[segment + i] for i in range(4))
    return 0.5 * (
        2.0 * p1 + (p2 - p0) * t + (2.0 * p0 - 5.0 * p1 + 4.0 * p2 - p3) * t**2 + (3.0 * p1 - p0 - 3.0 * p2 + p3) * t**3
    )


def slerp_unit(a: Array, b: Array, t: Array) -> Array:
    """SLERP between unit vectors a, b [3] at t []; normalised linear interpolation when they nearly
    coincide (and a zero vector when they are opposite: `look_at` then falls back to a safe up)."""
    cos = jnp.clip(jnp.dot(a, b), -1.0, 1.0)
    close = cos > 1.0 - 1e-6
    theta = jnp.arccos(jnp.where(close, 0.0, cos))
    sin = jnp.where(close, 1.0, jnp.sin(theta))
    wa = jnp.where(close, 1.0 - t, jnp.sin((1.0 - t) * theta) / sin)
    wb = jnp.where(close, t, jnp.sin(t * theta) / sin)
    v = wa * a + wb * b
    norm = jnp.linalg.norm(v)
    return jnp.where(norm > 1e-6, v / jnp.where(norm > 1e-6, norm, 1.0), v)


def _unit(v: Array) -> Array:
    norm = jnp.linalg.norm(v, axis=-1, keepdims=True)
    return jnp.where(norm > 1e-12, v / jnp.where(norm > 1e-12, norm, 1.0), v)


def _curve(keyframes: Pose, u: Array) -> Pose:
    """The path at curve parameters u [M] in [0, K - 1] (not arc-length spaced)."""
    ups = _unit(keyframes.up)
    segment = jnp.clip(jnp.floor(u), 0, ups.shape[0] - 2).astype(jnp.int32)
    up = jax.vmap(slerp_unit)(ups[segment], ups[segment + 1], u - segment)
    return Pose(origin=catmull_rom(keyframes.origin, u), target=catmull_rom(keyframes.target, u), up=up)


@functools.partial(jax.jit, static_argnames="frames")
def sample_path(keyframes: Pose, frames: int) -> Pose:
    """F = `frames` poses ([F, 3] fields) evenly spaced along the path through `keyframes` ([K, 3], K >= 2).

    The first and last frames are the first and last keyframes. Spacing is by the summed arc length
    of origin and look-at point (see the module docstring); a path that does not move at all is
    sampled evenly in the curve parameter.
    """
    count = keyframes.origin.shape[0]
    dense = jnp.linspace(0.0, count - 1.0, DENSITY * (frames - 1) + 1)
    curve = _curve(keyframes, dense)
    step = jnp.linalg.norm(jnp.diff(curve.origin, axis=0), axis=-1) + jnp.linalg.norm(
        jnp.diff(curve.target, axis=0), axis=-1
    )
    length = jnp.concatenate([jnp.zeros(1), jnp.cumsum(step + 1e-9)])  # strictly increasing for interp
    goal = jnp.linspace(0.0, 1.0, frames) * length[-1]
    u = jnp.interp(goal, length, dense)
    u = jnp.where(length[-1] > 1e-6 * (dense.shape[0]), u, jnp.linspace(0.0, count - 1.0, frames))
    return _curve(keyframes, u)


@functools.partial(jax.jit, static_argnames="frames")
def path_c2w(keyframes: Pose, frames: int) -> Array:
    """Camera-to-world matrices [F, 4, 4] of `sample_path`."""
    return jax.vmap(pose_to_c2w)(sample_path(keyframes, frames))


@functools.partial(jax.jit, static_argnames="keyframes")
def straight_path(start: Pose, end: Pose, keyframes: int) -> Pose:
    """K keyframes ([K, 3] fields) evenly spaced on the straight line from `start` to `end` ([3] fields):
    origin and look-at point linearly, up by SLERP. Sampled, it moves at constant speed."""
    t = jnp.linspace(0.0, 1.0, keyframes)[:, None]
    up = jax.vmap(lambda s: slerp_unit(_unit(start.up), _unit(end.up), s))(t[:, 0])
    return Pose(
        origin=(1.0 - t) * start.origin + t * end.origin, target=(1.0 - t) * start.target + t * end.target, up=up
    )


@flax.struct.dataclass
class Motion:
    """How a sampled path moves (per frame).

    Attributes:
      speed: float32 [F - 1], origin displacement per frame in units of the scene extent.
      turn: float32 [F - 1], rotation per frame in degrees.
      jerk: float32 [F - 3], |third difference of the origin| per frame, in extent units.
    """

    speed: Array
    turn: Array
    jerk: Array


@jax.jit
def path_motion(c2w: Array, extent: Array) -> Motion:
    """`Motion` of frames c2w [F, 4, 4] (F >= 4) in a scene whose extent is `extent` []."""
    origin = c2w[:, :3, 3]
    speed = jnp.linalg.norm(jnp.diff(origin, axis=0), axis=-1) / extent
    turn = jnp.degrees(jax.vmap(rotation_angle)(c2w[:-1, :3, :3], c2w[1:, :3, :3]))
    jerk = jnp.linalg.norm(jnp.diff(origin, n=3, axis=0), axis=-1) / extent
    return Motion(speed=speed, turn=turn, jerk=jerk)


@flax.struct.dataclass
class PathLimits:
    """The constraints every output path keeps (numbers, so a sweep can vmap over them).

    Attributes:
      max_speed: float32 [], largest origin displacement per frame, in units of the scene extent.
      max_turn: float32 [], largest rotation per frame, in degrees.
      min_opacity: float32 [], smallest mean opacity of a frame (0 disables: no empty views).
      min_travel: float32 [], shortest distance the camera travels over the whole path, in scene
        extents (0 disables; a criterion that rewards the best view alone favours paths that barely move).
      low, high: float32 [3], the box every frame's origin stays in.
      extent: float32 [], the scene extent (the unit of max_speed).
    """

    max_speed: Array
    max_turn: Array
    min_opacity: Array
    min_travel: Array
    low: Array
    high: Array
    extent: Array

    def violation(self, c2w: Array, opacity: Array) -> Tuple[Array, Motion]:
        """(total violation [], motion) of frames c2w [F, 4, 4] with mean opacities [F].

        The violation sums, over frames, how far each limit is exceeded relative to the limit (box:
        distance outside in extent units); it is 0 exactly when every limit holds and NaN when a
        frame is not finite.
        """
        motion = path_motion(c2w, self.extent)
        origin = c2w[:, :3, 3]
        outside = jnp.sum(jnp.maximum(self.low - origin, 0.0) + jnp.maximum(origin - self.high, 0.0)) / self.extent
        fast = jnp.sum(jnp.maximum(motion.speed - self.max_speed, 0.0)) / self.max_speed
        turning = jnp.sum(jnp.maximum(motion.turn - self.max_turn, 0.0)) / self.max_turn
        empty = jnp.sum(jnp.maximum(self.min_opacity - opacity, 0.0)) / jnp.maximum(self.min_opacity, 1e-6)
        short = jnp.maximum(self.min_travel - jnp.sum(motion.speed), 0.0) / jnp.maximum(self.min_travel, 1e-6)
        total = outside + fast + turning + empty + short
        finite = jnp.all(jnp.isfinite(c2w)) & jnp.all(jnp.isfinite(opacity))
        return jnp.where(finite, total, jnp.nan), motion
