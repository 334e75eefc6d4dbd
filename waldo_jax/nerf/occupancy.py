"""Instant-NGP's multi-scale occupancy grid and fixed-shape ray marching (Müller et al., SIGGRAPH 2022,
Sec. 5.4 and Appendix E.2 "Accelerated ray marching").

Geometry. The *base box* (cascade 0) has centre `center` and half-size `half_size` (world units, per
axis). Cascade c covers the base box scaled by 2**c about the same centre, c = 0 .. C-1, with
C = 1 + ceil(log2(aabb_scale)) capped at `MAX_CASCADES` (fox, aabb_scale 4: C = 3). Each cascade is a
G x G x G grid of cells (G = `resolution`, 128 in Instant-NGP). With the box coordinates
u = (x - center) / half_size (cascade 0 is u in [-1, 1]^3), a point belongs to the finest cascade that
contains it, c = clip(ceil(log2(max_i |u_i|)), 0, C - 1) (NGP's `mip_from_pos`); its cell is
(i, j, k) = floor((u / 2**c + 1) / 2 * G) and its flat index `cell = i + G * (j + G * k)` (x fastest,
as the dense hash-grid levels; NGP uses Morton order, which only changes memory locality). Points
with max |u_i| > 2**(C-1) lie outside the grid and are never occupied.

State (`OccupancyGrid`): `density` float32 [C, G**3], a decaying running maximum of the density sigma
(world units^-1) seen in each cell, and `bitfield` bool [C, G**3], the occupied cells.

Update (`update_occupancy`), as NGP's `update_density_grid`:
  * every old value decays: density <- decay * density (decay = 0.95);
  * new samples: the density at one uniformly jittered point inside each chosen cell; all cells of all
    cascades while `step < warmup_steps` (NGP: the first 256 training steps), afterwards, per cascade,
    M = `update_fraction` * G**3 uniformly drawn cells plus M cells drawn among the occupied ones
    (fixed shapes; cells may repeat). Cells not drawn keep their decayed value;
  * density <- max(decayed, new) (the maximum over repeated draws of a cell);
  * threshold: a cell of cascade c is occupied iff density > min(mean of cascade 0, tau) * 2**-c.
    tau = `density_threshold` is NGP's minimal optical thickness 0.01 per minimal step dt_min:
    tau = 0.01 / dt_min = 0.01 * 1024 / (base-box diagonal), i.e. 0.01 * 1024 / sqrt(3) for NGP's
    unit cube. NGP stores the optical thickness sigma * dt_min * 2**c of cascade c, so in density units
    the threshold halves with every coarser cascade, where NGP's steps may be longer. The mean is taken
    over cascade 0, as NGP reduces only the first cascade (its normaliser may differ; we use the plain
    mean of cascade 0). A cell whose density stays below the threshold is skipped even where long
    grazing paths through it would add up to visible opacity; that is NGP's trade-off too.

Marching (`march_ray`), for ONE ray: candidate bins [e_k, e_{k+1}], k < K = `max_steps`, from t_start,
of length dt(e_k) = clip(e_k * cone_angle, dt_min, dt_max) (NGP's `calc_dt`), with
dt_min = base-box diagonal / `steps_per_diagonal` (NGP: sqrt(3) / 1024 for the unit cube) and
dt_max = the cell diagonal of the coarsest cascade, base diagonal * 2**(C-1) / G (NGP's
MAX_CONE_STEPSIZE for its fixed 8 cascades). cone_angle = 0 (synthetic scenes) gives constant
steps; NGP uses 1/256 for real scenes, where steps grow with distance (constant, then geometric, then
constant: the bin edges have a closed form, so no sequential loop is needed). The sample of a bin is
t_k = e_k + u * delta_k with u = 0.5 (deterministic) or one uniform u per ray (training; NGP's random
offset of the first step); the last bin is cut at t_end. Candidates whose sample falls in an occupied
cell are compacted (cumsum + scatter) into the first S = `max_samples` slots, in order.

Names: `t` sample distances along unit directions, `delta` bin lengths (the quadrature step, 0 for
masked samples), `mask` valid samples, `sigma` densities, `w` weights, K candidates, S samples.

Transmittance early stop. NGP stops marching a ray once its transmittance falls below 1e-4
(`min_transmittance`). `render_samples_early_stop` (and `render_rays_early_stop` over a flat batch)
does this with fixed shapes: a `lax.while_loop` whose every pass evaluates the field at a static budget
B of slots, into which the next segment of samples of each live ray is packed (segments of
clip(B // live rays, 1, `max_segment`) samples: NGP's compaction rounds, which lengthen as rays
retire). Each ray carries its optical depth and its sums of w * rgb, w * t and w between passes, so
its weights are exactly those of the full composite; it retires when its transmittance is below
`min_transmittance` or its samples run out, and its later samples are never evaluated. The result
differs from the composite of all S samples only by the ignored tail: colour by at most the
transmittance left at retirement (< min_transmittance) times max |rgb - background|.
`render_ray_marched` instead evaluates all S samples and gives weight 0 to those behind which the
transmittance is below `min_transmittance`, counting as evaluations what an early-stopping marcher
would have evaluated (differentiable, for training-style use).

Cost. `render_rays_marched` (vmap of `render_ray_marched`) evaluates the field at all S slots of
every ray, so it saves time only through a smaller S than a dense renderer needs. `render_rays_packed`
does what NGP's compacted training batches do: the valid samples of a chunk of rays are packed into a
fixed budget of `packed_samples_per_ray` slots per ray, so the field cost follows the occupied space.
`render_rays_early_stop` packs only the samples up to each ray's termination, pass after pass, so the
cost follows the visible occupied space. Marching itself costs K grid lookups per ray (no field
evaluations).
"""

from __future__ import annotations

import functools
import math
from typing import Callable, NamedTuple, Optional, Tuple

import flax.struct
import jax
import jax.numpy as jnp
import numpy as np

from waldo_jax.render import MAX_DENSITY, RenderConfig, composite, ray_aabb_interval, volume_weights
from waldo_jax.types import Array, Field, PRNGKey, RenderOutput

__all__ = [
    "MAX_CASCADES",
    "MarchConfig",
    "OccupancyConfig",
    "OccupancyGrid",
    "grid_cell",
    "init_occupancy",
    "init_occupancy_for_scene",
    "is_occupied",
    "march_ray",
    "mark_all_occupied",
    "occupancy_thresholds",
    "render_ray_marched",
    "ray_interval",
    "render_rays_early_stop",
    "render_rays_marched",
    "render_rays_packed",
    "render_samples_early_stop",
    "update_occupancy",
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
    """The multi-scale occupancy grid (see the module docstring for the geometry and indexing).

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
      max_steps: K, candidate bins per ray (static).
      max_samples: S, samples kept per ray, the first S candidates in occupied cells (static).
      packed_samples_per_ray: `render_rays_packed` evaluates the field at ray_chunk times this many
        packed samples per chunk of rays, whatever S is (static).
      steps_per_diagonal: dt_min = base-box diagonal / steps_per_diagonal (NGP: 1024).
      cone_angle: steps grow as dt = clip(t * cone_angle, dt_min, dt_max); 0 gives constant steps
        (NGP: 0 for synthetic scenes, 1/256 for real ones).
      max_segment: `render_rays_early_stop`: the most samples a live ray takes in one pass (static;
        None: no cap beyond S). Each pass gives every live ray min(budget // live rays, max_segment).
      min_transmittance: NGP's early ray termination (1e-4): `render_rays_early_stop` retires a ray
        once its transmittance falls below this; `render_ray_marched` gives weight 0 to the samples
        behind which it is below this and does not count them as evaluations. 0 never stops.
    """

    max_steps: int = flax.struct.field(pytree_node=False, default=1024)
    max_samples: int = flax.struct.field(pytree_node=False, default=256)
    packed_samples_per_ray: int = flax.struct.field(pytree_node=False, default=64)
    max_segment: Optional[int] = flax.struct.field(pytree_node=False, default=None)
    steps_per_diagonal: Array = float(NGP_STEPS_PER_DIAGONAL)
    cone_angle: Array = 0.0
    min_transmittance: Array = 1e-4

    @classmethod
    def create(cls, max_steps: int = 1024, max_samples: int = 256, packed_samples_per_ray: int = 64,
               steps_per_diagonal: float = NGP_STEPS_PER_DIAGONAL, cone_angle: float = 0.0,
               min_transmittance: float = 1e-4, max_segment: Optional[int] = None) -> "MarchConfig":
        """A validated config with float32 leaves."""
        if min(max_steps, max_samples, packed_samples_per_ray) < 1:
            raise ValueError(
                f"max_steps, max_samples and packed_samples_per_ray must be >= 1, got "
                f"{max_steps}, {max_samples}, {packed_samples_per_ray}"
            )
        if max_segment is not None and max_segment < 1:
            raise ValueError(f"max_segment must be None or >= 1, got {max_segment}")
        if steps_per_diagonal <= 0 or cone_angle < 0 or min_transmittance < 0:
            raise ValueError(
                f"need steps_per_diagonal > 0, cone_angle >= 0, min_transmittance >= 0; got "
                f"{steps_per_diagonal}, {cone_angle}, {min_transmittance}"
            )
        return cls(
            max_steps=int(max_steps),
            max_samples=int(max_samples),
            packed_samples_per_ray=int(packed_samples_per_ray),
            max_segment=None if max_segment is None else int(max_segment),
            steps_per_diagonal=jnp.float32(steps_per_diagonal),
            cone_angle=jnp.float32(cone_angle),
            min_transmittance=jnp.float32(min_transmittance),
        )


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


def _cell_points(grid: OccupancyGrid, cascade: Array, cell: Array, jitter: Array) -> Array:
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
    """One Instant-NGP occupancy update (decay, sample, max, threshold; see the module docstring).

    Pure and jitted (`density_fn` is static: pass the same function object, e.g. `make_density(cfg)`,
    to reuse the compilation; `step` is cast to int32, so Python and JAX integers share it). Both the
    warm-up branch (all C * G**3 cells) and the later branch (2 * M cells per cascade) are compiled;
    `lax.cond` runs one of them.

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
    num_cascades, num_cells = grid.density.shape
    key_warmup, key_partial = jax.random.split(key)
    cascade_ids = jnp.arange(num_cascades, dtype=jnp.int32)  # [C]

    def sample_all(_) -> Array:
        cells = jnp.arange(num_cells, dtype=jnp.int32)  # [G**3]
        jitter = jax.random.uniform(key_warmup, (num_cascades, num_cells, 3))  # [C, G**3, 3]
        points = _cell_points(grid, cascade_ids[:, None], cells[None, :], jitter)  # [C, G**3, 3]
        sigma = _evaluate_density(density_fn, params, points.reshape(-1, 3), config.eval_chunk)
        return sigma.reshape(num_cascades, num_cells)  # [C, G**3]

    def sample_some(_) -> Array:
        num_draws = config.samples_per_cascade(grid)
        key_uniform, key_occupied, key_jitter = jax.random.split(key_partial, 3)
        uniform_cells = jax.random.randint(key_uniform, (num_cascades, num_draws), 0, num_cells)  # [C, M]
        occupied_cells = _sample_occupied(key_occupied, grid.bitfield, uniform_cells)  # [C, M]
        cells = jnp.concatenate([uniform_cells, occupied_cells], axis=1)  # [C, 2M]
        jitter = jax.random.uniform(key_jitter, cells.shape + (3,))  # [C, 2M, 3]
        points = _cell_points(grid, cascade_ids[:, None], cells, jitter)  # [C, 2M, 3]
        sigma = _evaluate_density(density_fn, params, points.reshape(-1, 3), config.eval_chunk)
        sigma = sigma.reshape(cells.shape)  # [C, 2M]
        # Cells not drawn stay 0 here, so max(decayed, new) keeps their decayed value.
        return jnp.zeros((num_cascades, num_cells), jnp.float32).at[cascade_ids[:, None], cells].max(sigma)

    new = jax.lax.cond(step < config.warmup_steps, sample_all, sample_some, None)  # [C, G**3]
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
    """Samples of ONE ray in occupied cells, compacted to a fixed budget (see the module docstring).

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


def render_ray_marched(field: Field, params, grid: OccupancyGrid, origin: Array, direction: Array,
                       render_config: RenderConfig, march_config: MarchConfig,
                       key: Optional[PRNGKey] = None) -> Tuple[RenderOutput, Array]:
    """Renders ONE ray with samples only in occupied cells.

    `render_config` gives near/far, the box (when `use_aabb`) and the background; its `num_samples`
    is not used (`march_config.max_samples` is the budget).

    Args:
      field: radiance field for one point, `field(params, x [3], d [3]) -> (sigma [], rgb [3])`.
      params: its parameters.
      grid: occupancy grid.
      origin: [3]. direction: [3] unit direction.
      render_config: `waldo_jax.render.RenderConfig`.
      march_config: `MarchConfig`.
      key: None (deterministic) or a PRNG key (random offset of the samples).

    Returns:
      (`RenderOutput` with rgb [3], depth [], acc [], num_evaluations int32 []): the field evaluations
      an early-stopping marcher needs, valid samples whose transmittance is >= min_transmittance.
    """
    t_start, t_end = ray_interval(grid, origin, direction, render_config)
    t, delta, mask = march_ray(grid, origin, direction, t_start, t_end, march_config, key)  # [S] each
    points = origin + t[:, None] * direction  # [S, 3]
    sigma, rgb = jax.vmap(field, in_axes=(None, 0, None))(params, points, direction)  # [S], [S, 3]
    return _composite_samples(sigma, rgb, t, delta, mask, render_config.background, march_config.min_transmittance)


def _composite_samples(sigma: Array, rgb: Array, t: Array, delta: Array, mask: Array, background: Array,
                       min_transmittance: Array) -> Tuple[RenderOutput, Array]:
    """Volume rendering of ONE ray's marched samples [S]; returns the output and the evaluations it needed."""
    sigma = jnp.where(mask, sigma, 0.0)  # masked samples have delta 0 too: zero optical depth
    rgb = jnp.nan_to_num(rgb)  # [S, 3]
    w = volume_weights(sigma, delta)  # [S]
    transmittance = 1.0 - (jnp.cumsum(w) - w)  # [S], before each sample (1 - exclusive sum of w)
    alive = mask & (transmittance >= min_transmittance)  # [S]
    out = composite(jnp.where(alive, w, 0.0), rgb, t, background)
    return out, jnp.sum(alive.astype(jnp.int32))


def _map_ray_chunks(render_chunk, origins: Array, directions: Array, chunk: int, key: Optional[PRNGKey]):
    """Pads rays [R, 3] to whole chunks, applies `render_chunk(origins, directions, keys)` to each chunk
    under `lax.map` (keys: one per ray, or None) and crops the [R, ...] results.

    Per-ray results (leading axis the chunk's rays) come back as [R, ...]; per-chunk scalars as
    [num_chunks]."""
    num_rays = origins.shape[0]
    chunk = max(1, min(chunk, num_rays))
    num_chunks = -(-num_rays // chunk)
    pad = num_chunks * chunk - num_rays
    origins = jnp.pad(origins, ((0, pad), (0, 0))).reshape(num_chunks, chunk, 3)
    # Padded rays get a valid unit direction so that they render without NaN before being cropped.
    directions = jnp.pad(directions, ((0, pad), (0, 0)), constant_values=1.0 / math.sqrt(3.0))
    directions = directions.reshape(num_chunks, chunk, 3)
    keys = None if key is None else jax.random.split(key, num_chunks * chunk).reshape(num_chunks, chunk)
    out = jax.lax.map(lambda args: render_chunk(*args), (origins, directions, keys))
    return jax.tree.map(lambda a: a if a.ndim == 1 else a.reshape((num_chunks * chunk,) + a.shape[2:])[:num_rays],
                        out)


def render_rays_marched(field: Field, params, grid: OccupancyGrid, origins: Array, directions: Array,
                        render_config: RenderConfig, march_config: MarchConfig,
                        key: Optional[PRNGKey] = None) -> Tuple[RenderOutput, Array]:
    """Renders a flat batch of rays [R, 3] with `render_ray_marched`, `render_config.ray_chunk` at a time.

    Rays are padded to whole chunks, vmapped within a chunk and `lax.map`ped over chunks, then cropped.
    Not jitted: wrap it in `jax.jit` with `field` static (and the configs as ordinary arguments).

    Returns:
      (`RenderOutput` with rgb [R, 3], depth [R], acc [R], num_evaluations int32 [R]).
    """

    def render_chunk(chunk_origins, chunk_directions, chunk_keys):
        return jax.vmap(
            lambda o, d, k: render_ray_marched(field, params, grid, o, d, render_config, march_config, k),
            in_axes=(0, 0, None if chunk_keys is None else 0),
        )(chunk_origins, chunk_directions, chunk_keys)

    return _map_ray_chunks(render_chunk, origins, directions, render_config.ray_chunk, key)


def render_rays_packed(field: Field, params, grid: OccupancyGrid, origins: Array, directions: Array,
                       render_config: RenderConfig, march_config: MarchConfig,
                       key: Optional[PRNGKey] = None) -> Tuple[RenderOutput, Array, Array]:
    """Renders a flat batch of rays [R, 3] evaluating the field only at a packed budget of samples.

    `render_rays_marched` evaluates the field at all S slots of every ray, masked or not. Here, as in
    NGP's compacted batches, the valid samples of a chunk of N = `render_config.ray_chunk` rays are
    packed one after another (ray by ray, in order) into N * `march_config.packed_samples_per_ray`
    slots; the field runs on those slots only, and the results are scattered back to [N, S] for the
    per-ray compositing. When a chunk's valid samples exceed the budget, the last ones (the far end of
    the chunk's last rays) are dropped (treated as empty) and counted in `num_dropped`.

    Returns:
      (`RenderOutput` with rgb [R, 3], depth [R], acc [R], num_evaluations int32 [R] as in
      `render_ray_marched`, num_dropped int32 [R]: valid samples left out of the budget).
    """
    num_slots_per_ray = march_config.packed_samples_per_ray

    def render_chunk(chunk_origins, chunk_directions, chunk_keys):
        num_rays = chunk_origins.shape[0]
        budget = num_rays * num_slots_per_ray
        t_start, t_end = jax.vmap(lambda o, d: ray_interval(grid, o, d, render_config))(chunk_origins, chunk_directions)
        t, delta, mask = jax.vmap(
            lambda o, d, a, b, k: march_ray(grid, o, d, a, b, march_config, k),
            in_axes=(0, 0, 0, 0, None if chunk_keys is None else 0),
        )(chunk_origins, chunk_directions, t_start, t_end, chunk_keys)  # [N, S] each
        num_samples = t.shape[1]
        counts = jnp.sum(mask, axis=1, dtype=jnp.int32)  # [N]
        ends = jnp.cumsum(counts)  # [N], valid samples of rays 0..n
        starts = ends - counts  # [N]

        # Packed slot b holds sample b - starts[r] of the ray r whose range [starts, ends) contains b.
        slot = jnp.arange(budget, dtype=jnp.int32)  # [B]
        ray = jnp.minimum(jnp.searchsorted(ends, slot, side="right"), num_rays - 1).astype(jnp.int32)  # [B]
        used = slot < ends[-1]  # [B]
        index = jnp.clip(slot - starts[ray], 0, num_samples - 1)  # [B]
        t_packed = t[ray, index]  # [B]
        points = chunk_origins[ray] + t_packed[:, None] * chunk_directions[ray]  # [B, 3]
        sigma, rgb = jax.vmap(field, in_axes=(None, 0, 0))(params, points, chunk_directions[ray])  # [B], [B, 3]

        # Back to [N, S]; unused slots are dropped by the scatter.
        target_ray = jnp.where(used, ray, num_rays)  # [B]
        sigma_rays = jnp.zeros((num_rays, num_samples), jnp.float32).at[target_ray, index].set(sigma, mode="drop")
        rgb_rays = jnp.zeros((num_rays, num_samples, 3), jnp.float32).at[target_ray, index].set(rgb, mode="drop")
        evaluated = mask & (starts[:, None] + jnp.arange(num_samples) < budget)  # [N, S]
        out, evaluations = jax.vmap(
            lambda *args: _composite_samples(*args, render_config.background, march_config.min_transmittance)
        )(sigma_rays, rgb_rays, t, jnp.where(evaluated, delta, 0.0), evaluated)
        dropped = counts - jnp.sum(evaluated, axis=1, dtype=jnp.int32)  # [N]
        return out, evaluations, dropped

    return _map_ray_chunks(render_chunk, origins, directions, render_config.ray_chunk, key)



# --------------------------------------------------------------------------------------------------
# Early ray termination


class _MarchState(NamedTuple):
    """What `render_samples_early_stop` carries from pass to pass (N rays)."""

    next_sample: Array  # int32 [N], samples [0, next_sample) of each ray are composited
    alive: Array  # bool [N], rays with samples left and transmittance >= min_transmittance
    optical_depth: Array  # float32 [N], sum of sigma * delta over the composited samples
    rgb: Array  # float32 [N, 3], sum of w * rgb
    depth: Array  # float32 [N], sum of w * t
    acc: Array  # float32 [N], sum of w
    evaluations: Array  # int32 [N], field evaluations spent on each ray
    passes: Array  # int32 [], passes run


def _segmented_cumsum(values: Array, head: Array) -> Array:
    """Inclusive sums of values [B, C] along B, restarting at every slot where head [B] is True."""

    def combine(a, b):
        (sum_a, head_a), (sum_b, head_b) = a, b
        return jnp.where(head_b[:, None], sum_b, sum_a + sum_b), head_a | head_b

    return jax.lax.associative_scan(combine, (values, head))[0]


def render_samples_early_stop(field: Field, params, origins: Array, directions: Array, t: Array, delta: Array,
                              mask: Array, background: Array, min_transmittance: Array, budget: int,
                              max_segment: Optional[int] = None) -> Tuple[RenderOutput, Array, Array]:
    """Composites N rays' marched samples front to back in passes of `budget` field evaluations, retiring
    each ray once its transmittance falls below `min_transmittance` (NGP's early ray termination).

    Pass after pass (a `lax.while_loop`; every shape fixed), each live ray asks for its next
    min(segment, samples left) samples, segment = clip(budget // live rays, 1, max_segment) (NGP's
    compaction rounds: few live rays take long segments, so a pass stays full); the requests are
    packed ray after ray into the `budget` slots (the ray at the end of the budget gets part of its
    request, later rays wait for the next pass) and the field runs on the slots only. Each ray carries
    its optical depth and its sums of w * rgb, w * t and w from pass to pass, so its weights are those
    of `render.volume_weights` over all its samples: w_j = exp(-sum_{k<j} sigma_k delta_k) *
    (1 - exp(-sigma_j delta_j)). A ray retires when it has no samples left or when exp(-optical depth)
    < min_transmittance; its remaining samples are never evaluated. Against the full composite of
    every sample, the colour then differs by sum_tail w (rgb - background), at most the transmittance
    left at retirement (< min_transmittance) times max |rgb - background|; acc by at most that
    transmittance, depth by at most it times the largest t. min_transmittance = 0 composites every
    sample.

    For evaluation and rendering (`lax.while_loop` has no reverse-mode derivative).

    Args:
      field: radiance field for one point, `field(params, x [3], d [3]) -> (sigma [], rgb [3])`.
      params: its parameters.
      origins, directions: [N, 3] (unit directions).
      t, delta: [N, S] sample distances and bin lengths (`march_ray`). mask: bool [N, S], a prefix per ray.
      background: colour [3] or [N, 3].
      min_transmittance: float [], the retirement threshold.
      budget: B, field evaluations per pass (static, >= 1).
      max_segment: most samples a ray takes per pass (static; None: S).

    Returns:
      (`RenderOutput` with rgb [N, 3], depth [N], acc [N]; evaluations int32 [N], the samples evaluated
      for each ray; passes int32 [], each of which evaluated the field at B slots).
    """
    num_rays, num_samples = t.shape
    if budget < 1:
        raise ValueError(f"budget must be >= 1, got {budget}")
    if max_segment is not None and max_segment < 1:
        raise ValueError(f"max_segment must be None or >= 1, got {max_segment}")
    max_segment = num_samples if max_segment is None else min(max_segment, num_samples)
    counts = jnp.sum(mask, axis=1, dtype=jnp.int32)  # [N], mask is a prefix
    background = jnp.broadcast_to(jnp.asarray(background, jnp.float32), (num_rays, 3))  # [N, 3]
    min_transmittance = jnp.asarray(min_transmittance, jnp.float32)
    slot = jnp.arange(budget, dtype=jnp.int32)  # [B]
    field_batch = jax.vmap(field, in_axes=(None, 0, 0))

    def one_pass(state: _MarchState) -> _MarchState:
        live = jnp.sum(state.alive, dtype=jnp.int32)  # []
        segment = jnp.clip(budget // jnp.maximum(live, 1), 1, max_segment)  # []
        request = jnp.where(state.alive, jnp.minimum(segment, counts - state.next_sample), 0)  # [N]
        starts = jnp.cumsum(request) - request  # [N]
        granted = jnp.clip(budget - starts, 0, request)  # [N], the ray at the end of the budget is cut
        ends = starts + granted  # [N], non-decreasing

        # Slot b holds sample next_sample[r] + b - starts[r] of the ray r with starts[r] <= b < ends[r].
        ray = jnp.searchsorted(ends, slot, side="right").astype(jnp.int32)  # [B], N past the last
        used = ray < num_rays  # [B]
        ray = jnp.minimum(ray, num_rays - 1)  # [B]
        index = jnp.clip(state.next_sample[ray] + slot - starts[ray], 0, num_samples - 1)  # [B]
        t_slot = t[ray, index]  # [B]
        delta_slot = jnp.where(used, delta[ray, index], 0.0)  # [B]
        points = origins[ray] + t_slot[:, None] * directions[ray]  # [B, 3]
        sigma, rgb = field_batch(params, points, directions[ray])  # [B], [B, 3]
        sigma = jnp.clip(jnp.nan_to_num(sigma, nan=0.0, posinf=MAX_DENSITY, neginf=0.0), 0.0, MAX_DENSITY)
        optical = jnp.where(used, sigma, 0.0) * delta_slot  # [B]
        rgb = jnp.where(used[:, None], jnp.nan_to_num(rgb), 0.0)  # [B, 3]

        # Optical depth before each slot: the ray's carried depth plus the exclusive sum in its segment.
        head = slot == starts[ray]  # [B], the first slot of each ray's segment
        inclusive = _segmented_cumsum(optical[:, None], head)[:, 0]  # [B]
        exclusive = jnp.where(head, 0.0, jnp.concatenate([jnp.zeros((1,), jnp.float32), inclusive[:-1]]))  # [B]
        w = jnp.exp(-(state.optical_depth[ray] + exclusive)) * -jnp.expm1(-optical)  # [B]
        sums = _segmented_cumsum(jnp.concatenate([w[:, None] * rgb, (w * t_slot)[:, None], w[:, None]], axis=1),
                                 head)  # [B, 5]

        # A ray's segment sums sit at its last slot.
        got = granted > 0  # [N]
        last = jnp.clip(ends - 1, 0, budget - 1)  # [N]
        segment_sums = jnp.where(got[:, None], sums[last], 0.0)  # [N, 5]
        optical_depth = state.optical_depth + jnp.where(got, inclusive[last], 0.0)  # [N]
        next_sample = state.next_sample + granted  # [N]
        alive = state.alive & (next_sample < counts) & (jnp.exp(-optical_depth) >= min_transmittance)  # [N]
        return _MarchState(
            next_sample=next_sample,
            alive=alive,
            optical_depth=optical_depth,
            rgb=state.rgb + segment_sums[:, :3],
            depth=state.depth + segment_sums[:, 3],
            acc=state.acc + segment_sums[:, 4],
            evaluations=state.evaluations + granted,
            passes=state.passes + 1,
        )

    zeros = jnp.zeros((num_rays,), jnp.float32)
    start = _MarchState(next_sample=jnp.zeros((num_rays,), jnp.int32), alive=counts > 0, optical_depth=zeros,
                        rgb=jnp.zeros((num_rays, 3), jnp.float32), depth=zeros, acc=zeros,
                        evaluations=jnp.zeros((num_rays,), jnp.int32), passes=jnp.int32(0))
    final = jax.lax.while_loop(lambda state: jnp.any(state.alive), one_pass, start)
    rgb = final.rgb + (1.0 - final.acc)[:, None] * background  # [N, 3]
    return RenderOutput(rgb=rgb, depth=final.depth, acc=final.acc), final.evaluations, final.passes


def render_rays_early_stop(field: Field, params, grid: OccupancyGrid, origins: Array, directions: Array,
                           render_config: RenderConfig, march_config: MarchConfig,
                           key: Optional[PRNGKey] = None) -> Tuple[RenderOutput, Array, Array]:
    """Renders a flat batch of rays [R, 3] with early ray termination (`render_samples_early_stop`).

    Chunks of N = `render_config.ray_chunk` rays are marched (`march_ray`) and composited in passes of
    B = N * `march_config.packed_samples_per_ray` field evaluations, with segments of at most
    `march_config.max_segment` samples, until every ray of the chunk has no samples left or its
    transmittance is below `march_config.min_transmittance`. Unlike `render_rays_packed` no sample
    is dropped: a chunk takes as many passes as it needs. Not differentiable (`lax.while_loop`); not
    jitted (wrap it in `jax.jit` with `field` static).

    Returns:
      (`RenderOutput` with rgb [R, 3], depth [R], acc [R]; evaluations int32 [R], the field evaluations
      spent on each ray; passes int32 [num_chunks], the passes of each chunk, each costing B slots).
    """

    def render_chunk(chunk_origins, chunk_directions, chunk_keys):
        budget = chunk_origins.shape[0] * march_config.packed_samples_per_ray
        t_start, t_end = jax.vmap(lambda o, d: ray_interval(grid, o, d, render_config))(chunk_origins, chunk_directions)
        t, delta, mask = jax.vmap(
            lambda o, d, a, b, k: march_ray(grid, o, d, a, b, march_config, k),
            in_axes=(0, 0, 0, 0, None if chunk_keys is None else 0),
        )(chunk_origins, chunk_directions, t_start, t_end, chunk_keys)  # [N, S] each
        return render_samples_early_stop(field, params, chunk_origins, chunk_directions, t, delta, mask,
                                         render_config.background, march_config.min_transmittance, budget,
                                         march_config.max_segment)

    return _map_ray_chunks(render_chunk, origins, directions, render_config.ray_chunk, key)
