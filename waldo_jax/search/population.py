"""The population buffer shared by the searches of "Finding Waldo" (MMSys'24), Algorithm 1.

`Population` holds the poses and scores (no images) of the training views and of every child, in a
fixed capacity C = n_train + epochs * children_per_epoch so that the whole search compiles once:
training view i in slot i, the children of each epoch after them in order. Its `fitness` [C] is the
signed, higher-is-better score (sign * score; -inf, never selected, where invalid or not finite), so
one selection code serves "max" and "min" criteria. Helpers build it (`init_population`,
`training_poses`, `training_look_at`), read it (`top_k_indices`, `gather_poses`) and write a
generation into it (`write_children`).

The slot layout and the names used throughout `waldo_jax.search` (score, direction, fitness,
look-at point): see docs/design.md, section "Search > Population and names".
"""

from __future__ import annotations

from typing import Optional, Tuple

import flax.struct
import jax
import jax.numpy as jnp
import numpy as np

from waldo_jax.cameras import camera_focus, pose_to_c2w
from waldo_jax.search.views import SceneFrame
from waldo_jax.types import Array, Pose

__all__ = [
    "DIRECTIONS",
    "Population",
    "direction_sign",
    "training_look_at",
    "training_poses",
    "init_population",
    "poses_frame",
    "top_k_indices",
    "write_children",
    "gather_poses",
    "draw_index",
    "uniform_rows",
]

DIRECTIONS = ("max", "min")


def direction_sign(direction: str) -> float:
    """+1.0 for "max", -1.0 for "min"; a ValueError names any other value."""
    if direction not in DIRECTIONS:
        raise ValueError(f"direction must be one of {DIRECTIONS}, got {direction!r}")
    return 1.0 if direction == "max" else -1.0


@flax.struct.dataclass
class Population:
    """All poses seen by one search run: the training views and every generated child.

    The raw criterion scores are stored as given (NaN kept, so failures can be counted); every
    selection uses `fitness`, the signed "higher is better" view in which invalid and non-finite
    entries are -inf.

    Attributes:
      origin: camera centres, float32 [C, 3].
      target: look-at points, float32 [C, 3].
      up: up vectors, float32 [C, 3].
      c2w: camera-to-world matrices, float32 [C, 4, 4] (the training views' own matrices for
        slots < num_train, `look_at(origin, target, up)` for children).
      score: raw criterion scores, float32 [C] (NaN for empty slots and failed scores).
      valid: bool [C], the slot holds a scored view (a training view or a rendered child).
      epoch: int32 [C], 0 for training views, e for a child born (and rendered) in epoch e,
        -1 for slots not filled (not yet reached, or masked children).
      explored: bool [C, C], PIBS's explored pairs (symmetric: both orders are marked).
      frame: the `SceneFrame` views are measured in (different shots, view cells).
      num_train: n_train, the number of leading training slots (static).
      direction: "max" or "min", the criterion's direction (static).
    """

    origin: Array
    target: Array
    up: Array
    c2w: Array
    score: Array
    valid: Array
    epoch: Array
    explored: Array
    frame: SceneFrame
    num_train: int = flax.struct.field(pytree_node=False, default=0)
    direction: str = flax.struct.field(pytree_node=False, default="max")

    @property
    def capacity(self) -> int:
        """C, the number of slots (static)."""
        return int(self.score.shape[-1])

    @property
    def fitness(self) -> Array:
        """Signed scores [C], higher is better; -inf where invalid or not finite."""
        usable = self.valid & jnp.isfinite(self.score)
        return jnp.where(usable, direction_sign(self.direction) * self.score, -jnp.inf)

    @property
    def poses(self) -> Pose:
        """All slots as one `Pose` with [C, 3] fields."""
        return Pose(origin=self.origin, target=self.target, up=self.up)

    @property
    def is_train(self) -> Array:
        """bool [C], the training slots."""
        return jnp.arange(self.capacity) < self.num_train


def training_look_at(c2w: Array, focus: Array, min_fraction: float = 0.1) -> Array:
    """Look-at point of one training camera (the paper leaves it undefined; this is our choice).

    The point of the camera's optical axis closest to the scene focus point, but at least
    `min_fraction * |focus - origin|` in front of the camera (so a camera facing away from the focus
    still gets a point in front of it, and the look-at point never equals the origin). A tiny
    absolute floor (1e-6 world units) covers a focus that coincides with the origin.

    Args:
      c2w: [4, 4] or [3, 4] camera-to-world matrix (OpenGL: the camera looks along -z).
      focus: [3] the scene focus point, e.g. `camera_focus` of all training cameras.
      min_fraction: minimum depth of the look-at point, as a fraction of the distance to the focus.

    Returns:
      [3] the look-at point.
    """
    origin = c2w[:3, 3]
    forward = -c2w[:3, 2]
    forward = forward / jnp.linalg.norm(forward)
    offset = focus - origin
    depth = jnp.maximum(jnp.dot(offset, forward), min_fraction * jnp.linalg.norm(offset))
    return origin + jnp.maximum(depth, 1e-6) * forward


def training_poses(c2w: Array, focus: Optional[Array] = None, min_fraction: float = 0.1) -> Pose:
    """The paper's (origin, look-at point, up) of every training camera.

    Args:
      c2w: float32 [N, 4, 4] training camera-to-world matrices.
      focus: [3] the scene focus point; default `camera_focus(c2w)` (computed on the host, so pass
        it explicitly to call this under `jit`).
      min_fraction: see `training_look_at`.

    Returns:
      `Pose` with [N, 3] fields: the camera centres, `training_look_at` points and the cameras' own
      up axes (the second column of c2w), so that `look_at` gives back each c2w.
    """
    if focus is None:
        focus = camera_focus(np.asarray(c2w))
    c2w = jnp.asarray(c2w, jnp.float32)
    target = _training_look_at_batch(c2w, jnp.asarray(focus, jnp.float32), jnp.float32(min_fraction))
    return Pose(origin=c2w[:, :3, 3], target=target, up=c2w[:, :3, 1])


# Jitted once here: called eagerly (as `explore` does on the host) it would dispatch op by op.
_training_look_at_batch = jax.jit(jax.vmap(training_look_at, in_axes=(0, None, None)))


def init_population(
    train_poses: Pose,
    train_scores: Array,
    capacity: int,
    direction: str = "max",
    train_c2w: Optional[Array] = None,
    frame: Optional[SceneFrame] = None,
) -> Population:
    """A population holding the N scored training views in its first N slots; the rest empty.

    Jit-able with `capacity` and `direction` static.

    Args:
      train_poses: `Pose` with [N, 3] fields (e.g. from `training_poses`).
      train_scores: raw criterion scores [N] (NaN allowed: such a view is never selected).
      capacity: C >= N, the total number of slots.
      direction: "max" or "min".
      train_c2w: [N, 4, 4] the training matrices; default `look_at` of `train_poses`.
      frame: the scene's `SceneFrame` (`views.scene_frame`, as `explore` passes it); default
        `poses_frame(train_poses)`.

    Returns:
      The `Population`.
    """
    direction_sign(direction)  # validates it
    n_train = int(train_poses.origin.shape[0])
    if capacity < n_train:
        raise ValueError(f"capacity {capacity} is smaller than the {n_train} training views")
    if train_c2w is None:
        train_c2w = jax.vmap(pose_to_c2w)(train_poses)
    pad = capacity - n_train

    def padded(x, fill):
        x = jnp.asarray(x)
        return jnp.concatenate([x, jnp.full((pad,) + x.shape[1:], fill, x.dtype)], axis=0)

    return Population(
        origin=padded(jnp.asarray(train_poses.origin, jnp.float32), 0.0),
        target=padded(jnp.asarray(train_poses.target, jnp.float32), 0.0),
        up=padded(jnp.asarray(train_poses.up, jnp.float32), 0.0),
        c2w=padded(jnp.asarray(train_c2w, jnp.float32)[:, :4, :4], 0.0),
        score=padded(jnp.asarray(train_scores, jnp.float32), jnp.nan),
        valid=padded(jnp.ones(n_train, bool), False),
        epoch=padded(jnp.zeros(n_train, jnp.int32), -1),
        explored=jnp.zeros((capacity, capacity), bool),
        frame=poses_frame(train_poses) if frame is None else frame,
        num_train=n_train,
        direction=direction,
    )


def poses_frame(poses: Pose) -> SceneFrame:
    """A `SceneFrame` from poses alone (jit-able): the mean look-at point as the focus, the normalised
    mean up (+z if they cancel) and the median distance of the origins to that focus (1 if zero)."""
    focus = jnp.mean(jnp.asarray(poses.target, jnp.float32), axis=0)
    up = jnp.mean(jnp.asarray(poses.up, jnp.float32), axis=0)
    norm = jnp.linalg.norm(up)
    up = jnp.where(norm > 1e-6, up / jnp.where(norm > 1e-6, norm, 1.0), jnp.array([0.0, 0.0, 1.0]))
    radius = jnp.median(jnp.linalg.norm(jnp.asarray(poses.origin, jnp.float32) - focus, axis=-1))
    return SceneFrame(focus=focus, up=up, radius=jnp.where(radius > 1e-9, radius, 1.0))


def top_k_indices(population: Population, k: int) -> Tuple[Array, Array]:
    """Indices of the k best slots by fitness, best first (ties: lower index first).

    Args:
      population: the population.
      k: how many (static), at most C.

    Returns:
      indices: int32 [k].
      ok: bool [k], False where fewer than k slots have a finite fitness (those indices point at
        -inf entries and must be ignored).
    """
    fitness = population.fitness
    values, indices = jax.lax.top_k(fitness, k)
    return indices.astype(jnp.int32), jnp.isfinite(values)


def uniform_rows(key: Array, rows: int, columns: int) -> Array:
    """A [rows, columns] block of uniforms in [0, 1), one per child row, from one key.

    Drawn flat and reshaped: with JAX's (default) partitionable threefry, XLA on CPU compiles a
    multi-dimensional draw several times slower than a flat one (about 2 s vs 0.2 s for a vmapped
    [51, 14] block on 2 cores), for the same kind of numbers.
    """
    return jax.random.uniform(key, (rows * columns,)).reshape(rows, columns)


def draw_index(u: Array, weights: Array) -> Array:
    """An index i drawn with probability weights[i] / sum(weights), by inverting the CDF at u.

    A binary search in the cumulative sum: O(log C) per draw once the O(C) sum (which does not
    depend on u) is computed, so vmapping over many draws with shared weights stays cheap.

    Args:
      u: a uniform number in [0, 1), [].
      weights: non-negative weights [C] (not normalised); zero-weight entries are never drawn.

    Returns:
      int32 [] index (0 when all weights are zero; callers mask that case).
    """
    cdf = jnp.cumsum(weights)
    total = cdf[-1]
    index = jnp.searchsorted(cdf, u * total, side="right").astype(jnp.int32)  # first i: cdf[i] > u * total
    last_positive = jnp.sum(cdf < total, dtype=jnp.int32)  # in case u * total rounds up to total
    return jnp.minimum(index, last_positive)


def gather_poses(population: Population, indices: Array) -> Pose:
    """The poses of the given slots, `Pose` with [..., 3] fields."""
    return Pose(origin=population.origin[indices], target=population.target[indices], up=population.up[indices])


def write_children(
    population: Population,
    children: Pose,
    c2w: Array,
    scores: Array,
    mask: Array,
    epoch: Array,
    offset: Array,
) -> Population:
    """Writes one epoch's n children into slots [offset, offset + n) (`lax.dynamic_update_slice`).

    Masked children (mask False) are stored as empty slots: not valid, epoch -1, score NaN; their
    poses are kept only for inspection.

    Args:
      population: the population.
      children: `Pose` with [n, 3] fields.
      c2w: [n, 4, 4] their matrices.
      scores: [n] raw scores (anything where mask is False).
      mask: bool [n], which children were actually generated.
      epoch: int32 [], the epoch they were born in.
      offset: int32 [], the first slot to write (may be traced).

    Returns:
      The updated population.
    """
    offset = jnp.asarray(offset, jnp.int32)

    def put(buffer, values):
        values = jnp.asarray(values, buffer.dtype)
        start = (offset,) + (0,) * (buffer.ndim - 1)
        return jax.lax.dynamic_update_slice(buffer, values, start)

    return population.replace(
        origin=put(population.origin, children.origin),
        target=put(population.target, children.target),
        up=put(population.up, children.up),
        c2w=put(population.c2w, c2w),
        score=put(population.score, jnp.where(mask, scores, jnp.nan)),
        valid=put(population.valid, mask),
        epoch=put(population.epoch, jnp.where(mask, epoch, -1)),
    )
