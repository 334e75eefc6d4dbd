"""Splitting a population of poses over devices (`jax.sharding`), for any population renderer.

A renderer in this convention is `render_fn(replicated, (c2w_local, per_pose_local))`: `replicated`
(params, grid, intrinsics, configs) is copied to every device, the poses and any per-pose arrays are
split along a one-axis mesh named "poses". Every renderer of `waldo_jax.render` computes each ray
independently of the others of its call, so the sharded images equal the single-device ones.

Several hosts (processes): every process calls `jax.distributed.initialize(...)` before JAX starts a
backend, then runs the same code with `global_pose_mesh()`; the result is a global `jax.Array` of which
each process holds its devices' poses, and `gather_to_hosts` gives every process the whole of it
(tests/test_multiprocess.py: two CPU processes, gloo collectives).
"""

from __future__ import annotations

import functools
from typing import Callable, Optional

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, PartitionSpec

from waldo_jax.render.volume import RenderConfig, pose_keys, render_population
from waldo_jax.types import Array, Field, Intrinsics, PRNGKey, RenderOutput

__all__ = ["pose_mesh", "global_pose_mesh", "gather_to_hosts", "render_views_sharded", "shard_over_poses"]


def pose_mesh(devices=None) -> Mesh:
    """A one-axis mesh named "poses" over `devices` (default: all local devices)."""
    devices = jax.local_devices() if devices is None else devices
    return Mesh(np.asarray(devices), ("poses",))


def global_pose_mesh() -> Mesh:
    """`pose_mesh` over the devices of every process (`jax.devices()`), in process order.

    Call `jax.distributed.initialize(...)` first on every process; in a single process this is
    `pose_mesh(jax.devices())`.
    """
    return pose_mesh(jax.devices())


def gather_to_hosts(tree):
    """The whole of each array of `tree` as a NumPy array, on every process.

    A global `jax.Array` sharded over several processes (the output of a renderer on
    `global_pose_mesh()`) is all-gathered across processes (`multihost_utils.process_allgather`;
    every process must call this, like any collective); any other array is copied to the host.

    Args:
      tree: pytree of arrays (e.g. a `RenderOutput`).

    Returns:
      The same pytree of `np.ndarray`s holding the global values, e.g. rgb [P, H, W, 3] of all poses.
    """
    from jax.experimental import multihost_utils

    def whole(a):
        if isinstance(a, jax.Array) and not a.is_fully_addressable:
            return np.asarray(multihost_utils.process_allgather(a, tiled=True))
        return np.asarray(jax.device_get(a))

    return jax.tree.map(whole, tree)


def _pad_poses(a: Array, pad: int) -> Array:
    """Appends `pad` copies of the last row (a valid camera or key, cropped away afterwards)."""
    return jnp.concatenate([a, jnp.repeat(a[-1:], pad, axis=0)]) if pad else a


@functools.lru_cache(maxsize=None)
def _sharded(render_fn: Callable, mesh: Mesh) -> Callable:
    """jit(shard_map(render_fn)): replicated first argument, poses split over the mesh axis "poses"."""
    spec = PartitionSpec("poses")
    # check_vma=False: renderers carry fresh (device-invariant) zeros through loops whose bodies make
    # them pose-varying; every output is per-pose, so no replication check is needed.
    return jax.jit(
        jax.shard_map(render_fn, mesh=mesh, in_specs=(PartitionSpec(), spec), out_specs=spec, check_vma=False)
    )


def shard_over_poses(render_fn: Callable, replicated, c2w: Array, mesh: Optional[Mesh] = None, per_pose=None):
    """Runs a population renderer with the poses split over the devices of `mesh`.

    `render_fn(replicated, (c2w_local, per_pose_local))` must render the poses it is given (any
    count) and return a pytree of arrays with the pose axis first; `replicated` (params, grid,
    intrinsics, config, ...) is copied to every device. The poses (and `per_pose`, e.g. sampling
    keys, a pytree with the pose axis first) are padded to a multiple of the mesh size with copies
    of the last pose, split, and the padding is cropped from the result. `render_fn` must be the
    same function object across calls to reuse the compilation.

    Multi-host: call `jax.distributed.initialize()` on every host first and pass `global_pose_mesh()`
    (all hosts' devices); every host then calls this function with the same arguments (SPMD), and the
    returned arrays are global `jax.Array`s sharded over the hosts (`gather_to_hosts` gathers them).

    Args:
      render_fn: the renderer (static).
      replicated: pytree copied to every device.
      c2w: [P, 4, 4] or [P, 3, 4] camera-to-world matrices.
      mesh: a one-axis mesh named "poses" (default: `pose_mesh()` over the local devices).
      per_pose: optional pytree of per-pose arrays [P, ...] split like the poses.

    Returns:
      `render_fn`'s output for the P poses, sharded over the mesh.
    """
    mesh = pose_mesh() if mesh is None else mesh
    num_poses = c2w.shape[0]
    pad = (-num_poses) % mesh.size
    c2w = _pad_poses(jnp.asarray(c2w, jnp.float32)[:, :3, :4], pad)
    per_pose = jax.tree.map(lambda a: _pad_poses(a, pad), per_pose)
    out = _sharded(render_fn, mesh)(replicated, (c2w, per_pose))
    return jax.tree.map(lambda a: a[:num_poses], out) if pad else out


@functools.lru_cache(maxsize=None)
def _population_local(field: Field) -> Callable:
    """`render_population` of `field` in the `shard_over_poses` calling convention (one object per field)."""

    def local(replicated, posed):
        params, intrinsics, config = replicated
        c2w, keys = posed
        return render_population(field, params, c2w, keys, intrinsics, config)

    return local


def render_views_sharded(
    field: Field,
    params,
    c2w: Array,
    intrinsics: Intrinsics,
    config: RenderConfig,
    key: Optional[PRNGKey] = None,
    mesh: Optional[Mesh] = None,
) -> RenderOutput:
    """`render_views` with the population split over devices along the pose axis.

    The poses are padded to a multiple of the mesh size and sharded over the mesh axis "poses"; the
    params are replicated; each device renders its share with the same code as `render_views`, so
    the images equal the single-device ones bit for bit (per-pose sampling keys are drawn before the
    split). For multi-host use see `shard_over_poses`.

    Args:
      field, params, c2w, intrinsics, config, key: as for `render_views`.
      mesh: a one-axis mesh named "poses" (default: `pose_mesh()` over the local devices).

    Returns:
      `RenderOutput` with rgb [P, H, W, 3], depth [P, H, W], acc [P, H, W], sharded over the mesh.
    """
    return shard_over_poses(
        _population_local(field), (params, intrinsics, config), c2w, mesh, per_pose=pose_keys(key, c2w.shape[0])
    )
