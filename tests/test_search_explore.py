"""The compiled exploration loop (waldo_jax.search.explore): determinism, scan == loop, NaN scores,
multi-seed vmap, no retracing, progress lines and input errors.

A toy criterion on 8 ring cameras stands in for render + criterion (no rendering): 3 epochs of 6
children, so each method compiles in about a second.
"""

from __future__ import annotations

import dataclasses
import sys

import numpy as np
import pytest

# Importing waldo_jax first sets the XLA flag it needs before JAX starts its CPU backend.
from waldo_jax.cameras import look_at
from waldo_jax.errors import ConfigError, WaldoError
from waldo_jax.search import METHODS, ExploreConfig, Initial, RefineConfig, explore, explore_loop, explore_seeds
from waldo_jax.search import get_method, pibs
from waldo_jax.search.method import ChildrenConfig

import jax  # noqa: E402  (after waldo_jax, see above)
import jax.numpy as jnp  # noqa: E402

CONFIG = ExploreConfig(epochs=3, children_per_epoch=6, top_k=5, top_n=4)
SWEET_SPOT = np.array([1.5, 1.2, 0.5], np.float32)
TRACES = []


def toy_score(c2w):
    """Higher near SWEET_SPOT and when looking towards the room's centre: [P, 4, 4] -> [P]."""
    TRACES.append(c2w.shape)  # Python side effect: runs once per trace (and per eager call)
    origin, forward = c2w[:, :3, 3], -c2w[:, :3, 2]
    to_centre = -origin / jnp.linalg.norm(origin, axis=-1, keepdims=True)
    return -jnp.sum((origin - SWEET_SPOT) ** 2, -1) + jnp.sum(forward * to_centre, -1)


def half_nan_score(c2w):
    """toy_score, but NaN for every camera with x > 0 (about half of them)."""
    return jnp.where(c2w[:, 0, 3] > 0.0, jnp.nan, toy_score(c2w))


def ring_initial(score_fn, n=8):
    angle = 2 * np.pi * np.arange(n) / n + 0.1
    origins = np.stack([3 * np.cos(angle), 1.0 + 0.3 * np.sin(2 * angle), 3 * np.sin(angle)], -1).astype(np.float32)
    targets = np.stack([0.2 * np.cos(3 * angle), 0.5 * np.ones(n), 0.2 * np.sin(angle)], -1).astype(np.float32)
    up = jnp.array([0.0, 1.0, 0.0])
    c2w = jax.vmap(look_at, in_axes=(0, 0, None))(jnp.asarray(origins), jnp.asarray(targets), up)
    return Initial(c2w=np.asarray(c2w), scores=np.asarray(score_fn(c2w)))


INITIAL = ring_initial(toy_score)


def leaves(tree):
    return [np.asarray(x) for x in jax.tree.leaves(tree)]


def assert_same(a, b, atol=0.0):
    for x, y in zip(leaves(a), leaves(b), strict=True):
        if atol == 0.0 or x.dtype == bool or np.issubdtype(x.dtype, np.integer):
            np.testing.assert_array_equal(x, y)
        else:
            np.testing.assert_allclose(x, y, atol=atol, rtol=0)


@pytest.mark.slow
@pytest.mark.parametrize("method", ["grs", "pibs", "egps"])
def test_scan_equals_python_loop(method):
    key = jax.random.key(4)
    scanned = explore(key, toy_score, INITIAL, method, CONFIG)
    looped = explore_loop(key, toy_score, INITIAL, method, CONFIG)
    assert_same(scanned, looped, atol=1e-6)
    np.testing.assert_array_equal(np.asarray(scanned.top_indices), np.asarray(looped.top_indices))
    # The run did something: 8 training views + 3 epochs of children, and it improved.
    assert np.asarray(scanned.population.valid).sum() > 8
    assert float(scanned.cvir) > 0.0


@pytest.mark.slow
def test_the_methods_share_one_compiled_finish():
    """A search runs as two programs, the epochs and the finish (top-k, metrics, archive); the finish's
    static config holds only what it reads, so the paper's three methods with one config compile it once,
    for one key and for a batch of keys, and a search equals its two parts run by hand."""
    module = sys.modules["waldo_jax.search.explore"]
    config = dataclasses.replace(CONFIG, top_k=3)  # no other test finishes with it: a program of its own
    key, keys = jax.random.key(4), jax.random.split(jax.random.key(4), 2)
    programs = (module._finish_jit, module._finish_seeds_jit)
    before, sizes = [p._cache_size() for p in programs], []
    for method in ("grs", "pibs", "egps"):
        one = explore(key, toy_score, INITIAL, method, config)
        explore_seeds(keys, toy_score, INITIAL, method, config)
        sizes.append([p._cache_size() for p in programs])
    # GRS compiled each finish (for one key and for a batch), PIBS and EGPS none.
    assert [s - b for s, b in zip(sizes[0], before)] == [1, 1] and sizes[0] == sizes[1] == sizes[2], sizes
    search_method, method_config, resolved, params, start, _ = module._prepare(INITIAL, "egps", config, None, None)
    population = module._scan_jit(
        key,
        jax.tree_util.Partial(toy_score),
        None,
        start,
        params,
        method=search_method,
        method_config=method_config,
        config=resolved,
    )
    assert_same(one, module._finish(population, resolved), atol=1e-6)  # the whole config, unjitted
    # The memory check (`search_memory`) counts the larger of the two programs' needs.
    statics = dict(method=search_method, method_config=method_config, config=resolved)
    epochs = module._scan_jit.lower(key, jax.tree_util.Partial(toy_score), None, start, params, **statics).compile()
    finishing = module._finish_jit.lower(population, config=module._finish_static(resolved)).compile()
    need = module.search_memory(key, toy_score, INITIAL, "egps", config)
    assert need >= max(module.program_memory(epochs), module.program_memory(finishing)) > 0


@pytest.mark.slow
@pytest.mark.parametrize("method", ["grs", "egps"])
def test_same_key_bit_identical_other_key_differs(method):
    first = explore(jax.random.key(4), toy_score, INITIAL, method, CONFIG)
    again = explore(jax.random.key(4), toy_score, INITIAL, method, CONFIG)
    assert_same(first, again)
    other = explore(jax.random.key(5), toy_score, INITIAL, method, CONFIG)
    assert not np.array_equal(np.asarray(first.population.origin), np.asarray(other.population.origin))
    assert not np.array_equal(np.asarray(first.population.score), np.asarray(other.population.score))


@pytest.mark.slow
def test_pibs_without_fallback_ignores_the_key():
    first = explore(jax.random.key(4), toy_score, INITIAL, "pibs", CONFIG)
    assert_same(first, explore(jax.random.key(5), toy_score, INITIAL, "pibs", CONFIG))


@pytest.mark.slow
@pytest.mark.parametrize("method", ["egps"])
def test_nan_scores_are_counted_and_never_selected(method):
    initial = ring_initial(half_nan_score)
    assert np.isnan(initial.scores).sum() == 4 and np.isfinite(initial.scores).sum() == 4
    result = explore(jax.random.key(0), half_nan_score, initial, method, CONFIG)
    population = result.population
    score = np.asarray(population.score)
    valid = np.asarray(population.valid)
    assert np.isnan(score[valid]).any()  # some children failed ...
    children = valid & (np.asarray(population.epoch) > 0)
    assert np.asarray(result.metrics.num_failed)[1:].sum() == np.isnan(score[children]).sum()
    assert np.asarray(result.metrics.num_failed)[0] == 4
    paper = np.asarray(result.paper_top_indices)[np.asarray(result.paper_top_valid)]
    assert len(paper) == CONFIG.top_k and np.all(np.isfinite(score[paper]))  # ... but none is selected
    top = np.asarray(result.top_indices)[np.asarray(result.top_valid)]  # nor among the different shots
    assert 1 <= len(top) <= CONFIG.top_k and np.all(np.isfinite(score[top]))
    np.testing.assert_array_equal(np.asarray(result.top_scores)[: len(top)], score[top])
    assert np.all(np.isnan(np.asarray(result.top_scores)[len(top) :]))
    assert np.all(np.asarray(population.c2w)[top][:, 0, 3] <= 0.0)
    assert np.isfinite(float(result.cvir)) and np.isfinite(float(result.mcvir))
    assert np.all(np.isfinite(np.asarray(result.metrics.best)))


def negated_toy_score(c2w):
    return -toy_score(c2w)


@pytest.mark.slow
def test_min_direction_mirrors_max_direction():
    maximised = explore(jax.random.key(4), toy_score, INITIAL, "egps", CONFIG)
    negated = Initial(c2w=INITIAL.c2w, scores=-INITIAL.scores)
    minimised = explore(
        jax.random.key(4), negated_toy_score, negated, "egps", dataclasses.replace(CONFIG, direction="min")
    )
    np.testing.assert_array_equal(np.asarray(minimised.population.origin), np.asarray(maximised.population.origin))
    np.testing.assert_array_equal(np.asarray(minimised.top_indices), np.asarray(maximised.top_indices))
    np.testing.assert_allclose(np.asarray(minimised.metrics.best), -np.asarray(maximised.metrics.best))
    assert float(minimised.cvir) == pytest.approx(float(maximised.cvir)) and float(minimised.cvir) > 0.0
    assert float(minimised.mcvir) == pytest.approx(float(maximised.mcvir))


@pytest.mark.slow
def test_multi_seed_vmap_equals_per_seed_runs():
    keys = jax.random.split(jax.random.key(11), 3)
    batch = explore_seeds(keys, toy_score, INITIAL, "egps", CONFIG)
    singles = [explore(keys[i], toy_score, INITIAL, "egps", CONFIG) for i in range(3)]
    for i, single in enumerate(singles):
        assert_same(jax.tree.map(lambda x: x[i], batch.results), single, atol=1e-6)
    cvirs = np.array([float(s.cvir) for s in singles])
    mcvirs = np.array([float(s.mcvir) for s in singles])
    assert float(batch.cvir_mean) == pytest.approx(cvirs.mean(), rel=1e-5)
    assert float(batch.cvir_std) == pytest.approx(cvirs.std(), rel=1e-4, abs=1e-5)
    assert float(batch.mcvir_mean) == pytest.approx(mcvirs.mean(), rel=1e-5)
    assert float(batch.mcvir_std) == pytest.approx(mcvirs.std(), rel=1e-4, abs=1e-5)
    assert len(set(cvirs.tolist())) > 1  # the seeds really differ


@pytest.mark.slow
def test_second_call_does_not_retrace():
    explore(jax.random.key(0), toy_score, INITIAL, "egps", CONFIG)  # compiled here or by an earlier test
    before = len(TRACES)
    explore(jax.random.key(1), toy_score, INITIAL, "egps", CONFIG)
    explore(jax.random.key(2), toy_score, ring_initial(jax.jit(toy_score)), "egps", CONFIG)  # new values
    assert len(TRACES) == before + 1  # only the jit(toy_score) of ring_initial traced


def _distance_score(spot, c2w):
    SPOT_TRACES.append(c2w.shape)
    return -jnp.sum((c2w[:, :3, 3] - spot) ** 2, -1)


SPOT_TRACES = []


@pytest.mark.slow
def test_partial_score_fn_takes_traced_arrays_without_retracing():
    near = explore(
        jax.random.key(0), jax.tree_util.Partial(_distance_score, jnp.asarray(SWEET_SPOT)), INITIAL, "grs", CONFIG
    )
    traces = len(SPOT_TRACES)
    assert traces >= 1
    far = explore(
        jax.random.key(0),
        jax.tree_util.Partial(_distance_score, jnp.asarray(SWEET_SPOT) + 10.0),
        INITIAL,
        "grs",
        CONFIG,
    )
    assert len(SPOT_TRACES) == traces  # the bound array is an argument, not a compile-time constant
    # Same poses (GRS ignores scores), different scores.
    np.testing.assert_array_equal(np.asarray(near.population.origin), np.asarray(far.population.origin))
    assert not np.array_equal(np.asarray(near.population.score), np.asarray(far.population.score))


@pytest.mark.slow
def test_progress_lines(capsys):
    config = ExploreConfig(epochs=2, children_per_epoch=3, top_k=3, top_n=2)
    results = {}
    for run in (explore, explore_loop):
        results[run] = run(jax.random.key(0), toy_score, INITIAL, "grs", config, progress=True)
        jax.effects_barrier()
        lines = [line for line in capsys.readouterr().out.splitlines() if line.startswith("[explore grs]")]
        assert len(lines) == 2 and lines[0].startswith("[explore grs] epoch 1/2: best "), run.__name__
    quiet = explore(jax.random.key(0), toy_score, INITIAL, "grs", config)  # off by default
    jax.effects_barrier()
    assert "[explore" not in capsys.readouterr().out
    # Printing changes no draw; the callback's metrics can change how XLA fuses the epoch (with the test
    # suite's fast-compile flags), hence equal up to rounding.
    assert_same(results[explore], quiet, atol=1e-6)


@pytest.mark.slow
def test_method_options_belong_to_their_method():
    # A method's config refuses an option it does not have, naming the option and the method.
    with pytest.raises(ConfigError, match=r"search method 'grs' has no option 'top_c' \(its options: none\)"):
        ChildrenConfig.create(6, 3, method="grs", top_c=4)
    with pytest.raises(ConfigError, match=r"'egps' has no option 'fallback'"):
        METHODS["egps"].make_config(6, 3, fallback="grs")
    with pytest.raises(ConfigError, match=r"'pibs' has no option 'refine' \(its options: top_c, fallback\)"):
        METHODS["pibs"].make_config(6, 3, refine=RefineConfig())
    with pytest.raises(
        ConfigError,
        match=r"'pibs\+refine' has no option 'topc' \(its options: top_c, fallback, "
        r"refine\)",
    ):
        METHODS["pibs+refine"].make_config(6, 3, topc=4)
    with pytest.raises(ConfigError, match=r"'evosax:SNES' has no option 'top_c'"):
        get_method("evosax:SNES").make_config(6, 3, top_c=4)
    with pytest.raises(ConfigError, match=r"'grs' has no option 'top_c'"):  # and so does explore
        explore(jax.random.key(0), toy_score, INITIAL, "grs", dataclasses.replace(CONFIG, options={"top_c": 4}))
    assert issubclass(ConfigError, ValueError) and issubclass(ConfigError, WaldoError)
    # The options a method has reach its config, and its search.
    assert METHODS["pibs"].make_config(6, 3, top_c=3, fallback="grs") == pibs.Config(6, top_c=3, fallback="grs")
    refined = METHODS["pibs+refine"].make_config(6, 3, top_c=3, refine=RefineConfig(poses=2))
    assert refined.base == pibs.Config(6, top_c=3) and refined.refine.poses == 2 and refined.epochs == 3
    assert METHODS["pibs"].options == ("top_c", "fallback") and METHODS["egps"].options == ()
    default = explore(jax.random.key(0), toy_score, INITIAL, "pibs", CONFIG)
    two = explore(jax.random.key(0), toy_score, INITIAL, "pibs", dataclasses.replace(CONFIG, options={"top_c": 2}))
    assert not np.array_equal(np.asarray(default.population.origin), np.asarray(two.population.origin))
    # Options are kept hashable and in one order, so equal configs share a compilation.
    first = ExploreConfig(method="pibs", options={"top_c": 3, "fallback": "grs"})
    second = ExploreConfig(method="pibs", options={"fallback": "grs", "top_c": 3})
    assert first == second and hash(first) == hash(second) and first.method_options == {"top_c": 3, "fallback": "grs"}


def test_registry_and_input_errors():
    bases = {"grs", "pibs", "egps", "map-elites"}
    assert set(METHODS) == bases | {f"{name}+refine" for name in bases}
    with pytest.raises(ValueError, match=r"unknown search method 'cmaes'.*evosax:NAME"):
        explore(jax.random.key(0), toy_score, INITIAL, "cmaes", CONFIG)
    with pytest.raises(ValueError, match=r"unknown evosax strategy 'CMAES'; choose one of .*CMA_ES"):
        explore(jax.random.key(0), toy_score, INITIAL, "evosax:CMAES", CONFIG)
    with pytest.raises(ValueError, match="SV_CMA_ES.* cannot run as a pose search"):
        explore(jax.random.key(0), toy_score, INITIAL, "evosax:SV_CMA_ES", CONFIG)
    with pytest.raises(ValueError, match="'egps\\+refine' takes gradient steps: pass a differentiable objective_fn"):
        explore(jax.random.key(0), toy_score, INITIAL, "egps+refine", CONFIG)
    with pytest.raises(ValueError, match=r"initial.scores must have shape \(8,\)"):
        explore(jax.random.key(0), toy_score, Initial(c2w=INITIAL.c2w, scores=INITIAL.scores[:5]), "grs", CONFIG)
    with pytest.raises(ValueError, match="initial.c2w"):
        explore(jax.random.key(0), toy_score, Initial(c2w=INITIAL.c2w[:, :2], scores=INITIAL.scores), "grs", CONFIG)
    with pytest.raises(ValueError, match="direction"):
        ExploreConfig(direction="up")
