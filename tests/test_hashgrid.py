"""Tests of the multiresolution hash encoding (waldo_jax.nerf.hashgrid) against NumPy references."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from waldo_jax.nerf import HASH_PRIMES, HashGridConfig, encode, grid_indices, init_hashgrid

# The paper's primes (Müller et al. 2022, Eq. 4), written out so that a change in the library shows.
PAPER_PRIMES = (1, 2654435761, 805459861)

# Small grid: levels N = 4, 11 (dense: 125 and 1728 vertices <= T) and 32 (hashed: 33**3 > T).
SMALL = HashGridConfig(L=3, T=2**12, F=2, N_min=4, N_max=32)
# The same resolutions with a table size that is not a power of two (mod T is not a bit mask).
ODD_T = HashGridConfig(L=3, T=3001, F=2, N_min=4, N_max=32)


# Test data comes from seeded NumPy generators: eager jax.random calls compile a kernel per shape,
# which would dominate the run time of this suite on 2 cores.
def _rng(seed: int) -> np.random.Generator:
    return np.random.default_rng(seed)


def _random_points(seed: int, n: int) -> np.ndarray:
    """n points strictly inside the unit cube, [n, 3] float32."""
    return _rng(seed).uniform(0.001, 0.999, (n, 3)).astype(np.float32)


def _np_hash(vertex: np.ndarray, T: int) -> np.ndarray:
    """The paper's spatial hash of integer vertices [..., 3] in exact integer arithmetic."""
    v = vertex.astype(np.uint64)
    mask = np.uint64(0xFFFFFFFF)
    h = (v[..., 0] * np.uint64(PAPER_PRIMES[0])) & mask
    h ^= (v[..., 1] * np.uint64(PAPER_PRIMES[1])) & mask
    h ^= (v[..., 2] * np.uint64(PAPER_PRIMES[2])) & mask
    return (h % np.uint64(T)).astype(np.int64)


def _np_level_rows(config: HashGridConfig, level: int, vertex: np.ndarray) -> np.ndarray:
    """Rows (with the level offset) of integer vertices [..., 3] at one level, from the documented layout."""
    n = config.resolutions[level]
    offset = int(config.layout.offsets[level])
    if (n + 1) ** 3 <= config.T:
        side = n + 1
        return offset + vertex[..., 0] + side * (vertex[..., 1] + side * vertex[..., 2])
    return offset + _np_hash(vertex, config.T)


def _np_trilinear(config: HashGridConfig, table: np.ndarray, level: int, x: np.ndarray) -> np.ndarray:
    """NumPy trilinear interpolation of one level's vertex features at one point x in [0, 1]^3 -> [F]."""
    n = config.resolutions[level]
    pos = np.clip(x.astype(np.float64), 0.0, 1.0) * n
    base = np.minimum(np.floor(pos), n - 1).astype(np.int64)
    frac = pos - base
    out = np.zeros(config.F)
    for dx in (0, 1):
        for dy in (0, 1):
            for dz in (0, 1):
                corner = base + np.array([dx, dy, dz])
                weight = np.prod(np.where([dx, dy, dz], frac, 1.0 - frac))
                out += weight * table[_np_level_rows(config, level, corner)]
    return out


# --------------------------------------------------------------------------------------------------
# Layout


def test_paper_default_layout_matches_formula():
    config = HashGridConfig()
    assert (config.L, config.T, config.F, config.N_min, config.N_max) == (16, 2**19, 2, 16, 2048)
    b = math.exp((math.log(2048) - math.log(16)) / 15)
    assert config.b == pytest.approx(b, rel=1e-12)
    assert config.b == pytest.approx(2 ** (7 / 15), rel=1e-12)
    expected = (16, 22, 30, 42, 58, 80, 111, 153, 212, 294, 406, 561, 776, 1072, 1482, 2048)
    assert config.resolutions == expected
    # floor(N_min * b**l) away from the exact-integer end point.
    assert all(n == math.floor(16 * b**level) for level, n in enumerate(expected[:-1]))
    # (58 + 1)**3 = 205379 fits in 2**19 = 524288; (80 + 1)**3 = 531441 does not.
    assert config.n_dense == 5
    np.testing.assert_array_equal(config.layout.is_dense, [True] * 5 + [False] * 11)
    dense_sizes = [(n + 1) ** 3 for n in expected[:5]]
    np.testing.assert_array_equal(config.layout.sizes, dense_sizes + [2**19] * 11)
    np.testing.assert_array_equal(config.layout.offsets, np.concatenate([[0], np.cumsum(config.layout.sizes)[:-1]]))
    assert config.n_rows == sum(dense_sizes) + 11 * 2**19
    assert config.output_dim == 32


def test_aabb_scale_sets_n_max():
    config = HashGridConfig.from_aabb_scale(4)
    assert config.N_max == 8192
    assert config.resolutions[0] == 16 and config.resolutions[-1] == 8192
    assert config.b == pytest.approx(math.exp((math.log(8192) - math.log(16)) / 15))
    assert HashGridConfig.from_aabb_scale(1) == HashGridConfig()


def test_dense_threshold_is_inclusive():
    # A level of N = 7 has 8**3 = 512 vertices: dense with T = 512 (size 512), hashed with T = 511.
    dense = HashGridConfig(L=1, T=512, F=2, N_min=7, N_max=7)
    hashed = HashGridConfig(L=1, T=511, F=2, N_min=7, N_max=7)
    assert dense.layout.is_dense.tolist() == [True] and dense.n_rows == 512
    assert hashed.layout.is_dense.tolist() == [False] and hashed.n_rows == 511


def test_the_finest_allowed_resolution_lays_out_without_overflow():
    """(N + 1) ** 3 of the finest levels passes int64 near N = 2**21: the layout counts in Python ints."""
    finest = HashGridConfig(N_max=2**20)
    assert finest.resolutions[-1] == 2**20 and not finest.layout.is_dense[-1]
    assert finest.n_rows == int(finest.layout.sizes.sum()) > 0


def test_small_config_layout():
    assert SMALL.resolutions == (4, 11, 32)
    np.testing.assert_array_equal(SMALL.layout.sizes, [125, 1728, 4096])
    np.testing.assert_array_equal(SMALL.layout.offsets, [0, 125, 1853])


@pytest.mark.parametrize(
    "kwargs",
    [dict(L=0), dict(T=0), dict(N_min=32, N_max=16), dict(F=1.5), dict(L=16, T=2**26, F=2), dict(N_max=2**20 + 1)],
)
def test_invalid_config_raises(kwargs):
    with pytest.raises(ValueError):
        HashGridConfig(**kwargs)


@pytest.mark.slow
def test_init_table_shape_range_and_determinism():
    table = init_hashgrid(jax.random.key(0), SMALL)
    assert table.shape == (SMALL.n_rows, 2) and table.dtype == jnp.float32
    assert float(jnp.max(jnp.abs(table))) <= 1e-4
    assert float(jnp.std(table)) > 1e-5  # not all zeros
    np.testing.assert_array_equal(table, init_hashgrid(jax.random.key(0), SMALL))
    assert not np.array_equal(table, init_hashgrid(jax.random.key(1), SMALL))


# --------------------------------------------------------------------------------------------------
# Encoding


@pytest.mark.parametrize("config", [SMALL, ODD_T], ids=["T=4096", "T=3001"])
def test_encode_matches_numpy_trilinear_on_all_levels(config):
    table = np.asarray(_rng(2).normal(size=(config.n_rows, config.F)).astype(np.float32))
    points = _random_points(3, 64)
    features = np.asarray(jax.jit(jax.vmap(lambda x: encode(table, x, config)))(points))  # [64, L*F]
    assert features.shape == (64, config.L * config.F)
    for level in range(config.L):
        expected = np.stack([_np_trilinear(config, table, level, x) for x in points])  # [64, F]
        got = features[:, level * config.F : (level + 1) * config.F]
        np.testing.assert_allclose(got, expected, rtol=1e-5, atol=1e-5, err_msg=f"level {level}")


def test_dense_level_is_trilinear_interpolation_of_vertex_grid():
    # Random values per vertex of level 1 (N = 11), laid out as documented: row i + 12 j + 144 k.
    level, n = 1, SMALL.resolutions[1]
    grid = _rng(4).normal(size=(n + 1, n + 1, n + 1, SMALL.F)).astype(np.float32)  # [i, j, k, F]
    table = np.zeros((SMALL.n_rows, SMALL.F), np.float32)
    offset = int(SMALL.layout.offsets[level])
    table[offset : offset + (n + 1) ** 3] = grid.transpose(2, 1, 0, 3).reshape(-1, SMALL.F)
    batched = jax.jit(jax.vmap(lambda table, x: encode(table, x, SMALL)[2:4], in_axes=(None, 0)))
    enc = lambda x: batched(table, x)  # noqa: E731  (reads the table as it is now)

    # At vertices (boundary ones included) the encoding is the vertex value.
    vertices = _rng(5).integers(0, n + 1, (64, 3))
    vertices[:3] = [[0, 0, 0], [n, n, n], [n, 0, n]]
    np.testing.assert_allclose(enc(vertices / n), grid[tuple(vertices.T)], atol=1e-5)

    # Between vertices: independent trilinear interpolation of the grid.
    points = _random_points(6, 64)
    pos = points.astype(np.float64) * n
    base = np.minimum(np.floor(pos), n - 1).astype(int)
    frac = pos - base
    expected = np.zeros((64, SMALL.F))
    for corner in np.ndindex(2, 2, 2):
        weight = np.prod(np.where(np.array(corner, bool), frac, 1.0 - frac), axis=1)
        expected += weight[:, None] * grid[tuple((base + corner).T)]
    np.testing.assert_allclose(enc(points), expected, rtol=1e-5, atol=1e-5)

    # A linear function of the vertex coordinates is reproduced exactly everywhere.
    i, j, k = np.meshgrid(*[np.arange(n + 1)] * 3, indexing="ij")
    linear = np.stack([i / n + 2 * j / n - k / n, 3 * k / n], axis=-1)
    table[offset : offset + (n + 1) ** 3] = linear.transpose(2, 1, 0, 3).reshape(-1, SMALL.F)
    x = points
    np.testing.assert_allclose(enc(x), np.stack([x[:, 0] + 2 * x[:, 1] - x[:, 2], 3 * x[:, 2]], -1), atol=1e-5)


@pytest.mark.parametrize("config", [SMALL, ODD_T], ids=["T=4096", "T=3001"])
def test_hashed_level_indices_match_numpy_hash(config):
    level, n = 2, config.resolutions[2]
    assert not config.layout.is_dense[level]
    points = _random_points(7, 32)
    rows, weights = jax.jit(jax.vmap(lambda x: grid_indices(x, config)))(points)  # [32, L, 8]
    base = np.minimum(np.floor(points.astype(np.float64) * n), n - 1).astype(np.int64)  # [32, 3]
    corners = np.array([[c & 1, (c >> 1) & 1, (c >> 2) & 1] for c in range(8)])  # [8, 3]
    vertices = base[:, None, :] + corners[None]  # [32, 8, 3]
    # Vertex coordinates up to 32 make y * 2654435761 exceed 2**32: the products must wrap as uint32.
    assert HASH_PRIMES == PAPER_PRIMES
    assert vertices[..., 1].max() * PAPER_PRIMES[1] >= 2**32
    expected = config.layout.offsets[level] + _np_hash(vertices, config.T)
    np.testing.assert_array_equal(np.asarray(rows[:, level]), expected)
    assert np.all(np.asarray(rows) < config.n_rows) and np.all(np.asarray(rows) >= 0)
    np.testing.assert_allclose(np.asarray(weights).sum(-1), 1.0, rtol=1e-6)


def test_points_outside_unit_cube_are_clamped():
    table = _rng(8).normal(size=(SMALL.n_rows, SMALL.F)).astype(np.float32)
    points = jnp.array([[-0.5, 0.3, 1.7], [2.0, -3.0, 0.5], [1e30, -1e30, 0.25]])
    enc = jax.jit(jax.vmap(lambda x: encode(table, x, SMALL)))
    np.testing.assert_allclose(enc(points), enc(jnp.clip(points, 0.0, 1.0)), atol=1e-6)
    assert np.all(np.isfinite(np.asarray(enc(jnp.array([[jnp.nan, jnp.inf, -jnp.inf]])))))


@pytest.mark.parametrize("config", [SMALL, ODD_T], ids=["T=4096", "T=3001"])
def test_rows_stay_inside_their_level_on_the_cube_faces(config):
    # x = 1 lies in the last cell (with fraction 1), never in a cell beyond the grid.
    points = np.array([[1.0, 1.0, 1.0], [0.0, 0.0, 0.0], [1.0, 0.0, 1.0], [0.5, 1.0, 0.0]], np.float32)
    rows, weights = jax.jit(jax.vmap(lambda x: grid_indices(x, config)))(points)  # [4, L, 8]
    start = config.layout.offsets[None, :, None]
    stop = start + config.layout.sizes[None, :, None]
    assert np.all((np.asarray(rows) >= start) & (np.asarray(rows) < stop))
    np.testing.assert_allclose(np.asarray(weights)[0, :, 7], 1.0)  # all weight on the far corner (1, 1, 1)
    np.testing.assert_allclose(np.asarray(weights)[1, :, 0], 1.0)  # all weight on the near corner (0, 0, 0)


@pytest.mark.slow
def test_gradient_reaches_exactly_the_touched_rows():
    table = init_hashgrid(jax.random.key(9), SMALL)
    points = _random_points(10, 3)
    coefficients = _rng(11).normal(size=(3, SMALL.L * SMALL.F)).astype(np.float32)

    def loss(table):
        return jnp.sum(coefficients * jax.vmap(lambda x: encode(table, x, SMALL))(points))

    grad = np.asarray(jax.jit(jax.grad(loss))(table))
    assert grad.shape == table.shape and np.all(np.isfinite(grad))
    touched = set()
    for x in points:
        for level in range(SMALL.L):
            n = SMALL.resolutions[level]
            base = np.minimum(np.floor(x.astype(np.float64) * n), n - 1).astype(int)
            for corner in np.ndindex(2, 2, 2):
                touched.add(int(_np_level_rows(SMALL, level, base + corner)))
    nonzero = set(np.flatnonzero(np.any(grad != 0.0, axis=1)).tolist())
    assert nonzero == touched

    # The gradient of one output feature with respect to a corner row is that corner's weight.
    x = points[0]
    n = SMALL.resolutions[2]
    pos = x.astype(np.float64) * n
    base = np.floor(pos).astype(int)
    frac = pos - base
    single = np.asarray(jax.jit(jax.grad(lambda t: encode(t, x, SMALL)[2 * SMALL.F + 1]))(table))
    for corner in np.ndindex(2, 2, 2):
        row = int(_np_level_rows(SMALL, 2, base + corner))
        weight = np.prod(np.where(np.array(corner, bool), frac, 1.0 - frac))
        assert single[row, 1] == pytest.approx(weight, abs=1e-5)
        assert single[row, 0] == 0.0


@pytest.mark.slow
def test_encode_is_differentiable_in_position():
    table = _rng(12).normal(size=(SMALL.n_rows, SMALL.F)).astype(np.float32)
    x = jnp.asarray(_random_points(13, 1)[0])
    enc = jax.jit(lambda x: encode(table, x, SMALL))
    jac = jax.jit(jax.jacfwd(enc))(x)  # [L*F, 3]
    assert jac.shape == (SMALL.L * SMALL.F, 3)
    assert np.all(np.isfinite(np.asarray(jac))) and float(jnp.max(jnp.abs(jac))) > 0.0
    step = jnp.array([1e-3, 0.0, 0.0])
    numeric = (enc(x + step) - enc(x - step)) / (2 * 1e-3)
    np.testing.assert_allclose(jac[:, 0], numeric, rtol=2e-2, atol=2e-2)


def _autodiff_encode(table, x01, config):
    """`encode` without its derivative rule or its gather: autodiff through the clip, floor and weight
    products, the table indexed by its rows."""
    rows, weights = grid_indices(x01, config)
    return jnp.sum(weights[:, :, None] * table[rows], axis=1).reshape(-1)


def test_encode_rule_gives_autodiffs_derivatives_in_both_modes():
    """`encode`'s rule for the point's derivative (the trilinear weights' own, on the gathered corners)
    gives what autodiff gives, to float rounding, in reverse and forward mode, inside and outside the
    cube (where the clamp's derivative is 0) and on every level; the table's gradient (training, through
    the flat gather's scatter) is bit for bit autodiff's through the table's rows, and the features
    under jvp are those without."""
    table = jnp.asarray(_rng(20).normal(size=(ODD_T.n_rows, ODD_T.F)), jnp.float32)
    points = jnp.asarray(_rng(21).uniform(-0.2, 1.2, (64, 3)), jnp.float32)
    weights = jnp.asarray(_rng(22).normal(size=(64, ODD_T.L * ODD_T.F)), jnp.float32)

    def loss(fn):
        return lambda t, p: jnp.sum(weights * jax.vmap(lambda x: fn(t, x, ODD_T))(p))

    ours, plain = loss(encode), loss(_autodiff_encode)
    assert np.array_equal(jax.jit(jax.grad(ours))(table, points), jax.jit(jax.grad(plain))(table, points))
    d_ours = jax.jit(jax.grad(ours, argnums=1))(table, points)
    d_plain = jax.jit(jax.grad(plain, argnums=1))(table, points)
    np.testing.assert_allclose(d_ours, d_plain, rtol=1e-5, atol=1e-5 * float(jnp.max(jnp.abs(d_plain))))
    outside = np.any((np.asarray(points) < 0) | (np.asarray(points) > 1), axis=1)
    assert outside.any() and np.all(np.asarray(d_ours)[np.asarray(points) < 0] == 0.0)
    tangent = jnp.asarray(_rng(23).normal(size=(64, 3)), jnp.float32)
    f_ours = jax.jit(lambda p: jax.jvp(lambda p: jax.vmap(lambda x: encode(table, x, ODD_T))(p), (p,), (tangent,)))
    f_plain = jax.jit(
        lambda p: jax.jvp(lambda p: jax.vmap(lambda x: _autodiff_encode(table, x, ODD_T))(p), (p,), (tangent,))
    )
    f_ours, f_plain = f_ours(points), f_plain(points)
    # The values under jvp are encode's own (autodiff's product rule computes `prod` another way).
    assert np.array_equal(f_ours[0], jax.jit(jax.vmap(lambda x: encode(table, x, ODD_T)))(points))
    np.testing.assert_allclose(f_ours[1], f_plain[1], rtol=1e-5, atol=1e-5 * float(jnp.max(jnp.abs(f_plain[1]))))
