"""Beyond the paper's searches: gradient refinement (`search.refine`, the `+refine` methods) and evosax
strategies (`search.strategy`, "evosax:NAME"), on the toy criterion of test_search_explore and on the
room's oracle: refine keeps the best, rejects failures, stays in the box; the budget sums; an evosax
method is deterministic and equals evosax's own ask/tell loop; criteria without a smooth stand-in are
refused.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from waldo_jax.cameras import pose_to_c2w
from waldo_jax.criteria import CriterionContext, CriterionError, make_criterion
from waldo_jax.procedural import make_room, waldo_coverage
from waldo_jax.search import (
    ExploreConfig,
    RefineConfig,
    SceneBox,
    explore,
    explore_loop,
    explore_seeds,
    init_population,
    refine,
    scene_box,
    training_poses,
)
from waldo_jax.search import strategy

import jax  # noqa: E402  (after waldo_jax: XLA flags)
import jax.numpy as jnp  # noqa: E402

from test_search_explore import CONFIG, INITIAL, assert_same, toy_score  # noqa: E402

REFINE = RefineConfig(poses=2, steps=3, step_size=0.05, gradient_cost=2)
REFINE_CONFIG = dataclasses.replace(CONFIG, options={"refine": REFINE})


def _population():
    return init_population(training_poses(INITIAL.c2w), INITIAL.scores, 8, train_c2w=INITIAL.c2w)


def _start(count=4):
    return jax.tree.map(lambda a: a[:count], training_poses(INITIAL.c2w))


def _c2w(poses):
    return jax.vmap(pose_to_c2w)(poses)


@pytest.mark.parametrize("method", ["egps+refine", "grs+refine", "evosax:CMA_ES", "evosax:SimpleGA"])
def test_new_methods_scan_equals_loop_and_rerun_is_bit_identical(method):
    objective = toy_score if method.endswith("+refine") else None
    config = REFINE_CONFIG if method.endswith("+refine") else CONFIG  # refine is the +refine methods' option
    key = jax.random.key(7)
    scanned = explore(key, toy_score, INITIAL, method, config, objective_fn=objective)
    again = explore(key, toy_score, INITIAL, method, config, objective_fn=objective)
    looped = explore_loop(key, toy_score, INITIAL, method, config, objective_fn=objective)
    assert_same(scanned, again)
    assert_same(scanned, looped, atol=1e-5)
    other = explore(jax.random.key(8), toy_score, INITIAL, method, config, objective_fn=objective)
    assert not np.array_equal(np.asarray(other.population.origin), np.asarray(scanned.population.origin))
    assert float(scanned.cvir) > 0.0


def test_refine_keeps_the_best_and_improves_a_smooth_objective():
    start = _start()
    scores = toy_score(_c2w(start))
    box = scene_box(_population())
    result = refine(toy_score, toy_score, start, scores, box, "max", REFINE)
    assert np.all(np.asarray(result.scores) >= np.asarray(scores))
    assert np.all(np.asarray(result.values) > np.asarray(result.start_values))  # the steps went uphill
    assert np.all(np.asarray(result.improved)) and np.all(np.asarray(result.accepted) == REFINE.steps)
    # Each coordinate moved at most steps * step_size scene extents.
    moved = np.abs(np.asarray(result.poses.origin) - np.asarray(start.origin))
    assert np.all(moved <= REFINE.steps * REFINE.step_size * float(box.extent) + 1e-5)


def test_refine_returns_the_start_when_the_exact_score_disagrees():
    """The steps follow the objective, but a refined pose the exact score finds worse is not kept."""
    start = _start()
    exact = lambda c2w: -toy_score(c2w)  # noqa: E731  (gradient steps raise toy_score: the exact score falls)
    scores = exact(_c2w(start))
    result = refine(toy_score, exact, start, scores, scene_box(_population()), "max", REFINE)
    assert not np.any(np.asarray(result.improved))
    np.testing.assert_array_equal(np.asarray(result.scores), np.asarray(scores))
    np.testing.assert_array_equal(np.asarray(result.poses.origin), np.asarray(start.origin))


def test_refine_failures_are_data():
    start = _start()
    scores = toy_score(_c2w(start))
    nan = lambda c2w: jnp.full(c2w.shape[0], jnp.nan)  # noqa: E731
    result = refine(nan, toy_score, start, scores, scene_box(_population()), "max", REFINE)
    np.testing.assert_array_equal(np.asarray(result.poses.origin), np.asarray(start.origin))
    assert np.all(np.isnan(np.asarray(result.values))) and np.all(np.asarray(result.accepted) == 0)
    np.testing.assert_array_equal(np.asarray(result.scores), np.asarray(scores))
    # A box that is the starting points themselves: every step leaves it and is undone.
    origin = np.asarray(start.origin)
    tight = SceneBox(low=jnp.asarray(origin.min(0)), high=jnp.asarray(origin.max(0)), extent=jnp.float32(3.0))
    result = refine(toy_score, toy_score, start, scores, tight, "max", REFINE)
    inside = np.asarray(tight.contains(result.poses.origin))
    assert inside.all()


def test_refine_budget_is_paid_with_children():
    n_train = 24
    for budget, (low, high) in (("low", (250, 300)), ("high", (900, 1000))):
        plain = ExploreConfig(method="egps", budget=budget).cost(n_train)
        refined_config = ExploreConfig(
            method="egps+refine", budget=budget, options={"refine": RefineConfig(gradient_cost=12)}
        )
        refined = refined_config.cost(n_train)
        assert low <= refined["renders"] <= plain["renders"] <= high
        assert plain["renders"] - refined["renders"] < 5  # at most epochs - 1 renders apart
        assert refined["renders"] == (
            refined["training_views"]
            + refined["children"]
            + refined["gradient_evaluations"] * refined["renders_per_gradient_evaluation"]
        )
        assert refined["gradient_evaluations"] == 4 * 4 and plain["gradient_evaluations"] == 0
    with pytest.raises(ValueError, match="refinement costs"):
        ExploreConfig(
            method="egps+refine", options={"refine": RefineConfig(poses=20, steps=10, gradient_cost=12)}
        ).resolve(24)


def test_refine_epoch_writes_refined_children_of_the_best_poses():
    key = jax.random.key(3)
    result = explore(key, toy_score, INITIAL, "egps+refine", REFINE_CONFIG, objective_fn=toy_score)
    population = result.population
    n, epochs = REFINE_CONFIG.children_per_epoch, REFINE_CONFIG.epochs
    before = 8 + (epochs - 1) * n
    last = slice(before, before + n)
    assert np.all(np.asarray(population.valid)[last])
    # The last REFINE.poses children of the last epoch are the best poses before it, best first,
    # moved uphill by at most steps * step_size scene extents per coordinate.
    scores = np.asarray(population.score)
    best = np.argsort(-scores[:before], kind="stable")[: REFINE.poses]
    extent = float(scene_box(_population()).extent)
    refined_origin = np.asarray(population.origin)[last][-REFINE.poses :]
    moved = np.abs(refined_origin - np.asarray(population.origin)[best])
    assert np.all(moved <= REFINE.steps * REFINE.step_size * extent + 1e-5) and np.all(moved.max(-1) > 0)
    assert np.all(scores[last][-REFINE.poses :] > scores[best])


def test_evosax_method_equals_evosax_own_loop():
    """explore's evosax:SNES is evosax's ask/tell loop on the normalised pose vector, key for key.

    (SNES, whose search distribution is diagonal: CMA-ES samples through an eigendecomposition of its
    covariance, whose eigenvectors two separately compiled programs may order or sign differently
    while the eigenvalues are nearly equal, same law but other draws; its scan equals its loop above.)
    """
    from evosax.algorithms import SNES

    key = jax.random.key(11)
    result = explore(key, toy_score, INITIAL, "evosax:SNES", CONFIG)
    n = CONFIG.children_per_epoch
    es = SNES(population_size=n, solution=jnp.zeros(9))
    params = es.default_params.replace(std_init=jnp.float32(1.0))
    population = init_population(
        training_poses(INITIAL.c2w), INITIAL.scores, 8 + CONFIG.epochs * n, train_c2w=INITIAL.c2w
    )
    shift, scale = strategy.pose_scaling(population)
    best = int(np.argmax(np.asarray(INITIAL.scores)))
    mean = (strategy.to_vector(training_poses(INITIAL.c2w))[best] - shift) / scale
    state = es.init(jax.random.fold_in(key, 0), mean, params)
    ask = jax.jit(lambda k, s: es.ask(k, s, params))
    tell = jax.jit(lambda k, x, f, s: es.tell(k, x, f, s, params)[0])
    for epoch in range(1, CONFIG.epochs + 1):
        ask_key, tell_key = jax.random.split(jax.random.fold_in(key, epoch))
        x, state = ask(ask_key, state)
        poses = strategy.to_pose(shift + scale * x)
        scores = toy_score(_c2w(poses))
        state = tell(tell_key, x, -scores, state)
        slots = slice(8 + (epoch - 1) * n, 8 + epoch * n)
        np.testing.assert_allclose(np.asarray(result.population.origin)[slots], np.asarray(poses.origin), atol=1e-4)
        np.testing.assert_allclose(np.asarray(result.population.score)[slots], np.asarray(scores), atol=1e-4)


def test_evosax_seeds_vmap_and_nan_scores_are_never_selected():
    half_nan = lambda c2w: jnp.where(c2w[:, 0, 3] > 0.0, jnp.nan, toy_score(c2w))  # noqa: E731
    keys = jax.vmap(jax.random.key)(jnp.arange(3))
    out = explore_seeds(keys, half_nan, INITIAL, "evosax:SNES", CONFIG)
    single = explore(jax.random.key(1), half_nan, INITIAL, "evosax:SNES", CONFIG)
    np.testing.assert_allclose(
        np.asarray(out.results.population.score[1]), np.asarray(single.population.score), atol=1e-5
    )
    top = np.asarray(out.results.top_scores)[np.asarray(out.results.top_valid)]
    assert np.all(np.isfinite(top))


def test_smooth_oracle_tracks_the_exact_one_and_has_a_gradient():
    room = make_room(0)
    oracle = make_criterion("waldo_oracle", CriterionContext(room=room))
    smooth = oracle.smooth()
    from waldo_jax.pipeline.sources import procedural_source

    source = procedural_source(0, resolution=32, views=8)
    exact = np.asarray(oracle.score_poses(source.train_c2w, source.intrinsics))
    soft = np.asarray(smooth.score_poses(source.train_c2w, source.intrinsics))
    seen = exact > 0.0
    assert seen.any()
    np.testing.assert_allclose(soft[seen], exact[seen], rtol=0.5)  # a smooth stand-in, not the oracle
    c2w = jnp.asarray(source.train_c2w[int(np.argmax(exact))])
    grad = jax.grad(lambda c: waldo_coverage(room, c, source.intrinsics, softness=0.05))(c2w)
    assert np.any(np.asarray(grad[:3, 3]) != 0.0) and np.all(np.isfinite(np.asarray(grad)))


@pytest.mark.parametrize("name", ["niqe", "brisque"])
def test_criteria_without_a_smooth_stand_in_are_refused(name):
    from conftest import require_weights

    require_weights(name)
    criterion = make_criterion(name)
    assert not criterion.differentiable
    with pytest.raises(CriterionError, match=f"criterion '{name}' is not differentiable.*waldo_oracle"):
        criterion.smooth()


def test_unknown_evosax_strategy_lists_the_choices():
    with pytest.raises(ValueError, match="choose one of .*SNES"):
        strategy.evosax_method("NOPE")
    assert "CMA_ES" in strategy.strategy_names()


def test_a_strategy_whose_defaults_need_concrete_sizes_runs_as_a_pose_search():
    """LM_MA_ES computes its default params with `int()` of a `jnp` expression of the dimension: traced, it
    ended `explore` and `path` in a ConcretizationTypeError traceback. Its defaults are now built from the
    static sizes, the same inside a compiled search as outside, and the search runs (and reruns bit for bit)."""
    lm = strategy.make_strategy("LM_MA_ES", CONFIG.children_per_epoch)
    params = strategy.Params()
    eager = strategy.strategy_params(lm, params)
    traced = jax.jit(lambda: strategy.strategy_params(lm, params))()
    jax.tree.map(lambda a, b: np.testing.assert_array_equal(np.asarray(a), np.asarray(b)), eager, traced)
    first = explore(jax.random.key(3), toy_score, INITIAL, "evosax:LM_MA_ES", CONFIG)
    again = explore(jax.random.key(3), toy_score, INITIAL, "evosax:LM_MA_ES", CONFIG)
    assert_same(first, again)
    assert np.isfinite(np.asarray(first.population.score)).any()
