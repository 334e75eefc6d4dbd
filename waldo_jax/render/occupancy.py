"""Instant-NGP's multi-scale occupancy grid (Müller et al., SIGGRAPH 2022, Sec. 5.4 and Appendix E.2).

`OccupancyGrid` holds, per cascade c < C (cascade c covers the base box scaled by 2**c) and cell of
its G x G x G grid, a decaying running maximum of the density (`density` float32 [C, G**3]) and the
occupied cells (`bitfield` bool [C, G**3]). `update_occupancy` is NGP's density-grid update (decay,
sample, max, threshold). Marching rays through the grid is `waldo_jax.render.marching`; the marched
renderer (`waldo_jax.render.marched`) and training build on both.

The grid's geometry and indexing, the update's schedule and threshold, the step sizes and the names:
see docs/design.md, section "Rendering > The occupancy grid".
"""

from __future__ import annotations

import functools
import math
from typing import Callable, Tuple

import flax.struct
import jax
import jax.numpy as jnp
import numpy as np

from waldo_jax.render.volume import MAX_DENSITY
from waldo_jax.types import Array, PRNGKey

__all__ = [
    "MAX_CASCADES",
    "OccupancyConfig",
    "OccupancyGrid",
    "cell_points",
    "grid_cell",
    "init_occupancy",
    "init_occupancy_for_scene",
    "is_occupied",
    "mark_all_occupied",
    "occupancy_thresholds",
    "update_occupancy",
    "update_occupancy_phase",
]

# Instant-NGP's cap on the number of cascades (NERF_CASCADES).
MAX_CASCADES = 8
# Instant-NGP's minimal steps per base-box diagonal (NERF_STEPS) and minimal optical thickness.
NGP_STEPS_PER_DIAGONAL = 1024
NGP_MIN_OPTICAL_THICKNESS = 0.01

# A density (one point) as the occupancy grid queries it: (params, x [3]) -> sigma [].
DensityFn = Callable[..., Array]


# --------------------------------------------------------------------------------------------------
# State and configuration


@flax.struct.dataclass
class OccupancyGrid:
    """The multi-scale occupancy grid (see docs/design.md, "Rendering" for the geometry and indexing).

    Attributes:
      density: float32 [C, G**3], decaying running maximum of the sampled density per cell.
      bitfield: bool [C, G**3], occupied cells.
      resolution: G, cells per axis and cascade (static).
      cascades: C (static).
      center: centre of the base box (cascade 0), 3 floats in world units (static).
      half_size: half extent of the base box per axis, 3 floats in world units (static).
    """

    density: Array
    bitfield: Array
    resolution: int = flax.struct.field(pytree_node=False, default=128)
    cascades: int = flax.struct.field(pytree_node=False, default=1)
    center: Tuple[float, float, float] = flax.struct.field(pytree_node=False, default=(0.0, 0.0, 0.0))
    half_size: Tuple[float, float, float] = flax.struct.field(pytree_node=False, default=(1.0, 1.0, 1.0))

    @property
    def cells_per_cascade(self) -> int:
        """G**3."""
        return self.resolution**3

    @property
    def base_aabb(self) -> np.ndarray:
        """The base box (cascade 0), float32 [2, 3] (min corner, max corner)."""
        center, half = np.asarray(self.center, np.float32), np.asarray(self.half_size, np.float32)
        return np.stack([center - half, center + half])

    @property
    def outer_aabb(self) -> np.ndarray:
        """The box of the coarsest cascade, float32 [2, 3]: nothing outside it is ever occupied."""
        center, half = np.asarray(self.center, np.float32), np.asarray(self.half_size, np.float32)
        scale = np.float32(2.0 ** (self.cascades - 1))
        return np.stack([center - scale * half, center + scale * half])

    @property
    def base_diagonal(self) -> float:
        """Length of the base box's diagonal, world units (NGP: sqrt(3) for its unit cube)."""
        return float(2.0 * np.linalg.norm(np.asarray(self.half_size, np.float64)))

    def cell_size(self, cascade: int) -> np.ndarray:
        """Edge lengths [3] of one cell of `cascade`, world units."""
        return 2.0 * np.asarray(self.half_size, np.float64) * 2.0**cascade / self.resolution


@flax.struct.dataclass
class OccupancyConfig:
    """Hyper-parameters of `update_occupancy`.

    Attributes:
      update_fraction: after warm-up, M = update_fraction * G**3 uniformly drawn cells and M occupied
        cells are sampled per cascade (static: sets shapes). NGP: 1/4.
      eval_chunk: density evaluations per `lax.map` step (static), to bound memory.
      warmup_steps: while `step < warmup_steps` every cell is sampled (NGP: 256).
      decay: factor applied to old densities at each update (NGP: 0.95).
      density_threshold: tau, the density (world units^-1) above which a cascade-0 cell is occupied
        (when the mean density is higher). NGP: 0.01 / dt_min = 0.01 * 1024 / sqrt(3) for the unit
        cube; `create` computes it for a grid's box.
    """

    update_fraction: float = flax.struct.field(pytree_node=False, default=0.25)
    eval_chunk: int = flax.struct.field(pytree_node=False, default=2**18)
    warmup_steps: Array = 256
    decay: Array = 0.95
    density_threshold: Array = NGP_MIN_OPTICAL_THICKNESS * NGP_STEPS_PER_DIAGONAL / math.sqrt(3.0)

    @classmethod
    def create(
        cls,
        grid: OccupancyGrid,
        min_optical_thickness: float = NGP_MIN_OPTICAL_THICKNESS,
        steps_per_diagonal: float = NGP_STEPS_PER_DIAGONAL,
        warmup_steps: int = 256,
        decay: float = 0.95,
        update_fraction: float = 0.25,
        eval_chunk: int = 2**18,
    ) -> "OccupancyConfig":
        """NGP's update for `grid`: tau = min_optical_thickness * steps_per_diagonal / base diagonal."""
        if not 0.0 < update_fraction <= 1.0:
            raise ValueError(f"update_fraction must be in (0, 1], got {update_fraction}")
        if not 0.0 <= decay <= 1.0:
            raise ValueError(f"decay must be in [0, 1], got {decay}")
        if eval_chunk < 1:
            raise ValueError(f"eval_chunk must be >= 1, got {eval_chunk}")
        return cls(
            update_fraction=float(update_fraction),
            eval_chunk=int(eval_chunk),
            warmup_steps=jnp.int32(warmup_steps),
            decay=jnp.float32(decay),
            density_threshold=jnp.float32(min_optical_thickness * steps_per_diagonal / grid.base_diagonal),
        )

    def samples_per_cascade(self, grid: OccupancyGrid) -> int:
        """M, the uniformly drawn (and, again, the occupied) cells per cascade after warm-up."""
        return max(1, int(round(self.update_fraction * grid.cells_per_cascade)))


def _as_box(aabb) -> Tuple[np.ndarray, np.ndarray]:
    """(min corner [3], max corner [3]) from a [2, 3] or [6] array-like, validated."""
    values = np.asarray(aabb, np.float64)
    if values.size != 6 or values.shape not in ((6,), (2, 3)):
        raise ValueError(f"aabb must have shape [2, 3] or [6], got {values.shape}: {aabb!r}")
    lo, hi = values.reshape(2, 3)
    if not np.all(np.isfinite(values)) or np.any(hi <= lo):
        raise ValueError(f"aabb needs finite bounds with max > min on every axis, got {values.tolist()}")
    return lo, hi


def init_occupancy(
    aabb, aabb_scale: float = 1.0, resolution: int = 128, max_cascades: int = MAX_CASCADES
) -> OccupancyGrid:
    """An empty-density grid with every cell marked occupied (nothing may be skipped before updates).

    Args:
      aabb: the base box (cascade 0), [2, 3] (min corner, max corner) or [6], world units.
      aabb_scale: NGP's aabb_scale; C = 1 + ceil(log2(aabb_scale)) cascades (at least 1, at most
        `max_cascades`), cascade c covering the base box scaled by 2**c about its centre.
      resolution: G, cells per axis and cascade.
      max_cascades: cap on C (NGP: 8).

    Returns:
      `OccupancyGrid` with density zeros [C, G**3] and bitfield all True [C, G**3].
    """
    lo, hi = _as_box(aabb)
    if not (isinstance(resolution, (int, np.integer)) and resolution >= 1):
        raise ValueError(f"resolution must be a positive int, got {resolution!r}")
    if not aabb_scale > 0 or not math.isfinite(aabb_scale):
        raise ValueError(f"aabb_scale must be positive and finite, got {aabb_scale!r}")
    cascades = 1
    while 2.0 ** (cascades - 1) < aabb_scale * (1.0 - 1e-9) and cascades < max_cascades:
        cascades += 1
    resolution = int(resolution)
    shape = (cascades, resolution**3)
    return OccupancyGrid(
        density=jnp.zeros(shape, jnp.float32),
        bitfield=jnp.ones(shape, bool),
        resolution=resolution,
        cascades=cascades,
        center=tuple(float(v) for v in 0.5 * (lo + hi)),
        half_size=tuple(float(v) for v in 0.5 * (hi - lo)),
    )


def init_occupancy_for_scene(scene, resolution: int = 128) -> OccupancyGrid:
    """The grid NGP would use for a `waldo_jax.types.Scene`.

    `Scene.aabb` is the whole box NGP marches in (for instant-ngp scenes the aabb_scale cube), so the
    base box is that box shrunk by `scene.metadata["aabb_scale"]` (1 when absent) about its centre.
    """
    lo, hi = _as_box(scene.aabb)
    aabb_scale = float(scene.metadata.get("aabb_scale", 1.0) or 1.0)
    if aabb_scale < 1.0:
        raise ValueError(f"scene {scene.name!r}: aabb_scale must be >= 1, got {aabb_scale}")
    center, half = 0.5 * (lo + hi), 0.5 * (hi - lo) / aabb_scale
    return init_occupancy(np.stack([center - half, center + half]), aabb_scale, resolution)


def mark_all_occupied(grid: OccupancyGrid) -> OccupancyGrid:
    """The grid with every cell occupied (densities kept): marching then samples everywhere."""
    return grid.replace(bitfield=jnp.ones_like(grid.bitfield))


# --------------------------------------------------------------------------------------------------
# Indexing


def grid_cell(grid: OccupancyGrid, x: Array) -> Tuple[Array, Array, Array]:
    """The cascade and cell of ONE world point (the finest cascade containing it).

    Args:
      grid: the occupancy grid (only its static geometry is used).
      x: world point, [3].

    Returns:
      cascade: int32 [] in [0, C). cell: int32 [] in [0, G**3), i + G * (j + G * k).
      inside: bool [], False outside the coarsest cascade (or for a non-finite point).
    """
    size = grid.resolution
    center = np.asarray(grid.center, np.float32)
    half = np.asarray(grid.half_size, np.float32)
    u = (jnp.asarray(x, jnp.float32) - center) / half  # [3], cascade 0 is [-1, 1]^3
    extent = jnp.max(jnp.abs(u))  # []
    inside = extent <= np.float32(2.0 ** (grid.cascades - 1))  # [], False for NaN
    level = jnp.ceil(jnp.log2(jnp.maximum(extent, jnp.finfo(jnp.float32).tiny)))  # []
    level = jnp.clip(jnp.nan_to_num(level), 0, grid.cascades - 1)  # []
    v = (u * jnp.exp2(-level) + 1.0) * (0.5 * size)  # [3], in cells of that cascade
    ijk = jnp.clip(jnp.floor(jnp.nan_to_num(v)), 0, size - 1).astype(jnp.int32)  # [3]
    cell = ijk[0] + size * (ijk[1] + size * ijk[2])  # []
    return level.astype(jnp.int32), cell, inside


def is_occupied(grid: OccupancyGrid, x: Array) -> Array:
    """Whether ONE world point x [3] lies in an occupied cell (False outside the grid). Returns bool []."""
    cascade, cell, inside = grid_cell(grid, x)
    flat = cascade * grid.cells_per_cascade + cell  # []
    return inside & grid.bitfield.reshape(-1)[flat]


def cell_points(grid: OccupancyGrid, cascade: Array, cell: Array, jitter: Array) -> Array:
    """World points at `jitter` [..., 3] in [0, 1)^3 inside cells `cell` [...] of cascades `cascade` [...]."""
    size = grid.resolution
    ijk = jnp.stack([cell % size, (cell // size) % size, cell // (size * size)], axis=-1)  # [..., 3]
    u = (ijk.astype(jnp.float32) + jitter) * (2.0 / size) - 1.0  # [..., 3] in [-1, 1]
    scale = jnp.exp2(jnp.asarray(cascade, jnp.float32))[..., None]  # [..., 1]
    return np.asarray(grid.center, np.float32) + np.asarray(grid.half_size, np.float32) * scale * u


# --------------------------------------------------------------------------------------------------
# Update


def occupancy_thresholds(grid: OccupancyGrid, config: OccupancyConfig) -> Array:
    """Per-cascade density thresholds [C]: min(mean density of cascade 0, tau) * 2**-c."""
    base = jnp.minimum(jnp.mean(grid.density[0]), config.density_threshold)  # []
    return base * jnp.exp2(-jnp.arange(grid.cascades, dtype=jnp.float32))  # [C]


def _evaluate_density(density_fn: DensityFn, params, points: Array, chunk: int) -> Array:
    """Densities [N] of points [N, 3], `chunk` at a time; non-finite values count as 0 / MAX_DENSITY."""
    if points.shape[0] <= chunk:
        sigma = jax.vmap(density_fn, in_axes=(None, 0))(params, points)  # [N]
    else:
        sigma = jax.lax.map(lambda x: density_fn(params, x), points, batch_size=chunk)  # [N]
    sigma = jnp.nan_to_num(sigma.astype(jnp.float32), nan=0.0, posinf=MAX_DENSITY, neginf=0.0)
    return jnp.clip(sigma, 0.0, MAX_DENSITY)


def _sample_occupied(key: PRNGKey, bitfield: Array, fallback: Array) -> Array:
    """Per cascade, cells [C, M] drawn uniformly (with replacement) among its occupied cells.

    Args:
      key: PRNG key. bitfield: bool [C, G**3]. fallback: int32 [C, M], returned for a cascade
        without any occupied cell.
    """
    num_cascades, num_cells = bitfield.shape
    # One running count over all cascades: cascade c's occupied cells have ranks [start_c, end_c).
    cdf = jnp.cumsum(bitfield.reshape(-1).astype(jnp.int32))  # [C * G**3]
    ends = cdf[num_cells - 1 :: num_cells]  # [C]
    starts = ends - jnp.sum(bitfield, axis=1, dtype=jnp.int32)  # [C]
    counts = ends - starts  # [C]
    rank = starts[:, None] + jax.random.randint(key, fallback.shape, 0, jnp.maximum(counts, 1)[:, None])  # [C, M]
    # The first index whose running count exceeds rank is the (rank + 1)-th occupied cell.
    flat = jnp.searchsorted(cdf, rank, side="right").astype(jnp.int32)  # [C, M]
    cells = flat - (jnp.arange(num_cascades, dtype=jnp.int32) * num_cells)[:, None]  # [C, M]
    return jnp.where((counts > 0)[:, None], cells, fallback)


def update_occupancy(
    key: PRNGKey, grid: OccupancyGrid, density_fn: DensityFn, params, step, config: OccupancyConfig
) -> OccupancyGrid:
    """One Instant-NGP occupancy update (decay, sample, max, threshold; see docs/design.md, "Rendering").

    Pure and jitted (`density_fn` is static: pass the same function object, e.g. `make_density(cfg)`,
    to reuse the compilation; `step` is cast to int32, so Python and JAX integers share it). Both the
    warm-up branch (all C * G**3 cells) and the later branch (2 * M cells per cascade) are compiled;
    `lax.cond` runs one of them. Training, which knows the phase of every step on the host, calls
    `update_occupancy_phase` instead (no `lax.cond`, whose predicate a GPU reads on the host).

    Args:
      key: PRNG key (consumed).
      grid: the current grid.
      density_fn: density of ONE point, `density_fn(params, x [3]) -> sigma []`, world units^-1.
      params: its parameters.
      step: the training step, int []: every cell is sampled while `step < config.warmup_steps`.
      config: `OccupancyConfig`.

    Returns:
      The updated `OccupancyGrid` (same static geometry).
    """
    return _update_occupancy(key, grid, density_fn, params, jnp.asarray(step, jnp.int32), config)


@functools.partial(jax.jit, static_argnames=("density_fn",))
def _update_occupancy(
    key: PRNGKey, grid: OccupancyGrid, density_fn: DensityFn, params, step: Array, config: OccupancyConfig
) -> OccupancyGrid:
    """`update_occupancy` with a traced int32 step."""
    return jax.lax.cond(
        step < config.warmup_steps,
        lambda g: update_occupancy_phase(key, g, density_fn, params, config, warmup=True),
        lambda g: update_occupancy_phase(key, g, density_fn, params, config, warmup=False),
        grid,
    )


def update_occupancy_phase(
    key: PRNGKey, grid: OccupancyGrid, density_fn: DensityFn, params, config: OccupancyConfig, warmup: bool
) -> OccupancyGrid:
    """`update_occupancy` for a phase known on the host: `warmup` (static) samples every cell,
    otherwise 2 * M cells per cascade. Not jitted (call it inside a traced function).

    The same key gives the same grid as `update_occupancy` at a step of that phase.
    """
    num_cascades, num_cells = grid.density.shape
    key_warmup, key_partial = jax.random.split(key)
    cascade_ids = jnp.arange(num_cascades, dtype=jnp.int32)  # [C]
    if warmup:
        cells = jnp.arange(num_cells, dtype=jnp.int32)  # [G**3]
        jitter = jax.random.uniform(key_warmup, (num_cascades, num_cells, 3))  # [C, G**3, 3]
        points = cell_points(grid, cascade_ids[:, None], cells[None, :], jitter)  # [C, G**3, 3]
        sigma = _evaluate_density(density_fn, params, points.reshape(-1, 3), config.eval_chunk)
        new = sigma.reshape(num_cascades, num_cells)  # [C, G**3]
    else:
        num_draws = config.samples_per_cascade(grid)
        key_uniform, key_occupied, key_jitter = jax.random.split(key_partial, 3)
        uniform_cells = jax.random.randint(key_uniform, (num_cascades, num_draws), 0, num_cells)  # [C, M]
        occupied_cells = _sample_occupied(key_occupied, grid.bitfield, uniform_cells)  # [C, M]
        cells = jnp.concatenate([uniform_cells, occupied_cells], axis=1)  # [C, 2M]
        jitter = jax.random.uniform(key_jitter, cells.shape + (3,))  # [C, 2M, 3]
        points = cell_points(grid, cascade_ids[:, None], cells, jitter)  # [C, 2M, 3]
        sigma = _evaluate_density(density_fn, params, points.reshape(-1, 3), config.eval_chunk)
        sigma = sigma.reshape(cells.shape)  # [C, 2M]
        # Cells not drawn stay 0 here, so max(decayed, new) keeps their decayed value. A scatter-max
        # gives the same result in any order (deterministic on every backend).
        new = jnp.zeros((num_cascades, num_cells), jnp.float32).at[cascade_ids[:, None], cells].max(sigma)
    density = jnp.maximum(grid.density * config.decay, new)  # [C, G**3]
    grid = grid.replace(density=density)
    bitfield = density > occupancy_thresholds(grid, config)[:, None]  # [C, G**3]
    return grid.replace(bitfield=bitfield)
