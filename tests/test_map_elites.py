"""The view archive (waldo_jax.search.archive) and MAP-Elites (waldo_jax.search.map_elites): cells on
analytic views, the archive against a brute-force one, filing in batches = all at once, the method's own
archive = the final population's, same key same archive, scan = loop, +refine, and configs refused."""

from __future__ import annotations

import math

import numpy as np
import pytest

from waldo_jax.errors import ConfigError
from waldo_jax.search import ExploreConfig, RefineConfig, explore, explore_loop, get_method, map_elites
from waldo_jax.search.archive import ViewGrid, archive_of, coverage, merge, qd_score, sky_map, view_cell

import jax  # noqa: E402  (after waldo_jax: it sets XLA flags first)
import jax.numpy as jnp  # noqa: E402

from test_search_explore import INITIAL, assert_same, toy_score  # noqa: E402
from test_shots import FRAME, orbit, random_views  # noqa: E402

GRID = ViewGrid(azimuth_cells=8, elevation_cells=4, distance_edges=(0.75, 1.33))
CONFIG = ExploreConfig(method="map-elites", epochs=3, children_per_epoch=12, top_k=5, grid=GRID)


def cell(c2w, grid=GRID):
    return int(view_cell(jnp.asarray(c2w), FRAME, grid))


@pytest.mark.slow
def test_cells_of_analytic_views():
    # FRAME: focus 0, up +y, radius 3; azimuth 0 is the world axis least aligned with up: +x.
    a, e = GRID.azimuth_cells, GRID.elevation_cells
    assert cell(orbit(0.0, 10.0, 3.0)) == (1 * e + 2) * a + 0  # the training distance, just above the horizon
    assert cell(orbit(0.0, 10.0, 1.0)) == (0 * e + 2) * a + 0  # closer than 0.75 r
    assert cell(orbit(0.0, 10.0, 5.0)) == (2 * e + 2) * a + 0  # farther than 1.33 r
    assert cell(orbit(0.0, -60.0, 3.0)) == (1 * e + 0) * a + 0  # from below
    assert cell(orbit(0.0, 80.0, 3.0)) == (1 * e + 3) * a + 0  # from above
    # Sector 0 is centred on azimuth 0: +-22.4 degrees stay in it. North (+90) is up x east = -z.
    assert cell(orbit(22.0, 10.0)) % a == 0 and cell(orbit(-22.0, 10.0)) % a == 0
    assert cell(orbit(-90.0, 10.0)) % a == 2  # orbit's azimuth -90 lies at -z: the frame's +90
    assert cell(orbit(180.0, 10.0)) % a == 4
    assert cell(np.full((4, 4), np.nan, np.float32)) == GRID.cells  # outside every cell
    # An elevation outside the range falls in the nearest band.
    narrow = ViewGrid(azimuth_cells=4, elevation_cells=2, elevation_range=(0.0, 60.0), distance_edges=())
    assert cell(orbit(0.0, -30.0), narrow) == 0 and cell(orbit(0.0, 80.0), narrow) == 4


def brute_force_archive(fitness, c2w, grid):
    """Every view filed one by one in slot order; an elite is replaced only by a strictly better view."""
    best = np.full(grid.cells, -np.inf, np.float32)
    slot = np.full(grid.cells, -1, np.int32)
    for i, (f, view) in enumerate(zip(fitness, c2w)):
        c = cell(view, grid)
        if np.isfinite(f) and c < grid.cells and f > best[c]:
            best[c], slot[c] = f, i
    return best, slot


@pytest.mark.slow
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_archive_equals_a_brute_force_archive(seed):
    fitness, c2w = random_views(seed, 60)
    fitness[5] = np.nan
    fitness[7] = fitness[8]  # a tie (the earlier slot keeps the cell if they share one)
    grid = ViewGrid(azimuth_cells=12, elevation_cells=3, distance_edges=(1.0,))
    archive = archive_of(jnp.asarray(fitness), jnp.asarray(c2w), jnp.arange(60, dtype=jnp.int32), FRAME, grid)
    best, slot = brute_force_archive(fitness, c2w, grid)
    np.testing.assert_array_equal(np.asarray(archive.fitness), best)
    np.testing.assert_array_equal(np.asarray(archive.slot), slot)
    # Filed in batches, in slot order, it is the same archive.
    batches = None
    for start in range(0, 60, 17):
        part = slice(start, start + 17)
        slots = jnp.arange(start, min(start + 17, 60), dtype=jnp.int32)
        newer = archive_of(jnp.asarray(fitness[part]), jnp.asarray(c2w[part]), slots, FRAME, grid)
        batches = newer if batches is None else merge(batches, newer)
    assert_same(batches, archive)
    filled = np.isfinite(best)
    assert float(coverage(archive)) == pytest.approx(filled.mean())
    floor = float(np.min(fitness[np.isfinite(fitness)]))
    assert float(qd_score(archive, jnp.float32(floor))) == pytest.approx(np.sum(best[filled] - floor), rel=1e-5)
    sky = sky_map(archive, grid)  # the best over the distance bands of each (elevation, sector)
    per_band = best.reshape(grid.distance_bands, grid.elevation_cells, grid.azimuth_cells)
    np.testing.assert_array_equal(np.asarray(sky.fitness), per_band.max(axis=0))


@pytest.mark.slow
def test_map_elites_archive_is_the_final_populations_and_the_key_fixes_it():
    result = explore(jax.random.key(7), toy_score, INITIAL, config=CONFIG)
    population = result.population
    method = get_method("map-elites")
    config = CONFIG.resolve(8).method_config(method)
    assert config.grid == GRID  # the run's grid reaches the method
    # The method's own archive, filed epoch by epoch as the search went (each ask files the epoch before),
    # equals the archive of the final population all at once (what explore reports for every method).
    state = map_elites.init(jax.random.key(0), population, method.default_params(), config)
    for epoch in range(2, CONFIG.epochs + 2):
        _, _, _, state = map_elites.ask(
            jax.random.key(0), population, state, method.default_params(), config, jnp.int32(epoch), None
        )
    assert_same(state.archive, result.archive)
    assert int(np.sum(np.isfinite(np.asarray(result.archive.fitness)))) > int(
        np.sum(np.isfinite(np.asarray(map_elites.init(None, population, None, config).archive.fitness)))
    )  # the children filled new cells
    again = explore(jax.random.key(7), toy_score, INITIAL, config=CONFIG)
    assert_same(again, result)
    other = explore(jax.random.key(8), toy_score, INITIAL, config=CONFIG)
    assert not np.array_equal(np.asarray(other.population.origin), np.asarray(result.population.origin))


@pytest.mark.slow
def test_map_elites_scan_equals_python_loop_and_refine_runs():
    key = jax.random.key(3)
    scanned = explore(key, toy_score, INITIAL, config=CONFIG)
    looped = explore_loop(key, toy_score, INITIAL, config=CONFIG)
    assert_same(scanned, looped, atol=1e-6)
    assert float(scanned.cvir) > 0.0 and float(scanned.coverage) > 0.0
    refine = RefineConfig(poses=2, steps=2, gradient_cost=2)
    config = ExploreConfig(method="map-elites+refine", epochs=3, budget=(60, 70), top_k=5, grid=GRID)
    config = config.with_options(refine=refine)
    refined = explore(key, toy_score, INITIAL, config=config, objective_fn=toy_score)
    assert config.cost(8)["renders"] <= 70  # the gradient steps come out of the budget
    last = np.asarray(refined.population.epoch) == 3
    assert last.sum() == config.resolve(8).children_per_epoch
    assert np.all(np.isfinite(np.asarray(refined.population.score)[last]))


@pytest.mark.slow
def test_map_elites_children_come_from_elites_and_configs_are_checked():
    method = get_method("map-elites")
    assert method.stateful and method.options == ("grid",)
    with pytest.raises(ConfigError, match="has no option 'top_c'"):
        method.make_config(6, 3, top_c=2)
    with pytest.raises(ValueError, match="view grid is ExploreConfig.grid"):
        ExploreConfig(method="map-elites", options={"grid": GRID})
    with pytest.raises(ValueError, match="azimuth_cells must be an int"):
        ViewGrid(azimuth_cells=0)
    with pytest.raises(ValueError, match="distance_edges must be"):
        ViewGrid(distance_edges=(1.5, 0.5))
    with pytest.raises(ValueError, match="elevation_range"):
        ViewGrid(elevation_range=(10.0, 10.0))
    # Iso+LineDD alone with no spread: every child is a copy of an elite's origin and look-at point.
    params = map_elites.Params(
        line_probability=jnp.float32(1.0), iso_sigma=jnp.float32(0.0), line_sigma=jnp.float32(0.0)
    )
    result = explore(jax.random.key(1), toy_score, INITIAL, config=CONFIG, params=params)
    origins = np.asarray(result.population.origin)
    train = {tuple(np.round(o, 5)) for o in origins[:8]}
    assert {tuple(np.round(o, 5)) for o in origins[8:]} <= train
    assert math.isfinite(float(result.qd_score))
    # EGPS breeding alone with no mutation: every child lies in the box between two training views.
    bred = map_elites.Params(
        line_probability=jnp.float32(0.0),
        breeding=map_elites.egps.Params(mutation_probs=jnp.array([0.0, 1.0, 0.0], jnp.float32)),
    )
    result = explore(jax.random.key(1), toy_score, INITIAL, config=CONFIG, params=bred)
    origins = np.asarray(result.population.origin)
    low, high = origins[:8].min(axis=0), origins[:8].max(axis=0)
    assert np.all((origins[8:] >= low - 1e-5) & (origins[8:] <= high + 1e-5))
    assert len({tuple(np.round(o, 5)) for o in origins[8:]} - train) > 0  # new poses, not copies
