"""Pose interpolation-based search (PIBS), the second baseline of "Finding Waldo" (MMSys'24), Algorithm 1.

Each epoch `ask` takes the `top_c` best views, lists their pairs not explored yet (better rank
first, in rank order; `pair_table`) and gives each pair in turn
interpolation_step = round(children_per_epoch / number_of_pairs) (at least 1) children, by SLERP
(`waldo_jax.cameras.slerp_pose`) strictly between the two, until the slots are used up; the pairs
that received children are marked explored. Slots left empty are masked (`fallback="none"`, the
default) or filled with GRS poses (`fallback="grs"`).

The algorithm step by step and the choices where the paper is silent (rounding, which pairs count as
explored, the fallback, the static `top_c`, up vectors): see docs/design.md, section "Search > PIBS".
"""

from __future__ import annotations

import dataclasses
from typing import Any, Optional, Tuple

import flax.struct
import jax
import jax.numpy as jnp
import numpy as np

from waldo_jax.cameras import slerp_pose
from waldo_jax.search import grs
from waldo_jax.search.method import SearchMethod, check_options
from waldo_jax.search.population import Population, gather_poses
from waldo_jax.types import Array, Pose, PRNGKey

__all__ = ["FALLBACKS", "Params", "Config", "ask", "pair_table", "METHOD"]

FALLBACKS = ("none", "grs")


@flax.struct.dataclass
class Params:
    """PIBS has no numeric hyper-parameters (its `top_c` is shape-setting, see `Config`)."""


@dataclasses.dataclass(frozen=True)
class Config:
    """Static settings of PIBS.

    Attributes:
      children_per_epoch: slots per epoch.
      top_c: how many of the best views are paired (top_c * (top_c - 1) / 2 pairs).
      fallback: what fills slots PIBS leaves empty: "none" (mask them) or "grs" (GRS poses).
    """

    children_per_epoch: int
    top_c: int = 5
    fallback: str = "none"

    def __post_init__(self):
        if self.children_per_epoch < 1:
            raise ValueError(f"children_per_epoch must be >= 1, got {self.children_per_epoch}")
        if self.top_c < 2:
            raise ValueError(f"top_c must be >= 2 (pairs are needed), got {self.top_c}")
        if self.fallback not in FALLBACKS:
            raise ValueError(f"fallback must be one of {FALLBACKS}, got {self.fallback!r}")

    # The options `create` accepts besides children_per_epoch and epochs.
    OPTIONS = ("top_c", "fallback")

    @classmethod
    def create(
        cls,
        children_per_epoch: int,
        epochs: Optional[int] = None,
        method: str = "pibs",
        top_c: int = 5,
        fallback: str = "none",
        **options: Any,
    ) -> "Config":
        """The config for `children_per_epoch` slots (`epochs` unused).

        Raises:
          ConfigError: an option PIBS does not have (the message names it and `method`).
        """
        del epochs
        check_options(method, options, cls.OPTIONS)
        return cls(children_per_epoch=int(children_per_epoch), top_c=int(top_c), fallback=fallback)


def pair_table(top_c: int) -> Tuple[np.ndarray, np.ndarray]:
    """The rank pairs (i, j), i < j < top_c, in the order PIBS visits them: int32 [P] each."""
    first, second = np.triu_indices(top_c, k=1)
    return first.astype(np.int32), second.astype(np.int32)


def _interpolate_one(pose_a: Pose, pose_b: Pose, t: Array) -> Pose:
    """The pose at parameter t in (0, 1) on the SLERP arc from pose_a to pose_b ([3] fields)."""
    return slerp_pose(pose_a, pose_b, t)


def ask(
    key: PRNGKey, population: Population, params: Params, config: Config, epoch: Array
) -> Tuple[Pose, Array, Population]:
    """Proposes one epoch of PIBS children and marks their pairs as explored.

    Args:
      key: PRNG key; consumed only by the GRS fallback (PIBS itself is deterministic).
      population: the population.
      params: `Params()` (none).
      config: `Config`.
      epoch: the current epoch (passed on to the fallback).

    Returns:
      children: `Pose` with [children_per_epoch, 3] fields (masked slots hold the best view's pose,
        or GRS poses with `fallback="grs"`).
      child_mask: bool [children_per_epoch].
      population: with the used pairs marked in `explored` (both orders).
    """
    del params
    n = config.children_per_epoch
    top_c = min(config.top_c, population.capacity)
    fitness = population.fitness
    order = jnp.argsort(-fitness, stable=True)  # best first, -inf last
    top = order[:top_c]  # [top_c] slots
    top_ok = jnp.isfinite(fitness[top])

    rank_a, rank_b = pair_table(top_c)
    num_pairs = rank_a.shape[0]
    slot_a, slot_b = top[rank_a], top[rank_b]  # [P]
    available = top_ok[rank_a] & top_ok[rank_b] & ~population.explored[slot_a, slot_b]
    num_available = jnp.sum(available, dtype=jnp.int32)
    step = jnp.maximum(1, jnp.round(n / jnp.maximum(num_available, 1))).astype(jnp.int32)

    position = jnp.cumsum(available, dtype=jnp.int32) - 1  # rank of each pair among the available
    used = available & (position * step < n)
    # The pairs are distinct, so every (a, b) cell is written at most once.
    explored = population.explored.at[slot_a, slot_b].set(population.explored[slot_a, slot_b] | used)
    explored = explored.at[slot_b, slot_a].set(explored[slot_b, slot_a] | used)

    (available_pairs,) = jnp.nonzero(available, size=num_pairs, fill_value=0)
    child = jnp.arange(n, dtype=jnp.int32)
    pair_position = child // step
    mask = pair_position < num_available
    pair = available_pairs[jnp.minimum(pair_position, num_pairs - 1)]
    t = (child % step + 1).astype(jnp.float32) / (step + 1).astype(jnp.float32)
    pose_a = gather_poses(population, slot_a[pair])
    pose_b = gather_poses(population, slot_b[pair])
    children = jax.vmap(_interpolate_one)(pose_a, pose_b, t)

    if config.fallback == "grs":
        filler, _, _ = grs.ask(key, population, grs.Params(), grs.Config(n), epoch)
        mask_out = jnp.ones(n, bool)
    else:
        del key
        filler = gather_poses(population, jnp.broadcast_to(order[0], (n,)))
        mask_out = mask
    children = jax.tree.map(lambda c, f: jnp.where(mask[:, None], c, f), children, filler)
    return children, mask_out, population.replace(explored=explored)


METHOD = SearchMethod(name="pibs", params_type=Params, config_type=Config, ask_fn=ask)
