"""Fixed-shape ray marching through an occupancy grid (Instant-NGP's `calc_dt` stepping): `MarchConfig`,
`march_ray` for ONE ray (candidate bins in closed form, samples in occupied cells compacted to a fixed
budget) and `ray_interval`. The stepping and the sampling: docs/design.md, "The occupancy grid".
"""

from __future__ import annotations

from typing import Optional, Tuple

import flax.struct
import jax
import jax.numpy as jnp

from waldo_jax.render.occupancy import NGP_STEPS_PER_DIAGONAL, OccupancyGrid, is_occupied
from waldo_jax.render.volume import RenderConfig, ray_aabb_interval
from waldo_jax.types import Array, PRNGKey

__all__ = ["MarchConfig", "march_steps", "march_ray", "ray_interval"]


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
    def create(
        cls,
        max_steps: int = 1024,
        max_samples: int = 256,
        steps_per_diagonal: float = NGP_STEPS_PER_DIAGONAL,
        cone_angle: float = 0.0,
        min_transmittance: float = 1e-4,
    ) -> "MarchConfig":
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
    def for_grid(
        cls,
        grid: "OccupancyGrid",
        steps_per_diagonal: float,
        cone_angle: float = 0.0,
        max_samples: Optional[int] = None,
        min_transmittance: float = 1e-4,
    ) -> "MarchConfig":
        """The march that crosses all of `grid` (K = `march_steps`), keeping at most min(max_samples, K)."""
        steps = march_steps(grid, steps_per_diagonal, cone_angle)
        samples = steps if max_samples is None else max(1, min(int(max_samples), steps))
        return cls.create(
            max_steps=steps,
            max_samples=samples,
            steps_per_diagonal=steps_per_diagonal,
            cone_angle=cone_angle,
            min_transmittance=min_transmittance,
        )


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


def march_ray(
    grid: OccupancyGrid,
    origin: Array,
    direction: Array,
    t_start: Array,
    t_end: Array,
    config: MarchConfig,
    key: Optional[PRNGKey] = None,
) -> Tuple[Array, Array, Array]:
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
