"""The renderer of trained fields: occupancy-grid marching (Instant-NGP) with packed samples, compaction
of live rays between passes and early ray termination, for whole populations of poses in one call.

`render_marched(field, params, setup, c2w [P, 4, 4], intrinsics, ...)` (`setup`: the occupancy grid,
render and march configs, `MarchSetup`): the P * H * W rays form one flat list cut into blocks of N
rays; a block marches each ray through the grid (`marching.march_ray`), then runs passes in which the
live rays' next samples are packed into M rows of s slots (`packed.layout_rows`), the field runs once
and the rows are composited (`packed.composite_rows`), until every ray is done or opaque.
`render_marched_sharded` splits the poses over devices; `Packing` holds the per-backend sizes. The images
differentiate with respect to the poses in forward mode, or with `gradient="reverse"` in reverse mode
(`render.marched_vjp`).

Design and measurements: docs/rendering.md; the steps in `Packing`'s terms, early termination's
error bound and the names: docs/design.md, section "Rendering > The marched renderer".
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Callable, NamedTuple, Optional, Tuple

import jax
import jax.numpy as jnp

from waldo_jax.render import marched_vjp, marching, occupancy, packed
from waldo_jax.render.sharding import shard_over_poses
from waldo_jax.render.volume import RenderConfig, map_ray_chunks, to_images, view_rays
from waldo_jax.types import Array, Field, Intrinsics, RenderOutput

__all__ = [
    "BlockShape",
    "GRADIENTS",
    "MarchSetup",
    "MarchedViews",
    "Packing",
    "block_shape",
    "field_slots",
    "render_marched",
    "render_marched_sharded",
]


@dataclasses.dataclass(frozen=True)
class Packing:
    """Static sizes of the marched renderer (hashable: one compilation per value).

    Attributes:
      rays_per_block: the most rays marched together, N (a call with fewer rays uses fewer).
      slots_per_ray: field evaluations per pass per ray of a block: a pass has M * s = N * this slots.
      row_length: s, samples per packed row (a ray's last row may be partly empty).
      max_rows_per_ray: R_max, the most rows one ray takes in one pass (a power of two).
      field_chunk: slots per field call within a pass (0: the whole pass in one call).
      pass_levels: pass sizes, the first N * slots_per_ray, each next one `level_ratio` times smaller.
      level_ratio: the ratio of successive pass sizes.
      level_fill: a pass size is left for the next smaller one when the live rays' requests would fill
        less than this fraction of its slots.
      min_pass_slots: a pass size below this many slots is not used (the first size always is): each
        size is one more copy of the field in the compiled program, and a pass this small saves less
        than that compile costs (see `for_backend`). 1 keeps every size.
    """

    rays_per_block: int = 2**15
    slots_per_ray: int = 32
    row_length: int = 8
    max_rows_per_ray: int = 32
    field_chunk: int = 0
    pass_levels: int = 4
    level_ratio: int = 3
    level_fill: float = 0.8
    min_pass_slots: int = 1

    def __post_init__(self):
        for name in (
            "rays_per_block",
            "slots_per_ray",
            "row_length",
            "max_rows_per_ray",
            "pass_levels",
            "level_ratio",
            "min_pass_slots",
        ):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ValueError(f"Packing.{name} must be a positive int, got {value!r}")
        if self.slots_per_ray % self.row_length:
            raise ValueError(
                f"Packing.slots_per_ray ({self.slots_per_ray}) must be a multiple of row_length ({self.row_length})"
            )
        if self.max_rows_per_ray & (self.max_rows_per_ray - 1):
            raise ValueError(f"Packing.max_rows_per_ray must be a power of two, got {self.max_rows_per_ray}")
        if not 0.0 <= self.level_fill <= 1.0:
            raise ValueError(f"Packing.level_fill must be in [0, 1], got {self.level_fill!r}")
        if isinstance(self.field_chunk, bool) or not isinstance(self.field_chunk, int) or self.field_chunk < 0:
            raise ValueError(f"Packing.field_chunk must be an int >= 0, got {self.field_chunk!r}")

    @classmethod
    def for_backend(cls, backend: Optional[str] = None, **overrides) -> "Packing":
        """Sizes for a backend (default: JAX's default backend), with `overrides`.

        GPU/TPU: blocks of 2**17 rays, so passes of 2**22 slots and 3, 9, 27 times fewer. CPU: blocks
        of 2**15 rays, passes of 2**20 slots and 3, 9, 27 times fewer. Every backend runs each pass in
        one field call (`field_chunk=0`): on the 2-core CPU, on the 400-step fox NeRF (16 poses at
        144x256), 14.4k rays/s against 8.3k in calls of 2**13 slots, the CPU default before, for a peak
        memory of about 2.4 GB instead of 1.2 GB (docs/rendering.md, "One field call per pass"); pass
        `field_chunk` (e.g. 2**13) to bound the memory instead. The pass sizes were chosen on the
        CPU-trained fox and lego_tiny at 144x256: 32 slots a ray and four sizes keep both under 10
        passes per view with about 80 % of the evaluated slots in use.

        Every backend: no pass size under 2**14 slots (`min_pass_slots`), so a block of under about
        14k rays (its first pass holds 32 slots a ray) uses fewer sizes, under about 1.5k rays one
        (chosen from CPU measurements only; no GPU was at hand). Measured on the 2-core CPU on a
        trained room NeRF, 4 poses at 16 px (1024 rays): one size compiles in 1.8 s and renders in
        116 ms, four sizes take 4.6 s and 66 ms, so the smaller sizes pay for their compile only
        after about 55 such calls (docs/rendering.md, "Pass sizes that follow the work"; measured
        with field calls of 2**13 slots).
        """
        backend = backend or jax.default_backend()
        values = dict(rays_per_block=2**15 if backend == "cpu" else 2**17, field_chunk=0)
        values["min_pass_slots"] = 2**14
        values.update(overrides)
        return cls(**values)


class BlockShape(NamedTuple):
    """The static sizes of one call's blocks."""

    rays: int  # N
    rows: Tuple[int, ...]  # M of each pass level, decreasing
    row_length: int  # s
    max_rows_per_ray: int  # R_max
    max_passes: int
    field_chunk: int
    first_rows: int  # rows a ray that has not started may ask for
    level_fill: float


def block_shape(packing: Packing, total_rays: int, max_samples: int) -> BlockShape:
    """Balanced blocks of at most `rays_per_block` rays (the last block is padded, by under 8 rays a block),
    and the pass sizes of `packing` that hold at least `min_pass_slots` slots (the first always)."""
    num_blocks = -(-total_rays // packing.rays_per_block)
    rays = -(-total_rays // num_blocks)
    rays = -(-rays // 8) * 8
    first = rays * packing.slots_per_ray // packing.row_length
    sizes = [max(1, first // packing.level_ratio**level) for level in range(packing.pass_levels)]
    sizes = [
        size for level, size in enumerate(sizes) if level == 0 or size * packing.row_length >= packing.min_pass_slots
    ]
    rows = tuple(sorted(set(sizes), reverse=True))
    rows_per_ray = -(-max_samples // packing.row_length)
    # Every pass either fills all its rows or gives every live ray all it asked for (>= 1 row), so no
    # block can need more passes than this, even in passes of the smallest size: no ray is ever cut.
    max_passes = -(-rays * rows_per_ray // rows[-1]) + rows_per_ray + 1
    chunk = packing.field_chunk or first * packing.row_length
    return BlockShape(
        rays,
        rows,
        packing.row_length,
        packing.max_rows_per_ray,
        max_passes,
        chunk,
        packing.slots_per_ray // packing.row_length,
        packing.level_fill,
    )


class _Rays(NamedTuple):
    """What a block carries from pass to pass (N rays)."""

    next_sample: Array  # int32 [N], samples [0, next_sample) are composited
    alive: Array  # bool [N]
    optical_depth: Array  # float32 [N], sum of sigma * delta so far
    rgb: Array  # float32 [N, 3], sum of w * rgb
    depth: Array  # float32 [N], sum of w * t
    acc: Array  # float32 [N], sum of w
    evaluations: Array  # int32 [N], field evaluations spent on each ray
    passes: Array  # int32 []
    slots: Array  # int32 [], slots the passes evaluated (padding included)


class MarchSetup(NamedTuple):
    """Where `render_marched` puts the samples of a field's rays (a pytree; `nerf.trained.render_setup` makes it).

    Attributes:
      grid: the occupancy grid (empty cells are never sampled).
      render_config: near, far, the box (when `use_aabb`) and the background; its `num_samples` and
        `ray_chunk` are not used.
      march: the marching step, cone angle, K candidates and S samples per ray, `min_transmittance`.
    """

    grid: occupancy.OccupancyGrid
    render_config: RenderConfig
    march: marching.MarchConfig


class MarchedViews(NamedTuple):
    """`render_marched`'s images and what they cost.

    Attributes:
      output: `RenderOutput` with rgb [P, H, W, 3], depth [P, H, W], acc [P, H, W].
      evaluations: int32 [P, H, W], field evaluations spent on each pixel's ray.
      passes: int32 [num_blocks], the passes of each block (each one field pass over its level's slots).
      slots: int32 [num_blocks], the slots the passes of each block evaluated (padding included).
    """

    output: RenderOutput
    evaluations: Array
    passes: Array
    slots: Array


def field_slots(field: Field, params, points: Array, directions: Array, chunk: int):
    """sigma [B], rgb [B, 3] at points [B, 3] seen along directions [B, 3], `chunk` slots per call."""
    if chunk >= points.shape[0]:
        return jax.vmap(field, in_axes=(None, 0, 0))(params, points, directions)
    return jax.lax.map(lambda pd: field(params, pd[0], pd[1]), (points, directions), batch_size=chunk)


def _march_block(
    grid: occupancy.OccupancyGrid,
    origins: Array,
    directions: Array,
    real: Array,
    render_config: RenderConfig,
    march: marching.MarchConfig,
) -> Tuple[Array, Array, Array]:
    """The marched samples of N rays [N, 3] (`real` [N] False for padding): t [N, S], delta [N, S] and
    the counts int32 [N]. Constants of the rays: a gradient moves the samples with the ray, not along it."""
    origins, directions = jax.lax.stop_gradient((origins, directions))
    t_start, t_end = jax.vmap(lambda o, d: marching.ray_interval(grid, o, d, render_config))(origins, directions)
    t_end = jnp.where(real, t_end, t_start)  # padding rays march an empty interval
    t, delta, mask = jax.vmap(lambda o, d, a, b: marching.march_ray(grid, o, d, a, b, march))(
        origins, directions, t_start, t_end
    )  # [N, S] each
    return t, delta, jnp.sum(mask, axis=1, dtype=jnp.int32)


def _requests(shape: BlockShape, rows: int, state: _Rays, count: Array, first_rows: int) -> Array:
    """Rows each live ray asks for in a pass of `rows` rows: min(rows // live, R_max, what it has left),
    and a ray that has not started yet at most `first_rows` (its nominal share, `slots_per_ray`, while
    nothing tells yet whether it will stop early)."""
    live = jnp.sum(state.alive, dtype=jnp.int32)
    rows_per_ray = jnp.clip(rows // jnp.maximum(live, 1), 1, shape.max_rows_per_ray)  # []
    rows_per_ray = jnp.where(state.next_sample == 0, jnp.minimum(rows_per_ray, first_rows), rows_per_ray)
    need = -(-(count - state.next_sample) // shape.row_length)  # [N]
    return jnp.where(state.alive, jnp.minimum(rows_per_ray, need), 0)  # [N]


def _pass_rows(
    evaluate: Callable,
    shape: BlockShape,
    layout: packed.RowLayout,
    state: _Rays,
    origins: Array,
    directions: Array,
    t: Array,
    delta: Array,
    count: Array,
) -> packed.RowSums:
    """One pass: the samples `layout` lays out from each ray's `next_sample`, evaluated (`evaluate(points
    [B, 3], directions [B, 3]) -> (sigma [B], rgb [B, 3])`) and composited onto the rays' optical depth.
    Differentiable in origins and directions [N, 3] (the points move with them)."""
    rows, row_length = layout.owner.shape[0], shape.row_length
    index, valid = packed.row_samples(layout, state.next_sample, count, row_length)  # [M, s]
    owner = layout.owner[:, None]  # [M, 1]
    index = jnp.minimum(index, t.shape[1] - 1)
    t_rows = t[owner, index]  # [M, s]
    delta_rows = jnp.where(valid, delta[owner, index], 0.0)  # [M, s]
    ray_dirs = jnp.broadcast_to(directions[layout.owner][:, None, :], (rows, row_length, 3))  # [M, s, 3]
    points = origins[layout.owner][:, None, :] + t_rows[..., None] * ray_dirs  # [M, s, 3]
    sigma, rgb = evaluate(points.reshape(-1, 3), ray_dirs.reshape(-1, 3))
    return packed.composite_rows(
        sigma.reshape(rows, row_length),
        rgb.reshape(rows, row_length, 3),
        t_rows,
        delta_rows,
        layout,
        state.optical_depth,
        shape.max_rows_per_ray,
    )


def _advance(state: _Rays, layout: packed.RowLayout, sums: packed.RowSums, count: Array, row_length: int) -> _Rays:
    """The rays after a pass: samples taken, sums added (`alive` is left to the caller)."""
    rows = layout.owner.shape[0]
    taken = jnp.minimum(layout.granted * row_length, count - state.next_sample)  # [N]
    return state._replace(
        next_sample=state.next_sample + taken,
        optical_depth=state.optical_depth + sums.optical_depth,
        rgb=state.rgb + sums.rgb,
        depth=state.depth + sums.depth,
        acc=state.acc + sums.acc,
        evaluations=state.evaluations + taken,
        passes=state.passes + 1,
        slots=state.slots + rows * row_length,
    )


def _run_passes(shape: BlockShape, count: Array, one_pass: Callable, state, rays: Callable, first_rows: int):
    """Passes over packed rows until no ray is live: one `lax.while_loop` per pass size of `shape.rows`.

    Args:
      shape: the block's sizes. count: int32 [N], samples each ray has.
      one_pass: (rows, layout, state) -> state, one pass of `rows` rows.
      state: the loop state; `rays(state)` is its `_Rays`.
      first_rows: the most rows a ray that has not started may ask for.
    """

    def keep_going(rows: int, last: bool, state) -> Array:
        """Passes of this size go on while rays are live and (but for the smallest size) the live rays'
        requests would fill `level_fill` of the pass; else the next smaller size takes over."""
        going = jnp.any(rays(state).alive) & (rays(state).passes < shape.max_passes)
        if last:
            return going
        return going & (jnp.sum(_requests(shape, rows, rays(state), count, first_rows)) >= shape.level_fill * rows)

    def step(rows: int, state):
        layout = packed.layout_rows(_requests(shape, rows, rays(state), count, first_rows), rows)
        return one_pass(rows, layout, state)

    # One while loop per pass size; each reads its predicate once per pass of millions of slots on an
    # accelerator (see `Packing.for_backend`), and the sizes shrink as the block's work runs out.
    for level, rows in enumerate(shape.rows):
        last = level + 1 == len(shape.rows)
        state = jax.lax.while_loop(functools.partial(keep_going, rows, last), functools.partial(step, rows), state)
    return state


def _start(count: Array) -> _Rays:
    num_rays = count.shape[0]
    zeros = jnp.zeros((num_rays,), jnp.float32)
    return _Rays(
        next_sample=jnp.zeros((num_rays,), jnp.int32),
        alive=count > 0,
        optical_depth=zeros,
        rgb=jnp.zeros((num_rays, 3), jnp.float32),
        depth=zeros,
        acc=zeros,
        evaluations=jnp.zeros((num_rays,), jnp.int32),
        passes=jnp.int32(0),
        slots=jnp.int32(0),
    )


def _composite(
    field: Field,
    shape: BlockShape,
    params,
    origins: Array,
    directions: Array,
    t: Array,
    delta: Array,
    count: Array,
    min_transmittance: Array,
) -> _Rays:
    """The passes of one block: every ray's samples composited until it is done or opaque."""
    evaluate = functools.partial(field_slots, field, params, chunk=shape.field_chunk)

    def one_pass(rows: int, layout: packed.RowLayout, state: _Rays) -> _Rays:
        sums = _pass_rows(evaluate, shape, layout, state, origins, directions, t, delta, count)
        state = _advance(state, layout, sums, count, shape.row_length)
        alive = state.alive & (state.next_sample < count) & (jnp.exp(-state.optical_depth) >= min_transmittance)
        return state._replace(alive=alive)

    return _run_passes(shape, count, one_pass, _start(count), lambda state: state, shape.first_rows)


def _finish(state: _Rays, background: Array):
    """(rgb [N, 3] on the background, depth [N], acc [N], evaluations [N], passes [], slots [])."""
    rgb = state.rgb + (1.0 - state.acc)[:, None] * background
    return rgb, state.depth, state.acc, state.evaluations, state.passes, state.slots


def _composite_forward(field, shape, params, origins, directions, t, delta, count, min_transmittance, background):
    """`_finish(_composite(...))`: differentiable in forward mode only (its `while_loop`s)."""
    return _finish(
        _composite(field, shape, params, origins, directions, t, delta, count, min_transmittance), background
    )


@functools.partial(jax.custom_vjp, nondiff_argnums=(0, 1))
def _composite_reverse(field, shape, params, origins, directions, t, delta, count, min_transmittance, background):
    """`_composite_forward` with a reverse-mode gradient with respect to origins and directions
    (`marched_vjp.composite_vjp`); no forward mode. Other inputs get no gradient."""
    return _composite_forward(field, shape, params, origins, directions, t, delta, count, min_transmittance, background)


def _composite_reverse_fwd(field, shape, params, origins, directions, t, delta, count, min_transmittance, background):
    state = _composite(field, shape, params, origins, directions, t, delta, count, min_transmittance)
    residuals = (
        params,
        origins,
        directions,
        t,
        delta,
        state.next_sample,
        state.rgb,
        state.depth,
        state.acc,
        background,
    )
    return _finish(state, background), residuals


def _composite_reverse_bwd(field, shape, residuals, cotangents):
    params, origins, directions, t, delta, used, rgb, depth, acc, background = residuals
    g_rgb, g_depth, g_acc = cotangents[:3]
    evaluate = functools.partial(field_slots, field, params, chunk=shape.field_chunk)

    def pass_rows(rows, layout, state, o, d):
        return _pass_rows(evaluate, shape, layout, state, o, d, t, delta, used)

    def advance(state, layout, sums):
        state = _advance(state, layout, sums, used, shape.row_length)
        return state._replace(alive=state.next_sample < used)

    # The samples each ray composited (`used`) are known: no ray needs to hold back in its first pass.
    passes = marched_vjp.Passes(pass_rows, advance, functools.partial(_run_passes, shape, used))
    d_origins, d_directions = marched_vjp.composite_vjp(
        passes,
        _start(used),
        origins,
        directions,
        (rgb, depth, acc),
        (g_rgb, g_depth, g_acc),
        background,
        shape.max_rows_per_ray,
    )
    return None, d_origins, d_directions, None, None, None, None, None


_composite_reverse.defvjp(_composite_reverse_fwd, _composite_reverse_bwd)


def _render_block(
    field: Field,
    params,
    grid: occupancy.OccupancyGrid,
    origins: Array,
    directions: Array,
    real: Array,
    render_config: RenderConfig,
    march: marching.MarchConfig,
    shape: BlockShape,
    gradient: str = "forward",
):
    """Renders one block of N rays [N, 3] (`real` [N] False for padding). Returns (RenderOutput [N],
    evaluations int32 [N], passes int32 [], slots int32 []). `gradient`: see `render_marched`."""
    t, delta, count = _march_block(grid, origins, directions, real, render_config, march)
    composite = _composite_reverse if gradient == "reverse" else _composite_forward
    rgb, depth, acc, evaluations, passes, slots = composite(
        field, shape, params, origins, directions, t, delta, count, march.min_transmittance, render_config.background
    )
    return RenderOutput(rgb=rgb, depth=depth, acc=acc), evaluations, passes, slots


def _render(
    field: Field,
    params,
    grid,
    c2w: Array,
    intrinsics: Intrinsics,
    render_config: RenderConfig,
    march: marching.MarchConfig,
    packing: Packing,
    gradient: str = "forward",
) -> MarchedViews:
    """`render_marched` unjitted (for `shard_over_poses`)."""
    c2w = jnp.asarray(c2w, jnp.float32)[:, :3, :4]
    num_poses = c2w.shape[0]
    total = num_poses * intrinsics.height * intrinsics.width
    shape = block_shape(packing, total, march.max_samples)

    def block(ids: Array):
        origins, directions, _, _ = view_rays(c2w, intrinsics, ids)
        out, evaluations, passes, slots = _render_block(
            field, params, grid, origins, directions, ids < total, render_config, march, shape, gradient
        )
        return out, evaluations, jnp.broadcast_to(jnp.stack([passes, slots]), ids.shape + (2,))

    out, evaluations, counts = map_ray_chunks(block, total, shape.rays)
    # Every ray of a block carries its block's counts; one value per block is kept.
    counts = jnp.pad(counts, ((0, (-total) % shape.rays), (0, 0)))[:: shape.rays]  # [num_blocks, 2]
    return MarchedViews(
        output=jax.tree.map(lambda a: to_images(a, num_poses, intrinsics), out),
        evaluations=to_images(evaluations, num_poses, intrinsics),
        passes=counts[:, 0],
        slots=counts[:, 1],
    )


GRADIENTS = ("forward", "reverse")

_render_jit = jax.jit(_render, static_argnames=("field", "packing", "gradient"))


def render_marched(
    field: Field,
    params,
    setup: MarchSetup,
    c2w: Array,
    intrinsics: Intrinsics,
    packing: Optional[Packing] = None,
    gradient: str = "forward",
) -> MarchedViews:
    """Renders P poses of a field through its occupancy grid in one jitted call (see docs/design.md, "Rendering").

    One compilation per (field, packing, grid geometry, march sizes, image size, P), and per gradient mode
    only where the call can be differentiated: a call on concrete arrays (no transformation traces it)
    cannot, so it runs the forward program whatever `gradient` says (the same images; one program, not
    two, for a source's renders outside a search and for held-out views).

    Args:
      field: radiance field for one point, `field(params, x [3], d [3]) -> (sigma [], rgb [3])` (static).
      params: its parameters.
      setup: the occupancy grid, the render config (near, far, box, background) and the march config
        (step, cone angle, K candidates and S samples per ray, `min_transmittance`): `MarchSetup`.
      c2w: [P, 4, 4] or [P, 3, 4] camera-to-world matrices.
      intrinsics: shared intrinsics (their width and height set the image size).
      packing: static sizes (default `Packing.for_backend()`).
      gradient: how the images may be differentiated with respect to c2w (static; the image is the same):
        "forward" (`jax.jvp` through the passes' `while_loop`s; no reverse mode) or "reverse" (`jax.vjp`,
        one backward pass over the samples each ray composited, `render.marched_vjp`; no forward mode).
        Either way the samples move with the rays, their distances along them fixed by the march, and
        nothing is differentiated with respect to params, grid or configs.

    Returns:
      `MarchedViews`: the images and the evaluations and passes they took.
    """
    if gradient not in GRADIENTS:
        raise ValueError(f"render_marched: gradient must be one of {GRADIENTS}, got {gradient!r}")
    if not any(isinstance(leaf, jax.core.Tracer) for leaf in jax.tree.leaves((params, setup, c2w, intrinsics))):
        gradient = "forward"  # nothing traced: no gradient can be taken, and the images are the same
    return _render_jit(
        field,
        params,
        setup.grid,
        c2w,
        intrinsics,
        setup.render_config,
        setup.march,
        packing or Packing.for_backend(),
        gradient,
    )


@functools.lru_cache(maxsize=None)
def _marched_local(field: Field, packing: Packing) -> Callable:
    """The marched renderer in `shard_over_poses`' calling convention (one object per field and packing)."""

    def local(replicated, posed):
        params, grid, intrinsics, render_config, march = replicated
        views = _render(field, params, grid, posed[0], intrinsics, render_config, march, packing)
        return views.output, views.evaluations

    return local


def render_marched_sharded(
    field: Field,
    params,
    setup: MarchSetup,
    c2w: Array,
    intrinsics: Intrinsics,
    packing: Optional[Packing] = None,
    mesh=None,
):
    """`render_marched` with the poses split over the devices of `mesh` (`sharding.shard_over_poses`).

    Returns:
      (`RenderOutput` [P, H, W], evaluations int32 [P, H, W]), sharded over the mesh. Each device packs
      its own poses' rays, so a ray's samples may fall into other passes than on one device: the
      images agree with `render_marched`'s to float32 rounding of the per-pass sums.
    """
    local = _marched_local(field, packing or Packing.for_backend())
    return shard_over_poses(local, (params, setup.grid, intrinsics, setup.render_config, setup.march), c2w, mesh)
