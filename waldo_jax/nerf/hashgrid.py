"""Multiresolution hash encoding of Instant-NGP (Müller et al., SIGGRAPH 2022, Sec. 3).

`HashGridConfig` (L, T, F, N_min, N_max: the paper's symbols), `HashGridLayout` (per-level
resolutions, sizes and row offsets, computed once from the static config), `init_hashgrid` and
`encode(table, x01)` -> [L * F] features of a point in the unit cube. Dense levels index their
vertices, hashed levels use the paper's primes; the layout and indexing: docs/design.md,
"The hash-grid field".
"""

from __future__ import annotations

import dataclasses
import functools
import math
from typing import NamedTuple, Tuple

import jax
import jax.numpy as jnp
from jax.custom_derivatives import SymbolicZero
import numpy as np

from waldo_jax.types import Array, PRNGKey

__all__ = [
    "HASH_PRIMES",
    "HashGridConfig",
    "HashGridLayout",
    "MAX_GRID_RESOLUTION",
    "encode",
    "grid_indices",
    "init_hashgrid",
]

# The paper's spatial-hash primes, one per axis (x, y, z); pi_1 = 1 keeps x coherent in memory.
HASH_PRIMES: Tuple[int, int, int] = (1, 2654435761, 805459861)

# Paper's initialisation range of the table entries, U(-1e-4, 1e-4).
_INIT_SCALE = 1e-4

# Offsets (0/1 along x, y, z) of the 8 corners of a grid cell, corner c = (c & 1, c >> 1 & 1, c >> 2 & 1).
_CORNERS = np.array([[(c >> axis) & 1 for axis in range(3)] for c in range(8)], np.uint32)  # [8, 3]


class HashGridLayout(NamedTuple):
    """Per-level layout of the concatenated table, as NumPy arrays (static constants under `jit`).

    Attributes:
      b: growth factor between successive level resolutions.
      resolutions: N_l, int64 [L].
      sizes: rows of each level table, int64 [L]: (N_l + 1)**3 for dense levels, T for hashed ones.
      offsets: first row of each level in the concatenated table, int64 [L].
      is_dense: bool [L], True where the level uses collision-free dense indexing.
      n_rows: total rows of the concatenated table, sum(sizes).
    """

    b: float
    resolutions: np.ndarray
    sizes: np.ndarray
    offsets: np.ndarray
    is_dense: np.ndarray
    n_rows: int


# The finest resolution a hash grid may have: positions are float32 in [0, 1], whose spacing near 1 is
# 2**-24, so at 2**20 cells a side the interpolation weights keep 4 bits.
MAX_GRID_RESOLUTION = 2**20


@dataclasses.dataclass(frozen=True)
class HashGridConfig:
    """Static hyper-parameters of the hash encoding (hashable, usable as a `jit` static argument).

    Defaults are the paper's (Table 1) for `aabb_scale = 1`; use `from_aabb_scale` for larger scenes.

    Attributes:
      L: number of levels.
      T: maximum entries per level (the paper's hash table size, 2**14 .. 2**24).
      F: features per entry.
      N_min: coarsest resolution.
      N_max: finest resolution (Instant-NGP uses 2048 * aabb_scale).
    """

    L: int = 16
    T: int = 2**19
    F: int = 2
    N_min: int = 16
    N_max: int = 2048

    def __post_init__(self):
        for name in ("L", "T", "F", "N_min", "N_max"):
            value = getattr(self, name)
            if not isinstance(value, (int, np.integer)) or value < 1:
                raise ValueError(f"HashGridConfig.{name} must be a positive int, got {value!r}")
            object.__setattr__(self, name, int(value))
        if self.N_max < self.N_min:
            raise ValueError(f"HashGridConfig needs N_max >= N_min, got N_min={self.N_min}, N_max={self.N_max}")
        if self.N_max > MAX_GRID_RESOLUTION:
            raise ValueError(
                f"HashGridConfig.N_max must be at most {MAX_GRID_RESOLUTION} (2**20: a float32 position in the "
                f"box resolves about 2**-24 of it, leaving the finest cell too few bits), got {self.N_max}"
            )
        if self.T > 2**31 or self.L * self.T * self.F >= 2**31:
            raise ValueError(
                f"HashGridConfig table too large for int32 indices: L={self.L}, T={self.T}, F={self.F} "
                "(L * T * F must stay below 2**31)"
            )

    @classmethod
    def from_aabb_scale(cls, aabb_scale: float = 1.0, **overrides) -> "HashGridConfig":
        """The Instant-NGP configuration for a scene with the given `aabb_scale`: N_max = 2048 * aabb_scale."""
        if aabb_scale <= 0:
            raise ValueError(f"aabb_scale must be positive, got {aabb_scale!r}")
        return cls(N_max=int(round(2048 * aabb_scale)), **overrides)

    @property
    def layout(self) -> HashGridLayout:
        """Level resolutions, sizes and offsets (computed once per distinct config)."""
        return _layout(self.L, self.T, self.N_min, self.N_max)

    @property
    def b(self) -> float:
        return self.layout.b

    @property
    def resolutions(self) -> Tuple[int, ...]:
        return tuple(int(n) for n in self.layout.resolutions)

    @property
    def n_rows(self) -> int:
        return self.layout.n_rows

    @property
    def n_dense(self) -> int:
        """Number of dense levels (always the first ones)."""
        return int(self.layout.is_dense.sum())

    @property
    def output_dim(self) -> int:
        """Length of the encoding, L * F."""
        return self.L * self.F


@functools.lru_cache(maxsize=None)
def _layout(L: int, T: int, N_min: int, N_max: int) -> HashGridLayout:
    """Computes the per-level layout of the concatenated table in NumPy."""
    b = math.exp((math.log(N_max) - math.log(N_min)) / (L - 1)) if L > 1 else 1.0
    levels = np.arange(L, dtype=np.float64)
    # The tiny slack keeps floor(N_min * b**(L-1)) == N_max despite rounding of exp/log (2047.9999...).
    resolutions = np.floor(N_min * b**levels + 1e-6).astype(np.int64)  # [L]
    dense_sizes = [(int(n) + 1) ** 3 for n in resolutions]  # Python ints: no int64 overflow
    is_dense = np.array([size <= T for size in dense_sizes], bool)  # [L]
    sizes = np.array([size if size <= T else T for size in dense_sizes], np.int64)  # [L]
    offsets = np.concatenate([[0], np.cumsum(sizes)[:-1]]).astype(np.int64)  # [L]
    # Resolutions never decrease, so dense levels are a prefix: `grid_indices` relies on it.
    n_dense = int(is_dense.sum())
    assert is_dense[:n_dense].all() and not is_dense[n_dense:].any()
    for array in (resolutions, sizes, offsets, is_dense):
        array.setflags(write=False)
    return HashGridLayout(b, resolutions, sizes, offsets, is_dense, int(sizes.sum()))


def init_hashgrid(key: PRNGKey, config: HashGridConfig, dtype=jnp.float32) -> Array:
    """Initialises the concatenated feature table, entries uniform in [-1e-4, 1e-4] as in the paper.

    Args:
      key: PRNG key.
      config: static hash-grid configuration.
      dtype: floating dtype of the table.

    Returns:
      table: [config.n_rows, F] feature table.
    """
    return jax.random.uniform(
        key, (config.n_rows, config.F), dtype, minval=-_INIT_SCALE, maxval=_INIT_SCALE
    )  # [n_rows, F]


def grid_indices(x01: Array, config: HashGridConfig) -> Tuple[Array, Array]:
    """Table rows and trilinear weights of the 8 cell corners at every level, for ONE point.

    Args:
      x01: point in the unit cube, [3] float; coordinates outside [0, 1] are clamped.
      config: static hash-grid configuration.

    Returns:
      rows: int32 [L, 8], rows of the concatenated table (level offsets included); corner c of a cell
        is the vertex base + (c & 1, c >> 1 & 1, c >> 2 & 1).
      weights: float [L, 8], trilinear weights (each level's weights sum to 1).
    """
    layout = config.layout
    n_dense = config.n_dense
    res_float = layout.resolutions.astype(np.float32)  # [L]
    res_uint = layout.resolutions.astype(np.uint32)  # [L]

    # NaN coordinates would index garbage rows; map them to the origin corner (callers mask them out).
    x01 = _clamp(x01)  # [3]
    pos = x01[None, :] * res_float[:, None]  # [L, 3], in grid units
    # The cell's lower vertex; x01 == 1 falls in the last cell with fraction 1, not outside the grid.
    base = jnp.clip(jnp.floor(pos), 0.0, (res_float - 1.0)[:, None])  # [L, 3]
    frac = pos - base  # [L, 3] in [0, 1]
    corners = base.astype(jnp.uint32)[:, None, :] + _CORNERS[None, :, :]  # [L, 8, 3]

    # Dense prefix: row = i + (N+1) * j + (N+1)**2 * k, exact in uint32 since (N+1)**3 <= T < 2**31.
    side = res_uint[:n_dense] + np.uint32(1)  # [n_dense]
    strides = np.stack([np.ones_like(side), side, side * side], axis=-1)  # [n_dense, 3]
    dense_rows = jnp.sum(corners[:n_dense] * strides[:, None, :], axis=-1)  # [n_dense, 8]

    # Hashed suffix: xor of per-axis products with the primes, wrapping modulo 2**32, then mod T.
    primes = np.asarray(HASH_PRIMES, np.uint32)  # [3]
    scrambled = corners[n_dense:] * primes  # [L - n_dense, 8, 3]
    hashed = scrambled[..., 0] ^ scrambled[..., 1] ^ scrambled[..., 2]  # [L - n_dense, 8]
    hashed_rows = hashed % np.uint32(config.T)  # [L - n_dense, 8]

    level_rows = jnp.concatenate([dense_rows, hashed_rows], axis=0).astype(jnp.int32)  # [L, 8]
    rows = level_rows + layout.offsets.astype(np.int32)[:, None]  # [L, 8]

    # Weight of corner c: product over axes of frac (corner bit 1) or 1 - frac (corner bit 0).
    bits = _CORNERS.astype(bool)  # [8, 3]
    per_axis = jnp.where(bits[None, :, :], frac[:, None, :], 1.0 - frac[:, None, :])  # [L, 8, 3]
    weights = jnp.prod(per_axis, axis=-1)  # [L, 8]
    return rows, weights


def encode(table: Array, x01: Array, config: HashGridConfig) -> Array:
    """Hash-grid features of ONE point: trilinear interpolation of the 8 cell corners at each level.

    Differentiable in the table (training: autodiff's gather, transposed into a scatter-add) and in
    the point (pose refinement), both modes; the point's derivative comes from a rule
    (`_interpolate_at`) that differentiates the trilinear weights on the corner features already
    gathered instead of autodiff's chain through the clip, floor and products: the same derivative,
    and the reverse-mode gradient of a render no longer spends most of its time on it.

    Args:
      table: [config.n_rows, F] concatenated feature table (from `init_hashgrid`).
      x01: point in the unit cube, [3]; the caller normalises world points by the scene aabb.
        Coordinates outside [0, 1] are clamped to the cube's faces.
      config: static hash-grid configuration.

    Returns:
      features: [L * F], level-major (level 0's F features first), in the table's dtype.
    """
    table = jnp.asarray(table)  # [n_rows, F]
    rows, _ = grid_indices(x01, config)  # [L, 8]: integers, no derivative
    return _interpolate_at(_gather_rows(table, rows), x01, config)


def _gather_rows(table: Array, rows: Array) -> Array:
    """The table's rows [L, 8, F] at `rows` [L, 8] (in bounds by construction): one gather for all levels.

    The gather reads the table as one flat vector, F values from element row * F, instead of indexing its
    rows: the same values, and autodiff's transpose of it (the table's gradient, a scatter-add, vmapped
    over a batch of points) then needs no relayout of the cotangents. On XLA:CPU indexing rows [n_rows, F]
    made the scatter copy its updates first (a size-1 window axis laid out apart): measured alone, about
    2.7x slower for the same sums in the same order (tests/test_hashgrid.py compares the two gradients bit
    for bit; inside a whole training step XLA may fuse the neighbouring operations differently, so a
    trained field need not be the same to the bit). docs/performance.md, "The field's gather and
    interpolation".
    """
    features = table.shape[-1]
    numbers = jax.lax.GatherDimensionNumbers(offset_dims=(2,), collapsed_slice_dims=(), start_index_map=(0,))
    starts = (rows * features)[..., None]  # [L, 8, 1]: rows * F < 2**31 (HashGridConfig checks L * T * F)
    return jax.lax.gather(
        table.reshape(-1),
        starts,
        numbers,
        slice_sizes=(features,),
        mode=jax.lax.GatherScatterMode.PROMISE_IN_BOUNDS,
    )  # [L, 8, F]


def _interpolate(weights: Array, corner_features: Array, config: HashGridConfig) -> Array:
    """sum over corners of weight x feature, [L * F] in the features' dtype."""
    weights = weights.astype(corner_features.dtype)  # [L, 8]
    features = jnp.sum(weights[:, :, None] * corner_features, axis=1)  # [L, F]
    return features.reshape(config.L * config.F)  # [L * F]


@functools.partial(jax.custom_jvp, nondiff_argnums=(2,))
def _interpolate_at(corners: Array, x01: Array, config: HashGridConfig) -> Array:
    """The features [L * F] of corners [L, 8, F] (the point's cell corners) at the point x01 [3]."""
    return _interpolate(grid_indices(x01, config)[1], corners, config)


@functools.partial(_interpolate_at.defjvp, symbolic_zeros=True)
def _interpolate_at_jvp(config: HashGridConfig, primals, tangents):
    """Tangent = the corners' tangent interpolated with the same weights + the weights' derivative
    along the point's tangent (`_slopes`, times the clamp's own derivative: JAX's, 0 outside [0, 1])."""
    corners, x01 = primals
    d_corners, d_x01 = tangents
    features = _interpolate_at(corners, x01, config)
    tangent = jnp.zeros_like(features)
    if not isinstance(d_corners, SymbolicZero):
        tangent = tangent + _interpolate(grid_indices(x01, config)[1], d_corners, config)
    if not isinstance(d_x01, SymbolicZero):
        x01 = jnp.asarray(x01, jnp.float32)
        clamped_tangent = jax.jvp(_clamp, (x01,), (jnp.asarray(d_x01, jnp.float32),))[1]  # [3]
        resolutions = config.layout.resolutions.astype(np.float32)  # [L]
        pos = _clamp(x01)[None, :] * resolutions[:, None]  # [L, 3]
        frac = pos - jnp.clip(jnp.floor(pos), 0.0, (resolutions - 1.0)[:, None])  # [L, 3], as `grid_indices`
        jacobian = _slopes(frac, corners, resolutions)  # [L, F, 3]
        tangent = tangent + jnp.sum(jacobian * clamped_tangent.astype(corners.dtype), axis=-1).reshape(-1)
    return features, tangent


def _slopes(frac: Array, corners: Array, resolutions: np.ndarray) -> Array:
    """d features / d x01 [L, F, 3] of the trilinear interpolation: along axis k, the difference of the
    corner features across the cell (bit k set and clear) weighted by the other two axes' factors,
    times the level's resolution. Written as sums of products of whole arrays (XLA fuses them into
    one loop; a batched einsum of [8, 3] by [8, F] matrices was several times slower on CPU)."""
    factor = (1.0 - frac, frac)  # [L, 3] each: an axis's factor for a corner bit 0 or 1
    columns = []
    for k in range(3):
        j1, j2 = (j for j in range(3) if j != k)
        total = 0.0
        for low in (c for c in range(8) if not c >> k & 1):
            weight = factor[low >> j1 & 1][:, j1] * factor[low >> j2 & 1][:, j2]  # [L]
            total = total + weight[:, None].astype(corners.dtype) * (corners[:, low | 1 << k] - corners[:, low])
        columns.append(total * resolutions[:, None].astype(corners.dtype))  # [L, F]
    return jnp.stack(columns, axis=-1)  # [L, F, 3]


def _clamp(x01: Array) -> Array:
    """The point as `grid_indices` reads it: NaN to 0, clipped to the unit cube."""
    return jnp.clip(jnp.nan_to_num(jnp.asarray(x01, jnp.float32), nan=0.0), 0.0, 1.0)
