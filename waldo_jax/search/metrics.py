"""The exploration metrics of "Finding Waldo" (MMSys'24): CVIR, mCVIR and per-epoch curves.

CVIR = 100 * (op(S_all) - op(S_train)) / |op(S_train)| (criterion value improvement ratio), with
S_train the training views' scores, S_all those of every view of the run and op = max; mCVIR is the
same on the mean of the best N = 10 scores of each set. dCVIR is the gain of the mean of the k best
*different shots* (`views.distinct_top_k`) over the best training view. For a "min" criterion both are computed on
the signed fitness F = sign * score, 100 * (F_all - F_train) / |F_train|, so that a positive value
still means an improvement. Only valid, finite scores count; a ratio is NaN when undefined. `cvir`
and `mcvir` take score arrays; `population_cvir`, `population_mcvir` and `epoch_metrics` a population.

Both directions in full and the edge cases: see docs/design.md, section "Search > CVIR and mCVIR".
"""

from __future__ import annotations

from typing import Optional

import flax.struct
import jax
import jax.numpy as jnp

from waldo_jax.search.population import Population, direction_sign
from waldo_jax.types import Array

__all__ = [
    "EpochMetrics",
    "best_score",
    "mean_top_n",
    "cvir",
    "mcvir",
    "population_cvir",
    "population_mcvir",
    "shot_gains",
    "epoch_metrics",
]


@flax.struct.dataclass
class EpochMetrics:
    """Curves over a run, index 0 = the training views, index e = after epoch e.

    Attributes:
      best: float32 [E + 1], the best raw score so far (by the direction).
      mean_top_n: float32 [E + 1], the mean of the best N raw scores so far.
      num_scored: int32 [E + 1], views scored in that epoch (training views at index 0).
      num_failed: int32 [E + 1], those of them whose score was NaN or infinite.
    """

    best: Array
    mean_top_n: Array
    num_scored: Array
    num_failed: Array


def _fitness(scores: Array, valid: Optional[Array], sign: float) -> Array:
    """Signed scores, -inf where invalid or not finite."""
    scores = jnp.asarray(scores, jnp.float32)
    usable = jnp.isfinite(scores) if valid is None else (jnp.asarray(valid, bool) & jnp.isfinite(scores))
    return jnp.where(usable, sign * scores, -jnp.inf)


def _best_fitness(fitness: Array) -> Array:
    return jnp.max(fitness, initial=-jnp.inf)


def _mean_top_fitness(fitness: Array, n: int) -> Array:
    """Mean of the n highest finite fitness values (fewer if fewer are finite; NaN if none)."""
    values, _ = jax.lax.top_k(fitness, min(n, fitness.shape[0]))
    finite = jnp.isfinite(values)
    count = jnp.sum(finite)
    total = jnp.sum(jnp.where(finite, values, 0.0))
    return jnp.where(count > 0, total / jnp.maximum(count, 1), jnp.nan)


def _ratio(f_all: Array, f_train: Array) -> Array:
    """100 * (f_all - f_train) / |f_train|, NaN when undefined."""
    defined = jnp.isfinite(f_train) & jnp.isfinite(f_all) & (f_train != 0.0)
    safe_train = jnp.where(defined, f_train, 1.0)
    return jnp.where(defined, 100.0 * (f_all - safe_train) / jnp.abs(safe_train), jnp.nan)


def best_score(scores: Array, valid: Optional[Array] = None, direction: str = "max") -> Array:
    """The best usable raw score of scores [P] (max or min by direction); NaN when none is usable."""
    sign = direction_sign(direction)
    best = _best_fitness(_fitness(scores, valid, sign))
    return jnp.where(jnp.isfinite(best), sign * best, jnp.nan)


def mean_top_n(scores: Array, n: int = 10, valid: Optional[Array] = None, direction: str = "max") -> Array:
    """Mean of the best n usable raw scores of scores [P] (fewer if fewer are usable; NaN if none)."""
    sign = direction_sign(direction)
    return sign * _mean_top_fitness(_fitness(scores, valid, sign), n)


def cvir(
    all_scores: Array,
    train_scores: Array,
    direction: str = "max",
    all_valid: Optional[Array] = None,
    train_valid: Optional[Array] = None,
) -> Array:
    """CVIR in percent (see docs/design.md, "Search" for the "min" direction).

    Args:
      all_scores: [P] raw scores of every view of the run, the training views included.
      train_scores: [N] raw scores of the training views.
      direction: "max" or "min".
      all_valid, train_valid: optional bool masks of the usable entries (else all entries count).

    Returns:
      float32 [], NaN when undefined.
    """
    sign = direction_sign(direction)
    return _ratio(
        _best_fitness(_fitness(all_scores, all_valid, sign)), _best_fitness(_fitness(train_scores, train_valid, sign))
    )


def mcvir(
    all_scores: Array,
    train_scores: Array,
    n: int = 10,
    direction: str = "max",
    all_valid: Optional[Array] = None,
    train_valid: Optional[Array] = None,
) -> Array:
    """mCVIR in percent: CVIR on the mean of the best n scores of each set (arguments as `cvir`)."""
    sign = direction_sign(direction)
    return _ratio(
        _mean_top_fitness(_fitness(all_scores, all_valid, sign), n),
        _mean_top_fitness(_fitness(train_scores, train_valid, sign), n),
    )


def population_cvir(population: Population) -> Array:
    """CVIR of a population: S_all = every scored slot, S_train = its training slots."""
    fitness = population.fitness
    return _ratio(_best_fitness(fitness), _best_fitness(jnp.where(population.is_train, fitness, -jnp.inf)))


def population_mcvir(population: Population, n: int = 10) -> Array:
    """mCVIR of a population (see `population_cvir`)."""
    fitness = population.fitness
    return _ratio(
        _mean_top_fitness(fitness, n), _mean_top_fitness(jnp.where(population.is_train, fitness, -jnp.inf), n)
    )


def shot_gains(population: Population, indices: Array, ok: Array) -> tuple:
    """dCVIR and how many of a set of views beat the best training view.

    Args:
      population: the population.
      indices: int32 [k] slots of the set (e.g. the distinct top-k), best first.
      ok: bool [k], which entries are real.

    Returns:
      (dcvir, beating): float32 [] 100 * (mean fitness of the set - best training fitness) / |best
      training fitness| (NaN when undefined), and int32 [] the entries whose fitness is strictly
      above the best training view's.
    """
    fitness = jnp.where(ok, population.fitness[indices], -jnp.inf)
    train_best = _best_fitness(jnp.where(population.is_train, population.fitness, -jnp.inf))
    finite = jnp.isfinite(fitness)
    count = jnp.sum(finite)
    mean = jnp.where(count > 0, jnp.sum(jnp.where(finite, fitness, 0.0)) / jnp.maximum(count, 1), jnp.nan)
    return _ratio(mean, train_best), jnp.sum(finite & (fitness > train_best), dtype=jnp.int32)


def epoch_metrics(population: Population, epochs: int, n: int = 10) -> EpochMetrics:
    """Per-epoch curves of a population, from the slots' birth epochs.

    Args:
      population: the population after (or during) the run.
      epochs: E, the number of epochs (static).
      n: N of the mean of the best N.

    Returns:
      `EpochMetrics` with [E + 1] curves.
    """
    sign = direction_sign(population.direction)
    fitness = population.fitness

    def after(epoch):
        so_far = (population.epoch >= 0) & (population.epoch <= epoch)
        f = jnp.where(so_far, fitness, -jnp.inf)
        best = _best_fitness(f)
        born = population.valid & (population.epoch == epoch)
        return (
            jnp.where(jnp.isfinite(best), sign * best, jnp.nan),
            sign * _mean_top_fitness(f, n),
            jnp.sum(born, dtype=jnp.int32),
            jnp.sum(born & ~jnp.isfinite(population.score), dtype=jnp.int32),
        )

    best, top_n, scored, failed = jax.vmap(after)(jnp.arange(epochs + 1, dtype=jnp.int32))
    return EpochMetrics(best=best, mean_top_n=top_n, num_scored=scored, num_failed=failed)
