"""Evolution-guided pose search (EGPS), the method of "Finding Waldo" (MMSys'24), Algorithm 1.

A generational genetic algorithm on poses: every child of an epoch is bred from the population as it
was at the start of the epoch, by rank-biased selection of two distinct parents from the better half
(`parent_weights`, `select_parents`), crossover (`crossover`: the normalised mean up; origin and
look-at point uniform per axis between the parents') and mutation (`mutation_delta`: each component
moves by -nabla, 0 or +nabla, nabla = `nabla_scale` * (parent1 - parent2)). `ask` draws one
[children_per_epoch, 14] block of uniforms; each operator is a deterministic map of its row.

The operators' probabilities, the choices where the paper is silent (better half, rank bias, parent
order, up vectors) and why one block of uniforms: see docs/design.md, section "Search > EGPS".
"""

from __future__ import annotations

from typing import Tuple

import flax.struct
import jax
import jax.numpy as jnp

from waldo_jax.search.method import ChildrenConfig, SearchMethod
from waldo_jax.search.population import Population, uniform_rows
from waldo_jax.types import Array, Pose, PRNGKey

__all__ = [
    "NUM_UNIFORMS",
    "Params",
    "Config",
    "ask",
    "parent_weights",
    "select_parents",
    "crossover",
    "mutation_delta",
    "breed",
    "METHOD",
]

# Uniform numbers one child consumes: 2 parent draws, 3 + 3 crossover, 3 + 3 mutation.
NUM_UNIFORMS = 14


def _default_mutation_probs() -> Array:
    return jnp.asarray([0.05, 0.9, 0.05], jnp.float32)


@flax.struct.dataclass
class Params:
    """Numeric hyper-parameters of EGPS (a pytree: a sweep can vmap over them).

    Attributes:
      mutation_probs: float32 [3], probabilities of delta = -nabla, 0, +nabla (normalised to sum 1).
      nabla_scale: float32 [], nabla = nabla_scale * (parent1 - parent2), per component.
      rank_bias: float32 [], exponent of the rank weights (h - r) ** rank_bias over the better half.
    """

    mutation_probs: Array = flax.struct.field(default_factory=_default_mutation_probs)
    nabla_scale: Array = flax.struct.field(default_factory=lambda: jnp.asarray(0.1, jnp.float32))
    rank_bias: Array = flax.struct.field(default_factory=lambda: jnp.asarray(1.0, jnp.float32))


# EGPS's only static setting is children_per_epoch.
Config = ChildrenConfig


def parent_weights(fitness: Array, rank_bias: Array) -> Tuple[Array, Array]:
    """Selection weights of each slot as a parent.

    Args:
      fitness: [C] signed scores, -inf for unusable slots.
      rank_bias: the exponent of the rank weights.

    Returns:
      weights: [C] ((h - rank) / h) ** rank_bias for the better half (rank 0 = best, h its size),
        0 elsewhere (unnormalised; the division by h only avoids overflow for large exponents).
      can_breed: bool [], at least two slots have a finite fitness.
    """
    capacity = fitness.shape[0]
    order = jnp.argsort(-fitness, stable=True)
    rank = jnp.zeros(capacity, jnp.int32).at[order].set(jnp.arange(capacity, dtype=jnp.int32))
    num_finite = jnp.sum(jnp.isfinite(fitness), dtype=jnp.int32)
    half = jnp.minimum(jnp.maximum(num_finite // 2, 2), num_finite)
    relative = (half - rank).astype(jnp.float32) / jnp.maximum(half, 1).astype(jnp.float32)
    weights = jnp.where(rank < half, jnp.power(jnp.maximum(relative, 1e-30), rank_bias), 0.0)
    return weights, num_finite >= 2


def select_parents(u: Array, weights: Array, fitness: Array) -> Tuple[Array, Array]:
    """Two distinct parent slots drawn from `parent_weights`; the better-ranked one first.

    Inverse-CDF sampling with a binary search, so a child costs O(log C) after an O(C) cumulative
    sum that does not depend on u (computed once when vmapped over children). The second draw
    skips the first parent's segment of the CDF, which is exact sampling without replacement; if
    float rounding ever lands it on the first parent again (probability ~1e-7), the best other slot
    is taken instead.

    Args:
      u: two uniforms in [0, 1), [2].
      weights: [C] from `parent_weights` (at least two positive entries).
      fitness: [C] the fitness the weights come from (orders the two parents).

    Returns:
      (parent1, parent2): int32 [] slot indices; parent1 has the higher fitness (ties: lower slot,
      as in the ranking).
    """
    cdf = jnp.cumsum(weights)
    total = cdf[-1]
    last_positive = jnp.sum(cdf < total, dtype=jnp.int32)  # guards u * total rounding up to total
    top_two = jax.lax.top_k(weights, 2)[1]

    def draw(v):
        return jnp.minimum(jnp.searchsorted(cdf, v, side="right").astype(jnp.int32), last_positive)

    first = draw(u[0] * total)
    first_weight = weights[first]
    first_start = cdf[first] - first_weight
    v = u[1] * (total - first_weight)
    v = jnp.where(v >= first_start, jnp.maximum(v + first_weight, cdf[first]), v)  # skip first's segment
    second = draw(v)
    other = jnp.where(first == top_two[0], top_two[1], top_two[0]).astype(jnp.int32)
    second = jnp.where(second == first, other, second)
    first_is_better = (fitness[first] > fitness[second]) | ((fitness[first] == fitness[second]) & (first < second))
    return jnp.where(first_is_better, first, second), jnp.where(first_is_better, second, first)


def crossover(u: Array, parent1: Pose, parent2: Pose) -> Pose:
    """EGPS crossover of two poses ([3] fields) from six uniforms u [6].

    Origin and look-at point are uniform per axis between the parents'; up is the normalised mean
    of the parents' ups (zero when they cancel; see docs/design.md, "Search").
    """

    def between(v, a, b):
        low, high = jnp.minimum(a, b), jnp.maximum(a, b)
        return jnp.clip(low + v * (high - low), low, high)  # the clip only guards rounding

    up = parent1.up + parent2.up  # the mean, up to a factor normalised away
    norm = jnp.linalg.norm(up)
    up = jnp.where(norm > 0.0, up / jnp.where(norm > 0.0, norm, 1.0), up)
    return Pose(
        origin=between(u[:3], parent1.origin, parent2.origin),
        target=between(u[3:], parent1.target, parent2.target),
        up=up,
    )


def mutation_delta(u: Array, nabla: Array, mutation_probs: Array) -> Array:
    """Per-component mutation [3] from uniforms u [3]: -nabla, 0 or +nabla with `mutation_probs` [3]."""
    cdf = jnp.cumsum(mutation_probs / jnp.sum(mutation_probs))
    step = (u >= cdf[0]).astype(nabla.dtype) + (u >= cdf[1]).astype(nabla.dtype) - 1.0  # -1, 0, +1
    return step * nabla


def breed(u: Array, parent1: Pose, parent2: Pose, params: Params) -> Pose:
    """One child of two parents ([3] fields) from 12 uniforms u [12]: crossover, then mutation."""
    child = crossover(u[:6], parent1, parent2)
    nabla_origin = params.nabla_scale * (parent1.origin - parent2.origin)
    nabla_target = params.nabla_scale * (parent1.target - parent2.target)
    return child.replace(
        origin=child.origin + mutation_delta(u[6:9], nabla_origin, params.mutation_probs),
        target=child.target + mutation_delta(u[9:12], nabla_target, params.mutation_probs),
    )


def _child(u: Array, poses: Pose, fitness: Array, weights: Array, params: Params) -> Pose:
    """Selection and breeding of one child from NUM_UNIFORMS uniforms and poses ([C, 3] fields)."""
    parent1, parent2 = select_parents(u[:2], weights, fitness)
    pick = lambda index: jax.tree.map(lambda x: x[index], poses)  # noqa: E731
    return breed(u[2:], pick(parent1), pick(parent2), params)


def ask(
    key: PRNGKey, population: Population, params: Params, config: Config, epoch: Array
) -> Tuple[Pose, Array, Population]:
    """Breeds one epoch of EGPS children.

    Args:
      key: PRNG key (consumed).
      population: the population at the start of the epoch.
      params: `Params`.
      config: `Config`.
      epoch: the current epoch (unused: the operators do not change over epochs).

    Returns:
      children: `Pose` with [children_per_epoch, 3] fields.
      child_mask: bool [children_per_epoch], all True unless fewer than two views have a finite
        score (then all False; the children are still finite poses).
      population: unchanged.
    """
    del epoch
    n = config.children_per_epoch
    fitness = population.fitness
    weights, can_breed = parent_weights(fitness, params.rank_bias)
    uniforms = uniform_rows(key, n, NUM_UNIFORMS)
    children = jax.vmap(_child, in_axes=(0, None, None, None, None))(
        uniforms, population.poses, fitness, weights, params
    )
    return children, jnp.broadcast_to(can_breed, (n,)), population


METHOD = SearchMethod(name="egps", params_type=Params, config_type=Config, ask_fn=ask)
