"""Instant-NGP in JAX: hash encoding, the density/colour MLPs, training, checkpoints and run directories.

Modules, bottom to top: `hashgrid`, `field` (the field, re-exported here) -> `config` (TrainConfig,
presets) -> `samplers` -> `step` (one training step, chunks of steps) -> `trained` (a trained field,
`TrainedField`, rendered through `waldo_jax.render.marched`: render_trained, evaluate) -> `train` (the
loop) -> `checkpoint` -> `runs`. Entry points: `train.train` (scenes in memory -> `TrainResult`),
`runs.train_run` (the same, writing a run directory), `runs.train_scene_run` (`waldo train`: a
scene on disk -> a run directory), `checkpoint.load_checkpoint` (a run back)."""

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
