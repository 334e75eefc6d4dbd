"""Volume rendering of any radiance field, for one ray, one view or a whole population of views.

A radiance field is a pure function for one point, `field(params, x [3], d [3]) -> (sigma [], rgb [3])`
(`waldo_jax.types.Field`); this module samples it along rays and evaluates the volume-rendering
integral (Max 1995; Mildenhall et al. 2020, eq. 3) in its quadrature form:

    alpha_i = 1 - exp(-sigma_i * delta_i)
    T_i     = exp(-sum_{j<i} sigma_j * delta_j)          (transmittance)
    w_i     = T_i * alpha_i                               (weights)
    rgb     = sum_i w_i * c_i + (1 - sum_i w_i) * background
    depth   = sum_i w_i * t_i                              acc = sum_i w_i

Names used throughout: `t` distances along unit ray directions (world units), `t_edges` the bin
edges [S + 1], `delta` bin lengths [S], `sigma` densities [S], `w` weights [S], `S` the number of
samples per ray. Samples cover [near, far] clipped to the scene box `aabb` when `use_aabb` is set;
a ray that misses the box gets zero-length bins and so zero weights.

Sampling is deterministic (bin midpoints) unless a PRNG key is passed (stratified jitter).
`render_views` renders P poses in one jitted call: poses are processed `pose_chunk` at a time under
`jax.lax.map` (vmap inside a chunk), and each view's rays `ray_chunk` at a time, to bound memory.
"""

from __future__ import annotations

import functools
from typing import Callable, Optional, Tuple

import flax.struct
import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, PartitionSpec

from waldo_jax.cameras import camera_rays
from waldo_jax.types import Array, Field, Intrinsics, PRNGKey, RenderOutput

__all__ = [
    "RenderConfig",
    "default_chunks",
    "ray_aabb_interval",
    "sample_interval",
    "volume_weights",
    "composite",
    "render_ray",
    "render_rays",
    "render_view",
    "render_views",
    "render_views_sharded",
    "shard_over_poses",
    "pose_mesh",
]

# Densities are clamped to this value: sigma * delta stays finite for any delta used here.
MAX_DENSITY = 1e10


def default_chunks(backend: Optional[str] = None) -> Tuple[int, int]:
    """(ray_chunk, pose_chunk) defaults for a backend (default: JAX's default backend).

    On a CPU, small working sets that stay in cache are fastest (measured on 2 cores: 8 poses x
    1024 rays per step ran at a third of the speed of 1 x 1024); an accelerator wants large
    batches to fill its cores, bounded by memory (pose_chunk x ray_chunk x num_samples field
    evaluations are live at once).
    """
    backend = backend or jax.default_backend()
    return (1024, 1) if backend == "cpu" else (32768, 8)


@flax.struct.dataclass
class RenderConfig:
    """How to sample and integrate rays.

    Static (shape-setting) fields are plain Python; numeric ones are pytree leaves, so a sweep can
    vmap over them and changing them does not recompile.

    Attributes:
      num_samples: samples per ray, S (static).
      ray_chunk: rays per `lax.map` step within one view (static).
      pose_chunk: poses rendered together under `vmap` per `lax.map` step (static).
      use_aabb: clip [near, far] to the ray's intersection with `aabb` (static).
      near, far: distance bounds along unit ray directions.
      aabb: scene box [2, 3] (min corner, max corner).
      background: colour [3] composited behind the volume.
    """

    num_samples: int = flax.struct.field(pytree_node=False, default=64)
    ray_chunk: int = flax.struct.field(pytree_node=False, default=4096)
    pose_chunk: int = flax.struct.field(pytree_node=False, default=4)
    use_aabb: bool = flax.struct.field(pytree_node=False, default=True)
    near: Array = 0.0
    far: Array = 10.0
    aabb: Array = ((-1.0, -1.0, -1.0), (1.0, 1.0, 1.0))
    background: Array = (1.0, 1.0, 1.0)

    @classmethod
    def create(cls, near=0.0, far=10.0, aabb=None, background=(1.0, 1.0, 1.0), num_samples=64,
               ray_chunk=None, pose_chunk=None) -> "RenderConfig":
        """Builds a config with float32 leaves; `aabb=None` samples [near, far] only.

        `ray_chunk` / `pose_chunk` default to `default_chunks()` for the default JAX backend.
        """
        default_rays, default_poses = default_chunks()
        ray_chunk = default_rays if ray_chunk is None else ray_chunk
        pose_chunk = default_poses if pose_chunk is None else pose_chunk
        if num_samples < 1:
            raise ValueError(f"num_samples must be >= 1, got {num_samples}")
        if not float(far) > float(near):
            raise ValueError(f"far ({far}) must exceed near ({near})")
        return cls(
            num_samples=int(num_samples),
            ray_chunk=int(ray_chunk),
            pose_chunk=int(pose_chunk),
            use_aabb=aabb is not None,
            near=jnp.float32(near),
            far=jnp.float32(far),
            aabb=jnp.asarray(aabb if aabb is not None else [[-1.0] * 3, [1.0] * 3], jnp.float32),
            background=jnp.asarray(background, jnp.float32),
        )

    @classmethod
    def for_scene(cls, scene, **kwargs) -> "RenderConfig":
        """A config whose near, far and box come from a `waldo_jax.types.Scene`."""
        return cls.create(near=scene.near, far=scene.far, aabb=scene.aabb, **kwargs)


def ray_aabb_interval(origin: Array, direction: Array, aabb: Array) -> Tuple[Array, Array]:
    """Entry and exit distances of one ray through an axis-aligned box (slab method).

    Args:
      origin: [3]. direction: [3] (unit). aabb: [2, 3].

    Returns:
      (t_enter, t_exit); t_exit < t_enter means the ray misses the box. Axis-parallel rays are
      handled without NaN (a zero direction component counts as a tiny one).
    """
    safe_dir = jnp.where(jnp.abs(direction) > 1e-12, direction, 1e-12)
    t0 = (aabb[0] - origin) / safe_dir
    t1 = (aabb[1] - origin) / safe_dir
    return jnp.max(jnp.minimum(t0, t1)), jnp.min(jnp.maximum(t0, t1))


def sample_interval(key: Optional[PRNGKey], t_start: Array, t_end: Array, num_samples: int) -> Tuple[Array, Array]:
    """Bin edges and sample distances along one ray.

    Args:
      key: None for bin midpoints, else a PRNG key for one uniform sample per bin.
      t_start, t_end: the interval; `t_end <= t_start` gives empty bins.
      num_samples: S.

    Returns:
      t_edges: [S + 1] bin edges. t: [S] sample distances, t_edges[i] <= t[i] <= t_edges[i + 1].
    """
    t_end = jnp.maximum(t_end, t_start)
    t_edges = t_start + (t_end - t_start) * jnp.linspace(0.0, 1.0, num_samples + 1)  # [S + 1]
    u = 0.5 if key is None else jax.random.uniform(key, (num_samples,))
    t = t_edges[:-1] + u * (t_edges[1:] - t_edges[:-1])  # [S]
    return t_edges, t


def volume_weights(sigma: Array, delta: Array) -> Array:
    """Quadrature weights w [S] of densities sigma [S] over bins of length delta [S].

    Non-finite densities are treated as empty (NaN) or `MAX_DENSITY` (+inf); values and gradients
    stay finite for densities from 0 up to `MAX_DENSITY`.
    """
    sigma = jnp.clip(jnp.nan_to_num(sigma, nan=0.0, posinf=MAX_DENSITY, neginf=0.0), 0.0, MAX_DENSITY)
    optical_depth = sigma * delta  # [S]
    alpha = -jnp.expm1(-optical_depth)  # 1 - exp(-sigma delta), accurate for small values
    depth_before = jnp.concatenate([jnp.zeros_like(optical_depth[:1]), jnp.cumsum(optical_depth[:-1])])
    transmittance = jnp.exp(-depth_before)  # [S]
    return transmittance * alpha


def composite(w: Array, rgb: Array, t: Array, background: Array) -> RenderOutput:
    """Colour, depth and opacity of one ray from its weights w [S], colours rgb [S, 3] and distances t [S]."""
    acc = jnp.sum(w)
    color = jnp.sum(w[:, None] * rgb, axis=0) + (1.0 - acc) * background
    depth = jnp.sum(w * t)
    return RenderOutput(rgb=color, depth=depth, acc=acc)


def render_ray(field: Field, params, origin: Array, direction: Array, config: RenderConfig,
               key: Optional[PRNGKey] = None) -> RenderOutput:
    """Renders one ray.

    Args:
      field: radiance field for one point (see module docstring).
      params: the field's parameters (any pytree).
      origin: [3]. direction: [3] unit direction.
      config: sampling bounds and sample count.
      key: None (deterministic bin midpoints) or a PRNG key (stratified samples).

    Returns:
      `RenderOutput` with rgb [3], depth [] and acc [].
    """
    t_start, t_end = config.near, config.far
    if config.use_aabb:
        t_enter, t_exit = ray_aabb_interval(origin, direction, config.aabb)
        t_start = jnp.maximum(t_start, t_enter)
        t_end = jnp.minimum(t_end, t_exit)
    t_edges, t = sample_interval(key, t_start, t_end, config.num_samples)
    points = origin + t[:, None] * direction  # [S, 3]
    sigma, rgb = jax.vmap(field, in_axes=(None, 0, None))(params, points, direction)  # [S], [S, 3]
    rgb = jnp.nan_to_num(rgb)
    w = volume_weights(sigma, t_edges[1:] - t_edges[:-1])
    return composite(w, rgb, t, config.background)


def render_rays(field: Field, params, origins: Array, directions: Array, config: RenderConfig,
                key: Optional[PRNGKey] = None) -> RenderOutput:
    """Renders a flat batch of rays [R, 3] in chunks of `config.ray_chunk` (padded, then cropped).

    Returns a `RenderOutput` with rgb [R, 3], depth [R], acc [R].
    """
    num_rays = origins.shape[0]
    chunk = max(1, min(config.ray_chunk, num_rays))
    num_chunks = -(-num_rays // chunk)
    pad = num_chunks * chunk - num_rays
    origins = jnp.pad(origins, ((0, pad), (0, 0))).reshape(num_chunks, chunk, 3)
    # Padded rays get a valid direction so that they render (and are then cropped) without NaN.
    directions = jnp.pad(directions, ((0, pad), (0, 0)), constant_values=1.0 / jnp.sqrt(3.0))
    directions = directions.reshape(num_chunks, chunk, 3)

    def render_chunk(args):
        index, chunk_origins, chunk_directions = args
        if key is None:
            keys = None
        else:
            keys = jax.random.split(jax.random.fold_in(key, index), chunk)
        return jax.vmap(
            lambda o, d, k: render_ray(field, params, o, d, config, k),
            in_axes=(0, 0, None if keys is None else 0),
        )(chunk_origins, chunk_directions, keys)

    out = jax.lax.map(render_chunk, (jnp.arange(num_chunks), origins, directions))
    return jax.tree.map(lambda a: a.reshape((num_chunks * chunk,) + a.shape[2:])[:num_rays], out)


def render_view(field: Field, params, c2w: Array, intrinsics: Intrinsics, config: RenderConfig,
                key: Optional[PRNGKey] = None) -> RenderOutput:
    """Renders one camera.

    Args:
      field, params: the radiance field and its parameters.
      c2w: [4, 4] or [3, 4] camera-to-world matrix.
      intrinsics: camera intrinsics; width and height set the image size.
      config: sampling configuration.
      key: None for a deterministic render, else a PRNG key for stratified sampling.

    Returns:
      `RenderOutput` with rgb [H, W, 3], depth [H, W], acc [H, W].
    """
    origins, directions = camera_rays(c2w, intrinsics)
    h, w = intrinsics.height, intrinsics.width
    out = render_rays(field, params, origins.reshape(-1, 3), directions.reshape(-1, 3), config, key)
    return jax.tree.map(lambda a: a.reshape((h, w) + a.shape[1:]), out)


def _pad_poses(a: Array, pad: int) -> Array:
    """Appends `pad` copies of the last row (a valid camera or key, cropped away afterwards)."""
    return jnp.concatenate([a, jnp.repeat(a[-1:], pad, axis=0)]) if pad else a


def _render_posed(field: Field, params, c2w: Array, pose_keys: Optional[Array], intrinsics: Intrinsics,
                  config: RenderConfig) -> RenderOutput:
    """Renders poses c2w [P, 3 or 4, 4] with per-pose keys [P] (or None), `pose_chunk` at a time."""
    num_poses = c2w.shape[0]
    chunk = max(1, min(config.pose_chunk, num_poses))
    num_chunks = -(-num_poses // chunk)
    pad = num_chunks * chunk - num_poses
    c2w = _pad_poses(jnp.asarray(c2w, jnp.float32)[:, :3, :4], pad).reshape(num_chunks, chunk, 3, 4)
    if pose_keys is not None:  # typed keys are [P]; legacy uint32 keys are [P, 2]
        pose_keys = _pad_poses(pose_keys, pad)
        pose_keys = pose_keys.reshape((num_chunks, chunk) + pose_keys.shape[1:])

    def render_chunk(args):
        chunk_c2w, chunk_keys = args
        return jax.vmap(
            lambda m, k: render_view(field, params, m, intrinsics, config, k),
            in_axes=(0, None if chunk_keys is None else 0),
        )(chunk_c2w, chunk_keys)

    out = jax.lax.map(render_chunk, (c2w, pose_keys))
    return jax.tree.map(lambda a: a.reshape((num_chunks * chunk,) + a.shape[2:])[:num_poses], out)


def _pose_keys(key: Optional[PRNGKey], num_poses: int) -> Optional[Array]:
    """One sampling stream per pose (the same whatever the chunking or device count)."""
    return None if key is None else jax.random.split(key, num_poses)


@functools.partial(jax.jit, static_argnames=("field",))
def render_views(field: Field, params, c2w: Array, intrinsics: Intrinsics, config: RenderConfig,
                 key: Optional[PRNGKey] = None) -> RenderOutput:
    """Renders a population of P poses in one jitted call.

    Poses are processed `config.pose_chunk` at a time (vmap within a chunk, `lax.map` over chunks)
    and each view's rays `config.ray_chunk` at a time, so memory is bounded by
    pose_chunk x ray_chunk x num_samples field evaluations whatever P is. The result is
    deterministic unless `key` is given; with a key each pose gets its own stratified-sampling stream
    (`split(key, P)[i]` for pose i). The field function is a static argument: pass the same function
    object to reuse the compilation.

    Args:
      field: radiance field for one point, `field(params, x, d) -> (sigma, rgb)`.
      params: its parameters (pytree).
      c2w: [P, 4, 4] or [P, 3, 4] camera-to-world matrices.
      intrinsics: shared intrinsics of all poses.
      config: a `RenderConfig`.
      key: optional PRNG key.

    Returns:
      `RenderOutput` with rgb [P, H, W, 3], depth [P, H, W], acc [P, H, W].
    """
    return _render_posed(field, params, c2w, _pose_keys(key, c2w.shape[0]), intrinsics, config)


def pose_mesh(devices=None) -> Mesh:
    """A one-axis mesh named "poses" over `devices` (default: all local devices)."""
    devices = jax.local_devices() if devices is None else devices
    return Mesh(np.asarray(devices), ("poses",))


@functools.lru_cache(maxsize=None)
def _sharded(render_fn: Callable, mesh: Mesh) -> Callable:
    """jit(shard_map(render_fn)): replicated first argument, poses split over the mesh axis "poses"."""
    spec = PartitionSpec("poses")
    # check_vma=False: renderers carry fresh (device-invariant) zeros through while_loops whose
    # bodies make them pose-varying; every output is per-pose, so no replication check is needed.
    return jax.jit(jax.shard_map(render_fn, mesh=mesh, in_specs=(PartitionSpec(), spec), out_specs=spec,
                                 check_vma=False))


def shard_over_poses(render_fn: Callable, replicated, c2w: Array, mesh: Optional[Mesh] = None, per_pose=None):
    """Runs a population renderer with the poses split over the devices of `mesh`.

    `render_fn(replicated, (c2w_local, per_pose_local))` must render the poses it is given (any
    count) and return a pytree of arrays with the pose axis first; `replicated` (params, grid,
    intrinsics, config, ...) is copied to every device. The poses (and `per_pose`, e.g. sampling
    keys, a pytree with the pose axis first) are padded to a multiple of the mesh size with copies
    of the last pose, split, and the padding is cropped from the result. `render_fn` must be the
    same function object across calls to reuse the compilation.

    Multi-host: call `jax.distributed.initialize()` on every host first and pass a mesh over
    `jax.devices()` (all hosts' devices); every host then calls this function with the same
    arguments (SPMD), and the returned arrays are global `jax.Array`s sharded over the hosts.

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
def _posed_local(field: Field) -> Callable:
    """`_render_posed` of `field` in the `shard_over_poses` calling convention (one object per field)."""

    def local(replicated, posed):
        params, intrinsics, config = replicated
        c2w, pose_keys = posed
        return _render_posed(field, params, c2w, pose_keys, intrinsics, config)

    return local


def render_views_sharded(field: Field, params, c2w: Array, intrinsics: Intrinsics, config: RenderConfig,
                         key: Optional[PRNGKey] = None, mesh: Optional[Mesh] = None) -> RenderOutput:
    """`render_views` with the population split over devices along the pose axis.

    The poses are padded to a multiple of the mesh size and sharded over the mesh axis "poses"
    (`jax.sharding`); the params are replicated; each device renders its share with the same
    chunked code as `render_views`, so the images equal the single-device ones (per-pose sampling
    keys are drawn before the split). On one device this is `render_views`. For multi-host use see
    `shard_over_poses`.

    Args:
      field, params, c2w, intrinsics, config, key: as for `render_views`.
      mesh: a one-axis mesh named "poses" (default: `pose_mesh()` over the local devices).

    Returns:
      `RenderOutput` with rgb [P, H, W, 3], depth [P, H, W], acc [P, H, W], sharded over the mesh.
    """
    return shard_over_poses(_posed_local(field), (params, intrinsics, config), c2w, mesh,
                            per_pose=_pose_keys(key, c2w.shape[0]))
