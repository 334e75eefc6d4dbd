"""A batched, differentiable tile renderer for 3D Gaussian splats, in pure JAX.

The semantics are those of the reference 3DGS rasteriser (Kerbl et al. 2023) and gsplat:

  projection   each splat's mean is taken to the camera frame (OpenCV axes: x right, y down, z forward)
               and projected with the pinhole, u = fx x / z + cx (pixel centres at i + 0.5, as everywhere
               in waldo); splats nearer than `near` are culled. Its covariance Sigma = R S S^T R^T goes
               through the perspective Jacobian J (EWA splatting), whose x/z and y/z are clamped to
               +-1.3 tan(fov / 2) so that splats at the border of the view do not blow up, and a 0.3 px^2
               low-pass is added to the 2D covariance's diagonal.
  colour       spherical harmonics at the unit direction from the camera centre to the mean, + 0.5,
               clamped at 0 (`waldo_jax.splats.sh`).
  compositing  alpha = min(0.99, o exp(-d^T Sigma2^-1 d / 2)) at each pixel centre, skipped below 1/255;
               front to back by camera depth; a pixel stops at the splat that would take its
               transmittance below 1e-4 (that splat not included); background times the final
               transmittance added.

Fixed shapes with counted overflow. The image is cut into tiles of `tile_size`^2 pixels. A splat
covers the tiles its exact support touches: the box around the ellipse where its alpha reaches 1/255,
which depends on its opacity (so no splat is cut where it still counts). The (splat, tile) pairs of a
view are made in depth order into `max_pairs` slots and sorted by tile (a stable sort keeps the depth
order inside a tile); each tile composites its nearest splats, all of them or, with `tile_chunks`, its
first `tile_chunks` chunks (a million splats seen at 128 px stack thousands deep in a tile, and the
first few hundred already stop every pixel). Pairs beyond either capacity are dropped, always the
farthest first, and counted in `SplatStats`; `lossy_pixels` counts the pixels that such a drop could
have changed (their transmittance had not reached 1e-4 when their list ended). Nothing is dropped
silently.

Batching: every view of a call runs the same program (`jax.vmap` over poses inside `jax.lax.map` over
groups of `pose_chunk` poses, sized to the memory of an accelerator; one pose a step on a CPU), and
`render_splats_sharded` splits the poses over devices. Everything is differentiable in reverse mode
with respect to the camera pose and the splats' parameters (the tile lists are integer bookkeeping;
the gradient flows through the projected means, covariances, colours and opacities), which is what
`egps+refine` and fitting (`waldo_jax.splats.fit`) use.

Names: N splats, P poses, T tiles of a view, S = tile_size^2 pixels of a tile, C = tile_capacity.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from typing import Optional, Tuple

import flax.struct
import jax
import jax.numpy as jnp
import numpy as np

from waldo_jax.render.sharding import shard_over_poses
from waldo_jax.splats.composite import ChunkSplats, composite_chunks
from waldo_jax.splats.model import Splats
from waldo_jax.splats.sh import sh_to_rgb
from waldo_jax.types import Array, Intrinsics

__all__ = [
    "SplatRenderConfig",
    "SplatStats",
    "SplatRenderOutput",
    "Projected",
    "project",
    "quat_to_rotmat",
    "tile_lists",
    "render_view",
    "render_splats",
    "render_splats_sharded",
    "render_splats_on_devices",
    "default_pose_chunk",
    "count_pairs",
    "depth_order",
]

# Elements of the compositing arrays (a few [chunks, pixels] per view) one step of the pose loop may
# hold: 2^24 (64 MiB of float32) on a CPU, 2^27 on an accelerator.
_CHUNK_ELEMENTS = {"cpu": 2**24}
_CHUNK_ELEMENTS_ACCELERATOR = 2**27
# Floats per splat that one view's projection and depth sort hold at once (the projected rows, the
# covariance's matrices, the SH basis, the sort's keys and indices; measured: 1M splats of SH degree
# 3 took 4.5 GiB for 24 views projected together, ~48 floats per splat and view).
_SPLAT_FLOATS_PER_VIEW = 48


@dataclasses.dataclass(frozen=True)
class SplatRenderConfig:
    """Static settings of the splat renderer (hashable: part of the jit's static configuration).

    Attributes:
      tile_size: tile side in pixels.
      chunk: splats composited together (B): a tile's depth-ordered list is cut into chunks of this many.
      max_pairs: (splat, tile) pairs a view may hold; more are dropped (farthest splats first) and counted.
        The work of a view is about (max_pairs + T * chunk) * tile_size^2 alpha evaluations, whatever
        the view needs: size it to the scene (`waldo_jax.splats.source` calibrates it).
      near: splats whose camera depth is at most this are culled (scene units).
      background: colour behind the splats (used when the call passes no `background`).
      pose_chunk: poses rendered per step of the pose loop (None: as many as the backend's memory
        budget allows for this image size, `default_pose_chunk`).
      low_pass: added to the 2D covariance's diagonal, px^2 (the reference's 0.3).
      jacobian_clamp: x/z and y/z of the EWA Jacobian are clamped to +-jacobian_clamp * tan(fov / 2).
      alpha_min: alphas below this are skipped (the reference's 1/255).
      alpha_max: alphas are clamped to this (0.99).
      min_transmittance: a pixel ends at the splat that would take its transmittance below this (1e-4).
      tile_chunks: at most this many chunks per tile (the nearest), or None for every chunk. The
        compositing work becomes about T * tile_chunks * chunk * tile_size^2 alpha evaluations; pairs
        beyond are dropped and counted (`SplatStats.tile_dropped`, `lossy_pixels`). A source sets it
        from the chunks its training views need before every pixel stops (`SplatStats.needed_chunks`).
      custom_gradient: differentiate the compositing by its hand-written reverse-mode rule
        (`waldo_jax.splats.composite`; reverse mode only), or by JAX's own rules (forward mode too).
    """

    tile_size: int = 8
    chunk: int = 32
    max_pairs: int = 2**16
    near: float = 0.01
    background: Tuple[float, float, float] = (0.0, 0.0, 0.0)
    pose_chunk: Optional[int] = None
    low_pass: float = 0.3
    jacobian_clamp: float = 1.3
    alpha_min: float = 1.0 / 255.0
    alpha_max: float = 0.99
    min_transmittance: float = 1e-4
    tile_chunks: Optional[int] = None
    custom_gradient: bool = True

    def __post_init__(self):
        for name in ("tile_size", "chunk", "max_pairs"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ValueError(f"SplatRenderConfig.{name} must be an int >= 1, got {value!r}")
        if self.tile_chunks is not None and (
            isinstance(self.tile_chunks, bool) or not isinstance(self.tile_chunks, int) or self.tile_chunks < 1
        ):
            raise ValueError(f"SplatRenderConfig.tile_chunks must be None or an int >= 1, got {self.tile_chunks!r}")
        if self.pose_chunk is not None and (not isinstance(self.pose_chunk, int) or self.pose_chunk < 1):
            raise ValueError(f"SplatRenderConfig.pose_chunk must be None or an int >= 1, got {self.pose_chunk!r}")
        if not (math.isfinite(self.near) and self.near > 0):
            raise ValueError(f"SplatRenderConfig.near must be a finite number > 0, got {self.near!r}")
        if len(self.background) != 3 or not all(math.isfinite(float(c)) for c in self.background):
            raise ValueError(f"SplatRenderConfig.background must be 3 finite numbers, got {self.background!r}")

    def tiles(self, intrinsics: Intrinsics) -> Tuple[int, int]:
        """(tiles across, tiles down) of an image of `intrinsics`' size."""
        return -(-intrinsics.width // self.tile_size), -(-intrinsics.height // self.tile_size)

    def chunk_slots(self, intrinsics: Intrinsics) -> int:
        """Chunks a view may use (K): every tile's last chunk may be part-full, so max_pairs / chunk + T;
        with `tile_chunks`, at most T * tile_chunks."""
        tiles_x, tiles_y = self.tiles(intrinsics)
        slots = -(-self.max_pairs // self.chunk) + tiles_x * tiles_y
        return slots if self.tile_chunks is None else min(slots, tiles_x * tiles_y * self.tile_chunks)


@flax.struct.dataclass
class SplatStats:
    """What a render dropped and how full its capacities were, per view (int32 [P] each).

    Attributes:
      visible: splats in front of the near plane, on screen, with alpha that can reach 1/255.
      pairs: (splat, tile) pairs the view needed.
      pair_overflow: pairs beyond `max_pairs`, dropped (the farthest splats' first).
      chunks: chunks the view used (of `chunk_slots`).
      max_tile_count: the most pairs one tile held.
      lossy_pixels: pixels an overflow may have changed: those of tiles that lost pairs whose
        transmittance had not reached `min_transmittance` (0 means none changed).
      tile_dropped: pairs beyond `tile_chunks` (the farthest of their tile), not composited.
      needed_chunks: the most chunks a tile needed: through the last of its chunks that added weight to
        any of its pixels (after it every pixel had stopped or lay outside every later splat's
        support). What `tile_chunks` must hold for this view to lose nothing.
    """

    visible: Array
    pairs: Array
    pair_overflow: Array
    chunks: Array
    max_tile_count: Array
    lossy_pixels: Array
    tile_dropped: Array
    needed_chunks: Array


@flax.struct.dataclass
class SplatRenderOutput:
    """rgb [P, H, W, 3], depth [P, H, W] (alpha-weighted camera depth, 0 where empty), acc [P, H, W]
    (accumulated opacity) and the per-view `SplatStats`."""

    rgb: Array
    depth: Array
    acc: Array
    stats: SplatStats


@flax.struct.dataclass
class Projected:
    """The splats as one view sees them (N rows, float32 unless said).

    Attributes:
      mean2d: [N, 2] projected centre in pixels.
      conic: [N, 3] (a, b, c) of the inverse 2D covariance [[a, b], [b, c]].
      depth: [N] camera depth z.
      opacity: [N] sigmoid of the logit.
      rgb: [N, 3] colour from the SH at this view's direction.
      extent: [N, 2] half sides of the box (px) outside which the splat's alpha stays below alpha_min.
      visible: bool [N] in front of the near plane, finite and able to reach alpha_min.
    """

    mean2d: Array
    conic: Array
    depth: Array
    opacity: Array
    rgb: Array
    extent: Array
    visible: Array


def quat_to_rotmat(quat: Array) -> Array:
    """Rotation matrices [..., 3, 3] of unit quaternions (w, x, y, z) [..., 4]."""
    w, x, y, z = quat[..., 0], quat[..., 1], quat[..., 2], quat[..., 3]
    rows = [
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ]
    return jnp.stack([jnp.stack(r, axis=-1) for r in rows], axis=-2)


def world_to_camera(c2w: Array) -> Tuple[Array, Array]:
    """(rotation [3, 3] world -> OpenCV camera axes, camera centre [3]) of an OpenGL c2w [3 or 4, 4]."""
    flip = jnp.array([1.0, -1.0, -1.0], jnp.float32)
    return c2w[:3, :3].T * flip[:, None], c2w[:3, 3]


def project(splats: Splats, c2w: Array, intrinsics: Intrinsics, config: SplatRenderConfig) -> Projected:
    """Projects every splat into one view (EWA splatting; see the module docstring).

    Args:
      splats: N splats.
      c2w: [3 or 4, 4] OpenGL camera-to-world matrix.
      intrinsics: the pinhole (its distortion is not applied: splats are rendered undistorted).
      config: the renderer's settings.

    Returns:
      `Projected` with N rows.
    """
    w2c, centre = world_to_camera(c2w)
    offset = splats.means - centre  # [N, 3]
    p = offset @ w2c.T  # [N, 3] camera frame (OpenCV)
    x, y, z = p[:, 0], p[:, 1], p[:, 2]
    in_front = z > config.near
    z = jnp.where(in_front, z, 1.0)  # culled rows keep finite values (and gradients)
    fx, fy, cx, cy = intrinsics.fx, intrinsics.fy, intrinsics.cx, intrinsics.cy
    mean2d = jnp.stack([fx * x / z + cx, fy * y / z + cy], axis=-1)  # [N, 2]

    rot = quat_to_rotmat(splats.rotations())  # [N, 3, 3]
    m = rot * splats.scales()[:, None, :]  # R diag(s): Sigma = m m^T
    lim_x = config.jacobian_clamp * intrinsics.width / (2.0 * fx)
    lim_y = config.jacobian_clamp * intrinsics.height / (2.0 * fy)
    tx = z * jnp.clip(x / z, -lim_x, lim_x)
    ty = z * jnp.clip(y / z, -lim_y, lim_y)
    zero = jnp.zeros_like(z)
    jac = jnp.stack(
        [jnp.stack([fx / z, zero, -fx * tx / (z * z)], -1), jnp.stack([zero, fy / z, -fy * ty / (z * z)], -1)], axis=-2
    )  # [N, 2, 3]
    # Sigma2 = A A^T with A = J W R diag(s) [N, 2, 3]. Its determinant is the sum of A's squared 2x2
    # minors (Cauchy-Binet): no cancellation for needle-like splats, where a c - b^2 loses float32.
    a_mat = jac @ w2c @ m  # [N, 2, 3]
    r0, r1 = a_mat[:, 0], a_mat[:, 1]
    a0, c0, b = jnp.sum(r0 * r0, -1), jnp.sum(r1 * r1, -1), jnp.sum(r0 * r1, -1)
    minors = jnp.cross(r0, r1)  # [N, 3] the 2x2 minors of A
    lp = config.low_pass
    a, c = a0 + lp, c0 + lp
    det = jnp.sum(minors * minors, -1) + lp * (a0 + c0) + lp * lp
    ok = det > 0
    det = jnp.where(ok, det, 1.0)
    conic = jnp.stack([c / det, -b / det, a / det], axis=-1)  # [N, 3]

    opacity = splats.opacities()
    # The support: alpha = o exp(-q / 2) >= alpha_min <=> q <= 2 log(o / alpha_min); its bounding box
    # has half sides sqrt(q_max * Sigma_xx), sqrt(q_max * Sigma_yy) (slightly grown against rounding).
    q_max = _support_q(opacity, config)
    extent = jnp.sqrt(jnp.stack([q_max * jax.lax.stop_gradient(a), q_max * jax.lax.stop_gradient(c)], -1)) + 1e-3

    # A safe norm: a mean at the camera centre gives a finite direction and gradient, not 0 * inf.
    direction = offset * jax.lax.rsqrt(jnp.maximum(jnp.sum(offset * offset, -1, keepdims=True), 1e-24))
    rgb = sh_to_rgb(splats.sh, direction)  # [N, 3]
    finite = jnp.all(jnp.isfinite(mean2d), -1) & jnp.all(jnp.isfinite(conic), -1) & jnp.all(jnp.isfinite(rgb), -1)
    visible = splats.valid & in_front & ok & (opacity >= config.alpha_min) & finite
    return Projected(
        mean2d=mean2d, conic=conic, depth=p[:, 2], opacity=opacity, rgb=rgb, extent=extent, visible=visible
    )


def _tile_spans(projected: Projected, intrinsics: Intrinsics, config: SplatRenderConfig):
    """Each splat's tiles: first and last tile (x, y) int32 [N, 2] each, tiles covered int32 [N]
    (0 when off screen or not visible) and whether it is on screen, bool [N]."""
    tiles_x, tiles_y = config.tiles(intrinsics)
    ts = float(config.tile_size)
    lo = jnp.floor((projected.mean2d - projected.extent) / ts)  # [N, 2] unclipped
    hi = jnp.floor((projected.mean2d + projected.extent) / ts)
    limit = jnp.array([tiles_x - 1, tiles_y - 1], jnp.float32)
    visible = projected.visible & jnp.all((hi >= 0) & (lo <= limit), axis=-1)
    lo = jnp.clip(lo, 0, limit).astype(jnp.int32)
    hi = jnp.clip(hi, 0, limit).astype(jnp.int32)
    span = hi - lo + 1
    return lo, hi, jnp.where(visible, span[:, 0] * span[:, 1], 0), visible


def count_pairs(splats: Splats, c2w: Array, intrinsics: Intrinsics, config: SplatRenderConfig) -> Array:
    """The (splat, tile) pairs each of P views needs, int32 [P]: what `max_pairs` must hold for them
    (the projection alone, no sorting or compositing)."""

    def one(pose):
        return jnp.sum(_tile_spans(project(splats, pose, intrinsics, config), intrinsics, config)[2])

    c2w = jnp.asarray(c2w, jnp.float32)[:, :3, :4]
    budget = _CHUNK_ELEMENTS.get(jax.default_backend(), _CHUNK_ELEMENTS_ACCELERATOR)
    batch = max(1, min(c2w.shape[0], 64, budget // max(1, splats.count * _SPLAT_FLOATS_PER_VIEW)))
    return jax.lax.map(one, c2w, batch_size=batch)


def tile_lists(projected: Projected, intrinsics: Intrinsics, config: SplatRenderConfig):
    """Each tile's splats, nearest first, cut into chunks of `chunk` splats in a fixed number of slots.

    The (splat, tile) pairs are made in depth order into `max_pairs` slots (those beyond are the
    farthest splats' and are dropped) and sorted by tile, stably, so each tile's run of pairs is in
    depth order; a pair whose tile no pixel of the splat's support reaches (`_reaches_tile`) sorts
    behind the lists with the unused slots. The runs are cut into chunks, tile by tile; `chunk_slots`
    (max_pairs / chunk + T) holds every chunk of any view whose pairs fit.

    Returns:
      ids: int32 [K, B] splat index of each chunk's slots (K = chunk_slots, B = chunk).
      filled: bool [K, B] whether the slot holds a splat.
      tile: int32 [K] the tile of each chunk (T for unused chunks).
      first: bool [K] whether the chunk is its tile's first (unused chunks count as first).
      last: int32 [T] each tile's last chunk (-1 when the tile has none).
      counts: int32 [T] pairs each tile holds (before `tile_chunks`).
      lost: bool [T] tiles that lost pairs to `max_pairs` or `tile_chunks`.
      level: int32 [K] each chunk's place in its tile's list (0 for its first).
      pairs: int32 [] pairs the view needed (the first `max_pairs` were made).
      visible: int32 [] splats on screen.
    """
    tiles_x, tiles_y = config.tiles(intrinsics)
    num_tiles = tiles_x * tiles_y
    lo, hi, n_tiles, visible = _tile_spans(projected, intrinsics, config)
    span = hi - lo + 1  # [N, 2]

    # Pairs in depth order, so that those beyond max_pairs are the farthest splats'.
    order = depth_order(jnp.where(visible, projected.depth, jnp.inf))  # [N]
    ends = jnp.cumsum(n_tiles[order])  # [N] inclusive
    pairs = ends[-1]
    slot = jnp.arange(config.max_pairs, dtype=jnp.int32)
    # The rank (depth order) of each pair slot's splat: each splat marks the slot where its run of pairs
    # starts and a running maximum fills the run (cheaper than a binary search per slot).
    n_sorted = n_tiles[order]
    starts = jnp.where(n_sorted > 0, ends - n_sorted, config.max_pairs)  # [N]
    marks = (
        jnp.zeros(config.max_pairs, jnp.int32).at[starts].max(jnp.arange(order.shape[0], dtype=jnp.int32), mode="drop")
    )
    rank = jax.lax.cummax(marks)  # [max_pairs]
    splat = order[rank]
    local = slot - (ends[rank] - n_sorted[rank])
    width = span[splat, 0]
    pair_x, pair_y = lo[splat, 0] + local % width, lo[splat, 1] + local // width
    # Unused slots sort last, and so do the pairs whose tile holds no pixel centre inside the splat's
    # support (the corner tiles of a tilted or round splat's box), which would composite nothing there.
    # (One gather per field, each fused into the test: a table of them gathered as rows was slower.)
    support = (*projected.mean2d.T, *projected.conic.T, _support_q(projected.opacity, config))
    keep = (slot < pairs) & _reaches_tile(jax.lax.stop_gradient(support), splat, pair_x, pair_y, config.tile_size)
    pair_tile = jnp.where(keep, pair_y * tiles_x + pair_x, num_tiles)
    pair_tile, rank = _sort_by_tile(pair_tile, rank, num_tiles, config.max_pairs)

    tile_ids = jnp.arange(num_tiles, dtype=jnp.int32)
    start = jnp.searchsorted(pair_tile, tile_ids, side="left").astype(jnp.int32)
    counts = jnp.searchsorted(pair_tile, tile_ids, side="right").astype(jnp.int32) - start  # [T]
    b = config.chunk
    n_chunks = (counts + b - 1) // b
    if config.tile_chunks is not None:
        n_chunks = jnp.minimum(n_chunks, config.tile_chunks)  # the nearest chunks; the rest are counted
    chunk_end = jnp.cumsum(n_chunks)  # [T] inclusive
    k = jnp.arange(config.chunk_slots(intrinsics), dtype=jnp.int32)
    used = k < chunk_end[-1]
    tile = jnp.minimum(jnp.searchsorted(chunk_end, k, side="right"), num_tiles - 1).astype(jnp.int32)
    level = k - (chunk_end[tile] - n_chunks[tile])
    index = (start[tile] + level * b)[:, None] + jnp.arange(b, dtype=jnp.int32)[None, :]  # [K, B]
    filled = used[:, None] & (index < (start + counts)[tile][:, None])
    ids = jnp.where(filled, order[rank[jnp.clip(index, 0, config.max_pairs - 1)]], 0)
    last = jnp.where(n_chunks > 0, chunk_end - 1, -1)
    # The tiles that lost pairs: those under the boxes of the splats whose pairs did not all fit
    # (a 2D difference array over the tiles, scattered and summed; integers, so in any order exactly).
    inverse = jnp.zeros_like(order).at[order].set(jnp.arange(order.shape[0], dtype=jnp.int32))
    cut = visible & (ends[inverse] > config.max_pairs)  # [N], in splat order
    corners = jnp.stack(
        [lo[:, 1], lo[:, 0], lo[:, 1], hi[:, 0] + 1, hi[:, 1] + 1, lo[:, 0], hi[:, 1] + 1, hi[:, 0] + 1], -1
    ).reshape(-1, 4, 2)  # [N, 4, (row, column)]
    signs = jnp.array([1, -1, -1, 1], jnp.int32)
    marks = (
        jnp.zeros((tiles_y + 1, tiles_x + 1), jnp.int32)
        .at[corners[..., 0], corners[..., 1]]
        .add(jnp.where(cut[:, None], signs, 0))
    )
    lost = (jnp.cumsum(jnp.cumsum(marks, 0), 1)[:tiles_y, :tiles_x] > 0).reshape(-1)  # [T]
    lost = lost | (counts > n_chunks * b)
    return (
        ids,
        filled,
        jnp.where(used, tile, num_tiles),
        (level == 0) | ~used,
        last,
        counts,
        lost,
        pairs,
        jnp.sum(visible).astype(jnp.int32),
        jnp.where(used, level, 0),
    )


def _reaches_tile(support, splat: Array, tile_x: Array, tile_y: Array, tile_size: int) -> Array:
    """bool [M]: whether splat `splat[m]` may reach alpha_min at a pixel centre of tile (tile_x[m],
    tile_y[m]). `support`: the splats' mean2d x and y, conic a, b, c and support bound q_max
    (`_support_q`), six arrays [N]. The test: the least q = d^T conic d over the rectangle of the
    tile's pixel centres (d from the mean) is at most q_max. A convex q's least value on a rectangle
    not holding its minimum (the mean) lies on an edge, where it is a parabola: four clamped minima.
    Conservative: q_max carries the projection's margin and a little more, so no pair whose alpha
    reaches alpha_min at a pixel is left out (the compositing skips the same alphas)."""
    mx, my, a, b, c, q_max = (column[splat] for column in support)
    ts = float(tile_size)
    x0 = tile_x.astype(jnp.float32) * ts + 0.5 - mx
    y0 = tile_y.astype(jnp.float32) * ts + 0.5 - my
    x1, y1 = x0 + (ts - 1.0), y0 + (ts - 1.0)
    a = jnp.maximum(a, 1e-30)
    c = jnp.maximum(c, 1e-30)

    def q(dx, dy):
        return a * dx * dx + 2.0 * b * dx * dy + c * dy * dy

    least = jnp.minimum(
        jnp.minimum(q(x0, jnp.clip(-b * x0 / c, y0, y1)), q(x1, jnp.clip(-b * x1 / c, y0, y1))),
        jnp.minimum(q(jnp.clip(-b * y0 / a, x0, x1), y0), q(jnp.clip(-b * y1 / a, x0, x1), y1)),
    )
    holds_mean = (x0 <= 0.0) & (x1 >= 0.0) & (y0 <= 0.0) & (y1 >= 0.0)
    return holds_mean | (least <= q_max + 1e-3)


def _support_q(opacity: Array, config: SplatRenderConfig) -> Array:
    """q_max [N]: alpha = o exp(-q / 2) >= alpha_min <=> q <= 2 log(o / alpha_min) (slightly grown
    against rounding)."""
    q_max = jax.lax.stop_gradient(2.0 * jnp.log(jnp.maximum(opacity, 1e-30) / config.alpha_min))
    return jnp.maximum(q_max, 0.0) * 1.0001


def _sortable_bits(x: Array) -> Array:
    """uint32 [N] whose unsigned order is the float order of x [N] (-0 and +0 equal, as argsort's)."""
    x = x.astype(jnp.float32)
    bits = jax.lax.bitcast_convert_type(jnp.where(x == 0.0, 0.0, x), jnp.uint32)
    negative = (bits >> 31) == 1
    return jnp.where(negative, ~bits, bits | jnp.uint32(0x80000000))


def depth_order(depth: Array, backend: Optional[str] = None) -> Array:
    """The stable argsort of depth [N] (float32), int32 [N].

    On a CPU, XLA sorts one uint32 operand about eight times faster than a (key, index) pair (1M
    floats: 80 ms against 720 ms on the 2-core development CPU), so the order is built there by an LSD
    radix sort whose passes are such single-operand sorts: each sorts (digit << b) | position, b =
    the bits of an index, by the next digit of the keys' sortable bits; a pass is stable since the
    position breaks its ties. ceil(32 / (32 - b)) passes: 3 for a million splats. Elsewhere `argsort`.
    The two give the same permutation (tested).
    """
    n = depth.shape[0]
    backend = jax.default_backend() if backend is None else backend
    index_bits = max(1, int(n - 1).bit_length())
    if backend != "cpu" or index_bits > 24:
        return jnp.argsort(depth, stable=True).astype(jnp.int32)
    digit_bits = 32 - index_bits
    keys = _sortable_bits(depth)
    position = jnp.arange(n, dtype=jnp.uint32)
    order = jnp.arange(n, dtype=jnp.int32)
    for shift in range(0, 32, digit_bits):
        digit = (keys[order] >> shift) & jnp.uint32((1 << min(digit_bits, 32 - shift)) - 1)
        packed = jax.lax.sort((digit << index_bits) | position)
        order = order[(packed & jnp.uint32((1 << index_bits) - 1)).astype(jnp.int32)]
    return order


def _sort_by_tile(pair_tile: Array, rank: Array, num_tiles: int, max_pairs: int) -> Tuple[Array, Array]:
    """The pairs sorted by tile, stably (so in depth order within a tile): (tiles, ranks) [max_pairs].

    One int32 key tile * max_pairs + slot when it fits (a single-operand sort is about three times
    faster than a stable two-operand one on a CPU), else the stable sort of (tile, rank).
    """
    if (num_tiles + 1) * max_pairs < 2**31:
        slot = jnp.arange(max_pairs, dtype=jnp.int32)
        key = jax.lax.sort(pair_tile * max_pairs + slot)
        return key // max_pairs, rank[key % max_pairs]
    return jax.lax.sort((pair_tile, rank), num_keys=1, is_stable=True)


def _pixel_offsets(tile_size: int) -> np.ndarray:
    """Pixel centres of a tile relative to its corner, [S, 2] (x, y), row-major."""
    j, i = np.meshgrid(np.arange(tile_size), np.arange(tile_size), indexing="ij")
    return np.stack([i.reshape(-1), j.reshape(-1)], -1).astype(np.float32) + 0.5


def render_view(
    splats: Splats,
    c2w: Array,
    intrinsics: Intrinsics,
    config: SplatRenderConfig,
    background: Optional[Array] = None,
    mean2d_offset: Optional[Array] = None,
):
    """Renders one view.

    Every chunk is composited on its own, in parallel; the chunks of a tile are then chained in
    depth order: the transmittance entering a chunk is the product of its tile's earlier chunks'
    transmittances (a segmented product, computed without the early stop, which is exact wherever the
    stop has not happened yet), a splat is kept while the transmittance after it stays at or above
    `min_transmittance`, and the kept weights are summed per tile (a segmented sum).

    Args:
      splats: N splats.
      c2w: [3 or 4, 4] OpenGL camera-to-world matrix.
      intrinsics: the pinhole and image size.
      config: the renderer's settings.
      background: [3] colour behind the splats (default `config.background`).
      mean2d_offset: [N, 2] added to the projected means (zeros: the gradient with respect to it is the
        view-space positional gradient fitting densifies by), or None.

    Returns:
      (rgb [H, W, 3], depth [H, W], acc [H, W], `SplatStats` of scalars).
    """
    bg = jnp.asarray(config.background if background is None else background, jnp.float32)
    projected = project(splats, c2w, intrinsics, config)
    if mean2d_offset is not None:
        projected = projected.replace(mean2d=projected.mean2d + mean2d_offset)
    ids, filled, tile, first, last, counts, lost, pairs, visible, level = tile_lists(projected, intrinsics, config)
    tiles_x, tiles_y = config.tiles(intrinsics)
    ts = config.tile_size
    tile_y, tile_x = jnp.divmod(jnp.minimum(tile, tiles_x * tiles_y - 1), tiles_x)
    corners = jnp.stack([tile_x, tile_y], -1).astype(jnp.float32) * ts  # [K, 2]
    pixels = corners[:, None, :] + _pixel_offsets(ts)[None]  # [K, S, 2]
    # One table row per splat (mean2d, conic, opacity, then the values r, g, b, 1, depth it adds),
    # gathered once: one random read per pair, not one per field.
    table = jnp.concatenate(
        [
            projected.mean2d,
            projected.conic,
            projected.opacity[:, None],
            projected.rgb,
            jnp.ones_like(projected.depth)[:, None],
            projected.depth[:, None],
        ],
        axis=-1,
    )  # [N, 11]
    values, leaving = composite_chunks(
        pixels,
        first,
        ChunkSplats(table, filled, ids),  # gathered where composited
        config.alpha_min,
        config.alpha_max,
        config.min_transmittance,
        config.custom_gradient,
    )  # [K, S, 5], [K, S]
    leaving = jax.lax.stop_gradient(leaving)
    # Summed per tile (chunks are in tile order; integer-free sums over a sorted segment, in a fixed order).
    per_tile = jax.ops.segment_sum(values, tile, num_segments=tiles_x * tiles_y + 1, indices_are_sorted=True)[
        :-1
    ]  # [T, S, 5]
    acc = per_tile[..., 3]
    transmittance = jnp.maximum(1.0 - acc, 0.0)
    colour = per_tile[..., :3] + transmittance[..., None] * bg

    pair_overflow = jnp.maximum(pairs - config.max_pairs, 0)
    pixel_corners = jnp.stack(jnp.divmod(jnp.arange(tiles_x * tiles_y), tiles_x)[::-1], -1).astype(jnp.float32) * ts
    # A pixel an overflow could change had not stopped when its list ended: the transmittance leaving its
    # tile's last chunk, carried without the stop, is still >= min_transmittance.
    open_end = jnp.where((last >= 0)[:, None], leaving[jnp.maximum(last, 0)], 1.0) >= config.min_transmittance
    lossy = jnp.sum(lost[:, None] & open_end & _inside(intrinsics, config, pixel_corners))
    # Chunks each tile needed: through its last chunk that added any weight to any pixel (after it,
    # every pixel had stopped or lay outside every later splat's support: dropping them changes nothing).
    num_tiles = tiles_x * tiles_y
    tile_chunks = jnp.where(last >= 0, level[jnp.maximum(last, 0)] + 1, 0)  # [T] chunks composited
    adds = (tile < num_tiles) & jnp.any(jax.lax.stop_gradient(values[..., 3]) > 0.0, axis=-1)  # [K]
    needed = jax.ops.segment_max(jnp.where(adds, level + 1, 0), tile, num_segments=num_tiles + 1)[:-1]  # [T]
    stats = SplatStats(
        visible=visible,
        pairs=pairs.astype(jnp.int32),
        pair_overflow=pair_overflow.astype(jnp.int32),
        chunks=jnp.sum(tile < num_tiles).astype(jnp.int32),
        max_tile_count=jnp.max(counts).astype(jnp.int32),
        lossy_pixels=lossy.astype(jnp.int32),
        tile_dropped=jnp.sum(jnp.maximum(counts - config.chunk * tile_chunks, 0)).astype(jnp.int32),
        needed_chunks=jnp.maximum(jnp.max(needed), 0).astype(jnp.int32),  # segment_max of none: int32 min
    )

    def image(a):  # [T, S, ...] -> [H, W, ...]
        a = a.reshape((tiles_y, tiles_x, ts, ts) + a.shape[2:])
        a = jnp.swapaxes(a, 1, 2).reshape((tiles_y * ts, tiles_x * ts) + a.shape[4:])
        return a[: intrinsics.height, : intrinsics.width]

    return image(colour), image(per_tile[..., 4]), image(acc), stats


def _inside(intrinsics: Intrinsics, config: SplatRenderConfig, corners: Array) -> Array:
    """bool [T, S]: which pixels of each tile lie inside the image (the last tiles may overhang it)."""
    pixels = corners[:, None, :] + _pixel_offsets(config.tile_size)[None]
    return (pixels[..., 0] < intrinsics.width) & (pixels[..., 1] < intrinsics.height)


def default_pose_chunk(
    intrinsics: Intrinsics, config: SplatRenderConfig, backend: Optional[str] = None, splats: int = 0
) -> int:
    """Poses per step of the pose loop. On a CPU one: the compositing then runs as a loop over blocks
    of chunks that passes over empty ones (`waldo_jax.splats.composite`), which a vmap over poses
    would turn into work on every block (measured on the 2-core CPU, 10k splats at 64 px: 48 views/s
    one pose a step, 13 with 7 poses vmapped). Elsewhere as many as keep their compositing arrays
    ([K, S] a few times) and their projections of `splats` splats within the backend's budget."""
    backend = jax.default_backend() if backend is None else backend
    if backend == "cpu":
        return 1
    budget = _CHUNK_ELEMENTS.get(backend, _CHUNK_ELEMENTS_ACCELERATOR)
    # A view's forward pass holds a few [K, S] arrays and the [K, S, 5] sums (the scans keep no [K, S, B]).
    per_pose = config.chunk_slots(intrinsics) * config.tile_size**2 * 16 + splats * _SPLAT_FLOATS_PER_VIEW
    return max(1, budget // per_pose)


def render_splats(
    splats: Splats, c2w: Array, intrinsics: Intrinsics, config: SplatRenderConfig, background: Optional[Array] = None
) -> SplatRenderOutput:
    """Renders P poses in one program: `render_view` vmapped over groups of `pose_chunk` poses (a plain
    loop when that is 1).

    Args:
      splats: N splats (replicated over the poses).
      c2w: [P, 3 or 4, 4] OpenGL camera-to-world matrices.
      intrinsics: the camera of every view.
      config: the renderer's settings.
      background: [3] colour behind the splats (default `config.background`).

    Returns:
      `SplatRenderOutput` with rgb [P, H, W, 3], depth and acc [P, H, W], stats of [P] each.
    """
    chunk = config.pose_chunk or default_pose_chunk(intrinsics, config, splats=splats.count)
    c2w = jnp.asarray(c2w, jnp.float32)[:, :3, :4]
    chunk = min(chunk, c2w.shape[0])

    def one(pose):
        rgb, depth, acc, stats = render_view(splats, pose, intrinsics, config, background)
        return SplatRenderOutput(rgb=rgb, depth=depth, acc=acc, stats=stats)

    # One pose a step: no vmap, so that the compositing's passes over empty blocks stay skipped.
    return jax.lax.map(one, c2w, batch_size=chunk if chunk > 1 else None)


def _render_local(config: SplatRenderConfig, replicated, posed):
    splats, intrinsics, background = replicated
    c2w, _ = posed
    return render_splats(splats, c2w, intrinsics, config, background)


@functools.lru_cache(maxsize=None)
def _local_fn(config: SplatRenderConfig):
    return functools.partial(_render_local, config)


def render_splats_sharded(
    splats: Splats,
    c2w: Array,
    intrinsics: Intrinsics,
    config: SplatRenderConfig,
    background: Optional[Array] = None,
    mesh=None,
) -> SplatRenderOutput:
    """`render_splats` with the poses split over the devices of `mesh` (default: all local devices).

    The splats are replicated; each device renders its poses with the same program, so the images
    equal the single-device ones. Multi-host: see `waldo_jax.render.sharding.shard_over_poses`.
    """
    bg = jnp.asarray(config.background if background is None else background, jnp.float32)
    return shard_over_poses(_local_fn(config), (splats, intrinsics, bg), c2w, mesh)


def render_splats_on_devices(
    splats: Splats, c2w: Array, intrinsics: Intrinsics, config: SplatRenderConfig, background: Optional[Array] = None
) -> SplatRenderOutput:
    """`render_splats` with the poses split over the local devices where there are several
    (`render_splats_sharded`; a CPU has one per core, `waldo_jax._xla_flags`), else `render_splats`. Each
    pose is rendered by the same per-view program either way, so the images are the same."""
    if jax.local_device_count() > 1:
        return render_splats_sharded(splats, c2w, intrinsics, config, background)
    return render_splats(splats, c2w, intrinsics, config, background)
