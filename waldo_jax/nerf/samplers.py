"""Samplers of training rays: "dense" (stratified samples) and "occupancy" (Instant-NGP's grid and marching).

A sampler is static code, one object per `TrainConfig` (`make_sampler`), with a pytree state carried in
the `TrainState` (the occupancy grid, or None). It renders a training batch and says how views of the
trained field are marched (`view_grid`, `view_march`). The occupancy sampler packs the batch's marched
samples into a fixed budget of field evaluations (`waldo_jax.render.packed`), so a step costs the same
whatever the grid. Names: `R` rays, `S` samples per ray, `M` packed rows. See docs/design.md, "Training".
"""

from __future__ import annotations

import functools
from typing import Dict, Optional, Tuple

import jax
import jax.numpy as jnp
import numpy as np

from waldo_jax.nerf.config import TrainConfig, TrainConfigError
from waldo_jax.nerf.field import make_density, make_field
from waldo_jax.render import marching, occupancy, packed
from waldo_jax.render.volume import RenderConfig, render_ray
from waldo_jax.types import Array, PRNGKey, RenderOutput

__all__ = ["TRAIN_ROW_LENGTH", "make_sampler"]

# Samples per packed row in training (`render.packed`). A ray's last row wastes under this many slots,
# and the rays of a step are those whose rows fit the budget: rows of 4 trained 7 % fewer rays a step
# on lego_tiny (about 10 samples a ray) and lost ~0.1 dB at 1000 steps; single-sample rows waste
# nothing, and their segmented sums (log2 S shifted adds over the slots) cost little next to the field.
TRAIN_ROW_LENGTH = 1

# A sampler is static code (one object per TrainConfig) with a pytree state carried in TrainState:
#   init(key, params) -> state
#   update(key, state, params, warmup) -> state                    (every occupancy_update_every steps;
#                                                                   warmup: static, every cell)
#   render_rays(key, params, state, origins [R, 3], directions [R, 3], background [R, 3], render_config)
#       -> (RenderOutput [R], included bool [R], stats)            (rays that count in the loss; stats:
#                                                                   int32 [] "samples" and "rows")
#   view_grid(state) -> the occupancy grid views are rendered through (`render.marched`)
#   view_march(scale) -> the MarchConfig of views, `scale` times the training step


class _DenseSampler:
    """Stratified samples in [near, far] ∩ aabb (`render.render_ray` with a key); no state.

    Views are rendered by the marched renderer through a one-cell grid that is always occupied, with
    `eval_samples` steps across the field's box.
    """

    def __init__(self, config: TrainConfig):
        self.config = config
        self.field = make_field(config.field)
        self.box = np.asarray(config.field.aabb, np.float64).reshape(2, 3)

    def init(self, key: PRNGKey, params) -> None:
        """No state."""
        return None

    def update(self, key: PRNGKey, state, params, warmup: bool):
        """No state to update."""
        return state

    def render_rays(
        self,
        key: PRNGKey,
        params,
        state,
        origins: Array,
        directions: Array,
        background: Array,
        render_config: RenderConfig,
    ) -> Tuple[RenderOutput, Array, Dict[str, Array]]:
        """Renders R training rays [R, 3] on per-ray backgrounds [R, 3]; every ray is included."""
        keys = jax.random.split(key, origins.shape[0])

        def one(k, o, d, bg):
            return render_ray(self.field, params, o, d, render_config.replace(background=bg), k)

        out = jax.vmap(one)(keys, origins, directions, background)
        samples = jnp.int32(origins.shape[0] * render_config.num_samples)
        return out, jnp.ones(origins.shape[:1], bool), {"samples": samples, "rows": samples}

    def view_grid(self, state) -> occupancy.OccupancyGrid:
        """A single always-occupied cell over the field's box."""
        return occupancy.init_occupancy(self.box, 1.0, resolution=1)

    def view_march(self, scale: float) -> marching.MarchConfig:
        """eval_samples / scale steps across the box's diagonal."""
        grid = self.view_grid(None)
        return marching.MarchConfig.for_grid(grid, self.config.eval_samples / scale)


class _OccupancySampler:
    """Instant-NGP's occupancy grid and ray marching (`waldo_jax.render.occupancy`), with packed rows.

    Each ray is marched (`marching.march_ray`: candidates every dt, kept where the grid is occupied,
    compacted to at most S = `num_samples`). The kept samples are packed one ray after another into
    a budget of `samples_per_batch` slots (`render.packed`, rows of `TRAIN_ROW_LENGTH` samples):
    rays enter in their (random) order while their samples fit, the others are left out of this
    step's loss (`included`), and the field runs on the packed slots only. As with Instant-NGP's dynamic batch
    size, the rays trained per step adapt to the scene (few while the grid is still full, many once
    it is sparse) at a fixed cost per step. The composite runs on the packed rows (`packed.composite_rows`).
    """

    def __init__(self, config: TrainConfig):
        self.config = config
        self.field = make_field(config.field)
        self.density = make_density(config.field)
        aabb = np.asarray(config.field.aabb, np.float64).reshape(2, 3)
        center, half = 0.5 * (aabb[0] + aabb[1]), 0.5 * (aabb[1] - aabb[0]) / config.aabb_scale
        self.base_aabb = np.stack([center - half, center + half])
        self.geometry = occupancy.init_occupancy(self.base_aabb, config.aabb_scale, resolution=1)
        self.march = marching.MarchConfig.for_grid(
            self.geometry.replace(resolution=config.occupancy_resolution),
            config.steps_per_diagonal,
            config.cone_angle,
            max_samples=config.num_samples,
        )
        self.row_length = TRAIN_ROW_LENGTH
        self.rows = config.samples_per_batch // self.row_length
        self.max_rows_per_ray = -(-self.march.max_samples // self.row_length)
        if self.rows < self.max_rows_per_ray:
            raise TrainConfigError(
                f"TrainConfig.samples_per_batch ({config.samples_per_batch}) must hold the samples one ray may "
                f"keep, min(num_samples, K) = {self.march.max_samples} (in rows of {self.row_length})"
            )

    def init(self, key: PRNGKey, params):
        """All cells occupied, zero densities (nothing is skipped before the first update)."""
        return occupancy.init_occupancy(
            self.base_aabb, self.config.aabb_scale, resolution=self.config.occupancy_resolution
        )

    def _occupancy_config(self, grid):
        return occupancy.OccupancyConfig.create(
            grid,
            steps_per_diagonal=self.config.steps_per_diagonal,
            warmup_steps=self.config.occupancy_warmup,
            decay=self.config.occupancy_decay,
        )

    def update(self, key: PRNGKey, grid, params, warmup: bool):
        """Instant-NGP's decay / sample / threshold update of the grid (`warmup`: every cell)."""
        return occupancy.update_occupancy_phase(
            key, grid, self.density, jax.lax.stop_gradient(params), self._occupancy_config(grid), warmup
        )

    def _march(
        self, grid, origins: Array, directions: Array, render_config: RenderConfig, key: Optional[PRNGKey]
    ) -> Tuple[Array, Array, Array]:
        """t, delta [R, S] and mask bool [R, S] of R rays (random offsets with a key)."""

        def one(o, d, k):
            t_start, t_end = marching.ray_interval(grid, o, d, render_config)
            return marching.march_ray(grid, o, d, t_start, t_end, self.march, k)

        keys = None if key is None else jax.random.split(key, origins.shape[0])
        return jax.vmap(one, in_axes=(0, 0, None if keys is None else 0))(origins, directions, keys)

    def render_rays(
        self,
        key: PRNGKey,
        params,
        grid,
        origins: Array,
        directions: Array,
        background: Array,
        render_config: RenderConfig,
    ) -> Tuple[RenderOutput, Array, Dict[str, Array]]:
        """Renders training rays [R, 3]; the leading rays whose rows fit the budget are `included`.

        Stats: "samples", the samples of the included rays (field evaluations that count), and "rows",
        the rows all R marched rays would need (to size the next chunk's R).
        """
        num_rays = origins.shape[0]
        s = self.row_length
        t, delta, mask = self._march(grid, origins, directions, render_config, key)  # [R, S] each
        count = jnp.sum(mask, axis=1, dtype=jnp.int32)  # [R]
        rows = -(-count // s)  # [R]
        included = jnp.cumsum(rows) <= self.rows  # [R], the leading rays that fit
        layout = packed.layout_rows(jnp.where(included, rows, 0), self.rows)
        index, valid = packed.row_samples(layout, jnp.zeros((num_rays,), jnp.int32), count, s)  # [M, s]
        owner = layout.owner[:, None]  # [M, 1]
        index = jnp.minimum(index, self.march.max_samples - 1)
        t_rows = t[owner, index]  # [M, s]
        delta_rows = jnp.where(valid, delta[owner, index], 0.0)  # [M, s]
        ray_dirs = jnp.broadcast_to(directions[layout.owner][:, None, :], (self.rows, s, 3))  # [M, s, 3]
        points = origins[layout.owner][:, None, :] + t_rows[..., None] * ray_dirs  # [M, s, 3]
        sigma, rgb = jax.vmap(self.field, in_axes=(None, 0, 0))(params, points.reshape(-1, 3), ray_dirs.reshape(-1, 3))
        sums = packed.composite_rows(
            sigma.reshape(self.rows, s),
            rgb.reshape(self.rows, s, 3),
            t_rows,
            delta_rows,
            layout,
            jnp.zeros((num_rays,), jnp.float32),
            self.max_rows_per_ray,
        )
        out = RenderOutput(rgb=sums.rgb + (1.0 - sums.acc)[:, None] * background, depth=sums.depth, acc=sums.acc)
        stats = {"samples": jnp.sum(jnp.where(included, count, 0)), "rows": jnp.sum(rows)}
        return out, included, stats

    def view_grid(self, grid) -> occupancy.OccupancyGrid:
        """The trained grid itself."""
        return grid

    def view_march(self, scale: float) -> marching.MarchConfig:
        """The training march with steps `scale` times longer (NGP's dt_min and cone angle both scaled)."""
        return marching.MarchConfig.for_grid(
            self.geometry.replace(resolution=self.config.occupancy_resolution),
            self.config.steps_per_diagonal / scale,
            self.config.cone_angle * scale,
            max_samples=self.config.eval_samples,
        )


@functools.lru_cache(maxsize=None)
def make_sampler(config: TrainConfig):
    """The sampler of a config (one object per config, so compiled functions are shared).

    Returns:
      An object with `init`, `update`, `render_rays`, `view_grid` and `view_march` (the protocol at the
      top of this module), and for the occupancy sampler the attributes `march` (training MarchConfig),
      `rows` (packed rows per step) and `row_length`.
    """
    if config.sampler == "occupancy":
        return _OccupancySampler(config)
    return _DenseSampler(config)
