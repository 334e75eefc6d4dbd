"""Tests of NeRF training (waldo_jax.nerf.train): convergence, determinism, scan vs. step loop, samplers.

Small configurations keep the suite fast on 2 CPU cores: the determinism and loop tests share one
compiled chunk (same config), and only the convergence test trains for real.
"""

from __future__ import annotations

import dataclasses

import waldo_jax  # noqa: F401  (XLA flags before the first computation)

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from conftest import require_scene
from waldo_jax.nerf import HashGridConfig, NGPFieldConfig
from waldo_jax.nerf import train as tr
from waldo_jax.nerf.config import TrainConfig, TrainConfigError, TrainHParams
from waldo_jax.nerf.trained import RENDER_STEP_TOLERANCE_DB
from waldo_jax.nerf.samplers import TRAIN_ROW_LENGTH, make_sampler
from waldo_jax.nerf.step import (
    ERROR_UNIFORM_SHARE,
    TrainData,
    _draw_pixels,
    _fit_rays,
    _sample_batch,
    _updated_errors,
    chunk_fn,
    make_occupancy_update,
    make_train_step,
    next_rays,
    rays_ladder,
    warmup_steps,
)
from waldo_jax.scenes import load_scene

# A tiny field for the mechanics tests (not for quality).
TINY_FIELD = dict(
    hashgrid=HashGridConfig(L=4, T=2**12, F=2, N_min=8, N_max=64), density_hidden=(16,), color_hidden=(16,)
)


@pytest.fixture(scope="module")
def lego_small():
    """lego_tiny's training split, 12 of its 90 views (enough for the mechanics tests)."""
    return load_scene(require_scene("lego_tiny"), split="train", max_images=12)


def _tiny_config(scene, sampler: str, **overrides) -> TrainConfig:
    field = NGPFieldConfig(aabb=scene.aabb, **TINY_FIELD)
    values = dict(
        field=field,
        steps=5,
        chunk=3,
        rays_per_batch=128,
        num_samples=16,
        samples_per_batch=1024,
        eval_samples=16,
        occupancy_resolution=16,
        occupancy_update_every=2,
        occupancy_warmup=2,
        steps_per_diagonal=64.0,
        sampler=sampler,
    )
    values.update(overrides)
    return TrainConfig(**values)


def _samplers():
    return ["dense", "occupancy"]


def _leaves_bytes(tree):
    return [np.asarray(leaf).tobytes() for leaf in jax.tree.leaves(tree)]


# ----------------------------------------------------------------------------------------------
# Convergence: the real preset code on lego_tiny.


def test_fast_preset_reaches_20db_on_lego_tiny(trained_lego_fast):
    """The fast preset (fewer steps, a smaller hash grid) beats 20 dB on lego_tiny's held-out views
    (the run is conftest's `trained_lego_fast`, shared with the renderer tests on a trained field)."""
    _, result = trained_lego_fast
    assert result["steps"] == 250
    assert result["n_train"] == 90 and result["n_test"] == 10
    assert result["psnr_test"] is not None and result["psnr_test"] >= 20.0, (
        result["psnr_test"],
        result["history"][-3:],
    )
    assert result["history"][-1]["psnr_test"] == result["psnr_test"]
    losses = [h["loss"] for h in result["history"] if "loss" in h]
    assert losses[-1] < 0.5 * losses[0]
    # The run's rendering step comes from its own quality/speed curve on the held-out views: the
    # largest scale within the tolerance of the training step's PSNR, and the scales tried stop at
    # the first one that loses more.
    chosen, curve = result["render_step_scale"], result["render_step_curve"]
    assert curve[0]["step_scale"] == 1.0 and chosen in [c["step_scale"] for c in curve]
    assert all(c["delta_db"] >= -RENDER_STEP_TOLERANCE_DB for c in curve if c["step_scale"] <= chosen)
    assert curve[-1]["step_scale"] == chosen or curve[-1]["delta_db"] < -RENDER_STEP_TOLERANCE_DB
    evaluations = [c["evaluations_per_ray"] for c in curve]
    assert all(a > b for a, b in zip(evaluations, evaluations[1:]))  # coarser steps, fewer evaluations
    assert result["history"][-1]["render_step_scale"] == chosen
    assert result["rays_per_second"] > 0 and np.isfinite(result["rays_per_second"])
    print(
        f"lego_tiny fast/test preset: {result['psnr_test']:.2f} dB in {result['seconds']:.1f} s "
        f"({result['rays_per_second']:.0f} rays/s, sampler {result['sampler']})"
    )


# ----------------------------------------------------------------------------------------------
# Determinism and the scan against a step loop.


@pytest.mark.parametrize("sampler", [*_samplers(), "occupancy+error"])
def test_same_seed_same_params_other_seed_differs(lego_small, sampler):
    sampler, _, pixels = sampler.partition("+")
    config = _tiny_config(lego_small, sampler, pixel_sampling=pixels or "uniform")
    first = tr.train(jax.random.key(3), lego_small, config, progress=False)
    second = tr.train(jax.random.key(3), lego_small, config, progress=False)
    other = tr.train(jax.random.key(4), lego_small, config, progress=False)
    assert first.steps == second.steps == other.steps == 5
    assert _leaves_bytes(first.params) == _leaves_bytes(second.params)
    assert _leaves_bytes(first.occupancy) == _leaves_bytes(second.occupancy)
    if pixels:  # the errors drawn from: the trained pixels' own, every other pixel still at 1
        inputs = tr.training_inputs(jax.random.key(3), lego_small, config)
        state, _ = chunk_fn(config, 128)(
            inputs.state, inputs.train_key, inputs.data, inputs.hparams, inputs.render_config, jnp.int32(2)
        )
        errors = np.asarray(state.pixel_error)
        assert errors.shape == (lego_small.n_images * lego_small.height * lego_small.width,)
        assert 0 < np.sum(errors < 1.0) <= 2 * 128 and np.all((errors >= 0.0) & (errors <= 1.0))
    assert [h["loss"] for h in first.history] == [h["loss"] for h in second.history]
    assert not np.array_equal(np.asarray(first.params["hash"]), np.asarray(other.params["hash"]))
    # One program serves the warm-up chunk and the later one, and the same config reuses it: no retrace
    # across the three runs.
    assert [h["rays_marched"] for h in first.history if "loss" in h] == [128, 128]
    assert [h["warmup"] for h in first.history if "loss" in h] == [True, False]
    assert chunk_fn(config, 128)._cache_size() == 1


@pytest.mark.filterwarnings("ignore:Mean of empty slice")
def test_chunks_count_steps_by_the_state_not_by_finite_losses(lego_small, monkeypatch):
    """A run whose every loss is NaN (a diverged field) still ends after `config.steps` steps, chunk by
    chunk: the loop counts the steps the state took (counting finite losses, it never moved on)."""
    config = _tiny_config(lego_small, "occupancy")
    real = tr.chunk_fn

    def nan_losses(config, rays):
        program = real(config, rays)

        def run(*args):
            state, metrics = program(*args)
            return state, {**metrics, "loss": jnp.full_like(metrics["loss"], jnp.nan)}

        run._cache_size = program._cache_size
        return run

    monkeypatch.setattr(tr, "chunk_fn", nan_losses)
    result = tr.train(jax.random.key(3), lego_small, config, progress=False)
    assert result.steps == config.steps == 5
    assert [h["step"] for h in result.history if "loss" in h] == [2, 5]


# A warm-up (6 steps) longer than a chunk program's period (3 steps): two chunks in the warm-up.
_LONG_WARMUP = dict(steps=11, chunk=4, occupancy_update_every=3, occupancy_warmup=4)


@pytest.mark.parametrize("sampler, overrides", [(s, {}) for s in _samplers()] + [("occupancy", _LONG_WARMUP)])
def test_scan_chunks_equal_step_loop(lego_small, sampler, overrides):
    """Steps as scanned chunks of whole periods (the warm-up chunk(s), then chunks whose last steps are
    skipped) equal calls of the jitted step, with the occupancy update (every cell through the warm-up)
    before every period's first step; one chunk program serves them all.
    (Not with error sampling: there a float32 rounding of one error moves a CDF boundary, and a ray's
    pixel with it, so the two programs part after the first step; the determinism test covers it.)"""
    config = _tiny_config(lego_small, sampler, **overrides)
    key = jax.random.key(3)
    result = tr.train(key, lego_small, config, progress=False)
    chunks = [h for h in result.history if "loss" in h]
    if overrides:
        assert [h["step"] for h in chunks] == [3, 6, 9, 11]
        assert [h["warmup"] for h in chunks] == [True, True, False, False]
    assert chunk_fn(config, chunks[0]["rays_marched"])._cache_size() == 1

    inputs = tr.training_inputs(key, lego_small, config)
    rays = chunks[0]["rays_marched"]
    step = jax.jit(make_train_step(config, rays))
    update = {warmup: jax.jit(make_occupancy_update(config, warmup)) for warmup in (True, False)}
    state = inputs.state
    for i in range(config.steps):
        if i % config.occupancy_update_every == 0:
            state = update[i < warmup_steps(config)](state, inputs.train_key)
        state, metrics = step(state, inputs.train_key, inputs.data, inputs.hparams, inputs.render_config)
    assert int(state.step) == result.steps == config.steps
    # The same operations compiled in two programs: XLA fuses a step inside a scan differently from a
    # step alone (on the CPU too), so they agree to float32 rounding, not bit for bit (a rerun of the
    # same program is bit-identical: see the determinism test above).
    for a, b in zip(
        jax.tree.leaves((result.params, result.occupancy)), jax.tree.leaves((state.params, state.sampler_state))
    ):
        a, b = np.asarray(a), np.asarray(b)
        if a.dtype == bool:
            assert (a != b).mean() < 1e-3  # a cell whose density sits at the threshold may flip
        else:
            # Adam divides by sqrt(v): an entry with a near-zero gradient moves by up to lr on a rounding.
            np.testing.assert_allclose(a, b, rtol=1e-3, atol=1e-3 * float(np.abs(b).max()))
    data = TrainData.from_scene(lego_small)
    origins = np.asarray(jax.jit(lambda k: _sample_batch(k, data, config)[0])(jax.random.key(1)))
    nearest = np.argmin(np.linalg.norm(origins[:, None] - lego_small.c2w[None, :, :3, 3], axis=-1), axis=1)
    counts = np.bincount(nearest, minlength=lego_small.n_images)
    assert np.all(counts > 0)  # 12 images, ~10 rays each


def test_error_sampling_draws_pixels_in_proportion_to_their_error():
    """A quarter of the rays uniform, the rest by each pixel's error: the drawn frequencies match those
    probabilities (200k draws), and all-equal errors give the uniform draw's frequencies."""
    pixels, draws = 1000, 200_000
    error = np.zeros(pixels, np.float32)
    error[7], error[500:510] = 3.0, 1.0  # pixel 7 carries 3 / 13 of the error, pixels 500..509 1 / 13 each
    flat = np.asarray(jax.jit(_draw_pixels, static_argnums=(1, 2))(jax.random.key(0), draws, pixels, error))
    assert flat.min() >= 0 and flat.max() < pixels
    expected = ERROR_UNIFORM_SHARE / pixels + (1.0 - ERROR_UNIFORM_SHARE) * error / error.sum()
    counts = np.bincount(flat, minlength=pixels)
    sigma = np.sqrt(draws * expected * (1.0 - expected))
    assert np.all(np.abs(counts - draws * expected) <= 5.0 * sigma + 1.0)
    assert abs(counts[7] / draws - expected[7]) < 0.005 and expected[7] > 0.17
    uniform = np.asarray(_draw_pixels(jax.random.key(1), draws, pixels, jnp.ones(pixels)))
    assert np.abs(np.bincount(uniform, minlength=pixels) - draws / pixels).max() < 5.0 * np.sqrt(draws / pixels)


def test_a_step_records_the_squared_error_of_the_pixels_it_trained():
    """Drawn pixels get their rays' mean squared residual (the larger of two draws of one pixel); pixels not
    drawn, or drawn by a ray left out of the batch, keep theirs."""
    old = jnp.full((6,), 0.5)
    flat = jnp.array([1, 3, 3, 4], jnp.int32)
    residual = jnp.array([[0.1, 0.1, 0.1], [0.3, 0.0, 0.0], [0.6, 0.0, 0.0], [1.0, 1.0, 1.0]])
    included = jnp.array([True, True, True, False])
    new = np.asarray(_updated_errors(old, flat, residual, included))
    np.testing.assert_allclose(new, [0.5, 0.01, 0.5, 0.12, 0.5, 0.5], rtol=1e-6)
    assert _updated_errors(None, flat, residual, included) is None  # uniform sampling keeps no errors


def test_rays_marched_adapt_to_the_budget(lego_small):
    """Instant-NGP's dynamic batch: R is the smallest rung of the ladder that marches 1.25 budgets."""
    config = _tiny_config(lego_small, "occupancy", rays_per_batch=1024)
    assert rays_ladder(config) == (128, 256, 512, 1024)
    rows = config.samples_per_batch // TRAIN_ROW_LENGTH  # the budget in packed rows
    assert _fit_rays(config, rows_per_ray=rows / 256) == 512  # 1.25 * 256 = 320 rays wanted
    assert _fit_rays(config, rows_per_ray=rows / 64) == 128  # 80 wanted
    assert _fit_rays(config, rows_per_ray=0.01) == 1024  # the top rung at most
    # The chunk's last period (2 steps) decides; discarded steps (NaN loss) do not count.
    metrics = {"loss": np.array([0.1, 0.1, 0.1, np.nan]), "rows": np.array([100 * rows, rows, rows, 0])}
    assert next_rays(config, metrics, 256) == 512  # rows / 256 rows per marched ray
    assert rays_ladder(config.replace(sampler="dense")) == (1024,)


@pytest.mark.slow
def test_first_rays_above_the_fitted_rung_train_the_same_rays(lego_small):
    """`first_rays` sets the warm-up's rung; the budget keeps the rays it kept on the fitted (lower)
    rung, in the order they were drawn: a step trains the same rays, to the loss's rounding."""
    config = _tiny_config(lego_small, "occupancy", rays_per_batch=1024)
    fitted = tr.first_rays(config)
    assert fitted < 1024 and tr.first_rays(config.replace(first_rays=1024)) == 1024
    inputs = tr.training_inputs(jax.random.key(5), lego_small, config)
    args = (inputs.train_key, inputs.data, inputs.hparams, inputs.render_config)
    update = jax.jit(make_occupancy_update(config, True))
    state = update(inputs.state, inputs.train_key)  # the warm-up's grid: every cell sampled
    (low, low_metrics), (high, high_metrics) = (
        jax.jit(make_train_step(config, r))(state, *args) for r in (fitted, 1024)
    )
    assert int(low_metrics["rays"]) == int(high_metrics["rays"]) < fitted  # the fitted rung overflowed already
    assert int(low_metrics["samples"]) == int(high_metrics["samples"])
    assert float(low_metrics["loss"]) == pytest.approx(float(high_metrics["loss"]), rel=1e-5)
    for a, b in zip(jax.tree.leaves(low.params), jax.tree.leaves(high.params)):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-4, atol=1e-6)
    for bad in (3, 96, 2048, 1000):  # not the ladder's: below 128, past rays_per_batch, not a power of 2
        with pytest.raises(TrainConfigError, match="first_rays must be rays_per_batch"):
            config.replace(first_rays=bad)
    with pytest.raises(TrainConfigError, match="first_rays must be rays_per_batch"):
        config.replace(sampler="dense", first_rays=512)


def test_packed_training_loss_and_gradients_equal_the_per_ray_reference(lego_small):
    """The occupancy sampler's packed rows (the training composite) against the [rays x samples]
    composite of the same marched samples: loss and gradients equal to relative 1e-5."""
    from waldo_jax.nerf.field import init_field
    from waldo_jax.render.volume import composite, volume_weights

    config = _tiny_config(lego_small, "occupancy", num_samples=24)
    sampler = make_sampler(config)
    params = init_field(jax.random.key(0), config.field)
    # A field with structure: random hash features, large enough to give real densities.
    params["hash"] = jax.random.normal(jax.random.key(1), params["hash"].shape) * 2.0
    grid = sampler.init(jax.random.key(2), params)
    grid = grid.replace(bitfield=jax.random.bernoulli(jax.random.key(3), 0.3, grid.bitfield.shape))
    inputs = tr.training_inputs(jax.random.key(0), lego_small, config)
    origins, directions, target, background, _ = _sample_batch(jax.random.key(5), inputs.data, config)
    render_config = inputs.render_config

    def packed_loss(params):
        out, included, _ = sampler.render_rays(None, params, grid, origins, directions, background, render_config)
        return jnp.sum(jnp.where(included[:, None], (out.rgb - target) ** 2, 0.0)), included

    def reference_loss(params):
        t, delta, mask = sampler._march(grid, origins, directions, render_config, None)  # [R, S]
        counts = jnp.sum(mask, axis=1)
        s = TRAIN_ROW_LENGTH
        included = jnp.cumsum(-(-counts // s)) <= config.samples_per_batch // s

        def one(o, d, t, delta, mask, bg):
            sigma, rgb = jax.vmap(sampler.field, in_axes=(None, 0, None))(params, o + t[:, None] * d, d)
            return composite(volume_weights(jnp.where(mask, sigma, 0.0), delta), rgb, t, bg).rgb

        rgb = jax.vmap(one)(origins, directions, t, delta, mask, background)
        return jnp.sum(jnp.where(included[:, None], (rgb - target) ** 2, 0.0)), (included, counts)

    (loss, included), grads = jax.jit(jax.value_and_grad(packed_loss, has_aux=True))(params)
    (ref_loss, (ref_included, counts)), ref_grads = jax.jit(jax.value_and_grad(reference_loss, has_aux=True))(params)
    np.testing.assert_array_equal(np.asarray(included), np.asarray(ref_included))
    # Some rays are left out of the budget, and the included ones have real samples.
    assert 0 < int(np.sum(included)) < included.shape[0] and int(np.sum(np.asarray(counts)[np.asarray(included)])) > 0
    np.testing.assert_allclose(float(loss), float(ref_loss), rtol=1e-5)
    for name in ("hash", "density_mlp", "color_mlp"):
        for a, b in zip(jax.tree.leaves(grads[name]), jax.tree.leaves(ref_grads[name])):
            a, b = np.asarray(a), np.asarray(b)
            scale = np.abs(b).max()
            assert scale > 0, name
            np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-5 * scale)


# ----------------------------------------------------------------------------------------------
# Configuration.


def test_preset_takes_box_and_aabb_scale_from_the_scene(lego_small):
    fast = TrainConfig.preset("fast", lego_small)
    quality = TrainConfig.preset("quality", lego_small)
    assert fast.field.aabb == tuple(float(v) for v in lego_small.aabb.reshape(-1))
    assert fast.aabb_scale == 1.0 and fast.cone_angle == 0.0  # Blender: synthetic, constant steps
    assert quality.field.hashgrid.N_max == 2048 and quality.field.hashgrid.T == 2**19
    assert 64 <= fast.field.hashgrid.N_max < 2048  # matched to 100x100 images
    scaled = dataclasses.replace(lego_small, metadata={"aabb_scale": 4}, format="instant-ngp")
    fox_like = TrainConfig.preset("quality", scaled)
    assert fox_like.aabb_scale == 4.0 and fox_like.field.hashgrid.N_max == 8192
    assert fox_like.cone_angle == pytest.approx(1 / 256)
    # A scene's aabb_scale past Instant-NGP's 128 is refused by name before a hash grid is sized by it
    # (1,024 made the quality preset's N_max = 2**21 overflow the layout: an AssertionError).
    for huge in (129, 1024, 65536):
        with pytest.raises(TrainConfigError, match=f"aabb_scale {huge} is outside"):
            TrainConfig.preset("quality", dataclasses.replace(scaled, metadata={"aabb_scale": huge}))
    assert TrainConfig.preset("quality", dataclasses.replace(scaled, metadata={"aabb_scale": 128})).aabb_scale == 128
    assert TrainConfig.preset("fast", lego_small, steps=7).steps == 7
    assert TrainConfig.preset("fast", lego_small, steps=10**7).steps == 10**7  # MAX_TRAIN_STEPS
    with pytest.raises(TrainConfigError, match="steps must be at most 10,000,000, got 10,000,001"):
        TrainConfig.preset("fast", lego_small, steps=10**7 + 1)
    with pytest.raises(TrainConfigError, match="unknown preset 'best'"):
        TrainConfig.preset("best", lego_small)
    with pytest.raises(TrainConfigError, match="rays_per_batch"):
        TrainConfig.preset("fast", lego_small, rays_per_batch=0)
    assert TrainConfig.from_dict(quality.to_dict()) == quality
    # A config written before `render_step_scale` and `pixel_sampling`, with the retired `eval_ray_chunk`, still loads.
    old = {k: v for k, v in quality.to_dict().items() if k not in ("render_step_scale", "pixel_sampling")}
    assert TrainConfig.from_dict({**old, "eval_ray_chunk": 4096}) == quality
    with pytest.raises(TrainConfigError, match="render_step_scale"):
        TrainConfig.preset("fast", lego_small, render_step_scale=0.0)
    by_error = TrainConfig.preset("fast", lego_small, pixel_sampling="error")
    assert TrainConfig.from_dict(by_error.to_dict()) == by_error and quality.pixel_sampling == "uniform"
    with pytest.raises(TrainConfigError, match="pixel_sampling must be one of uniform, error, got 'loss'"):
        TrainConfig.preset("fast", lego_small, pixel_sampling="loss")


def test_a_preset_with_the_dense_sampler_takes_the_dense_sizes(lego_small):
    """`waldo train --sampler dense` overrides the preset's sampler: its rays and samples are the dense
    sampler's (the occupancy sampler's 4,096 rays x 1,024 samples, marched densely, asked XLA for 13 GB a
    step with the fast preset and 53 GB with the quality one)."""
    for name, (rays, samples, evaluations) in {"fast": (1024, 64, 128), "quality": (4096, 128, 256)}.items():
        dense = TrainConfig.preset(name, lego_small, sampler="dense")
        assert (dense.sampler, dense.rays_per_batch, dense.num_samples, dense.eval_samples) == (
            "dense",
            rays,
            samples,
            evaluations,
        ), name
        assert TrainConfig.preset(name, lego_small).sampler == "occupancy"


def test_learning_rate_schedule_follows_instant_ngp_decay():
    hparams = TrainHParams(decay_start=100.0, decay_interval=50.0)
    rates = [float(hparams.learning_rate_at(s)) for s in (0, 99, 100, 149, 150, 200)]
    np.testing.assert_allclose(rates, [1e-2, 1e-2, 3.3e-3, 3.3e-3, 1.089e-3, 3.5937e-4], rtol=1e-5)


# ----------------------------------------------------------------------------------------------
# The held-out views: at most EVAL_MAX_PIXELS pixels each, evaluated after the field is saved.


@pytest.mark.parametrize("size", [(1080, 1920), (100, 100), (1008, 756), (17, 5), (4000, 3)])
@pytest.mark.parametrize("budget", [1, 2500, 2**16, 10**9])
def test_the_held_out_factor_is_the_least_whole_factor_that_fits(size, budget):
    from waldo_jax.scenes.images import _target_size, fit_factor

    k = fit_factor(*size, budget)
    fits = lambda f: np.prod(_target_size(*size, f)) <= budget  # noqa: E731
    assert fits(k) or np.prod(_target_size(*size, k)) == 1  # a single pixel is the least there is
    assert k == 1 or not fits(k - 1)


def test_held_out_views_are_the_box_means_of_the_images(lego_small):
    from waldo_jax.scenes.images import downscale_scene

    scene = dataclasses.replace(lego_small, alphas=np.random.default_rng(0).random((12, 100, 100), np.float32))
    small, factor = tr.held_out_views(scene, 2500)
    assert factor == 2 and (small.width, small.height) == (50, 50)
    blocks = scene.images.reshape(12, 50, 2, 50, 2, 3).astype(np.float64).mean(axis=(2, 4))
    np.testing.assert_allclose(small.images, blocks, atol=1e-6)
    np.testing.assert_allclose(small.alphas, scene.alphas.reshape(12, 50, 2, 50, 2).mean(axis=(2, 4)), atol=1e-6)
    assert small.intrinsics == scene.intrinsics.downscaled(2)
    assert small.metadata["downscale"] == 2 * (scene.metadata.get("downscale") or 1)
    assert tr.held_out_views(scene, None) == (scene, 1) and downscale_scene(scene, 1) is scene
    with pytest.raises(ValueError, match="pixel budget"):
        tr.held_out_views(scene, 0)


@pytest.mark.slow
def test_the_end_of_run_evaluation_renders_the_views_at_the_budget_and_can_come_later(lego_small):
    """`train` evaluates at `HeldOut.max_pixels` (here 1/2 of lego_tiny's 100x100), and `at_end=False`
    then `evaluate_held_out` gives the same result bit for bit (what `waldo train` does, saving the field
    between the two)."""
    from waldo_jax.nerf.trained import evaluate

    test = load_scene(require_scene("lego_tiny"), split="test", max_images=3)
    config = _tiny_config(lego_small, "occupancy")
    key = jax.random.key(0)
    whole = tr.train(key, lego_small, config, test, progress=False, held_out=tr.HeldOut(2500))
    assert whole.eval_size == (50, 50) and whole.eval_downscale == 2 and whole.n_test == 3
    assert whole.history[-1]["eval_size"] == [50, 50] and whole.history[-1]["psnr_test"] == whole.psnr_test
    half = tr.held_out_views(test, 2500)[0]
    by_hand = evaluate(whole.params, whole.occupancy, whole.config, half)["psnr"]
    assert by_hand == whole.psnr_test
    trained = tr.train(key, lego_small, config, test, progress=False, held_out=tr.HeldOut(2500, at_end=False))
    assert trained.psnr_test is None and trained.eval_size is None and trained.config.render_step_scale is None
    later = tr.evaluate_held_out(trained, test, 2500)
    assert later.psnr_test == whole.psnr_test and later.config == whole.config
    assert later.render_step_curve == whole.render_step_curve
    untimed = lambda history: [{k: v for k, v in h.items() if k != "seconds"} for h in history]  # noqa: E731
    assert untimed(later.history) == untimed(whole.history)
    full = tr.evaluate_held_out(trained, test, None)
    assert full.eval_size == (100, 100) and full.eval_downscale == 1 and full.psnr_test != whole.psnr_test
