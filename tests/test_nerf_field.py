"""Tests of the Instant-NGP field (waldo_jax.nerf.field): SH encoding, trunc_exp, MLPs, aabb handling."""

from __future__ import annotations

import math

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from waldo_jax.nerf import (
    HashGridConfig,
    NGPFieldConfig,
    encode,
    init_field,
    make_density,
    make_field,
    make_field_batch,
    spherical_harmonics,
    trunc_exp,
)

# A small, asymmetric box so that normalisation mistakes (centre, per-axis extent) show.
AABB = (-1.0, -2.0, 0.0, 1.0, 2.0, 3.0)
CONFIG = NGPFieldConfig(aabb=AABB, hashgrid=HashGridConfig(L=4, T=2**12, F=2, N_min=4, N_max=64))
LO, HI = np.array(AABB[:3]), np.array(AABB[3:])

# Shared compiled functions keep the suite fast: the tests call them with [8, 3] inputs.
_init = jax.jit(init_field, static_argnums=1)
FIELD_BATCH = jax.jit(make_field_batch(CONFIG))
DENSITY_BATCH = jax.jit(jax.vmap(make_density(CONFIG), in_axes=(None, 0)))


def _loss(params, xs, ds):
    """A scalar that depends on sigma and on every colour channel."""
    sigma, rgb = make_field_batch(CONFIG)(params, xs, ds)  # [N], [N, 3]
    return jnp.sum(sigma) + jnp.sum(rgb * jnp.array([1.0, -2.0, 3.0]))


LOSS_GRAD = jax.jit(jax.grad(_loss))
DENSITY_GRAD = jax.jit(jax.grad(lambda params, xs: jnp.sum(jax.vmap(make_density(CONFIG), (None, 0))(params, xs))))


@pytest.fixture(scope="module")
def params():
    return _init(jax.random.key(0), CONFIG)


# Test data comes from seeded NumPy generators: eager jax.random calls compile a kernel per shape,
# which would dominate the run time of this suite on 2 cores.
def _inside_points(seed: int, n: int) -> np.ndarray:
    return np.random.default_rng(seed).uniform(LO + 1e-3, HI - 1e-3, (n, 3)).astype(np.float32)


def _directions(seed: int, n: int) -> np.ndarray:
    d = np.random.default_rng(seed).normal(size=(n, 3))
    return (d / np.linalg.norm(d, axis=-1, keepdims=True)).astype(np.float32)


# --------------------------------------------------------------------------------------------------
# Spherical harmonics

_SH = jax.jit(jax.vmap(spherical_harmonics))


def test_sh_known_values_on_axes():
    c0, c1 = 0.5 / math.sqrt(math.pi), math.sqrt(3 / (4 * math.pi))
    assert c0 == pytest.approx(0.28209479177387814)
    sh = np.asarray(_SH(jnp.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])))
    assert sh.shape == (3, 16)
    z_axis = np.zeros(16)
    z_axis[[0, 2, 6, 12]] = [c0, c1, 0.63078313050504, 0.7463526651802308]
    x_axis = np.zeros(16)
    x_axis[[0, 3, 6, 8, 13, 15]] = [c0, -c1, -0.31539156525252, 0.54627421529604, 0.45704579946447, -0.59004358992664]
    y_axis = np.zeros(16)
    y_axis[[0, 1, 6, 8, 9, 11]] = [c0, -c1, -0.31539156525252, -0.54627421529604, 0.59004358992664, 0.45704579946447]
    np.testing.assert_allclose(sh, np.stack([z_axis, x_axis, y_axis]), atol=1e-6)


def test_sh_is_orthonormal_on_the_sphere():
    # Gauss-Legendre in z times uniform azimuths integrates these degree <= 6 products exactly.
    z_nodes, z_weights = np.polynomial.legendre.leggauss(8)
    phi = 2 * np.pi * np.arange(16) / 16
    z, p = np.meshgrid(z_nodes, phi, indexing="ij")
    r = np.sqrt(1 - z**2)
    dirs = np.stack([r * np.cos(p), r * np.sin(p), z], -1).reshape(-1, 3)
    weights = (z_weights[:, None] * np.full(16, 2 * np.pi / 16)[None, :]).reshape(-1)
    sh = np.asarray(_SH(jnp.asarray(dirs, jnp.float32)), np.float64)  # [128, 16]
    gram = (sh * weights[:, None]).T @ sh
    np.testing.assert_allclose(gram, np.eye(16), atol=1e-5)


def test_sh_matches_scipy_complex_harmonics():
    special = pytest.importorskip("scipy.special")
    if not hasattr(special, "sph_harm_y"):
        pytest.skip("scipy too old for sph_harm_y")
    d = np.asarray(_directions(1, 32), np.float64)
    theta, phi = np.arccos(np.clip(d[:, 2], -1, 1)), np.arctan2(d[:, 1], d[:, 0])
    expected = []
    for l in range(4):  # noqa: E741  (the spherical-harmonics degree, as the formulas write it)
        for m in range(-l, l + 1):
            y = special.sph_harm_y(l, abs(m), theta, phi)  # Condon-Shortley phase included
            expected.append(np.sqrt(2) * y.imag if m < 0 else (y.real if m == 0 else np.sqrt(2) * y.real))
    np.testing.assert_allclose(np.asarray(_SH(jnp.asarray(d, jnp.float32))), np.stack(expected, -1), atol=1e-5)


def test_sh_lower_degree_is_prefix():
    d = _directions(2, 4)
    full = _SH(d)
    for degree in (1, 2, 3):
        low = jax.vmap(lambda v: spherical_harmonics(v, degree))(d)
        np.testing.assert_allclose(low, full[:, : degree**2], atol=1e-7)
    with pytest.raises(ValueError):
        spherical_harmonics(d[0], 5)


# --------------------------------------------------------------------------------------------------
# trunc_exp


def test_trunc_exp_values_and_finite_gradients():
    x = np.array([-1e6, -40.0, -15.0, 0.0, 1.0, 15.0, 20.0, 100.0, 1e6], np.float32)
    value, grad = jax.jit(jax.vmap(jax.value_and_grad(trunc_exp)))(x)
    np.testing.assert_allclose(value, np.exp(np.minimum(np.asarray(x, np.float64), 15.0)), rtol=1e-6)
    np.testing.assert_allclose(grad, np.exp(np.clip(np.asarray(x, np.float64), -15.0, 15.0)), rtol=1e-6)
    assert np.all(np.isfinite(value)) and np.all(np.isfinite(grad))
    # The clamped gradient keeps a saturated negative logit trainable (plain clamp-then-exp would not).
    assert float(grad[1]) == pytest.approx(math.exp(-15.0), rel=1e-5)


# --------------------------------------------------------------------------------------------------
# Field


@pytest.mark.slow
def test_params_structure_and_determinism(params):
    assert set(params) == {"hash", "density_mlp", "color_mlp"}
    assert params["hash"].shape == (CONFIG.hashgrid.n_rows, 2)
    shapes = jax.tree.map(lambda a: a.shape, params)
    assert shapes["density_mlp"]["params"]["Dense_0"]["kernel"] == (8, 64)  # L * F = 8 inputs
    assert shapes["density_mlp"]["params"]["Dense_1"]["kernel"] == (64, 16)
    assert shapes["color_mlp"]["params"]["Dense_0"]["kernel"] == (32, 64)  # 16 geometry + 16 SH
    assert shapes["color_mlp"]["params"]["Dense_2"]["kernel"] == (64, 3)
    same = _init(jax.random.key(0), CONFIG)
    other = _init(jax.random.key(1), CONFIG)
    chex.assert_trees_all_equal(params, same)
    assert all(not np.array_equal(a, b) for a, b in zip(jax.tree.leaves(params), jax.tree.leaves(other)))


_ENCODE = jax.jit(jax.vmap(lambda table, x01: encode(table, x01, CONFIG.hashgrid), in_axes=(None, 0)))


def _numpy_field(params, xs, ds):
    """Independent NumPy forward pass of the Instant-NGP field (hash encoding and SH from the library)."""
    x01 = (np.asarray(xs, np.float64) - LO) / (HI - LO)  # [N, 3]
    features = np.asarray(_ENCODE(params["hash"], jnp.asarray(x01, jnp.float32)), np.float64)  # [N, 8]
    w = jax.tree.map(lambda a: np.asarray(a, np.float64), params)
    dens, col = w["density_mlp"]["params"], w["color_mlp"]["params"]
    h = np.maximum(features @ dens["Dense_0"]["kernel"], 0) @ dens["Dense_1"]["kernel"]  # [N, 16]
    inside = np.all((x01 >= 0) & (x01 <= 1), axis=-1)
    sigma = np.where(inside, np.exp(np.minimum(h[:, 0], 15.0)), 0.0)  # [N]
    d = np.asarray(ds, np.float64) / np.linalg.norm(ds, axis=-1, keepdims=True)
    sh = np.asarray(_SH(jnp.asarray(d, jnp.float32)), np.float64)  # [N, 16]
    a = np.maximum(np.concatenate([h, sh], -1) @ col["Dense_0"]["kernel"], 0)
    a = np.maximum(a @ col["Dense_1"]["kernel"], 0)
    rgb = 1 / (1 + np.exp(-(a @ col["Dense_2"]["kernel"])))  # [N, 3]
    return sigma, rgb


@pytest.mark.slow
def test_field_matches_numpy_forward_pass(params):
    # Scale the table up so that the hash features, not only the SH term, drive the outputs.
    params = dict(params, hash=params["hash"] * 2e4)
    xs = np.concatenate([_inside_points(3, 7), [[5.0, 0.0, 1.0]]]).astype(np.float32)  # last: outside
    ds = np.random.default_rng(4).normal(size=(8, 3)).astype(np.float32) * 3.0  # not unit: field normalises
    sigma, rgb = (np.asarray(a) for a in FIELD_BATCH(params, xs, ds))
    want_sigma, want_rgb = _numpy_field(params, xs, ds)
    np.testing.assert_allclose(sigma, want_sigma, rtol=1e-4, atol=1e-6)
    np.testing.assert_allclose(rgb, want_rgb, rtol=1e-4, atol=1e-5)
    assert sigma[-1] == 0.0
    assert np.std(sigma[:-1]) > 0.0  # densities depend on the position


@pytest.mark.slow
def test_density_agrees_with_field_and_reads_the_hash(params):
    xs, ds = _inside_points(5, 8), _directions(6, 8)
    sigma, _ = FIELD_BATCH(params, xs, ds)
    np.testing.assert_allclose(DENSITY_BATCH(params, xs), sigma, rtol=1e-6)
    changed = dict(params, hash=params["hash"] + 0.5)
    assert not np.allclose(DENSITY_BATCH(changed, xs), DENSITY_BATCH(params, xs))


@pytest.mark.slow
def test_outputs_finite_and_in_range_for_extreme_inputs(params):
    inf, nan = np.inf, np.nan
    xs = np.array(
        [
            [0.0, 0.0, 1.5],  # inside
            [1.0, 2.0, 3.0],  # max corner, inside
            [-1.0, -2.0, 0.0],  # min corner, inside
            [1.0001, 0.0, 1.0],  # just outside
            [1e30, -1e30, 1e30],
            [-1e6, 1e6, 0.5],
            [inf, 0.0, 1.0],
            [nan, 0.0, 1.0],
        ],
        np.float32,
    )
    ds = np.array(
        [[0, 0, 1], [1e30, 0, 0], [1e-30, 0, 0], [0, 0, 0], [1, 1, 1], [-1, 0, 0], [0, 1, 0], [0, 0, -1]], np.float32
    )  # unit, huge, tiny and zero directions
    # Huge density logits (|h[0]| ~ 1e13): a large table and a scaled last density layer.
    big = jax.tree.map(lambda a: a, params)
    big["density_mlp"]["params"]["Dense_1"]["kernel"] = params["density_mlp"]["params"]["Dense_1"]["kernel"] * 1e9
    big["hash"] = params["hash"] * 1e4
    for p in (params, big):
        sigma, rgb = (np.asarray(a) for a in FIELD_BATCH(p, xs, ds))
        assert np.all(np.isfinite(sigma)) and np.all(np.isfinite(rgb))
        assert np.all(sigma >= 0.0) and np.all((rgb >= 0.0) & (rgb <= 1.0))
        np.testing.assert_array_equal(sigma[3:], 0.0)
        if p is params:  # with the huge logits, inside densities may underflow to 0 or saturate
            assert np.all(sigma[:3] > 0.0)
        assert np.max(sigma) <= math.exp(15.0) * (1 + 1e-6)
        grads = LOSS_GRAD(p, xs, ds)
        assert all(np.all(np.isfinite(g)) for g in jax.tree.leaves(grads))
    big_sigma = np.asarray(DENSITY_BATCH(big, xs))
    assert np.max(big_sigma) == pytest.approx(math.exp(15.0), rel=1e-5)  # the clamp was reached


@pytest.mark.slow
def test_gradients_reach_every_parameter_and_respect_the_box(params):
    x_in = np.tile(np.array([[0.3, -0.5, 1.2]], np.float32), (8, 1))
    x_out = np.tile(np.array([[3.0, 0.0, 1.0]], np.float32), (8, 1))
    ds = np.tile(np.array([[0.0, 0.6, 0.8]], np.float32), (8, 1))
    grads = LOSS_GRAD(params, x_in, ds)
    for path, g in jax.tree_util.tree_leaves_with_path(grads):
        g = np.asarray(g)
        assert np.all(np.isfinite(g)), path
        assert np.max(np.abs(g)) > 0.0, f"no gradient reaches {jax.tree_util.keystr(path)}"
    # One point touches at most 8 rows per level of the table.
    assert np.sum(np.any(np.asarray(grads["hash"]) != 0, axis=1)) <= 8 * CONFIG.hashgrid.L

    # Outside the box sigma is 0 and carries no gradient; inside it reaches the table.
    assert all(np.max(np.abs(np.asarray(g))) == 0.0 for g in jax.tree.leaves(DENSITY_GRAD(params, x_out)))
    assert np.max(np.abs(np.asarray(DENSITY_GRAD(params, x_in)["hash"]))) > 0.0


@pytest.mark.slow
def test_jit_vmap_4096_points_without_retracing(params):
    traces = []

    @jax.jit
    @chex.assert_max_traces(n=1)
    def render_batch(p, xs, ds):
        traces.append(1)
        return make_field_batch(CONFIG)(p, xs, ds)

    for seed in range(3):
        sigma, rgb = render_batch(params, _inside_points(seed, 4096), _directions(seed + 10, 4096))
        assert sigma.shape == (4096,) and rgb.shape == (4096, 3)
    assert len(traces) == 1
    # Equal configs give the same field function, so callers' jit caches keyed on it are shared.
    twin_grid = HashGridConfig(L=4, T=2**12, F=2, N_min=4, N_max=64)
    twin = NGPFieldConfig(aabb=np.array([AABB[:3], AABB[3:]]), hashgrid=twin_grid)
    assert twin == CONFIG and hash(twin) == hash(CONFIG)
    assert make_field(twin) is make_field(CONFIG)


def test_config_from_aabb_scale_and_validation():
    config = NGPFieldConfig.create(np.array([[-2.0, -2.0, -2.0], [2.0, 2.0, 2.0]]), aabb_scale=4)
    assert config.aabb == (-2.0, -2.0, -2.0, 2.0, 2.0, 2.0)
    assert config.hashgrid.N_max == 8192 and config.hashgrid.L == 16 and config.hashgrid.T == 2**19
    assert config.density_hidden == (64,) and config.color_hidden == (64, 64) and config.geo_features == 16
    with pytest.raises(ValueError, match="aabb"):
        NGPFieldConfig(aabb=(0, 0, 0, 1, -1, 1))
    with pytest.raises(ValueError, match="aabb"):
        NGPFieldConfig(aabb=(0, 0, 1, 1))
