"""Tests of the renderer of trained fields (waldo_jax.render.marched) and its packed rows (render.packed).

The claim under test: rendering P views through an occupancy grid with packed passes gives, ray by
ray, the plain composite of the ray's marched samples (`volume.volume_weights` over all of them):
exactly up to float32 rounding when nothing stops early, and within the ignored tail
(min_transmittance * max |rgb - background|) with early ray termination, whatever the block size,
the budget per pass, the row length, the pose count and the field chunking; while evaluating the
field only at the samples it needs.
"""

from __future__ import annotations

import dataclasses
import functools
import math

import waldo_jax  # noqa: F401  (XLA flags before the first computation)

import hypothesis.strategies as st
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings

from waldo_jax.cameras import look_at
from waldo_jax.render import RenderConfig, marched, marching, occupancy as occ, packed
from waldo_jax.render.volume import composite, view_rays, volume_weights
from waldo_jax.types import Intrinsics

BOX = np.array([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]], np.float32)
MIN_T = 1e-4
# Per-ray float32 sums in another order: the tolerance of "exact".
EXACT = 3e-6
# The ignored tail's bound, plus that rounding.
TAIL = 1.0001 * MIN_T + EXACT

# --------------------------------------------------------------------------------------------------
# An analytic field: params = {"wall": z of a wall, "peak": density behind it, "fog": density inside a
# ball of radius 0.9, "hole": 1 empties the quadrant x > 0.5, y > 0.5}. One function for all cases.

TRACES = {"field": 0}


def density(params, x):
    behind = (x[2] > params["wall"]).astype(jnp.float32)
    fog = (jnp.sum(x * x) < 0.81).astype(jnp.float32)
    hole = params["hole"] * ((x[0] > 0.5) & (x[1] > 0.5)).astype(jnp.float32)
    return (params["peak"] * behind + params["fog"] * fog) * (1.0 - hole)


def field(params, x, d):
    TRACES["field"] += 1
    return density(params, x), 0.5 + 0.4 * jnp.sin(jnp.array([3.0, 5.0, 7.0]) * x + jnp.array([0.0, 1.0, 2.0]) + d)


def scene_params(wall=0.2, peak=0.0, fog=0.0, hole=0.0):
    return {k: jnp.float32(v) for k, v in dict(wall=wall, peak=peak, fog=fog, hole=hole).items()}


WALL = scene_params(peak=400.0, hole=1.0)  # opaque behind z = 0.2, except an empty quadrant
FOG = scene_params(fog=0.6)  # transmittance never below 0.3: no ray stops early
DENSE_FOG = scene_params(fog=8.0)  # transmittance reaches 1e-4 inside the fog: some rays stop there

RENDER_CONFIG = RenderConfig.create(near=0.1, far=8.0, aabb=BOX, background=(0.1, 0.2, 0.3), ray_chunk=1)
# dt_min = 2 sqrt(3) / 128 = 0.027: up to ~70 samples inside the box.
MARCH = marching.MarchConfig.create(max_steps=200, max_samples=200, steps_per_diagonal=128, min_transmittance=MIN_T)
FULL = MARCH.replace(min_transmittance=jnp.float32(0.0))
INTRINSICS = Intrinsics.from_fov(9, 7, math.radians(60.0))  # 63 rays a view: blocks never divide evenly


def cameras(count):
    """`count` cameras on a circle of radius 3.2 around the box, looking at its centre."""
    angles = np.linspace(0.3, 2.0, count, dtype=np.float32)
    origins = np.stack([3.2 * np.sin(angles), 0.4 * np.ones_like(angles), -3.2 * np.cos(angles)], -1)
    return jax.vmap(look_at, in_axes=(0, None, None))(jnp.asarray(origins), jnp.zeros(3), jnp.array([0.0, 1.0, 0.0]))


@functools.lru_cache(maxsize=None)
def grid_for(name):
    """The grid one warm-up update builds for a field (every cell sampled once)."""
    params = {"wall": WALL, "fog": FOG, "dense_fog": DENSE_FOG}[name]
    grid = occ.init_occupancy(BOX, resolution=16)
    return occ.update_occupancy(jax.random.key(0), grid, density, params, 0, occ.OccupancyConfig.create(grid))


def as_numpy(tree):
    return jax.tree.map(np.asarray, tree)


@functools.partial(jax.jit, static_argnames=("field_fn",))
def reference(field_fn, params, grid, c2w, intrinsics, render_config, march):
    """The per-ray reference: march each ray, evaluate the field at ALL its samples, composite them
    with `volume_weights` (no early stop). Returns (RenderOutput [P * H * W], samples per ray)."""
    ids = jnp.arange(c2w.shape[0] * intrinsics.height * intrinsics.width)
    origins, directions, _, _ = view_rays(c2w[:, :3, :4], intrinsics, ids)

    def one(o, d):
        t_start, t_end = marching.ray_interval(grid, o, d, render_config)
        t, delta, mask = marching.march_ray(grid, o, d, t_start, t_end, march)
        sigma, rgb = jax.vmap(field_fn, in_axes=(None, 0, None))(params, o + t[:, None] * d, d)
        w = volume_weights(jnp.where(mask, sigma, 0.0), delta)
        return composite(w, rgb, t, render_config.background), jnp.sum(mask)

    return jax.vmap(one)(origins, directions)


def render(params, grid, c2w, march=MARCH, packing=None, field_fn=field):
    setup = marched.MarchSetup(grid, RENDER_CONFIG, march)
    views = marched.render_marched(field_fn, params, setup, c2w, INTRINSICS, packing)
    flat = jax.tree.map(lambda a: np.asarray(a).reshape((-1,) + a.shape[3:]), views.output)
    return flat, np.asarray(views.evaluations).reshape(-1), np.asarray(views.passes)


PACKINGS = [
    # one block of the whole call, 32 slots a ray and pass, rows of 8, one field call a pass (the CPU defaults)
    marched.Packing.for_backend("cpu"),
    # blocks of 40 rays, 4 slots a ray and pass in rows of 2, at most 2 rows a ray: many passes
    marched.Packing(rays_per_block=40, slots_per_ray=4, row_length=2, max_rows_per_ray=2, field_chunk=0),
    # single-sample rows, field calls of 7 slots (a chunked field pass with a remainder)
    marched.Packing(rays_per_block=100, slots_per_ray=3, row_length=1, max_rows_per_ray=8, field_chunk=7),
]


# --------------------------------------------------------------------------------------------------
# Equal to the per-ray composite


@pytest.mark.parametrize("packing", PACKINGS, ids=["cpu-default", "small-blocks", "single-slot-rows"])
@pytest.mark.parametrize("poses", [1, 3])
def test_equals_the_per_ray_composite_without_early_stop(packing, poses):
    c2w = cameras(poses)
    for name, params in (("fog", FOG), ("wall", WALL)):
        grid = grid_for(name)
        out, evaluations, passes = render(params, grid, c2w, FULL, packing)
        expected, counts = as_numpy(reference(field, params, grid, c2w, INTRINSICS, RENDER_CONFIG, FULL))
        np.testing.assert_allclose(out.rgb, expected.rgb, atol=EXACT)
        np.testing.assert_allclose(out.acc, expected.acc, atol=EXACT)
        np.testing.assert_allclose(out.depth, expected.depth, atol=EXACT * 8)
        # Without early stop every marched sample is evaluated once, and nothing else.
        np.testing.assert_array_equal(evaluations, counts)
        assert counts.max() > 20 and (counts == 0).any()  # long rays, and rays that miss the box


@pytest.mark.parametrize("packing", PACKINGS[:2], ids=["cpu-default", "small-blocks"])
def test_early_stop_loses_only_the_tail(packing):
    c2w = cameras(2)
    for name, params in (("dense_fog", DENSE_FOG), ("wall", WALL)):
        grid = grid_for(name)
        out, evaluations, _ = render(params, grid, c2w, MARCH, packing)
        full, counts = as_numpy(reference(field, params, grid, c2w, INTRINSICS, RENDER_CONFIG, FULL))
        assert np.abs(out.rgb - full.rgb).max() <= TAIL  # colours and background in [0, 1]
        assert np.abs(out.acc - full.acc).max() <= TAIL
        assert np.all(out.acc <= full.acc + EXACT)  # only the tail is lost
        # Every sample before the ray's transmittance fell below MIN_T was evaluated, and none past its end.
        needed = needed_samples(params, grid, c2w)
        assert np.all(evaluations >= needed - 1) and np.all(evaluations <= counts)
        stopped = needed < counts
        assert stopped.sum() > 10


@jax.jit
def _march_reference(params, grid, c2w):
    """Every ray's full march (step sizes, mask) and the densities at its samples, in one program."""
    ids = jnp.arange(c2w.shape[0] * INTRINSICS.height * INTRINSICS.width)
    origins, directions, _, _ = view_rays(c2w[:, :3, :4], INTRINSICS, ids)
    t_start, t_end = jax.vmap(lambda o, d: marching.ray_interval(grid, o, d, RENDER_CONFIG))(origins, directions)
    t, delta, mask = jax.vmap(lambda o, d, a, b: marching.march_ray(grid, o, d, a, b, FULL))(
        origins, directions, t_start, t_end
    )
    points = origins[:, None] + t[..., None] * directions[:, None]
    sigma = jax.vmap(jax.vmap(density, in_axes=(None, 0)), in_axes=(None, 0))(params, points)
    return delta, mask, sigma


def needed_samples(params, grid, c2w):
    """Per ray, the samples an exact early stop evaluates: up to and including the first after which the
    transmittance is below MIN_T (float64 optical depths), or all of them."""
    delta, mask, sigma = as_numpy(_march_reference(params, grid, c2w))
    after = np.exp(-np.cumsum(np.where(mask, sigma.astype(np.float64) * delta, 0.0), axis=1))
    stopped = mask & (after < MIN_T)
    return np.where(stopped.any(1), np.argmax(stopped, axis=1) + 1, mask.sum(1))


def test_opaque_wall_is_evaluated_only_up_to_the_wall():
    """Rays hitting the opaque wall stop within a pass of it: a few samples past the wall at most."""
    c2w = cameras(3)
    grid = grid_for("wall")
    packing = marched.Packing(rays_per_block=64, slots_per_ray=4, row_length=2, max_rows_per_ray=2, field_chunk=0)
    out, evaluations, _ = render(WALL, grid, c2w, MARCH, packing)
    _, counts = as_numpy(reference(field, WALL, grid, c2w, INTRINSICS, RENDER_CONFIG, FULL))
    needed = needed_samples(WALL, grid, c2w)
    # The wall (density 400, dt 0.027: optical depth 10.8 a sample) stops a ray at its first sample
    # behind it; a pass hands a ray at most 2 rows of 2 samples, so at most 3 are wasted.
    hit = (out.acc > 0.9999) & (counts > 30)
    assert hit.sum() > 10
    assert np.all(evaluations[hit] <= needed[hit] + 3) and evaluations[hit].mean() < 0.6 * counts[hit].mean()


def test_empty_rays_render_the_background_without_evaluations():
    grid = occ.init_occupancy(BOX, resolution=16).replace(bitfield=jnp.zeros((1, 16**3), bool))
    out, evaluations, passes = render(WALL, grid, cameras(2))
    np.testing.assert_array_equal(evaluations, 0)
    np.testing.assert_allclose(out.rgb, np.broadcast_to(np.asarray(RENDER_CONFIG.background), out.rgb.shape))
    np.testing.assert_array_equal(out.acc, 0.0)
    np.testing.assert_array_equal(passes, 0)  # no live ray: not a single field pass


def test_passes_are_few_when_the_budget_is_large():
    """A pass hands every live ray M // live rows, so a block of one pass size needs about
    (samples / budget) passes; smaller pass sizes for the tail evaluate fewer slots for the same work."""
    grid = grid_for("fog")
    c2w = cameras(3)
    _, counts = as_numpy(reference(field, FOG, grid, c2w, INTRINSICS, RENDER_CONFIG, FULL))
    one_size = marched.Packing(
        rays_per_block=2**15, slots_per_ray=16, row_length=8, max_rows_per_ray=32, field_chunk=0, pass_levels=1
    )
    views = marched.render_marched(field, FOG, marched.MarchSetup(grid, RENDER_CONFIG, FULL), c2w, INTRINSICS, one_size)
    slots = 16 * 192  # one block of the 189 rays, rounded up to 192
    assert views.passes.shape == (1,)
    assert int(views.passes[0]) <= math.ceil(counts.sum() / slots) + math.ceil(counts.max() / (8 * 32)) + 2
    levels = marched.render_marched(
        field,
        FOG,
        marched.MarchSetup(grid, RENDER_CONFIG, FULL),
        c2w,
        INTRINSICS,
        dataclasses.replace(one_size, pass_levels=3),
    )
    np.testing.assert_array_equal(np.asarray(levels.evaluations), np.asarray(views.evaluations))
    assert int(levels.slots[0]) < int(views.slots[0]) and int(levels.slots[0]) < 2 * counts.sum()


# --------------------------------------------------------------------------------------------------
# Compilation and determinism


def test_one_compile_per_pose_count_and_deterministic():
    grid = grid_for("fog")
    packing = PACKINGS[1]
    first = render(FOG, grid, cameras(2), packing=packing)
    traces = TRACES["field"]
    size = marched._render_jit._cache_size()
    again = render(FOG, grid, cameras(2), packing=packing)
    other = render(DENSE_FOG, grid_for("dense_fog"), cameras(2)[::-1], packing=packing)  # other params, poses, grid
    assert TRACES["field"] == traces and marched._render_jit._cache_size() == size
    for a, b in zip(jax.tree.leaves(first), jax.tree.leaves(again)):
        np.testing.assert_array_equal(a, b)
    assert not np.array_equal(first[0].rgb, other[0].rgb)
    render(FOG, grid, cameras(4), packing=packing)  # a new pose count: one more program
    assert marched._render_jit._cache_size() == size + 1


def test_packing_is_validated():
    with pytest.raises(ValueError, match="multiple of row_length"):
        marched.Packing(slots_per_ray=6, row_length=4)
    with pytest.raises(ValueError, match="power of two"):
        marched.Packing(max_rows_per_ray=3)
    with pytest.raises(ValueError, match="rays_per_block"):
        marched.Packing(rays_per_block=0)


# --------------------------------------------------------------------------------------------------
# Packed rows


@settings(max_examples=40, deadline=None)
@given(st.lists(st.integers(0, 5), min_size=1, max_size=12), st.integers(1, 20))
def test_layout_rows_and_segment_sums_match_numpy(requests, num_rows):
    rows = np.asarray(requests, np.int32)
    layout = as_numpy(jax.jit(packed.layout_rows, static_argnums=1)(jnp.asarray(rows), num_rows))
    start = np.cumsum(rows) - rows
    granted = np.clip(num_rows - start, 0, rows)
    np.testing.assert_array_equal(layout.granted, granted)
    owner = np.full(num_rows, -1)
    rank = np.zeros(num_rows, np.int64)
    for ray, (a, n) in enumerate(zip(start, granted)):
        owner[a : a + n], rank[a : a + n] = ray, np.arange(n)
    used = owner >= 0
    np.testing.assert_array_equal(layout.used, used)
    np.testing.assert_array_equal(layout.owner[used], owner[used])
    np.testing.assert_array_equal(layout.rank[used], rank[used])
    np.testing.assert_array_equal(layout.last, np.where(granted > 0, start + granted - 1, num_rows))
    values = np.arange(1, num_rows + 1, dtype=np.float32) ** 1.5
    segment_cumsum = jax.jit(packed.segment_cumsum, static_argnums=2)  # one program, not op by op
    sums = np.asarray(
        segment_cumsum(jnp.asarray(np.where(used, values, 0.0)), jnp.asarray(layout.rank), max(1, int(rows.max())))
    )
    for ray, (a, n) in enumerate(zip(start, granted)):
        np.testing.assert_allclose(sums[a : a + n], np.cumsum(values[a : a + n]), rtol=1e-6)


@pytest.mark.parametrize("peak", [1e-6, 1.0, 1e6])
def test_row_composite_matches_volume_weights_with_finite_gradients(peak):
    """Rays of up to 9 samples in rows of 2 (a carry from a previous pass on one ray): the composite and
    its gradient in sigma equal those of `volume_weights` over each ray's samples."""
    key = jax.random.key(0)
    counts = np.array([9, 0, 3, 1, 4], np.int32)
    s, rows = 2, 12
    sigma_rays = peak * jax.random.uniform(key, (5, 9))
    t_rays = jnp.cumsum(jnp.full((5, 9), 0.1), axis=1)
    rgb_rays = jax.random.uniform(jax.random.key(1), (5, 9, 3))
    carry = jnp.array([0.0, 0.0, 0.7, 0.0, 0.0])
    layout = packed.layout_rows(jnp.asarray(-(-counts // s)), rows)
    index, valid = packed.row_samples(layout, jnp.zeros(5, jnp.int32), jnp.asarray(counts), s)
    index = jnp.minimum(index, 8)

    def packed_colour(sigma_rays):
        owner = layout.owner[:, None]
        sums = packed.composite_rows(
            sigma_rays[owner, index],
            rgb_rays[owner, index],
            t_rays[owner, index],
            jnp.where(valid, 0.1, 0.0),
            layout,
            carry,
            8,
        )
        return sums.rgb, sums.acc, sums.depth, sums.optical_depth

    def reference_colour(sigma_rays):
        mask = jnp.arange(9)[None] < counts[:, None]
        delta = jnp.where(mask, 0.1, 0.0)
        sigma = jnp.where(mask, sigma_rays, 0.0)
        w = jax.vmap(volume_weights)(sigma, delta) * jnp.exp(-carry)[:, None]
        return (jnp.sum(w[..., None] * rgb_rays, 1), jnp.sum(w, 1), jnp.sum(w * t_rays, 1), jnp.sum(sigma * delta, 1))

    packed_colour, reference_colour = jax.jit(packed_colour), jax.jit(reference_colour)  # not op by op
    for a, b in zip(packed_colour(sigma_rays), reference_colour(sigma_rays)):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=2e-6, atol=1e-6 * max(1.0, peak * 0.1))
    weights = jnp.array([1.0, -2.0, 3.0])
    loss_packed = lambda x: jnp.sum(packed_colour(x)[0] * weights) + jnp.sum(packed_colour(x)[2])  # noqa: E731
    loss_reference = lambda x: jnp.sum(reference_colour(x)[0] * weights) + jnp.sum(reference_colour(x)[2])  # noqa: E731
    grad_packed = np.asarray(jax.jit(jax.grad(loss_packed))(sigma_rays))
    grad_reference = np.asarray(jax.jit(jax.grad(loss_reference))(sigma_rays))
    assert np.all(np.isfinite(grad_packed))
    np.testing.assert_allclose(grad_packed, grad_reference, rtol=1e-5, atol=1e-7)


# --------------------------------------------------------------------------------------------------
# A trained field: lego_tiny


@pytest.fixture(scope="module")
def trained_lego(trained_lego_fast):
    """lego_tiny trained with the fast preset (conftest's `trained_lego_fast`, trained once per session
    and shared with the convergence test): a real field with surfaces and empty space."""
    from conftest import require_scene
    from waldo_jax.nerf.checkpoint import load_checkpoint
    from waldo_jax.scenes import load_scene

    checkpoint, _ = trained_lego_fast
    return load_scene(require_scene("lego_tiny"), split="train"), load_checkpoint(checkpoint)


@pytest.mark.parametrize("packing", PACKINGS[:2], ids=["cpu-default", "small-blocks"])
@pytest.mark.parametrize("poses", [1, 2])
def test_trained_lego_equals_the_per_ray_composite(trained_lego, packing, poses):
    from waldo_jax.nerf.field import make_field
    from waldo_jax.nerf.trained import TrainedField, render_setup

    scene, result = trained_lego
    trained = TrainedField.create(
        result.params, result.occupancy, result.config, scene.near, scene.far, np.ones(3, np.float32), scene.aabb
    )
    setup = render_setup(trained)
    grid, render_config, march = setup
    assert 0.01 < float(jnp.mean(grid.bitfield)) < 0.5  # the trained grid skips empty space
    field_fn = make_field(result.config.field)
    c2w = jnp.asarray(scene.c2w[:poses])
    intrinsics = scene.intrinsics.scaled(20, 20)
    full = march.replace(min_transmittance=jnp.float32(0.0))
    views = marched.render_marched(
        field_fn, result.params, marched.MarchSetup(grid, render_config, full), c2w, intrinsics, packing
    )
    expected, counts = as_numpy(reference(field_fn, result.params, grid, c2w, intrinsics, render_config, full))
    out = jax.tree.map(lambda a: np.asarray(a).reshape((-1,) + a.shape[3:]), views.output)
    np.testing.assert_allclose(out.rgb, expected.rgb, atol=EXACT)
    np.testing.assert_allclose(out.acc, expected.acc, atol=EXACT)
    np.testing.assert_array_equal(np.asarray(views.evaluations).reshape(-1), counts)
    assert out.acc.max() > 0.99 and counts.max() > 10  # opaque surfaces, long rays
    # With early termination (the renderer's default): within the ignored tail, never more evaluations.
    views = marched.render_marched(field_fn, result.params, setup, c2w, intrinsics, packing)
    out = jax.tree.map(lambda a: np.asarray(a).reshape((-1,) + a.shape[3:]), views.output)
    assert np.abs(out.rgb - expected.rgb).max() <= TAIL
    evaluations = np.asarray(views.evaluations).reshape(-1)
    assert np.all(evaluations <= counts)


def test_a_coarser_march_with_the_finest_marchs_sizes_renders_the_same(trained_lego):
    """`render_setup(..., sizes_of=1)`: a step scale rendered with the static sizes of the training step's
    march (more candidate slots, the extra ones beyond the grid) gives the same image and evaluations,
    so the render-step calibration needs one compiled program for all its scales."""
    from waldo_jax.nerf.field import make_field
    from waldo_jax.nerf.trained import TrainedField, render_setup

    scene, result = trained_lego
    trained = TrainedField.create(
        result.params, result.occupancy, result.config, scene.near, scene.far, np.ones(3, np.float32), scene.aabb
    )
    field_fn = make_field(result.config.field)
    c2w, intrinsics = jnp.asarray(scene.c2w[:1]), scene.intrinsics.scaled(20, 20)
    views = []
    for sizes_of in (None, 1.0):
        setup = render_setup(trained, step_scale=3.0, sizes_of=sizes_of)
        views.append((setup.march.max_steps, marched.render_marched(field_fn, result.params, setup, c2w, intrinsics)))
    (steps_own, own), (steps_finest, finest) = views
    assert steps_finest > steps_own  # the finest march has more candidates
    np.testing.assert_array_equal(np.asarray(own.output.rgb), np.asarray(finest.output.rgb))
    np.testing.assert_array_equal(np.asarray(own.evaluations), np.asarray(finest.evaluations))


def test_small_calls_use_fewer_pass_sizes():
    """`Packing.min_pass_slots`: the backend default drops pass sizes under 2^14 slots (one size for a
    thousand rays, all four from about 14k rays); the dataclass default keeps every size."""
    default, every = marched.Packing.for_backend("cpu"), marched.Packing()
    sizes = {rays: marched.block_shape(default, rays, 128).rows for rays in (1024, 4608, 16384)}
    assert [len(rows) for rows in sizes.values()] == [1, 3, 4]
    for rows in sizes.values():
        assert all(r * default.row_length >= default.min_pass_slots for r in rows[1:])
    assert len(marched.block_shape(every, 1024, 128).rows) == every.pass_levels
    with pytest.raises(ValueError, match="min_pass_slots"):
        marched.Packing(min_pass_slots=0)
