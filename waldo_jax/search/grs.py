"""Guided random search (GRS), the first baseline of "Finding Waldo" (MMSys'24), Algorithm 1.

Every child is drawn independently:
  * origin: uniform per axis within [min, max] of the training camera origins;
  * look-at point: one of the training cameras' look-at points (`population.training_look_at`),
    uniformly at random;
  * up: the mean of the training cameras' up vectors, normalised. Should it be (nearly) parallel to
    a child's view direction, `waldo_jax.cameras.look_at` still returns a deterministic valid
    rotation (it falls back to the world axis least aligned with the view), so nothing is done here.

GRS ignores scores: it only needs the training slots of the population.
"""

from __future__ import annotations

from typing import Tuple

import flax.struct
import jax
import jax.numpy as jnp

from waldo_jax.search.method import ChildrenConfig, SearchMethod
from waldo_jax.search.population import Population, draw_index, uniform_rows
from waldo_jax.types import Array, Pose, PRNGKey

__all__ = ["Params", "Config", "ask", "origin_bounds", "mean_up", "METHOD"]


@flax.struct.dataclass
class Params:
    """GRS has no numeric hyper-parameters; the empty pytree keeps the interface uniform."""


# GRS's only static setting is children_per_epoch.
Config = ChildrenConfig


def origin_bounds(population: Population) -> Tuple[Array, Array]:
    """Per-axis (min, max) [3] of the training camera origins."""
    train = population.is_train[:, None]
    low = jnp.min(population.origin, axis=0, where=train, initial=jnp.inf)
    high = jnp.max(population.origin, axis=0, where=train, initial=-jnp.inf)
    return low, high


def mean_up(population: Population) -> Array:
    """The mean training up vector, normalised [3] (left at zero if the ups cancel out exactly)."""
    total = jnp.sum(jnp.where(population.is_train[:, None], population.up, 0.0), axis=0)
    norm = jnp.linalg.norm(total)
    return jnp.where(norm > 0.0, total / jnp.where(norm > 0.0, norm, 1.0), total)


def _sample_one(u: Array, low: Array, high: Array, target_weights: Array, targets: Array, up: Array) -> Pose:
    """One GRS child from 4 uniforms u [4]: origin in the box [low, high] [3], a look-at point of targets [C, 3]."""
    # The clip only guards against rounding above `high`.
    origin = jnp.clip(low + u[:3] * (high - low), low, high)
    return Pose(origin=origin, target=targets[draw_index(u[3], target_weights)], up=up)


def ask(
    key: PRNGKey, population: Population, params: Params, config: Config, epoch: Array
) -> Tuple[Pose, Array, Population]:
    """Draws one epoch of GRS children.

    The key is used once, for a [children_per_epoch, 4] block of uniforms (3 for the origin, 1 for
    the look-at point) that the per-child function maps to a pose; one block compiles much faster
    than per-child keys under vmap.

    Args:
      key: PRNG key (consumed).
      population: the population; only its training slots are used.
      params: `Params()` (none).
      config: `Config`.
      epoch: the current epoch (unused: GRS draws the same way every epoch).

    Returns:
      children: `Pose` with [children_per_epoch, 3] fields.
      child_mask: bool [children_per_epoch], all True.
      population: unchanged.
    """
    del params, epoch
    n = config.children_per_epoch
    low, high = origin_bounds(population)
    target_weights = population.is_train.astype(jnp.float32)
    up = mean_up(population)
    uniforms = uniform_rows(key, n, 4)
    children = jax.vmap(_sample_one, in_axes=(0, None, None, None, None, None))(
        uniforms, low, high, target_weights, population.target, up
    )
    return children, jnp.ones(n, bool), population


METHOD = SearchMethod(name="grs", params_type=Params, config_type=Config, ask_fn=ask)
