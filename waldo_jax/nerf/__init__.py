"""Instant-NGP in JAX: hash encoding, the density/colour MLPs, training and checkpoints.

The occupancy grid, ray marching and the renderer of trained fields live in `waldo_jax.render`."""

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

__all__ = [
    "HASH_PRIMES",
    "HashGridConfig",
    "HashGridLayout",
    "MLP",
    "NGPFieldConfig",
    "encode",
    "grid_indices",
    "init_field",
    "init_hashgrid",
    "make_density",
    "make_field",
    "make_field_batch",
    "spherical_harmonics",
    "trunc_exp",
]
