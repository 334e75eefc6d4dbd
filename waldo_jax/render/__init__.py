"""Rendering: the volume integral, population rendering, sharding, and fields with an occupancy grid.

Modules, bottom to top: `volume` (the quadrature, any field along rays, `render_views` for a
population), `sharding` (a population split over devices), `occupancy` (Instant-NGP's grid and its
update), `marching` (rays marched through the grid), `packed` (samples of many rays in fixed budgets
of rows, composited by cumulative sums; shared with training), `marched` (the renderer of fields
with an occupancy grid: every trained field goes through it, via `waldo_jax.nerf.trained`).
"""

from waldo_jax.render.marched import MarchedViews as MarchedViews
from waldo_jax.render.marched import Packing as Packing
from waldo_jax.render.marched import render_marched as render_marched
from waldo_jax.render.marched import render_marched_sharded as render_marched_sharded
from waldo_jax.render.marching import MarchConfig as MarchConfig
from waldo_jax.render.occupancy import OccupancyConfig as OccupancyConfig
from waldo_jax.render.occupancy import OccupancyGrid as OccupancyGrid
from waldo_jax.render.sharding import gather_to_hosts as gather_to_hosts
from waldo_jax.render.sharding import global_pose_mesh as global_pose_mesh
from waldo_jax.render.sharding import pose_mesh as pose_mesh
from waldo_jax.render.sharding import render_views_sharded as render_views_sharded
from waldo_jax.render.sharding import shard_over_poses as shard_over_poses
from waldo_jax.render.volume import MAX_DENSITY as MAX_DENSITY
from waldo_jax.render.volume import RenderConfig as RenderConfig
from waldo_jax.render.volume import composite as composite
from waldo_jax.render.volume import default_ray_chunk as default_ray_chunk
from waldo_jax.render.volume import ray_aabb_interval as ray_aabb_interval
from waldo_jax.render.volume import render_ray as render_ray
from waldo_jax.render.volume import render_rays as render_rays
from waldo_jax.render.volume import render_view as render_view
from waldo_jax.render.volume import render_views as render_views
from waldo_jax.render.volume import sample_interval as sample_interval
from waldo_jax.render.volume import volume_weights as volume_weights

__all__ = [
    "MAX_DENSITY",
    "MarchConfig",
    "MarchedViews",
    "OccupancyConfig",
    "OccupancyGrid",
    "Packing",
    "RenderConfig",
    "composite",
    "default_ray_chunk",
    "gather_to_hosts",
    "global_pose_mesh",
    "pose_mesh",
    "ray_aabb_interval",
    "render_marched",
    "render_marched_sharded",
    "render_ray",
    "render_rays",
    "render_view",
    "render_views",
    "render_views_sharded",
    "sample_interval",
    "shard_over_poses",
    "volume_weights",
]
