"""Volume rendering of any radiance field, for one ray, one view or a whole population of views.

A field is a pure function for one point, `field(params, x [3], d [3]) -> (sigma [], rgb [3])`
(`waldo_jax.types.Field`); this module samples it along rays (bin midpoints, or stratified jitter
given a key) and evaluates the quadrature of the volume-rendering integral,
w_i = T_i * (1 - exp(-sigma_i * delta_i)), rgb = sum_i w_i c_i + (1 - sum_i w_i) * background.
`render_views` renders P poses in one jitted call, the rays of all poses as one flat list in
`ray_chunk` pieces. Trained fields with an occupancy grid go through `waldo_jax.render.marched`.

The quadrature, the names (`t`, `t_edges`, `delta`, `sigma`, `w`, `S`), the scene box and the
per-ray keys: see docs/design.md, section "Rendering > The volume integral".
"""

from __future__ import annotations

import functools
from typing import Optional, Tuple

import flax.struct
import jax
import jax.numpy as jnp

from waldo_jax.cameras import pixel_ray
from waldo_jax.types import Array, Field, Intrinsics, PRNGKey, RenderOutput

__all__ = [
    "RenderConfig",
    "default_ray_chunk",
    "ray_aabb_interval",
    "sample_interval",
    "volume_weights",
    "composite",
    "render_ray",
    "render_rays",
    "render_view",
    "map_ray_chunks",
    "pose_keys",
    "render_population",
    "render_views",
    "to_images",
    "view_rays",
]

# Densities are clamped to this value: sigma * delta stays finite for any delta used here.
MAX_DENSITY = 1e10


# The rays one `render_views` call may hold: its flat ray index is int32.
MAX_RAYS_PER_CALL = 2**31 - 1


def default_ray_chunk(backend: Optional[str] = None) -> int:
    """Rays rendered together (one `lax.map` step) by default on a backend (default: JAX's default).

    On a CPU, working sets that stay in cache are fastest (`benchmarks/render_population.py`); an
    accelerator wants large fused batches (ray_chunk x num_samples field evaluations are live at once).
    """
    backend = backend or jax.default_backend()
    return 1024 if backend == "cpu" else 32768


@flax.struct.dataclass
class RenderConfig:
    """How to sample and integrate rays.

    Static (shape-setting) fields are plain Python; numeric ones are pytree leaves, so a sweep can
    vmap over them and changing them does not recompile.

    Attributes:
      num_samples: samples per ray, S (static).
      ray_chunk: rays per `lax.map` step (static); the rays of all poses of a call are flattened first.
      use_aabb: clip [near, far] to the ray's intersection with `aabb` (static).
      near, far: distance bounds along unit ray directions.
      aabb: scene box [2, 3] (min corner, max corner).
      background: colour [3] composited behind the volume.
    """

    num_samples: int = flax.struct.field(pytree_node=False, default=64)
    ray_chunk: int = flax.struct.field(pytree_node=False, default=4096)
    use_aabb: bool = flax.struct.field(pytree_node=False, default=True)
    near: Array = 0.0
    far: Array = 10.0
    aabb: Array = ((-1.0, -1.0, -1.0), (1.0, 1.0, 1.0))
    background: Array = (1.0, 1.0, 1.0)

    @classmethod
    def create(
        cls, near=0.0, far=10.0, aabb=None, background=(1.0, 1.0, 1.0), num_samples=64, ray_chunk=None
    ) -> "RenderConfig":
        """Builds a config with float32 leaves; `aabb=None` samples [near, far] only.

        `ray_chunk` defaults to `default_ray_chunk()` for the default JAX backend.
        """
        ray_chunk = default_ray_chunk() if ray_chunk is None else ray_chunk
        if num_samples < 1:
            raise ValueError(f"num_samples must be >= 1, got {num_samples}")
        if ray_chunk < 1:
            raise ValueError(f"ray_chunk must be >= 1, got {ray_chunk}")
        if not float(far) > float(near):
            raise ValueError(f"far ({far}) must exceed near ({near})")
        return cls(
            num_samples=int(num_samples),
            ray_chunk=int(ray_chunk),
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


def render_ray(
    field: Field, params, origin: Array, direction: Array, config: RenderConfig, key: Optional[PRNGKey] = None
) -> RenderOutput:
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


def render_rays(
    field: Field, params, origins: Array, directions: Array, config: RenderConfig, key: Optional[PRNGKey] = None
) -> RenderOutput:
    """Renders a flat batch of rays [R, 3] in chunks of `config.ray_chunk` (padded, then cropped).

    With a key, ray i draws its stratified samples from `fold_in(key, i)`.

    Returns a `RenderOutput` with rgb [R, 3], depth [R], acc [R].
    """
    num_rays = origins.shape[0]

    def render_chunk(ids: Array) -> RenderOutput:
        index = jnp.minimum(ids, num_rays - 1)  # padding rays repeat the last ray, then are cropped
        keys = None if key is None else jax.vmap(jax.random.fold_in, in_axes=(None, 0))(key, ids)
        return jax.vmap(
            lambda o, d, k: render_ray(field, params, o, d, config, k), in_axes=(0, 0, None if keys is None else 0)
        )(origins[index], directions[index], keys)

    return map_ray_chunks(render_chunk, num_rays, min(config.ray_chunk, num_rays))


def map_ray_chunks(render_chunk, num_rays: int, chunk: int):
    """Applies `render_chunk(ids int32 [C])` to consecutive chunks of ray ids and joins the results.

    The ids 0 .. num_rays - 1 are padded to whole chunks of `chunk` (padding ids are >= num_rays: the
    chunk function must give them some valid ray) and mapped with `jax.lax.map`; every leaf of the
    result, [C, ...] per chunk, comes back as [num_rays, ...].
    """
    chunk = max(1, chunk)
    num_chunks = -(-num_rays // chunk)
    ids = jnp.arange(num_chunks * chunk, dtype=jnp.int32).reshape(num_chunks, chunk)
    out = jax.lax.map(render_chunk, ids)
    return jax.tree.map(lambda a: a.reshape((num_chunks * chunk,) + a.shape[2:])[:num_rays], out)


def view_rays(c2w: Array, intrinsics: Intrinsics, ids: Array) -> Tuple[Array, Array, Array, Array]:
    """Rays of flat ids [C] over P views: id = pose * H * W + pixel (row-major pixels).

    Ids past the last ray (padding) give the last ray again.

    Returns:
      origins [C, 3], unit directions [C, 3], pose int32 [C], pixel int32 [C].
    """
    num_poses = c2w.shape[0]
    pixels = intrinsics.height * intrinsics.width
    ids = jnp.minimum(ids, num_poses * pixels - 1)
    pose, pixel = ids // pixels, ids % pixels
    origins, directions = jax.vmap(lambda p, q: pixel_ray(c2w[p], intrinsics, q))(pose, pixel)
    return origins, directions, pose, pixel


def to_images(a: Array, num_poses: int, intrinsics: Intrinsics) -> Array:
    """[P * H * W, ...] per-ray values -> [P, H, W, ...]."""
    return a.reshape((num_poses, intrinsics.height, intrinsics.width) + a.shape[1:])


def render_population(
    field: Field, params, c2w: Array, pose_keys: Optional[Array], intrinsics: Intrinsics, config: RenderConfig
) -> RenderOutput:
    """Renders P poses c2w [P, 3 or 4, 4] (unjitted; `render_views` is the jitted entry).

    The P * H * W rays are one flat list, rendered `config.ray_chunk` at a time; ray (p, q) draws from
    `fold_in(pose_keys[p], q)` when `pose_keys` [P] is given. Every ray is computed the same way
    whatever P and the chunking are, so a pose renders the same alone, in a population or on
    another device.
    """
    c2w = jnp.asarray(c2w, jnp.float32)[:, :3, :4]
    num_poses = c2w.shape[0]

    def render_chunk(ids: Array) -> RenderOutput:
        origins, directions, pose, pixel = view_rays(c2w, intrinsics, ids)
        keys = None if pose_keys is None else jax.vmap(jax.random.fold_in)(pose_keys[pose], pixel)
        return jax.vmap(
            lambda o, d, k: render_ray(field, params, o, d, config, k), in_axes=(0, 0, None if keys is None else 0)
        )(origins, directions, keys)

    num_rays = num_poses * intrinsics.height * intrinsics.width
    if num_rays > MAX_RAYS_PER_CALL:  # the flat ray index is int32: past it, rays would wrap round
        raise ValueError(
            f"{num_poses} views of {intrinsics.width}x{intrinsics.height} are {num_rays:,} rays, more than the "
            f"{MAX_RAYS_PER_CALL:,} one render call indexes: render fewer views at a time"
        )
    out = map_ray_chunks(render_chunk, num_rays, min(config.ray_chunk, num_rays))
    return jax.tree.map(lambda a: to_images(a, num_poses, intrinsics), out)


def pose_keys(key: Optional[PRNGKey], num_poses: int) -> Optional[Array]:
    """One sampling stream per pose (the same whatever the chunking or device count)."""
    return None if key is None else jax.random.split(key, num_poses)


def render_view(
    field: Field, params, c2w: Array, intrinsics: Intrinsics, config: RenderConfig, key: Optional[PRNGKey] = None
) -> RenderOutput:
    """Renders one camera (as a population of one: the same image `render_views` gives it).

    Args:
      field, params: the radiance field and its parameters.
      c2w: [4, 4] or [3, 4] camera-to-world matrix.
      intrinsics: camera intrinsics; width and height set the image size.
      config: sampling configuration.
      key: None for a deterministic render, else a PRNG key for stratified sampling.

    Returns:
      `RenderOutput` with rgb [H, W, 3], depth [H, W], acc [H, W].
    """
    out = render_population(field, params, jnp.asarray(c2w)[None], pose_keys(key, 1), intrinsics, config)
    return jax.tree.map(lambda a: a[0], out)


@functools.partial(jax.jit, static_argnames=("field",))
def render_views(
    field: Field, params, c2w: Array, intrinsics: Intrinsics, config: RenderConfig, key: Optional[PRNGKey] = None
) -> RenderOutput:
    """Renders a population of P poses in one jitted call.

    The rays of all P views form one flat list rendered `config.ray_chunk` at a time (vmap within a
    chunk, `lax.map` over chunks), so memory is bounded by ray_chunk x num_samples field evaluations
    whatever P is, and a population costs the field evaluations of its rays and nothing more. The
    result is deterministic unless `key` is given; with a key each pose gets its own stratified
    stream (`split(key, P)[p]`, folded with the pixel index). The field function is a static
    argument: pass the same function object to reuse the compilation.

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
    return render_population(field, params, c2w, pose_keys(key, c2w.shape[0]), intrinsics, config)
