"""Any evosax strategy as a search method (`evosax:CMA_ES`, `evosax:SNES`, `evosax:SimpleGA`, ...).

The strategy searches the pose vector EGPS breeds, (origin, look-at point, up) [9], normalised by
the training poses: x = (pose - shift) / scale with `shift` their mean and `scale` their spread per
coordinate (floored: `_SCALE_FLOOR` of the scene extent for positions, of 1 for up), so that the
strategy's unit step is "about as far as the training cameras are apart" on every axis. It starts
from the training poses: a distribution-based strategy (CMA-ES, SNES, ...) at the best training
pose with `Params.std_init` (1.0: the training spread), a population-based one (SimpleGA, PSO, DE, ...)
from the best `children_per_epoch` training poses (repeated when there are fewer) and their fitness.
Each epoch asks `children_per_epoch` vectors (its population size), and tells their fitness back
negated (evosax minimises; a failed or masked child gets `WORST`, far worse than any score), inside
the exploration's one `lax.scan`. Choices and their reasons: docs/design.md, "Search > evosax strategies".
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Any, Optional, Tuple

import flax.struct
import jax
import jax.numpy as jnp

from waldo_jax.search import grs
from waldo_jax.search.method import SearchMethod, check_options
from waldo_jax.search.population import Population, top_k_indices
from waldo_jax.types import Array, Pose, PRNGKey

__all__ = [
    "PREFIX",
    "POSE_DIM",
    "WORST",
    "Params",
    "Config",
    "EvosaxState",
    "strategy_names",
    "make_strategy",
    "is_distribution_based",
    "strategy_params",
    "pose_scaling",
    "to_vector",
    "to_pose",
    "init",
    "ask",
    "tell",
    "evosax_method",
]

PREFIX = "evosax:"
POSE_DIM = 9
_SCALE_FLOOR = 0.05
# evosax minimises: a failed child's loss. Large but finite, so that rankings and means stay finite.
WORST = 1e30


@flax.struct.dataclass
class Params:
    """Numeric settings of an evosax method (a pytree).

    Attributes:
      std_init: float32 [], the initial search std in units of the training spread, for the
        strategies whose params have a `std_init` (CMA-ES, SNES, xNES, ...); others keep their own.
    """

    std_init: Array = flax.struct.field(default_factory=lambda: jnp.asarray(1.0, jnp.float32))


@dataclasses.dataclass(frozen=True)
class Config:
    """Static settings: the evosax strategy's name and its population size (= children per epoch)."""

    strategy: str
    children_per_epoch: int

    def __post_init__(self):
        if self.children_per_epoch < 2:
            raise ValueError(
                f"an evosax strategy needs a population of at least 2, got {self.children_per_epoch} children per epoch"
            )
        make_strategy(self.strategy, self.children_per_epoch)  # raises a clear error for an unusable one


@flax.struct.dataclass
class EvosaxState:
    """An evosax method's state across epochs.

    Attributes:
      strategy: the evosax strategy's own state.
      asked: float32 [children_per_epoch, 9], the last vectors asked (told back with their fitness).
      shift, scale: float32 [9], the normalisation x = (pose - shift) / scale.
    """

    strategy: Any
    asked: Array
    shift: Array
    scale: Array


def strategy_names() -> Tuple[str, ...]:
    """The evosax strategies by name (evosax's `algorithms` registry)."""
    from evosax.algorithms import algorithms

    return tuple(sorted(algorithms))


@functools.lru_cache(maxsize=None)
def make_strategy(name: str, population_size: int, dim: int = POSE_DIM):
    """The evosax strategy `name` for `population_size` solutions of `dim` numbers (one object per
    arguments, so compilations are shared). Raises ValueError naming an unknown or unusable strategy."""
    from evosax.algorithms import algorithms

    if name not in algorithms:
        raise ValueError(f"unknown evosax strategy {name!r}; choose one of {', '.join(strategy_names())}")
    try:
        # Cached: built eagerly even when first asked for inside a jit trace, so no tracer is kept.
        with jax.ensure_compile_time_eval():
            return algorithms[name](population_size=population_size, solution=jnp.zeros(dim, jnp.float32))
    except TypeError as error:  # strategies that need more than a population size (SV_CMA_ES, RandomSearch)
        raise ValueError(f"evosax strategy {name!r} cannot run as a pose search: {error}") from None
    except (AssertionError, ValueError) as error:  # a population size it refuses (odd for mirrored sampling, < 4)
        reason = str(error).strip().rstrip(".") or "an assertion of evosax's"
        raise ValueError(
            f"evosax strategy {name!r} cannot take a population of {population_size} ({reason}); "
            "set --children-per-epoch (or --paths-per-epoch) to a size it takes"
        ) from None


def is_distribution_based(strategy) -> bool:
    """True for evosax's distribution-based strategies (CMA-ES, SNES, ...): they start from one mean."""
    from evosax.algorithms.distribution_based.base import DistributionBasedAlgorithm

    return isinstance(strategy, DistributionBasedAlgorithm)


# What a trace raises where a strategy's code needs a concrete value.
_CONCRETE_ONLY = (
    jax.errors.ConcretizationTypeError,
    jax.errors.TracerIntegerConversionError,
    jax.errors.TracerArrayConversionError,
)


def strategy_params(strategy, params: Params):
    """The strategy's default evosax params with `Params.std_init` where it has one.

    Defaults that need concrete sizes (LM_MA_ES takes `int()` of a `jnp` expression of the dimension)
    cannot be traced: they are built eagerly, from the static sizes alone."""
    try:
        defaults = strategy.default_params
    except _CONCRETE_ONLY:
        with jax.ensure_compile_time_eval():
            defaults = strategy.default_params
    if "std_init" in getattr(defaults, "__dataclass_fields__", {}):
        return defaults.replace(std_init=jnp.asarray(params.std_init, jnp.float32))
    return defaults


def to_vector(poses: Pose) -> Array:
    """Poses ([..., 3] fields) as vectors [..., 9]: origin, look-at point, up."""
    return jnp.concatenate([poses.origin, poses.target, poses.up], axis=-1)


def to_pose(vectors: Array) -> Pose:
    """Vectors [..., 9] as a `Pose` (the inverse of `to_vector`)."""
    return Pose(origin=vectors[..., :3], target=vectors[..., 3:6], up=vectors[..., 6:])


def pose_scaling(population: Population) -> Tuple[Array, Array]:
    """(shift, scale) [9] of the normalisation, from the training slots of the population."""
    train = population.is_train[:, None]
    vectors = to_vector(population.poses)
    count = jnp.maximum(jnp.sum(train), 1)
    shift = jnp.sum(jnp.where(train, vectors, 0.0), axis=0) / count
    spread = jnp.sqrt(jnp.sum(jnp.where(train, (vectors - shift) ** 2, 0.0), axis=0) / count)
    low, high = grs.origin_bounds(population)
    extent = jnp.maximum(jnp.max(high - low), 1e-6)
    floor = _SCALE_FLOOR * jnp.concatenate([jnp.full((6,), extent), jnp.ones((3,))])
    return shift, jnp.maximum(spread, floor)


def init(key: PRNGKey, population: Population, params: Params, config: Config) -> EvosaxState:
    """The strategy's state before epoch 1, started from the training poses (the module docstring)."""
    strategy = make_strategy(config.strategy, config.children_per_epoch)
    shift, scale = pose_scaling(population)
    n = config.children_per_epoch
    order, ok = top_k_indices(population, min(n, population.num_train))
    order = jnp.tile(order, -(-n // order.shape[0]))[:n]  # the best training poses, repeated to n
    ok = jnp.tile(ok, -(-n // ok.shape[0]))[:n]
    start = (to_vector(population.poses)[order] - shift) / scale  # [n, 9]
    es_params = strategy_params(strategy, params)
    if is_distribution_based(strategy):
        es_state = strategy.init(key, start[0], es_params)
    else:
        loss = jnp.where(ok, -population.fitness[order], WORST)
        es_state = strategy.init(key, start, loss, es_params)
    return EvosaxState(strategy=es_state, asked=jnp.zeros((n, POSE_DIM), jnp.float32), shift=shift, scale=scale)


def ask(
    key: PRNGKey, population: Population, state: EvosaxState, params: Params, config: Config, epoch: Array, objective
) -> Tuple[Pose, Array, Population, EvosaxState]:
    """One epoch's children: the strategy's `children_per_epoch` asked vectors as poses (all real)."""
    del epoch, objective
    strategy = make_strategy(config.strategy, config.children_per_epoch)
    asked, es_state = strategy.ask(key, state.strategy, strategy_params(strategy, params))
    asked = jnp.asarray(asked, jnp.float32)
    children = to_pose(state.shift + state.scale * asked)
    return (
        children,
        jnp.ones(config.children_per_epoch, bool),
        population,
        state.replace(strategy=es_state, asked=asked),
    )


def tell(key: PRNGKey, state: EvosaxState, fitness: Array, params: Params, config: Config) -> EvosaxState:
    """The state after the asked vectors' fitness [children_per_epoch] is told back (negated: evosax minimises)."""
    strategy = make_strategy(config.strategy, config.children_per_epoch)
    loss = jnp.where(jnp.isfinite(fitness), -fitness, WORST)
    es_state, _ = strategy.tell(key, state.asked, loss, state.strategy, strategy_params(strategy, params))
    return state.replace(strategy=es_state)


@dataclasses.dataclass(frozen=True)
class _ConfigFactory:
    strategy: str

    # The options `create` accepts besides children_per_epoch and epochs.
    OPTIONS = ()

    def create(
        self, children_per_epoch: int, epochs: Optional[int] = None, method: str = "evosax", **options: Any
    ) -> Config:
        """The config for `children_per_epoch` children (`epochs` unused); `ConfigError` for any option."""
        del epochs
        check_options(method, options, self.OPTIONS)
        return Config(strategy=self.strategy, children_per_epoch=int(children_per_epoch))


@functools.lru_cache(maxsize=None)
def evosax_method(name: str) -> SearchMethod:
    """The search method "evosax:<name>" (one object per name, so its compilations are reused).

    Raises:
      ValueError: an unknown strategy (the message lists evosax's).
    """
    if name not in strategy_names():
        raise ValueError(f"unknown evosax strategy {name!r}; choose one of {', '.join(strategy_names())}")
    return SearchMethod(
        name=PREFIX + name, params_type=Params, config_type=_ConfigFactory(name), ask_fn=ask, init_fn=init, tell_fn=tell
    )
