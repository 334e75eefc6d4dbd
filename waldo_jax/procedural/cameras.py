"""The room's training cameras: a band inside the walls, looking inwards, each seeing Waldo at most partly."""

from __future__ import annotations

import dataclasses
import functools
import math
from typing import Optional, Tuple

import jax
import jax.numpy as jnp
import numpy as np

from waldo_jax.cameras import look_at
from waldo_jax.procedural.visibility import POSE_BUCKET, in_buckets, waldo_samples_seen, waldo_visibility_batch
from waldo_jax.procedural.room import WaldoRoom, room_sdf
from waldo_jax.types import Array, Intrinsics, PRNGKey

__all__ = ["RoomCameraConfig", "training_cameras"]


@dataclasses.dataclass(frozen=True)
class RoomCameraConfig:
    """Where the training cameras of the room go (a band inside the walls, looking inwards).

    Attributes:
      band_radius: (min, max) horizontal distance from the room's centre.
      band_height: (min, max) camera height.
      target_radius: look-at points lie within this distance of the centre ...
      target_height: ... at heights in this range.
      fov_x: horizontal field of view in radians.
      max_visibility: a camera is kept only if it sees at most this fraction of Waldo.
      oversample: candidate cameras drawn per kept camera.
      min_clearance: a camera is kept only if its centre lies at least this far (metres) outside every
        solid (a band that reaches into the clutter would otherwise put cameras inside boxes).
      cover_views: how many of the views are chosen to see Waldo's surface (0: none; every view is then
        chosen by its place on the band). Their candidates come from the same band but look at points
        around Waldo (`cover_aim` x his size from his centre), so that a frame or a crate cuts him; of
        those that see at most `max_visibility` of him, the greedy choice takes each time the one that
        sees the most surface still seen by fewer than `cover_depth` chosen views.
      cover_depth: views a surface sample needs before it stops counting (2: seen from two places).
      cover_aim: the half-width of the box of aim points around Waldo's centre, in units of his size.
      cover_band: None: the covering cameras' candidates stand on the band; (min, max): on a ring around
        Waldo at these horizontal distances from him, in units of his size (closer: he fills more pixels).
    """

    band_radius: Tuple[float, float] = (2.9, 3.4)
    band_height: Tuple[float, float] = (1.0, 1.7)
    target_radius: float = 1.2
    target_height: Tuple[float, float] = (0.2, 0.9)
    fov_x: float = math.radians(60.0)
    max_visibility: float = 0.5
    oversample: int = 6
    min_clearance: float = 0.15
    cover_views: int = 0
    cover_depth: int = 2
    cover_aim: float = 0.6
    cover_band: Optional[Tuple[float, float]] = None


def training_cameras(
    key: PRNGKey, room: WaldoRoom, num_views: int, intrinsics: Intrinsics, config: RoomCameraConfig = RoomCameraConfig()
) -> np.ndarray:
    """Training cameras on a band around the room that see Waldo at most partly.

    Candidates are spread evenly in angle (with jitter) over the band, each looking at a random
    point near the centre; of those whose oracle visibility is at most `config.max_visibility` and
    that stand in free space (`config.min_clearance`), `num_views` spread over the band are kept.

    Args:
      key: PRNG key.
      room: the room.
      num_views: cameras to return.
      intrinsics: the cameras' intrinsics (the frame decides what "cut by the frame" means).
      config: the band.

    Returns:
      c2w: float32 [num_views, 4, 4].

    Raises:
      ValueError: when too few candidates qualify (ask for fewer views or a larger oversample), or
        `config.cover_views` is not in [0, num_views].
    """
    if not 0 <= config.cover_views <= num_views:
        raise ValueError(f"cover_views must lie in [0, {num_views}] (the views asked for), got {config.cover_views}")
    n = num_views * config.oversample
    c2w = _candidates(
        key,
        n,
        np.float32(config.band_radius),
        np.float32(config.band_height),
        np.float32(config.target_radius),
        np.float32(config.target_height),
    )
    visibility = np.asarray(waldo_visibility_batch(room, c2w, intrinsics))
    clearance = in_buckets(_clearance, room, c2w)
    keep = np.flatnonzero((visibility <= config.max_visibility) & (clearance >= config.min_clearance))
    if len(keep) < num_views - config.cover_views:
        raise ValueError(
            f"only {len(keep)} of {n} candidate cameras see Waldo at most {config.max_visibility:.0%} from free "
            f"space; ask for fewer than {num_views - config.cover_views} views or raise oversample"
        )
    spread = num_views - config.cover_views
    # Spread the kept cameras over the whole band rather than taking the first ones in angle.
    chosen = keep[np.round(np.linspace(0, len(keep) - 1, spread)).astype(int)] if spread > 0 else keep[:0]
    spread_c2w = np.asarray(c2w)[chosen].astype(np.float32)
    if config.cover_views == 0:
        return spread_c2w
    covering = _covering_cameras(jax.random.fold_in(key, 1), room, intrinsics, config, spread_c2w)
    return np.concatenate([spread_c2w, covering]).astype(np.float32)


def _covering_cameras(
    key: PRNGKey, room: WaldoRoom, intrinsics: Intrinsics, config: RoomCameraConfig, chosen: np.ndarray
) -> np.ndarray:
    """`config.cover_views` cameras chosen greedily to see Waldo's surface (`RoomCameraConfig.cover_views`),
    counting what the `chosen` cameras [V, 4, 4] see already. float32 [cover_views, 4, 4]."""
    n = config.cover_views * config.oversample * 4
    scale = float(room.waldo_scale)
    low = np.asarray(room.waldo_center) - config.cover_aim * scale
    k_place, k_aim = jax.random.split(key)
    band = config.band_radius if config.cover_band is None else tuple(scale * r for r in config.cover_band)
    places = _candidates(
        k_place,
        n,
        np.float32(band),
        np.float32(config.band_height),
        np.float32(config.target_radius),
        np.float32(config.target_height),
    )[:, :3, 3]
    if config.cover_band is not None:  # the ring is about Waldo, not the room's centre
        places = places + jnp.asarray(room.waldo_base, jnp.float32) * jnp.array([1.0, 0.0, 1.0])
    aims = jnp.asarray(low, jnp.float32) + 2 * config.cover_aim * scale * jax.random.uniform(k_aim, (n, 3))
    c2w = jax.vmap(look_at, in_axes=(0, 0, None))(places, aims, jnp.array([0.0, 1.0, 0.0]))
    visibility = np.asarray(waldo_visibility_batch(room, c2w, intrinsics))
    clearance = in_buckets(_clearance, room, c2w)
    usable = (visibility <= config.max_visibility) & (visibility > 0.0) & (clearance >= config.min_clearance)
    if int(usable.sum()) < config.cover_views:
        raise ValueError(
            f"only {int(usable.sum())} of {n} cameras aimed near Waldo see at most {config.max_visibility:.0%} of "
            f"him from free space; ask for fewer than {config.cover_views} covering views"
        )
    seen = np.asarray(waldo_samples_seen(room, c2w, intrinsics))  # [n, M]
    area = np.asarray(room.waldo_areas, np.float64)
    counts = np.asarray(waldo_samples_seen(room, jnp.asarray(chosen), intrinsics)).sum(0) if len(chosen) else 0
    counts = np.zeros(len(area)) + counts
    picked = []
    for _ in range(config.cover_views):
        gain = (seen * (counts < config.cover_depth)) @ area  # [n]
        gain = np.where(usable, gain, -1.0)
        gain[picked] = -1.0
        best = int(np.argmax(gain))  # the first on ties: deterministic
        picked.append(best)
        counts = counts + seen[best]
    return np.asarray(c2w)[picked]


@jax.jit
def _clearance(room: WaldoRoom, c2w: Array) -> jax.Array:
    """Distances float32 [n] from the centres of cameras c2w [n, 4, 4] to the nearest solid (one program:
    eagerly, the vmapped distance would compile each of its operations on its own)."""
    return jax.vmap(lambda c: room_sdf(room, c[:3, 3]))(c2w)


def _candidates(
    key: PRNGKey, n: int, band_radius: Array, band_height: Array, target_radius: Array, target_height: Array
) -> np.ndarray:
    """`n` candidate cameras c2w [n, 4, 4] spread evenly in angle (with jitter) over the band
    (`RoomCameraConfig`'s ranges, as arrays), each looking at a random point near the centre.

    Drawn `POSE_BUCKET` at a time (`_candidates_in`, n a value, not a shape) and cropped: the counts a
    room asks for (training, covering and held-out cameras) share one or two programs instead of
    compiling one each (0.5-1.1 s apiece on the 2-core CPU). JAX's threefry bits of an element depend
    on its index alone (`jax_threefry_partitionable`, the default), so the first n cameras are those
    drawn for n, bit for bit (tests/test_procedural.py)."""
    capacity = max(-(-int(n) // POSE_BUCKET), 1) * POSE_BUCKET
    c2w = _candidates_in(key, capacity, np.float32(n), band_radius, band_height, target_radius, target_height)
    return np.asarray(c2w)[: int(n)]


@functools.partial(jax.jit, static_argnames="capacity")
def _candidates_in(
    key: PRNGKey,
    capacity: int,
    n: Array,
    band_radius: Array,
    band_height: Array,
    target_radius: Array,
    target_height: Array,
) -> jax.Array:
    """`_candidates` for `capacity` slots, the angles spaced for `n` cameras: c2w [capacity, 4, 4]."""
    k_angle, k_radius, k_height, k_target = jax.random.split(key, 4)
    angle = 2 * jnp.pi * (jnp.arange(capacity) + jax.random.uniform(k_angle, (capacity,))) / n
    radius = jax.random.uniform(k_radius, (capacity,), minval=band_radius[0], maxval=band_radius[1])
    height = jax.random.uniform(k_height, (capacity,), minval=band_height[0], maxval=band_height[1])
    origins = jnp.stack([radius * jnp.cos(angle), height, radius * jnp.sin(angle)], -1)
    kt_r, kt_a, kt_h = jax.random.split(k_target, 3)
    t_r = target_radius * jnp.sqrt(jax.random.uniform(kt_r, (capacity,)))
    t_a = 2 * jnp.pi * jax.random.uniform(kt_a, (capacity,))
    t_h = jax.random.uniform(kt_h, (capacity,), minval=target_height[0], maxval=target_height[1])
    targets = jnp.stack([t_r * jnp.cos(t_a), t_h, t_r * jnp.sin(t_a)], -1)
    return jax.vmap(look_at, in_axes=(0, 0, None))(origins, targets, jnp.array([0.0, 1.0, 0.0]))
