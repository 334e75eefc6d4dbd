"""Packed rows: the samples of many rays laid out in a fixed budget of field evaluations, composited
with plain cumulative sums (Instant-NGP's compacted samples; nerfacc's packed samples).

`layout_rows` lays the rays out one after another in a budget of M rows of s slots, each ray owning
the rows it asked for while they fit; `composite_rows` evaluates the quadrature of
`waldo_jax.render.volume` on them, a `cumsum` within a row and a segmented scan across a ray's rows
(Hillis-Steele shifted adds), from the optical depth `carry` each ray brings from earlier passes. A
ray's sums are gathered from its last row: no scatter-add, no [rays x max samples] array, no padding
that collects gradients. Shared by the marched renderer and training.

The layout, the compositing formula and the names (`M`, `s`, `N`, `owner`, `rank`, `tau`): see
docs/design.md, section "Rendering > Packed rows"; why packed rows: docs/rendering.md.
"""

from __future__ import annotations

import math
from typing import NamedTuple, Tuple

import jax
import jax.numpy as jnp

from waldo_jax.render.volume import MAX_DENSITY
from waldo_jax.types import Array

__all__ = ["RowLayout", "RowSums", "composite_rows", "gather_rows", "layout_rows", "row_samples", "segment_cumsum"]


class RowLayout(NamedTuple):
    """Where each ray's rows sit in a budget of M rows (see docs/design.md, "Rendering").

    Attributes:
      owner: int32 [M], the ray of each row (a valid ray index for unused rows too).
      rank: int32 [M], the row's index among its ray's rows (0 for a ray's first row).
      used: bool [M], rows that hold a ray.
      start: int32 [N], each ray's first row.
      granted: int32 [N], rows each ray got (0 for rays that asked for none or did not fit).
      last: int32 [N], each ray's last row, or M (out of range: gathers give 0) for rays with none.
    """

    owner: Array
    rank: Array
    used: Array
    start: Array
    granted: Array
    last: Array


def layout_rows(rows: Array, num_rows: int) -> RowLayout:
    """Lays out requests of `rows` int32 [N] rows per ray, in ray order, into `num_rows` rows.

    Deterministic on every backend: one cumsum, one scatter with unique indices, one cummax.
    """
    num_rays = rows.shape[0]
    rows = rows.astype(jnp.int32)
    start = jnp.cumsum(rows) - rows  # [N]
    granted = jnp.clip(num_rows - start, 0, rows)  # [N]
    ray = jnp.arange(num_rays, dtype=jnp.int32)  # [N]
    head = jnp.where(granted > 0, start, num_rows)  # [N], distinct for the rays that got rows
    owner = jnp.full((num_rows,), -1, jnp.int32).at[head].set(ray, mode="drop")  # [M]
    owner = jnp.clip(jax.lax.cummax(owner, axis=0), 0, num_rays - 1)  # [M], filled forward
    used = jnp.arange(num_rows, dtype=jnp.int32) < jnp.sum(granted)  # [M]
    rank = jnp.arange(num_rows, dtype=jnp.int32) - start[owner]  # [M]
    last = jnp.where(granted > 0, start + granted - 1, num_rows)  # [N]
    return RowLayout(owner=owner, rank=rank, used=used, start=start, granted=granted, last=last)


def segment_cumsum(values: Array, rank: Array, max_rows_per_ray: int) -> Array:
    """Inclusive sums of values [M, ...] over each ray's rows, in row order (Hillis-Steele).

    Args:
      values: [M, ...], one entry per row; rows of a ray are consecutive.
      rank: int32 [M], the row's index among its ray's rows (segments restart where rank is 0).
      max_rows_per_ray: the most rows any ray has (static): ceil(log2) of it shifted adds.

    Returns:
      [M, ...]: at row m, the sum of its ray's rows up to and including m.
    """
    steps = max(0, math.ceil(math.log2(max(1, max_rows_per_ray))))
    extra = (1,) * (values.ndim - 1)
    out = values
    for k in range(steps):
        shift = 2**k
        if shift >= values.shape[0]:
            break
        before = jnp.concatenate([jnp.zeros((shift,) + values.shape[1:], values.dtype), out[:-shift]])  # [M, ...]
        out = out + jnp.where((rank >= shift).reshape((-1,) + extra), before, 0.0)
    return out


def gather_rows(a: Array, index: Array) -> Array:
    """a[index] along axis 0, 0 for an out-of-range index (whose gradient is dropped, not scattered)."""
    return jnp.take(a, index, axis=0, mode="fill", fill_value=0)


class RowSums(NamedTuple):
    """What one ray gets from one batch of rows (`composite_rows`).

    Attributes:
      rgb: float32 [N, 3], sum of w * rgb over the ray's samples in the rows (no background).
      depth: float32 [N], sum of w * t.
      acc: float32 [N], sum of w.
      optical_depth: float32 [N], sum of sigma * delta (to carry into the ray's next rows).
    """

    rgb: Array
    depth: Array
    acc: Array
    optical_depth: Array


def composite_rows(
    sigma: Array, rgb: Array, t: Array, delta: Array, layout: RowLayout, carry: Array, max_rows_per_ray: int
) -> RowSums:
    """Volume rendering over packed rows: per-ray sums of w * rgb, w * t, w and sigma * delta.

    Args:
      sigma: [M, s] densities (non-finite values are sanitised as in `volume.volume_weights`).
      rgb: [M, s, 3] colours.
      t: [M, s] sample distances.
      delta: [M, s] bin lengths, 0 for empty slots (which then weigh nothing).
      layout: the rows' `RowLayout` (N rays).
      carry: float32 [N], the optical depth each ray brings (0 for a first pass).
      max_rows_per_ray: the most rows one ray has in this layout (static).

    Returns:
      `RowSums` for the N rays (zeros for rays without rows). Differentiable in sigma and rgb.
    """
    sigma = jnp.clip(jnp.nan_to_num(sigma, nan=0.0, posinf=MAX_DENSITY, neginf=0.0), 0.0, MAX_DENSITY)
    used = layout.used[:, None]  # [M, 1]
    tau = jnp.where(used, sigma * delta, 0.0)  # [M, s]
    rgb = jnp.where(used[..., None], jnp.nan_to_num(rgb), 0.0)  # [M, s, 3]
    inside = jnp.cumsum(tau, axis=1)  # [M, s], inclusive within the row
    before_in_row = jnp.concatenate([jnp.zeros_like(inside[:, :1]), inside[:, :-1]], axis=1)  # [M, s]
    row_tau = inside[:, -1]  # [M]
    rows_tau = segment_cumsum(row_tau, layout.rank, max_rows_per_ray)  # [M], inclusive over the ray's rows
    before_rows = jnp.where(layout.rank > 0, jnp.concatenate([jnp.zeros((1,), tau.dtype), rows_tau[:-1]]), 0.0)
    depth_before = carry[layout.owner][:, None] + before_rows[:, None] + before_in_row  # [M, s]
    w = jnp.exp(-depth_before) * -jnp.expm1(-tau)  # [M, s]
    sums = jnp.concatenate(
        [jnp.sum(w[..., None] * rgb, axis=1), jnp.sum(w * t, axis=1, keepdims=True), jnp.sum(w, axis=1, keepdims=True)],
        axis=1,
    )  # [M, 5]
    sums = segment_cumsum(sums, layout.rank, max_rows_per_ray)  # [M, 5]
    per_ray = gather_rows(sums, layout.last)  # [N, 5]
    return RowSums(
        rgb=per_ray[:, :3], depth=per_ray[:, 3], acc=per_ray[:, 4], optical_depth=gather_rows(rows_tau, layout.last)
    )


def row_samples(layout: RowLayout, first: Array, count: Array, row_length: int) -> Tuple[Array, Array]:
    """Sample indices [M, s] of each row and whether they hold a sample.

    Row m of ray r = owner[m] holds samples first[r] + rank[m] * s + j, j < s, of that ray; a slot is
    valid when its row is used and the index is below count[r].

    Args:
      layout: the rows' layout. first: int32 [N], each ray's first sample in these rows.
      count: int32 [N], each ray's number of samples. row_length: s.

    Returns:
      index int32 [M, s], valid bool [M, s].
    """
    column = jnp.arange(row_length, dtype=jnp.int32)  # [s]
    index = (first[layout.owner] + layout.rank * row_length)[:, None] + column[None, :]  # [M, s]
    valid = layout.used[:, None] & (index < count[layout.owner][:, None])  # [M, s]
    return index, valid
