"""CVIR / mCVIR, budgets and the population buffer of waldo_jax.search (hand-computed cases)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

# Importing waldo_jax first sets the XLA flag it needs before JAX starts its CPU backend.
from waldo_jax.cameras import look_at
from waldo_jax.search import BUDGETS, ExploreConfig, budget_children, cvir, mcvir, mean_top_n
from waldo_jax.search.metrics import best_score, epoch_metrics, population_cvir, population_mcvir
from waldo_jax.search.population import (
    draw_index,
    init_population,
    top_k_indices,
    training_look_at,
    training_poses,
    write_children,
)
from waldo_jax.types import Pose

import jax  # noqa: E402  (after waldo_jax, see above)
import jax.numpy as jnp  # noqa: E402

NAN, INF = float("nan"), float("inf")

# ------------------------------------------------------------------------------------------------
# CVIR and mCVIR


def f(x):
    return float(np.asarray(x))


@pytest.mark.slow
def test_cvir_max_direction():
    train = [1.0, 2.0, 4.0]
    all_scores = train + [5.0, NAN, 3.0, INF]  # NaN and inf are failures, not improvements
    assert f(cvir(all_scores, train)) == pytest.approx(100 * (5 - 4) / 4)
    # best two: train (4 + 2) / 2 = 3, all (5 + 4) / 2 = 4.5
    assert f(mcvir(all_scores, train, n=2)) == pytest.approx(100 * (4.5 - 3) / 3)
    # N larger than the usable scores: the mean is over those available.
    assert f(mcvir(all_scores, train, n=10)) == pytest.approx(100 * (15 / 5 - 7 / 3) / (7 / 3))


@pytest.mark.slow
def test_cvir_min_direction_positive_means_better():
    train = [4.0, 2.0, 8.0]
    all_scores = train + [1.5, NAN, -INF, 9.0]
    # 100 * (min(train) - min(all)) / |min(train)|
    assert f(cvir(all_scores, train, direction="min")) == pytest.approx(100 * (2 - 1.5) / 2)
    # two lowest: train (2 + 4) / 2 = 3, all (1.5 + 2) / 2 = 1.75
    assert f(mcvir(all_scores, train, n=2, direction="min")) == pytest.approx(100 * (3 - 1.75) / 3)
    # no improvement is 0, not negative
    assert f(cvir(train + [5.0], train, direction="min")) == 0.0


def test_cvir_negative_scores_use_the_absolute_value():
    train = [-8.0, -4.0]
    assert f(cvir(train + [-2.0], train)) == pytest.approx(100 * (-2 + 4) / 4)
    assert f(cvir(train + [-10.0], train, direction="min")) == pytest.approx(100 * (-8 + 10) / 8)


def test_cvir_undefined_cases_and_masks():
    assert np.isnan(f(cvir([1.0, NAN], [NAN])))  # no usable training score
    assert np.isnan(f(cvir([0.0, 1.0], [0.0])))  # relative to zero
    # Masks exclude entries (an invalid 9.0 does not count).
    assert f(cvir([1.0, 2.0, 9.0], [1.0, 2.0], all_valid=[True, True, False])) == 0.0
    assert f(best_score([3.0, NAN, 1.0], direction="min")) == 1.0
    assert f(mean_top_n([3.0, NAN, 1.0, 2.0], n=2)) == pytest.approx(2.5)
    assert np.isnan(f(best_score([NAN, NAN])))


@jax.jit
def _hand_population():
    """4 ring views (min direction, one NaN) and two epochs of 3 children, one of them masked."""
    angle = jnp.arange(4) * (jnp.pi / 2)
    origins = jnp.stack([3 * jnp.cos(angle), jnp.ones(4), 3 * jnp.sin(angle)], -1)
    up = jnp.array([0.0, 1.0, 0.0])
    c2w = jax.vmap(look_at, in_axes=(0, None, None))(origins, jnp.zeros(3), up)
    poses = training_poses(c2w, focus=jnp.zeros(3))
    population = init_population(poses, jnp.asarray([1.0, 2.0, NAN, 4.0]), 10, "min", train_c2w=c2w)
    for epoch, offset, scores, mask in (
        (1, 4, [0.5, NAN, 3.0], [True, True, True]),
        (2, 7, [0.25, -9.0, 7.0], [True, False, True]),
    ):  # -9 is masked
        child = Pose(origin=jnp.full((3, 3), float(epoch)), target=jnp.zeros((3, 3)), up=jnp.tile(up, (3, 1)))
        child_c2w = jax.vmap(look_at)(child.origin, child.target, child.up)
        population = write_children(population, child, child_c2w, jnp.asarray(scores), jnp.asarray(mask), epoch, offset)
    return (
        population,
        population_cvir(population),
        population_mcvir(population, 2),
        epoch_metrics(population, epochs=2, n=2),
        top_k_indices(population, 8),
    )


@pytest.mark.slow
def test_population_metrics_and_epoch_curves():
    population, population_cvir_value, population_mcvir_value, curves, (indices, ok) = _hand_population()
    np.testing.assert_array_equal(np.asarray(population.epoch), [0, 0, 0, 0, 1, 1, 1, 2, -1, 2])
    np.testing.assert_array_equal(np.asarray(population.valid), [1, 1, 1, 1, 1, 1, 1, 1, 0, 1])
    # min direction: best training 1.0, best overall 0.25 (the masked -9 never counts)
    assert f(population_cvir_value) == pytest.approx(100 * (1.0 - 0.25) / 1.0)
    # two lowest: training (1 + 2) / 2 = 1.5; all (0.25 + 0.5) / 2 = 0.375
    assert f(population_mcvir_value) == pytest.approx(100 * (1.5 - 0.375) / 1.5)
    np.testing.assert_allclose(np.asarray(curves.best), [1.0, 0.5, 0.25])
    np.testing.assert_allclose(np.asarray(curves.mean_top_n), [1.5, 0.75, 0.375])
    np.testing.assert_array_equal(np.asarray(curves.num_scored), [4, 3, 2])
    np.testing.assert_array_equal(np.asarray(curves.num_failed), [1, 1, 0])
    # Top-k never selects NaN, masked or empty slots; surplus entries are flagged.
    assert np.asarray(indices)[np.asarray(ok)].tolist() == [7, 4, 0, 1, 6, 3, 9]
    assert np.asarray(ok).tolist() == [True] * 7 + [False]


@pytest.mark.slow
def test_draw_index_never_draws_zero_weights():
    weights = jnp.asarray([0.0, 2.0, 0.0, 1.0, 1.0, 0.0])
    u = jnp.concatenate([jnp.linspace(0.0, 1.0, 1001)[:-1], jnp.asarray([0.9999999])])
    drawn = np.asarray(jax.vmap(draw_index, in_axes=(0, None))(u, weights))
    assert set(drawn.tolist()) == {1, 3, 4}
    np.testing.assert_allclose([np.mean(drawn == i) for i in (1, 3, 4)], [0.5, 0.25, 0.25], atol=0.005)


# ------------------------------------------------------------------------------------------------
# Training look-at points

_look_at_point = jax.jit(training_look_at)
_look_at_matrix = jax.jit(look_at)
coords = st.floats(-5.0, 5.0, allow_nan=False, width=32)


@settings(max_examples=30, deadline=None)
@given(st.tuples(coords, coords, coords), st.tuples(coords, coords, coords), st.tuples(coords, coords, coords))
def test_training_look_at_is_on_the_axis_in_front(origin, target, focus):
    origin, target, focus = (np.asarray(v, np.float32) for v in (origin, target, focus))
    c2w = _look_at_matrix(jnp.asarray(origin), jnp.asarray(target), jnp.array([0.0, 1.0, 0.0]))
    point = np.asarray(_look_at_point(c2w, jnp.asarray(focus), 0.1), np.float64)
    forward = -np.asarray(c2w, np.float64)[:3, 2]
    offset = point - origin
    depth = float(offset @ forward)
    np.testing.assert_allclose(offset, depth * forward, atol=1e-4)  # on the optical axis
    dist = float(np.linalg.norm(focus - origin))
    assert depth >= max(0.1 * dist, 1e-6) - 1e-4  # in front, at least the minimum depth
    # When the focus is well in front of the camera, it is the closest axis point to the focus.
    along = float((focus - origin) @ forward)
    if along > 0.1 * dist + 1e-3:
        assert depth == pytest.approx(along, abs=1e-3)


# ------------------------------------------------------------------------------------------------
# Budgets


@pytest.mark.parametrize("n_train", [20, 50, 65, 90, 185])
@pytest.mark.parametrize("budget", ["low", "high"])
def test_budget_totals(n_train, budget):
    low, high = BUDGETS[budget]
    children = budget_children(n_train, budget)
    assert children >= 1
    assert low <= n_train + 5 * children <= high
    config = ExploreConfig(budget=budget).resolve(n_train)
    assert config.children_per_epoch == children
    assert config.capacity(n_train) == n_train + 5 * children


def test_budget_overrides_and_errors():
    assert (900, 1000) == BUDGETS["high"] and (250, 300) == BUDGETS["low"]
    assert ExploreConfig(children_per_epoch=7).resolve(20).children_per_epoch == 7  # explicit wins
    assert 250 <= 20 + 4 * budget_children(20, "low", epochs=4) <= 300
    assert 100 <= 30 + 5 * budget_children(30, (100, 110)) <= 110
    assert budget_children(290, "low") == 1  # training alone within the budget: one child per epoch
    with pytest.raises(ValueError, match="300 training views"):
        budget_children(300, "low")
    with pytest.raises(ValueError, match="1000"):
        budget_children(1200, "high")
    with pytest.raises(ValueError, match="budget"):
        ExploreConfig(budget="medium")
    with pytest.raises(ValueError, match="whole number"):
        budget_children(20, (101, 104), epochs=5)
