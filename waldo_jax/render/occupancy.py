"""Instant-NGP's multi-scale occupancy grid and fixed-shape ray marching (Müller et al., SIGGRAPH 2022,
Sec. 5.4 and Appendix E.2 "Accelerated ray marching").

`OccupancyGrid` holds, per cascade c < C (cascade c covers the base box scaled by 2**c) and cell of
its G x G x G grid, a decaying running maximum of the density (`density` float32 [C, G**3]) and the
occupied cells (`bitfield` bool [C, G**3]). `update_occupancy` is NGP's density-grid update (decay,
sample, max, threshold); `march_ray` marches ONE ray with NGP's step sizes (closed-form bin edges, no
sequential loop) and compacts the samples in occupied cells into its first S slots. The marched
renderer (`waldo_jax.render.marched`) and training build on it.

The grid's geometry and indexing, the update's schedule and threshold, the step sizes and the names:
see docs/design.md, section "Rendering > The occupancy grid".
"""

from __future__ import annotations

import functools
import math
from typing import Callable, Optional, Tuple

import flax.struct
import jax
import jax.numpy as jnp
import numpy as np

from waldo_jax.render.volume import MAX_DENSITY, RenderConfig, ray_aabb_interval
from waldo_jax.types import Array, PRNGKey

__all__ = [
    "MAX_CASCADES",
    "MarchConfig",
    "OccupancyConfig",
    "OccupancyGrid",
    "cell_points",
    "grid_cell",
    "init_occupancy",
    "init_occupancy_for_scene",
    "is_occupied",
    "march_ray",
    "march_steps",
    "mark_all_occupied",
    "occupancy_thresholds",
    "ray_interval",
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
    def create(cls, grid: OccupancyGrid, min_optical_thickness: float = NGP_MIN_OPTICAL_THICKNESS,
               steps_per_diagonal: float = NGP_STEPS_PER_DIAGONAL, warmup_steps: int = 256,
               decay: float = 0.95, update_fraction: float = 0.25, eval_chunk: int = 2**18) -> "OccupancyConfig":
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


@flax.struct.dataclass
class MarchConfig:
    """How `march_ray` places samples.

    Defaults suit a 128**3 grid: 1024 candidates cross the base box's diagonal at the minimal step.
    For fox (aabb_scale 4, 3 cascades, cone_angle 1/256) about 790 candidates reach a corner of the
    whole box from its centre and about 970 cross its whole diagonal, so 1024 also suffices there.
    S = 256 samples in occupied space is far more than an opaque surface needs (NGP's early stop
    usually ends a ray after a few dozen); rays through much semi-transparent occupied space (early
    in training) are cut after S samples, as NGP cuts them after its step budget.

    Attributes:
      max_steps: K, candidate bins per ray (static); `march_steps` gives the K that crosses a grid.
      max_samples: S, samples kept per ray, the first S candidates in occupied cells (static).
      steps_per_diagonal: dt_min = base-box diagonal / steps_per_diagonal (NGP: 1024).
      cone_angle: steps grow as dt = clip(t * cone_angle, dt_min, dt_max); 0 gives constant steps
        (NGP: 0 for synthetic scenes, 1/256 for real ones).
      min_transmittance: NGP's early ray termination (1e-4): a renderer stops evaluating a ray once
        its transmittance falls below this (`waldo_jax.render.marched`). 0 never stops.
    """

    max_steps: int = flax.struct.field(pytree_node=False, default=1024)
    max_samples: int = flax.struct.field(pytree_node=False, default=256)
    steps_per_diagonal: Array = float(NGP_STEPS_PER_DIAGONAL)
    cone_angle: Array = 0.0
    min_transmittance: Array = 1e-4

    @classmethod
    def create(cls, max_steps: int = 1024, max_samples: int = 256,
               steps_per_diagonal: float = NGP_STEPS_PER_DIAGONAL, cone_angle: float = 0.0,
               min_transmittance: float = 1e-4) -> "MarchConfig":
        """A validated config with float32 leaves."""
        if min(max_steps, max_samples) < 1:
            raise ValueError(f"max_steps and max_samples must be >= 1, got {max_steps}, {max_samples}")
        if not (steps_per_diagonal > 0 and cone_angle >= 0 and min_transmittance >= 0):
            raise ValueError(
                f"need steps_per_diagonal > 0, cone_angle >= 0, min_transmittance >= 0; got "
                f"{steps_per_diagonal}, {cone_angle}, {min_transmittance}"
            )
        return cls(
            max_steps=int(max_steps),
            max_samples=int(max_samples),
            steps_per_diagonal=jnp.float32(steps_per_diagonal),
            cone_angle=jnp.float32(cone_angle),
            min_transmittance=jnp.float32(min_transmittance),
        )

    @classmethod
    def for_grid(cls, grid: "OccupancyGrid", steps_per_diagonal: float, cone_angle: float = 0.0,
                 max_samples: Optional[int] = None, min_transmittance: float = 1e-4) -> "MarchConfig":
        """The march that crosses all of `grid` (K = `march_steps`), keeping at most min(max_samples, K)."""
        steps = march_steps(grid, steps_per_diagonal, cone_angle)
        samples = steps if max_samples is None else max(1, min(int(max_samples), steps))
        return cls.create(max_steps=steps, max_samples=samples, steps_per_diagonal=steps_per_diagonal,
                          cone_angle=cone_angle, min_transmittance=min_transmittance)


def march_steps(grid: "OccupancyGrid", steps_per_diagonal: float, cone_angle: float, cap: int = 8192) -> int:
    """K, the candidates a ray needs to cross the grid's whole outer box from t = 0 (host-side).

    Follows NGP's stepping dt = clip(t * cone_angle, dt_min, dt_max) over the outer box's diagonal.
    """
    dt_min = grid.base_diagonal / float(steps_per_diagonal)
    dt_max = max(dt_min, grid.base_diagonal * 2.0 ** (grid.cascades - 1) / grid.resolution)
    length = grid.base_diagonal * 2.0 ** (grid.cascades - 1)
    t, steps = 0.0, 0
    while t < length and steps < cap:
        t += min(max(t * float(cone_angle), dt_min), dt_max)
        steps += 1
    return steps


def _as_box(aabb) -> Tuple[np.ndarray, np.ndarray]:
    """(min corner [3], max corner [3]) from a [2, 3] or [6] array-like, validated."""
    values = np.asarray(aabb, np.float64)
    if values.size != 6 or values.shape not in ((6,), (2, 3)):
        raise ValueError(f"aabb must have shape [2, 3] or [6], got {values.shape}: {aabb!r}")
    lo, hi = values.reshape(2, 3)
    if not np.all(np.isfinite(values)) or np.any(hi <= lo):
        raise ValueError(f"aabb needs finite bounds with max > min on every axis, got {values.tolist()}")
    return lo, hi


def init_occupancy(aabb, aabb_scale: float = 1.0, resolution: int = 128,
                   max_cascades: int = MAX_CASCADES) -> OccupancyGrid:
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


def update_occupancy(key: PRNGKey, grid: OccupancyGrid, density_fn: DensityFn, params, step,
                     config: OccupancyConfig) -> OccupancyGrid:
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
def _update_occupancy(key: PRNGKey, grid: OccupancyGrid, density_fn: DensityFn, params, step: Array,
                      config: OccupancyConfig) -> OccupancyGrid:
    """`update_occupancy` with a traced int32 step."""
    return jax.lax.cond(step < config.warmup_steps,
                        lambda g: update_occupancy_phase(key, g, density_fn, params, config, warmup=True),
                        lambda g: update_occupancy_phase(key, g, density_fn, params, config, warmup=False),
                        grid)


def update_occupancy_phase(key: PRNGKey, grid: OccupancyGrid, density_fn: DensityFn, params,
                           config: OccupancyConfig, warmup: bool) -> OccupancyGrid:
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


# --------------------------------------------------------------------------------------------------
# Marching


def _step_limits(grid: OccupancyGrid, config: MarchConfig) -> Tuple[Array, Array]:
    """(dt_min, dt_max) in world units for this grid."""
    dt_min = grid.base_diagonal / jnp.asarray(config.steps_per_diagonal, jnp.float32)
    dt_max = grid.base_diagonal * 2.0 ** (grid.cascades - 1) / grid.resolution
    return dt_min, jnp.maximum(dt_min, dt_max)


def _step_edges(t_start: Array, num_steps: int, dt_min: Array, dt_max: Array, cone_angle: Array) -> Array:
    """Bin edges e [num_steps + 1] of NGP's stepping e_{k+1} = e_k + clip(e_k * cone_angle, dt_min, dt_max).

    Closed form of the three phases: constant dt_min until e * cone_angle reaches dt_min (at
    t1 = dt_min / cone_angle), geometric with ratio 1 + cone_angle until it reaches dt_max (t2), then
    constant dt_max. cone_angle = 0 stays in the first phase.
    """
    k = jnp.arange(num_steps + 1, dtype=jnp.float32)  # [K + 1]
    cone = jnp.asarray(cone_angle, jnp.float32)
    has_cone = cone > 0.0
    safe_cone = jnp.where(has_cone, cone, 1.0)
    big = jnp.float32(num_steps + 1)
    t1 = dt_min / safe_cone
    t2 = dt_max / safe_cone
    steps_a = jnp.where(has_cone, jnp.clip(jnp.ceil((t1 - t_start) / dt_min), 0.0, big), big)  # []
    t_b = t_start + steps_a * dt_min  # [] start of the geometric phase, > 0 when it is reached
    log_ratio = jnp.log1p(safe_cone)
    safe_t_b = jnp.maximum(t_b, jnp.finfo(jnp.float32).tiny)
    steps_b = jnp.clip(jnp.ceil(jnp.log(jnp.maximum(t2 / safe_t_b, 1.0)) / log_ratio), 0.0, big)  # []
    t_c = safe_t_b * jnp.exp(steps_b * log_ratio)  # [] start of the last phase
    phase_a = t_start + k * dt_min
    phase_b = safe_t_b * jnp.exp(jnp.minimum(k - steps_a, steps_b) * log_ratio)
    phase_c = t_c + (k - steps_a - steps_b) * dt_max
    return jnp.where(k <= steps_a, phase_a, jnp.where(k <= steps_a + steps_b, phase_b, phase_c))  # [K + 1]


def march_ray(grid: OccupancyGrid, origin: Array, direction: Array, t_start: Array, t_end: Array,
              config: MarchConfig, key: Optional[PRNGKey] = None) -> Tuple[Array, Array, Array]:
    """Samples of ONE ray in occupied cells, compacted to a fixed budget (see docs/design.md, "Rendering").

    Args:
      grid: occupancy grid.
      origin: [3]. direction: [3] unit direction.
      t_start, t_end: the interval to march; t_end <= t_start gives no samples.
      config: `MarchConfig` (K = max_steps candidates, S = max_samples kept).
      key: None for bin midpoints, else a PRNG key for one random offset u in [0, 1) of the ray.

    Returns:
      t: [S] sample distances, strictly increasing over the valid prefix, 0 where masked.
      delta: [S] bin lengths (the quadrature steps), 0 where masked.
      mask: bool [S], valid samples; always a prefix (the first n slots).
    """
    num_samples = config.max_samples
    dt_min, dt_max = _step_limits(grid, config)
    edges = _step_edges(t_start, config.max_steps, dt_min, dt_max, config.cone_angle)  # [K + 1]
    lo, hi = edges[:-1], edges[1:]  # [K]
    in_range = lo < t_end  # [K]
    delta_all = jnp.maximum(jnp.minimum(hi, t_end) - lo, 0.0)  # [K], the last bin cut at t_end
    u = 0.5 if key is None else jax.random.uniform(key, ())
    t_all = lo + u * delta_all  # [K]
    points = origin + t_all[:, None] * direction  # [K, 3]
    keep = in_range & jax.vmap(lambda x: is_occupied(grid, x))(points)  # [K]

    # Compaction: the n-th kept candidate goes to slot n; slots >= S (and dropped candidates) fall off.
    rank = jnp.cumsum(keep.astype(jnp.int32)) - 1  # [K]
    slot = jnp.where(keep, rank, num_samples)  # [K]
    t = jnp.zeros((num_samples,), jnp.float32).at[slot].set(t_all, mode="drop")  # [S]
    delta = jnp.zeros((num_samples,), jnp.float32).at[slot].set(delta_all, mode="drop")  # [S]
    mask = jnp.arange(num_samples) < rank[-1] + 1  # [S]
    return t, delta, mask


def ray_interval(grid: OccupancyGrid, origin: Array, direction: Array, config: RenderConfig) -> Tuple[Array, Array]:
    """[near, far] clipped to the render box (when used) and to the grid's outer box."""
    t_start, t_end = config.near, config.far
    if config.use_aabb:
        t_enter, t_exit = ray_aabb_interval(origin, direction, config.aabb)
        t_start, t_end = jnp.maximum(t_start, t_enter), jnp.minimum(t_end, t_exit)
    t_enter, t_exit = ray_aabb_interval(origin, direction, jnp.asarray(grid.outer_aabb))
    return jnp.maximum(t_start, t_enter), jnp.minimum(t_end, t_exit)
