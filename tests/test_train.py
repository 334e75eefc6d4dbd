"""Tests of NeRF training (waldo_jax.nerf.train): convergence, determinism, scan vs. step loop, samplers.

Small configurations keep the suite fast on 2 CPU cores: the determinism and loop tests share one
compiled chunk (same config), and only the convergence test trains for real.
"""

from __future__ import annotations

import dataclasses
import time

import waldo_jax  # noqa: F401  (XLA flags before the first computation)

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from conftest import require_scene
from waldo_jax.nerf import HashGridConfig, NGPFieldConfig
from waldo_jax.nerf import train as tr
from waldo_jax.scenes import load_scene

# A tiny field for the mechanics tests (not for quality).
TINY_FIELD = dict(hashgrid=HashGridConfig(L=4, T=2**12, F=2, N_min=8, N_max=64),
                  density_hidden=(16,), color_hidden=(16,))


@pytest.fixture(scope="module")
def lego_small():
    """lego_tiny's training split, 12 of its 90 views (enough for the mechanics tests)."""
    return load_scene(require_scene("lego_tiny"), split="train", max_images=12)


def _tiny_config(scene, sampler: str, **overrides) -> tr.TrainConfig:
    field = NGPFieldConfig(aabb=scene.aabb, **TINY_FIELD)
    values = dict(field=field, steps=5, chunk=3, rays_per_batch=128, num_samples=16, samples_per_batch=1024,
                  eval_samples=16, occupancy_resolution=16, occupancy_update_every=2, occupancy_warmup=2,
                  steps_per_diagonal=64.0, sampler=sampler)
    values.update(overrides)
    return tr.TrainConfig(**values)


def _samplers():
    return ["dense", "occupancy"]


def _leaves_bytes(tree):
    return [np.asarray(leaf).tobytes() for leaf in jax.tree.leaves(tree)]


# ----------------------------------------------------------------------------------------------
# Convergence: the real preset code on lego_tiny.


def test_fast_preset_reaches_20db_on_lego_tiny():
    """The fast preset (fewer steps, a smaller hash grid) beats 20 dB on lego_tiny's held-out views."""
    path = require_scene("lego_tiny")
    train_scene = load_scene(path, split="train")
    test_scene = load_scene(path, split="test")
    config = tr.TrainConfig.preset("fast", train_scene, steps=250, chunk=50, num_samples=128,
                                   samples_per_batch=2**14, eval_samples=128)
    hashgrid = dataclasses.replace(config.field.hashgrid, L=8, T=2**14)
    config = config.replace(field=dataclasses.replace(config.field, hashgrid=hashgrid))
    start = time.perf_counter()
    result = tr.train(jax.random.key(0), train_scene, config, test_scene, progress=False)
    seconds = time.perf_counter() - start
    assert result.steps == 250
    assert result.n_train == 90 and result.n_test == 10
    assert result.psnr_test is not None and result.psnr_test >= 20.0, (result.psnr_test, result.history[-3:])
    assert result.history[-1]["psnr_test"] == result.psnr_test
    losses = [h["loss"] for h in result.history if "loss" in h]
    assert losses[-1] < 0.5 * losses[0]
    assert result.rays_per_second > 0 and np.isfinite(result.rays_per_second)
    print(f"lego_tiny fast/test preset: {result.psnr_test:.2f} dB in {seconds:.1f} s "
          f"({result.rays_per_second:.0f} rays/s, sampler {config.sampler})")


# ----------------------------------------------------------------------------------------------
# Determinism and the scan against a step loop.


@pytest.mark.parametrize("sampler", _samplers())
def test_same_seed_same_params_other_seed_differs(lego_small, sampler):
    config = _tiny_config(lego_small, sampler)
    first = tr.train(jax.random.key(3), lego_small, config, progress=False)
    second = tr.train(jax.random.key(3), lego_small, config, progress=False)
    other = tr.train(jax.random.key(4), lego_small, config, progress=False)
    assert first.steps == second.steps == other.steps == 5
    assert _leaves_bytes(first.params) == _leaves_bytes(second.params)
    assert _leaves_bytes(first.occupancy) == _leaves_bytes(second.occupancy)
    assert [h["loss"] for h in first.history] == [h["loss"] for h in second.history]
    assert not np.array_equal(np.asarray(first.params["hash"]), np.asarray(other.params["hash"]))
    # The same config reuses the compiled chunk: no retrace across the three runs.
    assert tr._chunk_fn(config)._cache_size() == 1


@pytest.mark.parametrize("sampler", _samplers())
def test_scan_chunks_equal_step_loop(lego_small, sampler):
    """5 steps as scanned chunks of 3 (the last one half skipped) equal 5 calls of the jitted step."""
    config = _tiny_config(lego_small, sampler)
    key = jax.random.key(3)
    result = tr.train(key, lego_small, config, progress=False)

    inputs = tr.training_inputs(key, lego_small, config)
    step = jax.jit(tr.make_train_step(config))
    state = inputs.state
    losses = []
    for _ in range(config.steps):
        state, metrics = step(state, inputs.train_key, inputs.data, inputs.hparams, inputs.render_config)
        losses.append(float(metrics["loss"]))
    assert int(state.step) == result.steps == 5
    # The same operations compiled in two programs: bit-equal on CPU (XLA:CPU is deterministic and
    # fuses both alike); elsewhere equal to float32 rounding.
    for a, b in zip(jax.tree.leaves(result.params), jax.tree.leaves(state.params)):
        if jax.default_backend() == "cpu":
            np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
        else:
            np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-5, atol=1e-7)
    chunk_losses = [h["loss"] for h in result.history if "loss" in h]
    np.testing.assert_allclose(chunk_losses, [np.mean(losses[:3]), np.mean(losses[3:])], rtol=1e-5)
    # The skipped tail of the last chunk does not move the state past `steps`.
    if result.occupancy is not None:
        np.testing.assert_allclose(np.asarray(result.occupancy.density), np.asarray(state.sampler_state.density),
                                   rtol=1e-5, atol=1e-6)


# ----------------------------------------------------------------------------------------------
# Rays and targets.


def test_batch_targets_composite_rgba_on_the_ray_background(lego_small):
    """Targets are rgb * a + (1 - a) * bg with the ray's own background, and rays pass through their pixel."""
    config = _tiny_config(lego_small, "dense", rays_per_batch=512)
    data = tr.TrainData.from_scene(lego_small)
    origins, directions, target, background = jax.jit(lambda k: tr._sample_batch(k, data, config))(
        jax.random.key(0))
    origins, directions, target, background = map(np.asarray, (origins, directions, target, background))
    assert background.std() > 0.2  # random per ray, not one colour
    np.testing.assert_allclose(np.linalg.norm(directions, axis=-1), 1.0, rtol=1e-5)
    # Recover each ray's pixel by projecting a point on it into each training camera.
    intr = lego_small.intrinsics
    matched = 0
    for o, d, t, bg in zip(origins[:64], directions[:64], target[:64], background[:64]):
        image = int(np.argmin(np.linalg.norm(lego_small.c2w[:, :3, 3] - o, axis=-1)))
        c2w = lego_small.c2w[image].astype(np.float64)
        p = (o + 3.0 * d - c2w[:3, 3]) @ c2w[:3, :3]
        u = float(intr.fx) * p[0] / -p[2] + float(intr.cx)
        v = -float(intr.fy) * p[1] / -p[2] + float(intr.cy)
        col, row = int(np.floor(u)), int(np.floor(v))
        a = lego_small.alphas[image, row, col]
        straight = lego_small.images[image, row, col] - (1.0 - a) * lego_small.background
        np.testing.assert_allclose(t, straight + (1.0 - a) * bg, atol=1e-5)
        matched += 1
    assert matched == 64


def test_rays_cover_all_training_images(lego_small):
    config = _tiny_config(lego_small, "dense", rays_per_batch=2048)
    data = tr.TrainData.from_scene(lego_small)
    origins = np.asarray(jax.jit(lambda k: tr._sample_batch(k, data, config)[0])(jax.random.key(1)))
    nearest = np.argmin(np.linalg.norm(origins[:, None] - lego_small.c2w[None, :, :3, 3], axis=-1), axis=1)
    counts = np.bincount(nearest, minlength=lego_small.n_images)
    assert np.all(counts > 0)  # 12 images, ~170 rays each


# ----------------------------------------------------------------------------------------------
# The occupancy sampler's packing against the occupancy module's own per-ray renderer.


def test_packed_rendering_matches_per_ray_marching(lego_small):
    from waldo_jax.nerf import occupancy as occ
    from waldo_jax.nerf.field import init_field

    config = _tiny_config(lego_small, "occupancy", num_samples=24)
    sampler = tr.make_sampler(config)
    params = init_field(jax.random.key(0), config.field)
    # A field with structure: random hash features, large enough to give real densities.
    params["hash"] = jax.random.normal(jax.random.key(1), params["hash"].shape) * 2.0
    grid = sampler.init(jax.random.key(2), params)
    bits = np.asarray(jax.random.bernoulli(jax.random.key(3), 0.3, grid.bitfield.shape))
    grid = grid.replace(bitfield=jnp.asarray(bits))
    inputs = tr.training_inputs(jax.random.key(0), lego_small, config)
    origins, directions, _, background = tr._sample_batch(jax.random.key(5), inputs.data, config)
    render_config = inputs.render_config
    march = sampler.march_config(config.num_samples).replace(min_transmittance=jnp.float32(0.0))
    reference = jax.vmap(lambda o, d, bg: occ.render_ray_marched(
        sampler.field, params, grid, o, d, render_config.replace(background=bg), march)[0])(
        origins, directions, background)
    # A budget of 3 rays' worth of samples forces many packing passes.
    packed = jax.jit(lambda: sampler.render_ray_batch(params, grid, origins, directions, background,
                                                      render_config, config.num_samples, 3 * config.num_samples))()
    counts = np.asarray(sampler._march(grid, origins, directions, render_config, config.num_samples, None)[2].sum(-1))
    assert counts.max() > 0
    np.testing.assert_allclose(np.asarray(packed.rgb), np.asarray(reference.rgb), atol=2e-5)
    np.testing.assert_allclose(np.asarray(packed.acc), np.asarray(reference.acc), atol=2e-5)
    # Training: the leading rays that fit the budget are rendered exactly, the others are left out.
    out, included = jax.jit(lambda: sampler.render_rays(None, params, grid, origins, directions, background,
                                                        render_config))()
    included = np.asarray(included)
    expected = np.cumsum(counts) <= config.samples_per_batch
    np.testing.assert_array_equal(included, expected)


# ----------------------------------------------------------------------------------------------
# Configuration.


def test_preset_takes_box_and_aabb_scale_from_the_scene(lego_small):
    fast = tr.TrainConfig.preset("fast", lego_small)
    quality = tr.TrainConfig.preset("quality", lego_small)
    assert fast.field.aabb == tuple(float(v) for v in lego_small.aabb.reshape(-1))
    assert fast.aabb_scale == 1.0 and fast.cone_angle == 0.0  # Blender: synthetic, constant steps
    assert quality.field.hashgrid.N_max == 2048 and quality.field.hashgrid.T == 2**19
    assert 64 <= fast.field.hashgrid.N_max < 2048  # matched to 100x100 images
    scaled = dataclasses.replace(lego_small, metadata={"aabb_scale": 4}, format="instant-ngp")
    fox_like = tr.TrainConfig.preset("quality", scaled)
    assert fox_like.aabb_scale == 4.0 and fox_like.field.hashgrid.N_max == 8192
    assert fox_like.cone_angle == pytest.approx(1 / 256)
    assert tr.TrainConfig.preset("fast", lego_small, steps=7).steps == 7
    with pytest.raises(tr.TrainConfigError, match="unknown preset 'best'"):
        tr.TrainConfig.preset("best", lego_small)
    with pytest.raises(tr.TrainConfigError, match="rays_per_batch"):
        tr.TrainConfig.preset("fast", lego_small, rays_per_batch=0)
    assert tr.TrainConfig.from_dict(quality.to_dict()) == quality


def test_learning_rate_schedule_follows_instant_ngp_decay():
    hparams = tr.TrainHParams(decay_start=100.0, decay_interval=50.0)
    rates = [float(hparams.learning_rate_at(s)) for s in (0, 99, 100, 149, 150, 200)]
    np.testing.assert_allclose(rates, [1e-2, 1e-2, 3.3e-3, 3.3e-3, 1.089e-3, 3.5937e-4], rtol=1e-5)
