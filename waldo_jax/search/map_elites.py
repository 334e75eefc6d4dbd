"""MAP-Elites (Mouret & Clune, 2015) on camera poses: many good views from different places, not one.

The archive (`search.archive`) has one cell per (azimuth, elevation, distance band) of a camera seen
from the scene's focus in the scene's own up frame, and keeps each cell's best view (its elite). It
starts from the scored training views (`init`); each epoch `ask` first files the previous epoch's
children into it (reading their poses and fitness from the population, so a `+refine` method's refined
children are filed where they really are), then draws `children_per_epoch` children: two elites per
child, chosen among the filled cells with weights ((h - rank) / h) ** `elite_bias` (h filled cells,
rank 0 the best; `elite_bias` 0 is MAP-Elites' uniform choice), the better one first, then one of two
variation operators:

  * with probability `line_probability`, Iso+LineDD (Vassiliades & Mouret, 2018) on (origin, look-at
    point): x1 + iso_sigma * r * N(0, I) + line_sigma * (x2 - x1) * N(0, 1), r the training cameras'
    median distance to the focus, the first parent's up: steps out of and between cells;
  * else the paper's EGPS breeding of the two elites (`egps.breed`: crossover, then mutation by
    +-nabla_scale times their difference): a child between two good views of different cells.

The population holds every view, so the archive is an index into it: `archive.archive_of` of the final
population is the archive the method ends with (tested), and `explore` reports it for every method.
As QDax's `MapElitesRepertoire` and emitters, written here on the population (docs/design.md,
"Search > MAP-Elites": why not QDax itself, the defaults and what they were measured against).
"""

from __future__ import annotations

import dataclasses
from typing import Any, Optional, Tuple

import flax.struct
import jax
import jax.numpy as jnp

from waldo_jax.search import egps
from waldo_jax.search.archive import Archive, ViewGrid, archive_of, merge
from waldo_jax.search.method import SearchMethod, check_options
from waldo_jax.search.population import Population, draw_index, uniform_rows
from waldo_jax.types import Array, Pose, PRNGKey

__all__ = [
    "NUM_UNIFORMS",
    "NUM_NORMALS",
    "Params",
    "Config",
    "MapElitesState",
    "elite_weights",
    "init",
    "ask",
    "METHOD",
]


@flax.struct.dataclass
class Params:
    """Numeric hyper-parameters of MAP-Elites (a pytree: a sweep can vmap over them).

    Attributes:
      elite_bias: float32 [], exponent of the rank weights of the filled cells (0: uniform, as MAP-Elites).
      line_probability: float32 [], the share of children made by Iso+LineDD (the rest by EGPS breeding).
      iso_sigma: float32 [], Iso+LineDD's isotropic Gaussian step per coordinate of origin and look-at
        point, in units of the training cameras' median distance to the focus.
      line_sigma: float32 [], Iso+LineDD's spread along the line from the first parent to the second.
      breeding: `egps.Params`, the EGPS operators' (mutation probabilities, nabla scale).
    """

    elite_bias: Array = flax.struct.field(default_factory=lambda: jnp.asarray(1.0, jnp.float32))
    line_probability: Array = flax.struct.field(default_factory=lambda: jnp.asarray(0.5, jnp.float32))
    iso_sigma: Array = flax.struct.field(default_factory=lambda: jnp.asarray(0.1, jnp.float32))
    line_sigma: Array = flax.struct.field(default_factory=lambda: jnp.asarray(0.2, jnp.float32))
    breeding: egps.Params = flax.struct.field(default_factory=egps.Params)


# Uniform numbers one child consumes: 2 elites, 1 operator choice, 12 for EGPS breeding; and 7 normals.
NUM_UNIFORMS = 15
NUM_NORMALS = 7


@dataclasses.dataclass(frozen=True)
class Config:
    """Static settings of MAP-Elites.

    Attributes:
      children_per_epoch: poses proposed per epoch.
      grid: the archive's cells (`ViewGrid`; `explore` passes `ExploreConfig.grid`).
    """

    children_per_epoch: int
    grid: ViewGrid = ViewGrid()

    # The options `create` accepts besides children_per_epoch and epochs.
    OPTIONS = ("grid",)

    def __post_init__(self):
        if self.children_per_epoch < 1:
            raise ValueError(f"children_per_epoch must be >= 1, got {self.children_per_epoch}")
        if not isinstance(self.grid, ViewGrid):
            raise ValueError(f"grid must be a ViewGrid, got {type(self.grid).__name__}")

    @classmethod
    def create(
        cls, children_per_epoch: int, epochs: Optional[int] = None, method: Optional[str] = None, **options: Any
    ) -> "Config":
        """The config for `children_per_epoch` children (`epochs` unused); `grid` is the only option."""
        del epochs
        check_options(method, options, cls.OPTIONS)
        return cls(children_per_epoch=int(children_per_epoch), **options)


@flax.struct.dataclass
class MapElitesState:
    """The method's state: the archive, an index of the population's best view per cell."""

    archive: Archive


def init(key: PRNGKey, population: Population, params: Params, config: Config) -> MapElitesState:
    """The archive of the training views (the key is not used)."""
    del key, params
    train = population.is_train
    slots = jnp.arange(population.capacity, dtype=jnp.int32)
    fitness = jnp.where(train, population.fitness, -jnp.inf)
    return MapElitesState(archive=archive_of(fitness, population.c2w, slots, population.frame, config.grid))


def _file_last_epoch(population: Population, archive: Archive, epoch: Array, n: int, grid: ViewGrid) -> Archive:
    """`archive` with the children of epoch - 1 filed (none before epoch 2)."""
    offset = population.num_train + jnp.maximum(epoch - 2, 0) * n
    take = lambda x: jax.lax.dynamic_slice_in_dim(x, offset, n)  # noqa: E731
    fitness = jnp.where(epoch >= 2, take(population.fitness), -jnp.inf)
    slots = offset + jnp.arange(n, dtype=jnp.int32)
    return merge(archive, archive_of(fitness, take(population.c2w), slots, population.frame, grid))


def elite_weights(archive: Archive, elite_bias: Array) -> Array:
    """Parent weights [M] of the cells: ((h - rank) / h) ** elite_bias for the h filled ones, 0 for empty ones."""
    m = archive.fitness.shape[0]
    order = jnp.argsort(-archive.fitness, stable=True)
    rank = jnp.zeros(m, jnp.int32).at[order].set(jnp.arange(m, dtype=jnp.int32))
    filled = archive.filled
    h = jnp.maximum(jnp.sum(filled, dtype=jnp.int32), 1)
    relative = (h - rank).astype(jnp.float32) / h.astype(jnp.float32)
    return jnp.where(filled, jnp.power(jnp.maximum(relative, 1e-30), elite_bias), 0.0)


def _child(u: Array, z: Array, poses: Pose, archive: Archive, weights: Array, scale: Array, params: Params) -> Pose:
    """One child from NUM_UNIFORMS uniforms u and NUM_NORMALS normals z (the module docstring)."""
    a, b = draw_index(u[0], weights), draw_index(u[1], weights)
    first_better = archive.fitness[a] >= archive.fitness[b]
    first = jnp.where(first_better, archive.slot[a], archive.slot[b])
    second = jnp.where(first_better, archive.slot[b], archive.slot[a])
    pick = lambda slot: jax.tree.map(lambda x: x[slot], poses)  # noqa: E731
    parent1, parent2 = pick(first), pick(second)
    x1 = jnp.concatenate([parent1.origin, parent1.target])
    x2 = jnp.concatenate([parent2.origin, parent2.target])
    x = x1 + params.iso_sigma * scale * z[:6] + params.line_sigma * (x2 - x1) * z[6]
    line = Pose(origin=x[:3], target=x[3:], up=parent1.up)
    bred = egps.breed(u[3:15], parent1, parent2, params.breeding)
    use_line = u[2] < params.line_probability
    return jax.tree.map(lambda p, q: jnp.where(use_line, p, q), line, bred)


def ask(
    key: PRNGKey, population: Population, state: MapElitesState, params: Params, config: Config, epoch: Array, objective
) -> Tuple[Pose, Array, Population, MapElitesState]:
    """Files the last epoch's children, then draws this epoch's from the archive's elites.

    Args:
      key: PRNG key (consumed: one block of uniforms, one of normals).
      population: the population at the start of the epoch.
      state: `MapElitesState`.
      params: `Params`.
      config: `Config`.
      epoch: the current epoch (1-based; epoch e files the children of epoch e - 1).
      objective: unused.

    Returns:
      children: `Pose` with [children_per_epoch, 3] fields.
      child_mask: bool [children_per_epoch], all True unless the archive is empty (then all False).
      population: unchanged.
      state: the archive with the last epoch's children filed.
    """
    del objective
    n = config.children_per_epoch
    archive = _file_last_epoch(population, state.archive, epoch, n, config.grid)
    weights = elite_weights(archive, params.elite_bias)
    uniform_key, normal_key = jax.random.split(key)
    uniforms = uniform_rows(uniform_key, n, NUM_UNIFORMS)
    normals = jax.random.normal(normal_key, (n * NUM_NORMALS,)).reshape(n, NUM_NORMALS)
    children = jax.vmap(_child, in_axes=(0, 0, None, None, None, None, None))(
        uniforms, normals, population.poses, archive, weights, population.frame.radius, params
    )
    can_breed = jnp.any(archive.filled)
    return children, jnp.broadcast_to(can_breed, (n,)), population, MapElitesState(archive=archive)


def _no_tell(key: PRNGKey, state: MapElitesState, fitness: Array, params: Params, config: Config) -> MapElitesState:
    """The state as it was: the children are filed by the next `ask`, from the population."""
    del key, fitness, params, config
    return state


METHOD = SearchMethod(
    name="map-elites", params_type=Params, config_type=Config, ask_fn=ask, init_fn=init, tell_fn=_no_tell
)
