"""Tests of early ray termination in the marched renderer (occupancy.render_samples_early_stop,
occupancy.render_rays_early_stop and the occupancy sampler's view renderer).

The claim under test: compositing each ray's samples front to back in fixed-budget passes and
retiring it once its transmittance falls below `min_transmittance` gives the full composite of all
its samples up to the ignored tail (colour within min_transmittance * max |rgb - background|), while
evaluating the field only up to the termination point (plus at most one segment).
"""

from __future__ import annotations

import functools
import math

import waldo_jax  # noqa: F401  (XLA flags before the first computation)

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from waldo_jax.cameras import camera_rays, look_at
from waldo_jax.nerf import HashGridConfig, NGPFieldConfig
from waldo_jax.nerf import occupancy as occ
from waldo_jax.nerf import train as tr
from waldo_jax.nerf.field import init_field
from waldo_jax.render import RenderConfig
from waldo_jax.types import Intrinsics

BOX = np.array([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]], np.float32)
MIN_T = 1e-4
# The bound of the ignored tail, plus float32 rounding of sums in a different order.
TAIL = 1.0001 * MIN_T + 2e-6
EXACT = 2e-6

# --------------------------------------------------------------------------------------------------
# Analytic fields: params = {"wall": z of the wall, "peak": density behind it, "fog": density inside the
# fog ball of radius 0.9, "hole": 1 makes the quadrant x > 0.5, y > 0.5 empty}. One density function
# for all cases, so each shape compiles once.

TRACES = {"field": 0}


def density(params, x):
    behind = (x[2] > params["wall"]).astype(jnp.float32)
    fog = (jnp.sum(x * x) < 0.81).astype(jnp.float32)
    hole = params["hole"] * ((x[0] > 0.5) & (x[1] > 0.5)).astype(jnp.float32)
    return (params["peak"] * behind + params["fog"] * fog) * (1.0 - hole)


def field(params, x, d):
    TRACES["field"] += 1
    return density(params, x), 0.5 + 0.4 * jnp.sin(jnp.array([3.0, 5.0, 7.0]) * x + jnp.array([0.0, 1.0, 2.0]))


def scene_params(wall=0.2, peak=0.0, fog=0.0, hole=0.0):
    return {k: jnp.float32(v) for k, v in dict(wall=wall, peak=peak, fog=fog, hole=hole).items()}


WALL = scene_params(peak=400.0, hole=1.0)  # opaque behind z = 0.2, except an empty quadrant
FOG = scene_params(fog=0.6)  # optical depth at most 0.6 * 1.8: transmittance never below 0.3
DENSE_FOG = scene_params(fog=8.0)  # transmittance reaches 1e-4 after ~1.15 of fog: some rays stop inside

RENDER_CONFIG = RenderConfig.create(near=0.1, far=8.0, aabb=BOX, background=(0.1, 0.2, 0.3), ray_chunk=32)
# dt_min = 2 sqrt(3) / 128 = 0.027; 4 packed slots per ray and pass; segments of at most 4 samples.
MARCH = occ.MarchConfig.create(max_steps=200, max_samples=200, steps_per_diagonal=128, packed_samples_per_ray=4,
                               max_segment=4, min_transmittance=MIN_T)
FULL = MARCH.replace(min_transmittance=jnp.float32(0.0))


@functools.lru_cache(maxsize=None)
def rays():
    """70 rays: 64 from z = -3 towards +z, fanning out a little, 4 through the wall's empty quadrant,
    2 that miss the box (70 is not a multiple of the 32-ray chunk: the last chunk is padded)."""
    u = np.linspace(-0.6, 0.6, 8, dtype=np.float32)
    x, y = np.meshgrid(u, u)
    origins = np.stack([x.ravel() * 0.5, y.ravel() * 0.5, np.full(64, -3.0, np.float32)], -1)
    directions = np.stack([x.ravel() * 0.1, y.ravel() * 0.1, np.ones(64, np.float32)], -1)
    hole_origins = np.array([[0.7, 0.7, -3.0], [0.8, 0.6, -3.0], [0.6, 0.9, -3.0], [0.75, 0.75, -3.0]], np.float32)
    miss_origins = np.array([[0.0, 3.0, -3.0], [3.0, 0.0, -3.0]], np.float32)
    origins = np.concatenate([origins, hole_origins, miss_origins])
    directions = np.concatenate([directions, np.tile([[0.0, 0.0, 1.0]], (4, 1)), [[0.0, 1.0, 0.0], [1.0, 0.0, 0.0]]])
    directions = directions / np.linalg.norm(directions, axis=-1, keepdims=True)
    return jnp.asarray(origins), jnp.asarray(directions.astype(np.float32))


@functools.lru_cache(maxsize=None)
def grid_for(name):
    """The grid one warm-up update builds for a field (every cell sampled once)."""
    params = {"wall": WALL, "fog": FOG, "dense_fog": DENSE_FOG}[name]
    grid = occ.init_occupancy(BOX, resolution=16)
    return occ.update_occupancy(jax.random.key(0), grid, density, params, 0, occ.OccupancyConfig.create(grid))


RENDER_EARLY = jax.jit(occ.render_rays_early_stop, static_argnames=("field",))
RENDER_MARCHED = jax.jit(occ.render_rays_marched, static_argnames=("field",))
MARCH_RAYS = jax.jit(jax.vmap(
    lambda grid, o, d, config: occ.march_ray(grid, o, d, *occ.ray_interval(grid, o, d, RENDER_CONFIG), config),
    in_axes=(None, 0, 0, None)))


def as_numpy(tree):
    return jax.tree.map(np.asarray, tree)


def needed_samples(params, grid):
    """Per ray: valid marched samples, and the samples an exact early stop evaluates (up to and including
    the first after which the transmittance is below MIN_T), from float64 optical depths."""
    origins, directions = rays()
    t, delta, mask = as_numpy(MARCH_RAYS(grid, origins, directions, MARCH))
    points = np.asarray(origins)[:, None] + t[..., None] * np.asarray(directions)[:, None]
    sigma = np.asarray(jax.vmap(jax.vmap(density, in_axes=(None, 0)), in_axes=(None, 0))(params, jnp.asarray(points)))
    optical = np.where(mask, sigma.astype(np.float64) * delta, 0.0)
    after = np.exp(-np.cumsum(optical, axis=1))  # transmittance after each sample
    counts = mask.sum(1)
    stopped = mask & (after < MIN_T)
    needed = np.where(stopped.any(1), np.argmax(stopped, axis=1) + 1, counts)
    return counts, needed


def check_tail_bound(early, full, max_depth):
    """Early-stopped vs full composite: differences within the transmittance threshold's bound."""
    assert np.abs(early.rgb - full.rgb).max() <= TAIL  # colours and background in [0, 1]
    assert np.abs(early.acc - full.acc).max() <= TAIL
    assert np.abs(early.depth - full.depth).max() <= TAIL * max_depth
    # The composite only loses the tail: opacity never above the full one.
    assert np.all(early.acc <= full.acc + EXACT)


# --------------------------------------------------------------------------------------------------
# Equal to the full composite up to the ignored tail


@pytest.mark.parametrize("name", ["wall", "fog", "dense_fog"])
def test_early_stop_matches_full_composite(name):
    params = {"wall": WALL, "fog": FOG, "dense_fog": DENSE_FOG}[name]
    grid = grid_for(name)
    origins, directions = rays()
    early, evaluations, passes = as_numpy(RENDER_EARLY(field, params, grid, origins, directions, RENDER_CONFIG, MARCH))
    no_stop, all_evaluations, _ = as_numpy(RENDER_EARLY(field, params, grid, origins, directions, RENDER_CONFIG, FULL))
    # The reference: render_ray_marched evaluates and composites all S samples of each ray.
    full, _ = as_numpy(RENDER_MARCHED(field, params, grid, origins, directions, RENDER_CONFIG, FULL))
    counts, needed = needed_samples(params, grid)

    # Without a threshold, the passes composite every sample: the full composite up to rounding.
    for a, b in zip(jax.tree.leaves(no_stop), jax.tree.leaves(full)):
        np.testing.assert_allclose(a, b, atol=EXACT * 4, rtol=1e-5)
    np.testing.assert_array_equal(all_evaluations, counts)
    check_tail_bound(early, full, max_depth=8.0)
    assert passes.shape == (3,) and np.all(passes >= 1)

    hit = needed < counts  # rays whose transmittance falls below the threshold
    if name == "fog":
        assert not hit.any() and float(full.acc.max()) < 0.7
        np.testing.assert_array_equal(evaluations, counts)  # nothing to stop: every sample is evaluated
        np.testing.assert_allclose(early.rgb, full.rgb, atol=EXACT * 4)
    else:
        assert hit.sum() >= 10 if name == "dense_fog" else hit.sum() == 64
        if name == "dense_fog":  # rays through the fog ball's rim stay semi-transparent
            assert (~hit & (counts > 0)).sum() >= 4
        assert np.all(full.acc[hit] > 1.0 - TAIL)
        # The colour really comes from the front: with the wall's colour, not the background's.
        assert np.abs(full.rgb[hit] - np.asarray(RENDER_CONFIG.background)).max() > 0.1


def test_empty_rays_render_the_background_without_evaluations():
    grid = grid_for("wall")
    origins, directions = rays()
    early, evaluations, _ = as_numpy(RENDER_EARLY(field, WALL, grid, origins, directions, RENDER_CONFIG, MARCH))
    counts, _ = needed_samples(WALL, grid)
    # The last two rays miss the box; the four through the empty quadrant cross only empty cells.
    assert np.all(counts[-6:] == 0) and np.all(counts[:64] > 0)
    np.testing.assert_array_equal(evaluations[-6:], 0)
    np.testing.assert_array_equal(early.rgb[-6:], np.broadcast_to(np.asarray(RENDER_CONFIG.background), (6, 3)))
    np.testing.assert_array_equal(early.acc[-6:], 0.0)
    np.testing.assert_array_equal(early.depth[-6:], 0.0)
    # A grid with nothing occupied: every ray is empty, the loop ends at once.
    empty = grid.replace(bitfield=jnp.zeros_like(grid.bitfield))
    out, evaluations, passes = as_numpy(RENDER_EARLY(field, WALL, empty, origins, directions, RENDER_CONFIG, MARCH))
    np.testing.assert_array_equal(evaluations, 0)
    np.testing.assert_array_equal(passes, 0)
    np.testing.assert_array_equal(out.acc, 0.0)


# Hand-built samples [N = 6, S = 7] along +z from the origin (t = z), for rays with 0, 1 or all samples.
SAMPLE_T = np.linspace(-0.6, 0.6, 7, dtype=np.float32)
SAMPLE_COUNTS = np.array([0, 1, 1, 7, 7, 3])
SAMPLE_WALLS = np.array([0.0, 0.0, -1.0, 9.0, 0.1, 0.35], np.float32)  # ray 2: its one sample is behind a wall


def _hand_samples():
    mask = np.arange(7)[None] < SAMPLE_COUNTS[:, None]
    t = np.where(mask, SAMPLE_T, 0.0).astype(np.float32)
    delta = np.where(mask, 0.2, 0.0).astype(np.float32)
    origins = np.stack([np.linspace(-0.3, 0.3, 6), np.zeros(6), np.zeros(6)], -1).astype(np.float32)
    directions = np.tile(np.float32([[0.0, 0.0, 1.0]]), (6, 1))
    return origins, directions, t, delta, mask


def _one_ray_field(params, x, d):
    """Fog 0.5 everywhere plus a wall of density 300 behind z = params["wall"][ray], the ray told by x."""
    ray = jnp.clip(jnp.round((x[0] + 0.3) / 0.12), 0, 5).astype(jnp.int32)
    sigma = 0.5 + 300.0 * (x[2] > params["wall"][ray]).astype(jnp.float32)
    return sigma, 0.5 + 0.4 * jnp.sin(jnp.array([3.0, 5.0, 7.0]) * x + jnp.array([0.0, 1.0, 2.0]))


def _numpy_composite(origins, directions, t, delta, mask, background):
    """float64 volume rendering of all valid samples (the reference)."""
    points = origins[:, None] + t[..., None] * directions[:, None]
    sigma, rgb = jax.vmap(jax.vmap(_one_ray_field, in_axes=(None, 0, None)), in_axes=(None, 0, None))(
        {"wall": jnp.asarray(SAMPLE_WALLS)}, jnp.asarray(points), jnp.zeros(3))
    sigma, rgb = np.asarray(sigma, np.float64), np.asarray(rgb, np.float64)
    optical = np.where(mask, sigma * delta, 0.0)
    before = np.exp(-(np.cumsum(optical, 1) - optical))
    w = before * -np.expm1(-optical)
    acc = w.sum(1)
    return (w[..., None] * rgb).sum(1) + (1.0 - acc)[:, None] * background, (w * t).sum(1), acc, optical


RENDER_SAMPLES = jax.jit(occ.render_samples_early_stop, static_argnames=("field", "budget", "max_segment"))


@pytest.mark.parametrize("budget, max_segment", [(1, None), (3, 2), (5, 1), (64, None)])
def test_single_sample_rays_and_any_packing(budget, max_segment):
    """Rays with 0, 1 and 7 samples, cut into passes at every position: the float64 composite."""
    origins, directions, t, delta, mask = _hand_samples()
    background = np.float32([0.1, 0.2, 0.3])
    rgb, depth, acc, optical = _numpy_composite(origins, directions, t, delta, mask, background)
    params = {"wall": jnp.asarray(SAMPLE_WALLS)}
    for min_t in (0.0, MIN_T):
        out, evaluations, passes = as_numpy(RENDER_SAMPLES(_one_ray_field, params, origins, directions, t, delta,
                                                           mask, background, jnp.float32(min_t), budget, max_segment))
        tolerance = EXACT * 4 if min_t == 0.0 else TAIL
        np.testing.assert_allclose(out.rgb, rgb, atol=tolerance)
        np.testing.assert_allclose(out.acc, acc, atol=tolerance)
        np.testing.assert_allclose(out.depth, depth, atol=tolerance)
        assert out.acc[0] == 0.0 and evaluations[0] == 0  # no sample: the background
        np.testing.assert_allclose(out.rgb[0], background)
        assert evaluations[1] == 1 and evaluations[2] == 1
        assert acc[2] > 1.0 - 1e-12 and 0.0 < acc[1] < 0.2  # the single samples: opaque and faint
        if min_t == 0.0:
            np.testing.assert_array_equal(evaluations, SAMPLE_COUNTS)
        else:
            # Ray 4 (wall at z = 0.1) is opaque from its 5th sample (z = 0.2): nothing behind it is evaluated
            # when segments are short.
            assert np.exp(-optical[4, :5].sum()) < MIN_T
            assert evaluations[4] <= 5 + (budget if max_segment is None else max_segment) - 1
            assert evaluations[4] >= 5
        assert passes >= -(-int(evaluations.sum()) // budget)


# --------------------------------------------------------------------------------------------------
# Fewer evaluations


def test_opaque_wall_evaluates_only_up_to_the_wall():
    grid = grid_for("wall")
    origins, directions = rays()
    _, evaluations, passes = as_numpy(RENDER_EARLY(field, WALL, grid, origins, directions, RENDER_CONFIG, MARCH))
    counts, needed = needed_samples(WALL, grid)
    hit = needed < counts
    assert hit.sum() >= 60
    # Up to the wall, then at most one segment (4 samples) more; float32 vs float64 may move the
    # termination by one sample.
    assert np.all(evaluations >= np.maximum(needed - 1, 0))
    assert np.all(evaluations <= np.minimum(needed + MARCH.max_segment, counts))
    # The wall is opaque at its first sample: ~1-5 samples per hit ray instead of its ~30 valid ones.
    assert evaluations[hit].mean() <= 5 and counts[hit].mean() >= 25
    assert evaluations.sum() * 5 <= counts.sum()
    # Each pass evaluates B = 32 * 4 slots: the passes follow the evaluations, not the valid samples.
    assert passes.sum() * 32 * 4 < counts.sum()


def test_sampler_views_match_the_full_composite_with_fewer_evaluations():
    """The occupancy sampler's view renderer (render_views, used by evaluate and render_trained) on a
    random tiny NGP field: the old full composite of every marched sample, up to the tail."""
    field_config = NGPFieldConfig(aabb=BOX, hashgrid=HashGridConfig(L=4, T=2**12, F=2, N_min=8, N_max=64),
                                  density_hidden=(16,), color_hidden=(16,))
    config = tr.TrainConfig(field=field_config, steps=1, chunk=1, rays_per_batch=64, num_samples=48,
                            samples_per_batch=1024, eval_samples=48, occupancy_resolution=16, steps_per_diagonal=64.0,
                            sampler="occupancy", eval_ray_chunk=40)
    sampler = tr.make_sampler(config)
    params = init_field(jax.random.key(1), field_config)
    # Large hash features and a steeper log-density give partly opaque structure.
    params["hash"] = jax.random.normal(jax.random.key(2), params["hash"].shape) * 4.0
    density_out = params["density_mlp"]["params"]["Dense_1"]["kernel"]
    params["density_mlp"]["params"]["Dense_1"]["kernel"] = density_out.at[:, 0].multiply(2.0)
    grid = sampler.update(jax.random.key(3), sampler.init(jax.random.key(4), params), params, jnp.int32(0))
    positions = jnp.array([[3.0, 1.0, 3.5], [-3.5, 2.0, 1.0], [0.5, -3.0, -3.0]])
    c2w = jax.vmap(look_at, in_axes=(0, None, None))(positions, jnp.zeros(3), jnp.array([0.0, 1.0, 0.0]))
    intrinsics = Intrinsics.from_fov(10, 9, 0.9)  # 90 rays per view: chunks of 40, the last one padded
    render_config = tr._render_config(config, 0.5, 12.0, BOX, np.ones(3, np.float32), config.eval_samples)
    counted = sampler.render_views_counted(params, grid, c2w, intrinsics, render_config)
    views, view_evaluations, view_passes = as_numpy(counted)
    plain = as_numpy(sampler.render_views(params, grid, c2w, intrinsics, render_config))
    for a, b in zip(jax.tree.leaves(plain), jax.tree.leaves(views)):
        np.testing.assert_array_equal(a, b)
    assert tr._marched_views(config, config.eval_samples)._cache_size() == 1  # one program for both
    assert view_passes.shape == (3, 3) and view_evaluations.shape == (3, 9, 10)

    # The same rays as one batch. (Rays built in another program may differ in the last bit, which can
    # move a candidate across a cell boundary: the views are compared with a looser tolerance.)
    origins, directions = jax.jit(lambda c: jax.lax.map(lambda m: camera_rays(m, intrinsics), c[:, :3, :4]))(c2w)
    origins, directions = origins.reshape(-1, 3), directions.reshape(-1, 3)
    background = jnp.ones_like(origins)

    @jax.jit
    def batch(params, grid):
        """The early-stopped batch renderer and, as reference, every marched sample of every ray packed
        at once and composited (the renderer before early termination)."""
        early = sampler.render_ray_batch_counted(params, grid, origins, directions, background, render_config,
                                                 config.eval_samples, 7)
        t, delta, mask = sampler._march(grid, origins, directions, render_config, config.eval_samples, None)
        included = jnp.ones(origins.shape[:1], bool)
        full = sampler._render_packed(params, origins, directions, background, t, delta, mask, included, t.size)
        return early, full, jnp.sum(mask, axis=1)

    (early, evaluations, passes), full, counts = as_numpy(batch(params, grid))
    check_tail_bound(early, full, max_depth=12.0)
    stopped = evaluations < counts
    assert stopped.sum() >= 20 and np.all(full.acc[stopped] > 1.0 - TAIL)
    assert np.all(evaluations <= counts) and evaluations[stopped].sum() < 0.6 * counts[stopped].sum()
    assert np.all(evaluations[~stopped] == counts[~stopped])
    assert passes >= evaluations.sum() / 7

    # The views: chunked, padded and cropped as the batch.
    view_rgb = views.rgb.reshape(-1, 3)
    close = np.abs(view_rgb - early.rgb).max(-1) <= TAIL
    assert close.mean() > 0.95 and np.abs(view_rgb - early.rgb).max() < 0.05
    # Passes of 320 slots for 40 rays: once few rays are live, their segments take the free slots.
    view_evaluations = view_evaluations.reshape(-1)
    assert np.mean(view_evaluations <= counts) > 0.95 and np.mean(view_evaluations >= evaluations) > 0.95
    assert view_evaluations.sum() <= view_passes.sum() * 320


# --------------------------------------------------------------------------------------------------
# Compilation and determinism


def test_compiles_once_per_shape_and_is_deterministic():
    grid = grid_for("wall")
    origins, directions = rays()
    first = as_numpy(RENDER_EARLY(field, WALL, grid, origins, directions, RENDER_CONFIG, MARCH))
    traced = TRACES["field"]
    # Other parameters, grid, background and threshold: the same shapes, no new trace.
    again = as_numpy(RENDER_EARLY(field, WALL, grid, origins, directions, RENDER_CONFIG, MARCH))
    RENDER_EARLY(field, FOG, grid_for("fog"), origins + 0.01, directions, RENDER_CONFIG.replace(
        background=jnp.float32([0.5, 0.5, 0.5])), MARCH.replace(min_transmittance=jnp.float32(1e-2)))
    RENDER_EARLY(field, DENSE_FOG, grid, origins, directions, RENDER_CONFIG, FULL)
    assert TRACES["field"] == traced
    for a, b in zip(jax.tree.leaves(first), jax.tree.leaves(again)):
        np.testing.assert_array_equal(a, b)
    # Another shape-setting value (the segment cap) is another program.
    RENDER_EARLY(field, WALL, grid, origins, directions, RENDER_CONFIG, MARCH.replace(max_segment=2))
    assert TRACES["field"] > traced


def test_bad_budget_raises():
    origins, directions, t, delta, mask = _hand_samples()
    with pytest.raises(ValueError, match="budget must be >= 1"):
        occ.render_samples_early_stop(_one_ray_field, {"wall": jnp.asarray(SAMPLE_WALLS)}, origins, directions,
                                      t, delta, mask, jnp.zeros(3), MIN_T, 0)
    with pytest.raises(ValueError, match="max_segment"):
        occ.MarchConfig.create(max_segment=0)
    assert math.isclose(float(MARCH.min_transmittance), MIN_T, rel_tol=1e-6)
