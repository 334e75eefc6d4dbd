"""Different shots (waldo_jax.search.views): the separation of two views on analytic cases, the greedy
distinct top-k against a NumPy brute force, separation 0 = the paper's top-k bit for bit, and the
explore results (dCVIR, the paper's top-k kept, every pair of the returned top-k far enough apart)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from waldo_jax.cameras import look_at
from waldo_jax.search import ExploreConfig, explore, explore_seeds
from waldo_jax.search.population import top_k_indices
from waldo_jax.search.views import SceneFrame, distinct_count, distinct_top_k, scene_frame, view_separation

import jax  # noqa: E402  (after waldo_jax: it sets XLA flags first)
import jax.numpy as jnp  # noqa: E402

from test_search_explore import INITIAL, toy_score  # noqa: E402

FRAME = SceneFrame(focus=jnp.zeros(3), up=jnp.array([0.0, 1.0, 0.0]), radius=jnp.float32(3.0))
UP = np.array([0.0, 1.0, 0.0], np.float32)


def orbit(azimuth_deg, elevation_deg=0.0, distance=3.0, target=(0.0, 0.0, 0.0)):
    """c2w [4, 4] of a camera on a sphere about the origin (y up) looking at `target`."""
    a, e = math.radians(azimuth_deg), math.radians(elevation_deg)
    origin = distance * np.array([math.cos(e) * math.cos(a), math.sin(e), math.cos(e) * math.sin(a)], np.float32)
    return np.asarray(look_at(origin, np.asarray(target, np.float32), UP))


def sep(a, b, frame=FRAME):
    return float(view_separation(jnp.asarray(a), jnp.asarray(b), frame))


def test_separation_of_analytic_pairs():
    # Two cameras 30 degrees apart on a circle, both looking at the focus: 30 (centre and direction).
    assert sep(orbit(0), orbit(30)) == pytest.approx(30.0, abs=1e-3)
    assert sep(orbit(0), orbit(0)) == pytest.approx(0.0, abs=1e-3)
    assert sep(orbit(10), orbit(70)) == pytest.approx(sep(orbit(70), orbit(10)), abs=1e-6)  # symmetric
    # A pan: the same place, looking 25 degrees to the side.
    panned = orbit(0, target=(0.0, 0.0, 3.0 * math.tan(math.radians(25.0))))
    assert sep(orbit(0), panned) == pytest.approx(25.0, abs=1e-2)
    # A dolly: the same direction, twice as far: ln 2 radians.
    assert sep(orbit(0, distance=3.0), orbit(0, distance=6.0)) == pytest.approx(math.degrees(math.log(2.0)), abs=1e-3)
    # Elevation counts like azimuth; the largest of the three terms wins.
    assert sep(orbit(0, 0.0), orbit(0, 50.0)) == pytest.approx(50.0, abs=1e-3)
    assert sep(orbit(0, distance=3.0), orbit(10, distance=6.0)) == pytest.approx(math.degrees(math.log(2.0)), abs=1e-3)
    # A camera on the focus still has a direction (no NaN); a NaN pose is NaN (never a copy of another).
    on_focus = np.asarray(look_at(np.zeros(3, np.float32), np.array([1.0, 0.0, 0.0], np.float32), UP))
    assert np.isfinite(sep(on_focus, orbit(0)))
    assert math.isnan(sep(np.full((4, 4), np.nan, np.float32), orbit(0)))


def test_scene_frame_from_cameras_and_its_checks():
    c2w = np.stack([orbit(a, 20.0, 2.0 + 0.1 * i) for i, a in enumerate(range(0, 360, 45))])
    frame = scene_frame(c2w)
    np.testing.assert_allclose(np.asarray(frame.focus), 0.0, atol=1e-4)  # where the axes meet
    assert float(frame.radius) == pytest.approx(np.median(2.0 + 0.1 * np.arange(8)), rel=1e-4)
    assert float(jnp.linalg.norm(frame.up)) == pytest.approx(1.0) and float(frame.up[1]) > 0.9
    given_up = scene_frame(c2w, focus=np.array([0.0, 1.0, 0.0]), up=np.array([0.0, 0.0, 2.0]))
    np.testing.assert_allclose(np.asarray(given_up.up), [0.0, 0.0, 1.0])
    with pytest.raises(ValueError, match="up must not be zero"):
        scene_frame(c2w, up=np.zeros(3))
    with pytest.raises(ValueError, match="focus must be 3 finite numbers"):
        scene_frame(c2w, focus=np.array([0.0, np.nan, 0.0]))


def brute_force_distinct(fitness, c2w, frame, k, min_separation):
    """Greedy in NumPy: every view in order of fitness (ties: lower index), kept when it is at least
    min_separation from every view kept so far."""
    order = sorted(range(len(fitness)), key=lambda i: (-fitness[i], i))
    kept = []
    for i in order:
        if not np.isfinite(fitness[i]) or len(kept) == k:
            continue
        if all(not sep(c2w[i], c2w[j], frame) < min_separation for j in kept):
            kept.append(i)
    return kept


def random_views(seed, count):
    rng = np.random.default_rng(seed)
    azimuth = rng.uniform(0, 90, count)  # crowded: many views within 20 degrees of each other
    elevation = rng.uniform(-10, 40, count)
    distance = rng.uniform(2.0, 5.0, count)
    target = rng.normal(0.0, 0.3, (count, 3))
    c2w = np.stack([orbit(a, e, d, t) for a, e, d, t in zip(azimuth, elevation, distance, target)])
    fitness = rng.normal(size=count).astype(np.float32)
    fitness[rng.random(count) < 0.15] = -np.inf
    fitness[rng.integers(0, count)] = fitness[rng.integers(0, count)]  # a tie
    return fitness, c2w.astype(np.float32)


@pytest.mark.slow
@settings(max_examples=12, deadline=None)
@given(seed=st.integers(0, 10_000), separation=st.sampled_from([5.0, 20.0, 45.0]))
def test_distinct_top_k_is_the_greedy_brute_force_and_pairwise_apart(seed, separation):
    fitness, c2w = random_views(seed, 40)
    k = 10
    indices, ok = distinct_top_k(jnp.asarray(fitness), jnp.asarray(c2w), FRAME, k, separation)
    got = [int(i) for i, good in zip(np.asarray(indices), np.asarray(ok)) if good]
    assert got == brute_force_distinct(fitness, c2w, FRAME, k, separation)
    assert list(np.asarray(ok)) == [True] * len(got) + [False] * (k - len(got))  # the real ones first
    for a in range(len(got)):
        for b in range(a + 1, len(got)):
            assert sep(c2w[got[a]], c2w[got[b]]) >= separation
    count = distinct_count(jnp.asarray(c2w[got]), jnp.ones(len(got), bool), FRAME, separation)
    assert int(count) == len(got)  # different shots stay different


@pytest.mark.slow
def test_separation_zero_is_the_paper_top_k_bit_for_bit():
    fitness, c2w = random_views(3, 40)
    indices, ok = distinct_top_k(jnp.asarray(fitness), jnp.asarray(c2w), FRAME, 10, 0.0)
    values, expected = jax.lax.top_k(jnp.asarray(fitness), 10)
    np.testing.assert_array_equal(np.asarray(indices), np.asarray(expected))
    np.testing.assert_array_equal(np.asarray(ok), np.isfinite(np.asarray(values)))
    # and explore returns the paper's top-k with it (the rest of the run is the same run)
    zero = explore(jax.random.key(1), toy_score, INITIAL, "egps", ExploreConfig(epochs=3, children_per_epoch=12))
    config = ExploreConfig(epochs=3, children_per_epoch=12, min_separation=0.0)
    paper = explore(jax.random.key(1), toy_score, INITIAL, "egps", config)
    reference, reference_ok = top_k_indices(paper.population, 10)
    np.testing.assert_array_equal(np.asarray(paper.top_indices), np.asarray(reference))
    np.testing.assert_array_equal(np.asarray(paper.top_valid), np.asarray(reference_ok))
    np.testing.assert_array_equal(np.asarray(paper.top_indices), np.asarray(paper.paper_top_indices))
    np.testing.assert_array_equal(np.asarray(zero.population.score), np.asarray(paper.population.score))
    np.testing.assert_array_equal(np.asarray(zero.paper_top_indices), np.asarray(paper.paper_top_indices))
    assert float(zero.mcvir) == float(paper.mcvir) and float(zero.cvir) == float(paper.cvir)


@pytest.mark.slow
def test_distinct_count_of_copies_and_of_different_views():
    copies = np.stack([orbit(40 + 0.5 * i) for i in range(6)] + [orbit(120)])
    assert int(distinct_count(jnp.asarray(copies), jnp.ones(7, bool), FRAME, 20.0)) == 2
    assert int(distinct_count(jnp.asarray(copies), jnp.array([True] * 6 + [False]), FRAME, 20.0)) == 1
    assert int(distinct_count(jnp.asarray(copies), jnp.ones(7, bool), FRAME, 0.0)) == 7


@pytest.mark.slow
def test_explore_reports_different_shots_and_the_gain_over_the_best_training_view():
    config = ExploreConfig(epochs=4, children_per_epoch=20, top_k=6)
    out = explore_seeds(jax.random.split(jax.random.key(2), 2), toy_score, INITIAL, "egps", config)
    for s in range(2):
        result = jax.tree.map(lambda a, s=s: a[s], out.results)
        population = result.population
        fitness = np.asarray(population.fitness)
        top = np.asarray(result.top_indices)[np.asarray(result.top_valid)]
        assert len(top) == 6
        c2w = np.asarray(population.c2w)
        for a in range(len(top)):
            for b in range(a + 1, len(top)):
                assert sep(c2w[top[a]], c2w[top[b]], population.frame) >= 20.0
        train_best = fitness[: population.num_train].max()
        gain = 100.0 * (fitness[top].mean() - train_best) / abs(train_best)
        assert float(result.dcvir) == pytest.approx(gain, rel=1e-4)
        assert int(result.shots_beating_train) == int(np.sum(fitness[top] > train_best))
        assert top[0] == np.asarray(result.paper_top_indices)[0]  # the best view is the best view
        paper = np.asarray(result.paper_top_indices)
        shots = distinct_count(jnp.asarray(c2w[paper]), jnp.ones(6, bool), population.frame, 20.0)
        assert int(result.paper_top_shots) == int(shots)
    assert float(out.dcvir_mean) == pytest.approx(float(np.mean(np.asarray(out.results.dcvir))))
