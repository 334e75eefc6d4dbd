"""Tests of the occupancy grid and fixed-shape ray marching (waldo_jax.render.occupancy), and of
rendering through it (`render.marched`) against dense sampling.

The fields are analytic (balls and blobs) whose parameters are the `params` pytree, so that one
compiled update or render serves every configuration of a given shape.
"""

from __future__ import annotations

import functools
import math
import types

import waldo_jax  # noqa: F401  (XLA flags before the first computation)

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from waldo_jax.cameras import camera_rays, look_at
from waldo_jax.render import RenderConfig, marched, marching, occupancy as occ, render_rays
from waldo_jax.types import Intrinsics

BOX = np.array([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]], np.float32)
G = 16
STEP_BEYOND_WARMUP = 10**6


# --------------------------------------------------------------------------------------------------
# Analytic fields: params = {"center": [B, 3], "radius": [B], "peak": [B], "profile": []}, peak 0
# disables a ball. One density function serves all profiles, so each grid shape compiles once.

HARD, SMOOTH, GAUSS = 0.0, 1.0, 2.0


def make_balls(centers, radii, peaks, profile, num=3) -> dict:
    """Ball parameters padded to `num` balls (so shapes, and compilations, are shared)."""
    n = len(radii)
    c = np.full((num, 3), 9.0, np.float32)
    r = np.full((num,), 0.1, np.float32)
    p = np.zeros((num,), np.float32)
    c[:n], r[:n], p[:n] = np.asarray(centers, np.float32), radii, peaks
    return {"center": jnp.asarray(c), "radius": jnp.asarray(r), "peak": jnp.asarray(p), "profile": jnp.float32(profile)}


# Times each function below was traced (Python side effects run only while tracing).
TRACES = {"density": 0}


def ball_density(params, x):
    """Sum over balls of peak * profile(d / r), d the distance to the ball's centre.

    HARD: 1 for d < r, else 0. SMOOTH: (1 - (d / r)^2)^2 for d < r, else 0. GAUSS: exp(-(d / r)^2 / 2).
    """
    TRACES["density"] += 1
    d2 = jnp.sum((x - params["center"]) ** 2, axis=-1) / params["radius"] ** 2  # [B]
    hard = (d2 < 1.0).astype(jnp.float32)
    smooth = jnp.maximum(1.0 - d2, 0.0) ** 2
    gauss = jnp.exp(-0.5 * d2)
    profile = jnp.where(params["profile"] == HARD, hard, jnp.where(params["profile"] == SMOOTH, smooth, gauss))
    return jnp.sum(params["peak"] * profile)


def ball_field(params, x, d):
    return ball_density(params, x), 0.5 + 0.4 * jnp.sin(jnp.array([3.0, 5.0, 7.0]) * x + jnp.array([0.0, 1.0, 2.0]))


def _np_gauss_bounds(params, lo, hi):
    """Lower and upper bounds [N] of the GAUSS profile's density over boxes [lo, hi] ([N, 3] each)."""
    lower, upper = 0.0, 0.0
    for c, r, p in zip(np.asarray(params["center"]), np.asarray(params["radius"]), np.asarray(params["peak"])):
        nearest = np.clip(c, lo, hi)
        farthest = np.where(np.abs(lo - c) > np.abs(hi - c), lo, hi)
        lower = lower + p * np.exp(-0.5 * np.sum((farthest - c) ** 2, -1) / r**2)
        upper = upper + p * np.exp(-0.5 * np.sum((nearest - c) ** 2, -1) / r**2)
    return lower, upper


# --------------------------------------------------------------------------------------------------
# NumPy reference of the documented indexing


def np_cells(grid, points):
    """(cascade [N], flat cell [N], cell min corner [N, 3], cell max corner [N, 3]) per the docstring."""
    center, half = np.asarray(grid.center), np.asarray(grid.half_size)
    u = (points - center) / half
    extent = np.abs(u).max(-1)
    cascade = np.clip(np.ceil(np.log2(np.maximum(extent, 1e-30))), 0, grid.cascades - 1).astype(int)
    scale = 2.0 ** cascade[:, None]
    ijk = np.clip(np.floor((u / scale + 1.0) * 0.5 * grid.resolution), 0, grid.resolution - 1).astype(int)
    cell = ijk[:, 0] + grid.resolution * (ijk[:, 1] + grid.resolution * ijk[:, 2])
    lo = center + half * scale * (ijk * 2.0 / grid.resolution - 1.0)
    return cascade, cell, lo, lo + half * scale * 2.0 / grid.resolution


def np_all_cell_boxes(grid):
    """Min and max corners [C, G^3, 3] of every cell."""
    n = grid.resolution
    cell = np.arange(n**3)
    ijk = np.stack([cell % n, (cell // n) % n, cell // (n * n)], -1)
    scale = 2.0 ** np.arange(grid.cascades)[:, None, None]
    half, center = np.asarray(grid.half_size), np.asarray(grid.center)
    lo = center + half * scale * (ijk[None] * 2.0 / n - 1.0)
    return lo, lo + half * scale * 2.0 / n


def _points_in_balls(seed, params, per_ball):
    rng = np.random.default_rng(seed)
    out = []
    for c, r, p in zip(np.asarray(params["center"]), np.asarray(params["radius"]), np.asarray(params["peak"])):
        if p <= 0:
            continue
        d = rng.normal(size=(per_ball, 3))
        d /= np.linalg.norm(d, axis=-1, keepdims=True)
        out.append(c + d * r * rng.uniform(0, 1, (per_ball, 1)) ** (1 / 3) * 0.999)
    return np.concatenate(out).astype(np.float32)


GRID_CELL = jax.jit(jax.vmap(occ.grid_cell, in_axes=(None, 0)))
IS_OCCUPIED = jax.jit(jax.vmap(occ.is_occupied, in_axes=(None, 0)))


def _run_updates(grid, density_fn, params, config, steps, seed=0):
    for i, step in enumerate(steps):
        grid = occ.update_occupancy(jax.random.fold_in(jax.random.key(seed), i), grid, density_fn, params, step, config)
    return grid


# --------------------------------------------------------------------------------------------------
# Grid construction and indexing


@pytest.mark.parametrize("aabb_scale, cascades", [(1, 1), (0.5, 1), (2, 2), (3, 3), (4, 3), (16, 5), (2**12, 8)])
def test_cascade_count_follows_aabb_scale(aabb_scale, cascades):
    grid = occ.init_occupancy(BOX, aabb_scale=aabb_scale, resolution=4)
    assert grid.cascades == cascades
    assert grid.density.shape == grid.bitfield.shape == (cascades, 64)
    assert bool(grid.bitfield.all()) and float(grid.density.max()) == 0.0
    np.testing.assert_allclose(grid.outer_aabb, BOX * 2.0 ** (cascades - 1))


def test_bad_arguments_raise():
    with pytest.raises(ValueError, match="aabb"):
        occ.init_occupancy([[0, 0, 0], [1, -1, 1]])
    with pytest.raises(ValueError, match="resolution"):
        occ.init_occupancy(BOX, resolution=0)
    with pytest.raises(ValueError, match="aabb_scale"):
        occ.init_occupancy(BOX, aabb_scale=0.0)
    with pytest.raises(ValueError, match="max_steps"):
        marching.MarchConfig.create(max_steps=0)


def test_scene_grid_uses_the_aabb_scale_of_its_metadata():
    # fox-like: the scene box is NGP's aabb_scale cube, the base box a quarter of it.
    scene = types.SimpleNamespace(
        aabb=np.array([[-6.0, -5.0, -4.0], [6.0, 7.0, 8.0]]), metadata={"aabb_scale": 4}, name="fox"
    )
    grid = occ.init_occupancy_for_scene(scene, resolution=8)
    assert grid.cascades == 3
    np.testing.assert_allclose(grid.center, (0.0, 1.0, 2.0))
    np.testing.assert_allclose(grid.half_size, (1.5, 1.5, 1.5))
    np.testing.assert_allclose(grid.outer_aabb, scene.aabb)


def test_ngp_threshold_value():
    unit = occ.init_occupancy([[0, 0, 0], [1, 1, 1]], resolution=4)
    assert float(occ.OccupancyConfig.create(unit).density_threshold) == pytest.approx(
        0.01 * 1024 / math.sqrt(3), rel=1e-6
    )
    assert float(occ.OccupancyConfig().density_threshold) == pytest.approx(0.01 * 1024 / math.sqrt(3), rel=1e-6)
    big = occ.init_occupancy(BOX, resolution=4)  # twice the size: half the density for the same opacity
    assert float(occ.OccupancyConfig.create(big).density_threshold) == pytest.approx(
        0.01 * 1024 / (2 * math.sqrt(3)), rel=1e-6
    )


def test_grid_cell_matches_numpy_reference_across_cascades():
    grid = occ.init_occupancy([[-1.0, 0.0, 1.0], [1.0, 4.0, 2.0]], aabb_scale=4, resolution=8)  # anisotropic
    rng = np.random.default_rng(0)
    outer = grid.outer_aabb
    points = rng.uniform(outer[0] * 1.1 - 0.1, outer[1] * 1.1 + 0.1, (2000, 3)).astype(np.float32)
    points = np.concatenate([points, grid.base_aabb, outer * 0.999 + 0.001 * np.asarray(grid.center)])
    cascade, cell, inside = (np.asarray(a) for a in GRID_CELL(grid, points))
    ref_cascade, ref_cell, lo, hi = np_cells(grid, points)
    u = np.abs((points - np.asarray(grid.center)) / np.asarray(grid.half_size)).max(-1)
    np.testing.assert_array_equal(inside, u <= 2.0 ** (grid.cascades - 1))
    np.testing.assert_array_equal(cascade[inside], ref_cascade[inside])
    np.testing.assert_array_equal(cell[inside], ref_cell[inside])
    assert set(np.unique(cascade[inside])) == {0, 1, 2}
    # Every inside point lies in its cell's box, and in no finer cascade's box.
    assert np.all((points[inside] >= lo[inside] - 1e-5) & (points[inside] <= hi[inside] + 1e-5))
    coarse = inside & (cascade > 0)
    assert np.all(u[coarse] > 2.0 ** (cascade[coarse] - 1.0) - 1e-6)


@pytest.mark.slow
def test_cell_points_round_trip():
    grid = occ.init_occupancy(BOX, aabb_scale=2, resolution=4)
    cells = jnp.arange(64)
    centres = occ.cell_points(grid, jnp.zeros(64, jnp.int32), cells, jnp.full((64, 3), 0.5))
    cascade, cell, inside = GRID_CELL(grid, centres)
    assert np.all(np.asarray(inside)) and np.all(np.asarray(cascade) == 0)
    np.testing.assert_array_equal(np.asarray(cell), np.arange(64))
    # Cascade-1 cells on the outer shell do not overlap cascade 0, so they map back to cascade 1.
    centres = occ.cell_points(grid, jnp.ones(64, jnp.int32), cells, jnp.full((64, 3), 0.5))
    shell = np.abs(np.asarray(centres)).max(-1) > 1.0
    cascade, cell, _ = GRID_CELL(grid, centres)
    assert shell.sum() == 64 - 8
    np.testing.assert_array_equal(np.asarray(cascade)[shell], 1)
    np.testing.assert_array_equal(np.asarray(cell)[shell], np.arange(64)[shell])


# --------------------------------------------------------------------------------------------------
# Update


@pytest.mark.slow
@pytest.mark.parametrize("aabb_scale", [1, 2])
def test_cells_inside_dense_balls_are_occupied(aabb_scale):
    """No region of density above the threshold is skipped.

    A cell is sampled at one jittered point per update, so a cell that only grazes a ball is found
    with a probability equal to its overlap (as in NGP); a cell lying wholly inside a ball must always
    be found. Dense samples of each ball's interior check every such cell, indexing redone in NumPy.
    """
    grid = occ.init_occupancy(BOX, aabb_scale=aabb_scale, resolution=G)
    config = occ.OccupancyConfig.create(grid)
    centers = [[0.3, -0.2, 0.4], [-0.5, 0.45, -0.4], [1.45, -1.2, 0.6]]
    radii = [0.3, 0.24, 0.4]
    n = 1 + aabb_scale
    params = make_balls(centers[:n], radii[:n], [1e3] * n, HARD)
    grid = _run_updates(grid, ball_density, params, config, steps=[0, 1, 2, 3])

    points = _points_in_balls(1, params, 3000)
    cascade, cell, lo, hi = np_cells(grid, points)
    corners = np.stack([np.where(np.array([(b >> a) & 1 for a in range(3)], bool), hi, lo) for b in range(8)], 1)
    wholly_inside = np.zeros(len(points), bool)
    for c, r in zip(np.asarray(params["center"])[:n], np.asarray(params["radius"])[:n]):
        wholly_inside |= np.linalg.norm(corners - c, axis=-1).max(-1) < r
    bitfield = np.asarray(grid.bitfield)
    assert wholly_inside.sum() > 500 and len(np.unique(cell[wholly_inside])) >= 10
    assert bitfield[cascade[wholly_inside], cell[wholly_inside]].all()
    if aabb_scale == 2:  # the ball outside the base box lives in cascade 1
        assert np.any(wholly_inside & (cascade == 1))
    # Through the public lookup as well.
    assert np.asarray(IS_OCCUPIED(grid, points[wholly_inside])).all()

    # Cells farther than a cell diagonal from every ball are empty.
    lo_all, hi_all = np_all_cell_boxes(grid)
    centre_all = 0.5 * (lo_all + hi_all)
    diag = np.linalg.norm(hi_all - lo_all, axis=-1)
    far = np.ones(bitfield.shape, bool)
    for c, r in zip(np.asarray(params["center"]), np.asarray(params["radius"])):
        far &= np.linalg.norm(centre_all - c, axis=-1) > r + diag
    assert far.sum() > 0.8 * far.size and not bitfield[far].any()


@pytest.mark.slow
@pytest.mark.parametrize("aabb_scale", [1, 2])
def test_threshold_separates_cells_by_density(aabb_scale):
    """A cell whose least density exceeds its cascade's threshold is occupied; one whose greatest is below is not."""
    grid = occ.init_occupancy(BOX, aabb_scale=aabb_scale, resolution=G)
    config = occ.OccupancyConfig.create(grid)
    params = make_balls([[0.2, -0.1, 0.3], [-0.6, 0.5, -0.2]], [0.3, 0.5], [60.0, 8.0], GAUSS)
    grid = _run_updates(grid, ball_density, params, config, steps=[0, 1, 2])

    density, bitfield = np.asarray(grid.density), np.asarray(grid.bitfield)
    tau = float(config.density_threshold)
    thresholds = min(density[0].mean(), tau) * 2.0 ** -np.arange(grid.cascades)
    np.testing.assert_allclose(np.asarray(occ.occupancy_thresholds(grid, config)), thresholds, rtol=1e-6)
    np.testing.assert_array_equal(bitfield, density > thresholds[:, None])

    lower, upper = _np_gauss_bounds(params, *np_all_cell_boxes(grid))
    surely_full = lower > thresholds[:, None] * 1.001
    surely_empty = upper < thresholds[:, None] * 0.999
    assert surely_full.sum() > 20 and surely_empty.sum() > 20
    assert bitfield[surely_full].all() and not bitfield[surely_empty].any()
    # The running maximum stays between the cell's least (decayed twice at most) and greatest density.
    assert np.all(density <= upper * 1.0001 + 1e-6) and np.all(density >= lower * 0.95**2 * 0.9999)


def _deep_points(seed, center, radius, depth, num=400):
    """Points at least `depth` inside a ball."""
    return _points_in_balls(seed, make_balls([center], [radius - depth], [1.0], HARD), num)


@pytest.mark.slow
def test_removed_ball_decays_to_unoccupied():
    grid = occ.init_occupancy(BOX, resolution=G)
    config = occ.OccupancyConfig.create(grid, warmup_steps=2)
    cell_diagonal = float(np.linalg.norm(grid.cell_size(0)))
    center_a, center_b = [0.4, 0.3, 0.2], [-0.4, -0.3, -0.2]
    both = make_balls([center_a, center_b], [0.45, 0.5], [100.0, 100.0], HARD)
    grid = _run_updates(grid, ball_density, both, config, steps=[0, 1])
    points_a = _deep_points(2, center_a, 0.45, cell_diagonal)
    points_b = _deep_points(3, center_b, 0.5, cell_diagonal)
    assert np.asarray(IS_OCCUPIED(grid, points_a)).all() and np.asarray(IS_OCCUPIED(grid, points_b)).all()
    cascade_a, cell_a, _, _ = np_cells(grid, points_a)
    np.testing.assert_array_equal(np.asarray(grid.density)[cascade_a, cell_a], 100.0)

    # Ball A vanishes; its cells now see density 0 and only decay (post-warm-up sampling).
    only_b = make_balls([center_b], [0.5], [100.0], HARD)
    # 0.95**80 * 100 = 1.7 is below the threshold min(mean, tau) = tau = 2.96.
    grid = _run_updates(grid, ball_density, only_b, config, steps=[STEP_BEYOND_WARMUP] * 80, seed=1)
    np.testing.assert_allclose(np.asarray(grid.density)[cascade_a, cell_a], 100.0 * 0.95**80, rtol=1e-4)
    assert not np.asarray(IS_OCCUPIED(grid, points_a)).any()
    assert np.asarray(IS_OCCUPIED(grid, points_b)).all()


@pytest.mark.slow
def test_cells_not_sampled_keep_their_decayed_value():
    grid = occ.init_occupancy(BOX, aabb_scale=2, resolution=G)
    config = occ.OccupancyConfig.create(grid)
    rng = np.random.default_rng(0)
    old = rng.uniform(0.0, 10.0, grid.density.shape).astype(np.float32)
    grid = grid.replace(density=jnp.asarray(old))
    nothing = make_balls([[0.0, 0.0, 0.0]], [0.5], [0.0], HARD)
    decayed = occ.update_occupancy(jax.random.key(0), grid, ball_density, nothing, STEP_BEYOND_WARMUP, config)
    np.testing.assert_allclose(np.asarray(decayed.density), old * np.float32(0.95), rtol=1e-6)

    # A constant density of 100 replaces exactly the sampled cells: at most 2 M per cascade.
    everything = make_balls([[0.0, 0.0, 0.0]], [10.0], [100.0], HARD)
    updated = occ.update_occupancy(jax.random.key(1), grid, ball_density, everything, STEP_BEYOND_WARMUP, config)
    changed = np.asarray(updated.density) == 100.0
    np.testing.assert_allclose(np.asarray(updated.density)[~changed], old[~changed] * np.float32(0.95), rtol=1e-6)
    num_draws = config.samples_per_cascade(grid)
    assert num_draws == G**3 // 4
    assert np.all(changed.sum(1) <= 2 * num_draws) and np.all(changed.sum(1) >= num_draws // 2)


@pytest.mark.slow
def test_occupied_cells_are_resampled_after_warmup():
    grid = occ.init_occupancy(BOX, aabb_scale=2, resolution=G)
    config = occ.OccupancyConfig.create(grid)
    target = (0, 1234), (1, 99)
    grid = grid.replace(bitfield=jnp.zeros_like(grid.bitfield).at[target[0]].set(True).at[target[1]].set(True))
    everything = make_balls([[0.0, 0.0, 0.0]], [10.0], [100.0], HARD)
    for seed in range(5):
        updated = occ.update_occupancy(jax.random.key(seed), grid, ball_density, everything, STEP_BEYOND_WARMUP, config)
        # 1024 uniform draws hit one given cell of 4096 with probability 22 %; the occupied draws always do.
        assert float(updated.density[target[0]]) == 100.0 and float(updated.density[target[1]]) == 100.0


@pytest.mark.slow
def test_update_is_deterministic_per_key():
    grid = occ.init_occupancy(BOX, resolution=G)
    config = occ.OccupancyConfig.create(grid)
    params = make_balls([[0.1, 0.0, 0.0]], [0.5], [5.0], GAUSS)
    a = occ.update_occupancy(jax.random.key(3), grid, ball_density, params, 0, config)
    b = occ.update_occupancy(jax.random.key(3), grid, ball_density, params, 0, config)
    c = occ.update_occupancy(jax.random.key(4), grid, ball_density, params, 0, config)
    np.testing.assert_array_equal(np.asarray(a.density), np.asarray(b.density))
    assert not np.array_equal(np.asarray(a.density), np.asarray(c.density))


def test_mark_all_occupied():
    grid = occ.init_occupancy(BOX, resolution=4)
    grid = grid.replace(bitfield=jnp.zeros_like(grid.bitfield), density=jnp.ones_like(grid.density))
    marked = occ.mark_all_occupied(grid)
    assert bool(marked.bitfield.all())
    np.testing.assert_array_equal(np.asarray(marked.density), 1.0)


# --------------------------------------------------------------------------------------------------
# Marching

# One budget for every test (one compilation per ray-batch shape): 512 minimal steps per box diagonal.
MARCH = marching.MarchConfig.create(max_steps=540, max_samples=540, steps_per_diagonal=512)
DT_MIN = 2 * math.sqrt(3) / 512
SHORT = MARCH.replace(max_samples=64)  # for single rays with fewer occupied candidates than steps
MARCH_RAYS = jax.jit(jax.vmap(marching.march_ray, in_axes=(None, 0, 0, 0, 0, None, None)))
MARCH_RAYS_KEYED = jax.jit(jax.vmap(marching.march_ray, in_axes=(None, 0, 0, 0, 0, None, 0)))


CAMERA = look_at(jnp.array([0.6, 0.9, 3.2]), jnp.zeros(3), jnp.array([0.0, 1.0, 0.0]))
VIEW = Intrinsics.from_fov(16, 16, math.radians(50.0))


@functools.lru_cache(maxsize=None)
def _camera_rays():
    """Rays [256, 3] of a 16x16 camera at (0.6, 0.9, 3.2) looking at the origin, 50 degree field of view."""
    origins, directions = jax.jit(camera_rays)(CAMERA, VIEW)
    return origins.reshape(-1, 3), directions.reshape(-1, 3)


def _render(params, grid, march_config, packing=None):
    """The view of CAMERA through `grid` with the marched renderer: (RenderOutput [256], evaluations [256])."""
    setup = marched.MarchSetup(grid, RENDER_CONFIG, march_config)
    views = marched.render_marched(ball_field, params, setup, CAMERA[None], VIEW, packing)
    return jax.tree.map(lambda a: a.reshape((-1,) + a.shape[3:]), views.output), views.evaluations.reshape(-1)


RENDER_DENSE = jax.jit(render_rays, static_argnames=("field",))
RENDER_CONFIG = RenderConfig.create(near=0.1, far=8.0, aabb=BOX, num_samples=512, background=(0.1, 0.2, 0.3))
BALL = make_balls([[0.15, -0.1, 0.05]], [0.4], [40.0], SMOOTH)
FULL = MARCH.replace(min_transmittance=jnp.float32(0.0))


def _marked_grid(center, radius):
    """The grid whose occupied cells are exactly those intersecting a ball (computed in NumPy)."""
    grid = occ.init_occupancy(BOX, resolution=G)
    lo, hi = np_all_cell_boxes(grid)
    nearest = np.clip(np.asarray(center), lo, hi)
    return grid.replace(bitfield=jnp.asarray(np.linalg.norm(nearest - np.asarray(center), axis=-1) < radius))


@pytest.fixture(scope="module")
def sparse_grid():
    """The grid NGP's updates build for BALL."""
    grid = occ.init_occupancy(BOX, resolution=G)
    return _run_updates(grid, ball_density, BALL, occ.OccupancyConfig.create(grid), steps=list(range(16)))


@pytest.fixture(scope="module")
def dense_render():
    origins, directions = _camera_rays()
    return RENDER_DENSE(ball_field, BALL, origins, directions, RENDER_CONFIG)


@pytest.mark.slow
def test_marching_on_full_grid_matches_dense_sampling():
    grid = occ.init_occupancy(BOX, resolution=G)  # all occupied
    origins, directions = _camera_rays()
    params = make_balls([[0.1, 0.2, -0.1], [-0.4, -0.3, 0.3]], [0.5, 0.3], [3.0, 6.0], GAUSS)
    out, evaluations = _render(params, grid, FULL)
    dense = RENDER_DENSE(ball_field, params, origins, directions, RENDER_CONFIG)
    assert 0.2 < float(dense.acc.mean()) and float(dense.acc.max()) < 0.9999  # semi-transparent
    np.testing.assert_allclose(np.asarray(out.rgb), np.asarray(dense.rgb), atol=2e-4)
    np.testing.assert_allclose(np.asarray(out.acc), np.asarray(dense.acc), atol=2e-4)
    np.testing.assert_allclose(np.asarray(out.depth), np.asarray(dense.depth), atol=2e-3)
    # Every step inside the box is evaluated: about 512 per box diagonal.
    assert int(evaluations.max()) > 300


@pytest.mark.slow
def test_marching_on_marked_grid_matches_dense_with_fewer_evaluations(dense_render):
    grid = _marked_grid(BALL["center"][0], float(BALL["radius"][0]))
    assert 0.01 < float(grid.bitfield.mean()) < 0.1
    origins, _ = _camera_rays()
    out, evaluations = _render(BALL, grid, MARCH)
    assert float(dense_render.acc.max()) > 0.99 and float(dense_render.acc.min()) < 1e-6  # ball and background
    np.testing.assert_allclose(np.asarray(out.rgb), np.asarray(dense_render.rgb), atol=3e-4)
    np.testing.assert_allclose(np.asarray(out.acc), np.asarray(dense_render.acc), atol=3e-4)
    assert int(evaluations.sum()) * 5 <= origins.shape[0] * RENDER_CONFIG.num_samples
    # Rays that miss every occupied cell cost nothing.
    assert int((np.asarray(evaluations) == 0).sum()) > origins.shape[0] // 4


@pytest.mark.slow
def test_marching_on_updated_grid_is_close_to_dense(sparse_grid, dense_render):
    """With the grid NGP's update builds, cells that the ball only grazes can be missed (one jittered
    sample per cell and update): the image matches everywhere but at a few silhouette pixels."""
    origins, _ = _camera_rays()
    out, evaluations = _render(BALL, sparse_grid, MARCH)
    error = np.abs(np.asarray(out.rgb) - np.asarray(dense_render.rgb)).max(-1)
    assert error.mean() < 1e-3 and error.max() < 0.05 and (error > 5e-3).mean() < 0.02
    assert int(evaluations.sum()) * 5 <= origins.shape[0] * RENDER_CONFIG.num_samples


@pytest.mark.slow
def test_early_stop_drops_samples_behind_opaque_surfaces():
    grid = occ.init_occupancy(BOX, resolution=G)
    params = make_balls([[0.0, 0.0, 0.0]], [0.8], [400.0], SMOOTH)
    # At most 8 samples a ray and pass: a ray stops within 8 samples of the surface.
    packing = marched.Packing(slots_per_ray=8, row_length=4, max_rows_per_ray=2)
    stop, n_stop = _render(params, grid, MARCH, packing)
    full, n_full = _render(params, grid, FULL, packing)
    np.testing.assert_allclose(np.asarray(stop.rgb), np.asarray(full.rgb), atol=2e-4)
    hit = np.asarray(full.acc) > 0.9999
    assert hit.sum() > 10 and np.all(np.asarray(n_stop)[hit] < 0.7 * np.asarray(n_full)[hit])


def _ray_batch():
    origins, directions = _camera_rays()
    miss_dirs = jnp.array([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])  # from (0.6, 0.9, 3.2): away from the box
    origins = jnp.concatenate([origins, jnp.broadcast_to(origins[:1], (2, 3))])
    directions = jnp.concatenate([directions, miss_dirs])
    geometry = occ.init_occupancy(BOX, resolution=G)  # the interval only depends on the grid's box
    t_enter, t_exit = jax.vmap(lambda o, d: marching.ray_interval(geometry, o, d, RENDER_CONFIG))(origins, directions)
    return origins, directions, t_enter, t_exit


@pytest.mark.slow
def test_march_samples_are_ordered_occupied_and_masked(sparse_grid):
    origins, directions, t_start, t_end = _ray_batch()
    t, delta, mask = (np.asarray(a) for a in MARCH_RAYS(sparse_grid, origins, directions, t_start, t_end, MARCH, None))
    num = mask.sum(1)
    assert num.max() > 10 and num[-2:].sum() == 0  # the last two rays miss the box
    # Valid samples form a prefix, strictly increasing, inside [t_start, t_end], in occupied cells.
    np.testing.assert_array_equal(mask, np.arange(mask.shape[1])[None] < num[:, None])
    for i in range(len(num)):
        assert np.all(np.diff(t[i, : num[i]]) > 0)
    assert np.all(t[mask] >= np.repeat(np.asarray(t_start), num) - 1e-6)
    assert np.all(t[mask] <= np.repeat(np.asarray(t_end), num) + 1e-6)
    points = np.asarray(origins)[:, None] + t[..., None] * np.asarray(directions)[:, None]
    assert np.asarray(IS_OCCUPIED(sparse_grid, points[mask])).all()
    assert np.all(delta[~mask] == 0.0) and np.all(t[~mask] == 0.0) and np.all(delta[mask] > 0.0)
    assert np.all(delta[mask] <= DT_MIN * (1 + 1e-4))
    # Compaction keeps exactly the candidates in occupied cells: count them independently.
    k = np.arange(MARCH.max_steps)
    skipped = 0
    for i in range(len(num)):
        lo = float(t_start[i]) + k * DT_MIN
        cand = lo + 0.5 * np.minimum(DT_MIN, float(t_end[i]) - lo)
        inside = lo < float(t_end[i])
        keep = inside & np.asarray(
            IS_OCCUPIED(sparse_grid, np.asarray(origins[i]) + cand[:, None] * np.asarray(directions[i]))
        )
        assert keep.sum() == num[i]
        np.testing.assert_allclose(t[i, : num[i]], cand[keep], atol=1e-4)
        skipped += int(num[i] > 0 and keep.sum() < inside.sum())
    assert skipped >= 3  # rays through the ball skip the empty cells before and after it


@pytest.mark.slow
def test_march_budget_keeps_the_first_samples():
    grid = occ.init_occupancy(BOX, resolution=G)
    origin, direction = jnp.array([[0.0, 0.0, -3.0]]), jnp.array([[0.0, 0.0, 1.0]])
    # The box holds 2 / DT_MIN = 295 candidates of this ray; the first 64 are kept.
    t, delta, mask = MARCH_RAYS(grid, origin, direction, jnp.array([2.0]), jnp.array([4.0]), SHORT, None)
    assert bool(mask.all())
    np.testing.assert_allclose(np.asarray(t[0]), 2.0 + DT_MIN * (np.arange(64) + 0.5), rtol=1e-5)
    np.testing.assert_allclose(np.asarray(delta[0]), DT_MIN, rtol=1e-4)


@pytest.mark.slow
def test_march_determinism_and_random_offset(sparse_grid):
    origins, directions, t_start, t_end = _ray_batch()
    first = MARCH_RAYS(sparse_grid, origins, directions, t_start, t_end, MARCH, None)
    second = MARCH_RAYS(sparse_grid, origins, directions, t_start, t_end, MARCH, None)
    for a, b in zip(first, second):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    keys = jax.random.split(jax.random.key(0), origins.shape[0])
    keyed = MARCH_RAYS_KEYED(sparse_grid, origins, directions, t_start, t_end, MARCH, keys)
    again = MARCH_RAYS_KEYED(sparse_grid, origins, directions, t_start, t_end, MARCH, keys)
    np.testing.assert_array_equal(np.asarray(keyed[0]), np.asarray(again[0]))
    other = MARCH_RAYS_KEYED(
        sparse_grid, origins, directions, t_start, t_end, MARCH, jax.random.split(jax.random.key(1), origins.shape[0])
    )
    valid = np.asarray(keyed[2]) & np.asarray(other[2])
    assert valid.any() and not np.allclose(np.asarray(keyed[0])[valid], np.asarray(other[0])[valid])
    # The offset moves samples within their bins only: the same bins, so nearly the same sample count.
    assert np.abs(np.asarray(keyed[2]).sum(1) - np.asarray(first[2]).sum(1)).max() <= 8


STEP_EDGES = jax.jit(marching._step_edges, static_argnums=1)


@pytest.mark.parametrize("t_start", [0.0, 0.05, 0.7, 3.0])
def test_cone_stepping_follows_ngp_recurrence(t_start):
    dt_min, dt_max, cone = 0.01, 0.08, 1 / 32
    edges = np.asarray(STEP_EDGES(jnp.float32(t_start), 600, dt_min, dt_max, cone), np.float64)
    expected = [t_start]
    for _ in range(600):
        expected.append(expected[-1] + min(max(expected[-1] * cone, dt_min), dt_max))
    np.testing.assert_allclose(edges, expected, rtol=2e-4, atol=1e-5)
    assert np.all(np.diff(edges) > 0)


@pytest.mark.slow
def test_cone_stepping_grows_steps_with_distance():
    grid = occ.init_occupancy(BOX, aabb_scale=4, resolution=G)  # 3 cascades, the outer one [-4, 4]^3
    cone = SHORT.replace(cone_angle=jnp.float32(1 / 8))
    origin, direction = jnp.array([[0.0, 0.0, -3.9]]), jnp.array([[0.0, 0.0, 1.0]])
    t, delta, mask = (
        np.asarray(a[0]) for a in MARCH_RAYS(grid, origin, direction, jnp.array([0.0]), jnp.array([7.8]), cone, None)
    )
    dt_max = 2 * math.sqrt(3) * 4 / G  # the coarsest cascade's cell diagonal
    valid = delta[mask][:-1]  # the last bin is cut at t_end
    assert t[mask].max() > 7.5 and mask.sum() < 64  # constant steps would need 1153
    # dt = t / 8 reaches dt_max only at t = 6.9, where this ray leaves the grid.
    assert valid.min() == pytest.approx(DT_MIN, rel=1e-4) and 0.5 * dt_max < valid.max() <= dt_max * (1 + 1e-5)
    assert np.all(np.diff(valid) >= -1e-6)


# --------------------------------------------------------------------------------------------------
# Compilation


@pytest.mark.slow
def test_update_and_render_compile_once(sparse_grid):
    grid = occ.init_occupancy(BOX, resolution=G)
    config = occ.OccupancyConfig.create(grid)
    grid = occ.update_occupancy(jax.random.key(0), grid, ball_density, BALL, 0, config)
    traced = TRACES["density"]
    other = make_balls([[0.0, 0.1, 0.0]], [0.3], [10.0], GAUSS)
    grid = occ.update_occupancy(jax.random.key(1), grid, ball_density, other, 300, config)
    grid = occ.update_occupancy(
        jax.random.key(2), grid, ball_density, BALL, jnp.int32(5), config.replace(decay=jnp.float32(0.9))
    )
    assert TRACES["density"] == traced

    # A render of tiny shapes: traced once, whatever the params, grid and march numbers.
    tiny = marching.MarchConfig.create(max_steps=64, max_samples=16, steps_per_diagonal=32)
    first, n_first = _render(BALL, sparse_grid, tiny)
    traced = TRACES["density"]
    _render(other, occ.mark_all_occupied(sparse_grid), tiny.replace(cone_angle=jnp.float32(0.01)))
    again, _ = _render(BALL, sparse_grid, tiny)
    assert TRACES["density"] == traced
    np.testing.assert_array_equal(np.asarray(first.rgb), np.asarray(again.rgb))
    assert int(n_first.sum()) > 0
