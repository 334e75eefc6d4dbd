"""Instant-NGP in JAX: hash encoding, the density/colour MLPs, the occupancy grid and ray marching."""

from waldo_jax.nerf.field import MLP as MLP
from waldo_jax.nerf.field import NGPFieldConfig as NGPFieldConfig
from waldo_jax.nerf.field import init_field as init_field
from waldo_jax.nerf.field import make_density as make_density
from waldo_jax.nerf.field import make_field as make_field
from waldo_jax.nerf.field import make_field_batch as make_field_batch
from waldo_jax.nerf.field import spherical_harmonics as spherical_harmonics
from waldo_jax.nerf.field import trunc_exp as trunc_exp
from waldo_jax.nerf.hashgrid import HASH_PRIMES as HASH_PRIMES
from waldo_jax.nerf.hashgrid import HashGridConfig as HashGridConfig
from waldo_jax.nerf.hashgrid import HashGridLayout as HashGridLayout
from waldo_jax.nerf.hashgrid import encode as encode
from waldo_jax.nerf.hashgrid import grid_indices as grid_indices
from waldo_jax.nerf.hashgrid import init_hashgrid as init_hashgrid
from waldo_jax.nerf.occupancy import MarchConfig as MarchConfig
from waldo_jax.nerf.occupancy import OccupancyConfig as OccupancyConfig
from waldo_jax.nerf.occupancy import OccupancyGrid as OccupancyGrid
from waldo_jax.nerf.occupancy import init_occupancy as init_occupancy
from waldo_jax.nerf.occupancy import init_occupancy_for_scene as init_occupancy_for_scene
from waldo_jax.nerf.occupancy import is_occupied as is_occupied
from waldo_jax.nerf.occupancy import march_ray as march_ray
from waldo_jax.nerf.occupancy import render_rays_marched as render_rays_marched
from waldo_jax.nerf.occupancy import render_rays_packed as render_rays_packed
from waldo_jax.nerf.occupancy import update_occupancy as update_occupancy

__all__ = [
    "HASH_PRIMES",
    "HashGridConfig",
    "HashGridLayout",
    "MLP",
    "MarchConfig",
    "NGPFieldConfig",
    "OccupancyConfig",
    "OccupancyGrid",
    "encode",
    "grid_indices",
    "init_field",
    "init_hashgrid",
    "init_occupancy",
    "init_occupancy_for_scene",
    "is_occupied",
    "make_density",
    "make_field",
    "make_field_batch",
    "march_ray",
    "render_rays_marched",
    "render_rays_packed",
    "spherical_harmonics",
    "trunc_exp",
    "update_occupancy",
]
