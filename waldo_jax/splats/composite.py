"""Compositing a view's chunks of depth-sorted splats, with a hand-written reverse-mode gradient.

A chunk is B splats of one tile, nearest first; a tile's chunks follow each other in the K chunk slots
(`first` marks each tile's first). Every chunk is composited at its tile's S pixels, one splat per
step of a `lax.scan` over the B slots; the chunks of a tile are chained by the transmittance that
enters each (the product of its tile's earlier chunks' transmittances, a segmented scan). On an
accelerator all K chunks go at once, in two passes (the transmittances, then the weighted sums); on a
CPU one pass goes over blocks of `CPU_BLOCK` chunks in order, evaluating each block's alphas once and
passing over blocks with no splat (`_forward_blocked`). Per pixel:

  T_i      transmittance before splat i, carried without the stop (it only falls);
  kept_i   T_i (1 - alpha_i) >= min_transmittance: the splats before the reference's stop;
  w_i      kept_i alpha_i T_i, the weight of splat i's values v_i = (r, g, b, 1, depth);
  values   sum_i w_i v_i over the chunk (the per-tile sums are the image).

The gradient (`jax.custom_vjp`): with g the cotangent of a pixel's values and e_i = g . v_i,
  dL/dv_i     = w_i g,
  dL/dalpha_i = kept_i T_i e_i - R_i / (1 - alpha_i),   R_i = sum_{j after i in its tile} w_j e_j,
the back-to-front rule of the reference rasteriser's backward pass, here with R's share from later
chunks given by a segmented suffix sum and the rest by a reversed scan over the chunk's slots; then
alpha = min(0.99, o exp(power)) and power = -(a dx^2 + c dy^2) / 2 - b dx dy carry it to the opacity,
the conic (a, b, c) and the projected mean. The stop's mask and the 1/255 skip count as constants, as
in the reference. A pose gradient costs about 3 renders, against 5 when JAX differentiates the scans
(docs/splats.md).
"""

from __future__ import annotations

import functools
from typing import NamedTuple, Optional

import jax
import jax.numpy as jnp

from waldo_jax.types import Array

__all__ = ["ChunkSplats", "alphas", "segmented", "composite_chunks"]

# Chunks composited together in one step of the CPU's pass over the chunks (`_forward_blocked`): their
# alphas, [chunk, CPU_BLOCK, S] floats, stay in a core's cache between the two uses.
CPU_BLOCK = 64
# The packed columns of a slot before its values: mean2d (2), conic (3), opacity (1).
_GEOMETRY = 6


def alphas(
    pixels: Array, mean2d: Array, conic: Array, opacity: Array, filled: Array, alpha_min: float, alpha_max: float
) -> Array:
    """alpha [K, S] of one splat per chunk (the i-th of each) at its tile's pixel centres (0 where skipped).

    Args:
      pixels: [K, S, 2] pixel centres of each chunk's tile.
      mean2d [K, 2], conic [K, 3], opacity [K]: the splat of each chunk.
      filled: bool [K] whether the chunk has an i-th splat.
      alpha_min, alpha_max: the skip threshold and the clamp.
    """
    dx = pixels[..., 0] - mean2d[:, None, 0]  # [K, S]
    dy = pixels[..., 1] - mean2d[:, None, 1]
    power = -0.5 * (conic[:, None, 0] * dx * dx + conic[:, None, 2] * dy * dy) - conic[:, None, 1] * dx * dy
    alpha = jnp.minimum(alpha_max, opacity[:, None] * jnp.exp(jnp.minimum(power, 0.0)))
    return jnp.where(filled[:, None] & (power <= 0.0) & (alpha >= alpha_min), alpha, 0.0)


def segmented(op, first: Array, values: Array) -> Array:
    """Inclusive scan of `op` along axis 0 that restarts where `first` [K] is true."""

    def combine(a, b):
        flag_a, value_a = a
        flag_b, value_b = b
        flag = flag_b.reshape(flag_b.shape + (1,) * (value_b.ndim - flag_b.ndim))
        return flag_a | flag_b, jnp.where(flag, value_b, op(value_a, value_b))

    return jax.lax.associative_scan(combine, (first, values))[1]


def _entering(pixels, first, mean2d, conic, opacity, filled, alpha_min, alpha_max):
    """The transmittance entering each chunk [K, S] (exclusive product of its tile's earlier chunks')."""

    @jax.checkpoint
    def through(transmittance, xs):
        return transmittance * (1.0 - alphas(pixels, *xs, alpha_min, alpha_max)), None

    through, _ = jax.lax.scan(through, jnp.ones(pixels.shape[:2], jnp.float32), (mean2d, conic, opacity, filled))
    entering = segmented(jnp.multiply, first, through)  # inclusive
    return jnp.where(first[:, None], 1.0, jnp.roll(entering, 1, axis=0))


def _forward(pixels, first, mean2d, conic, opacity, filled, sample, alpha_min, alpha_max, min_transmittance):
    """(values [K, S, 5], transmittance leaving each chunk without the stop [K, S], entering [K, S])."""
    entering = _entering(pixels, first, mean2d, conic, opacity, filled, alpha_min, alpha_max)

    @jax.checkpoint
    def step(carry, xs):
        transmittance, values = carry
        *geometry, v = xs
        alpha = alphas(pixels, *geometry, alpha_min, alpha_max)
        after = transmittance * (1.0 - alpha)
        weight = jnp.where(after >= min_transmittance, alpha * transmittance, 0.0)  # [K, S]
        return (after, values + weight[..., None] * v[:, None, :]), None

    values = jnp.zeros(pixels.shape[:2] + (sample.shape[-1],), jnp.float32)
    (leaving, values), _ = jax.lax.scan(step, (entering, values), (mean2d, conic, opacity, filled, sample))
    return values, leaving, entering


def _forward_blocked(pixels, first, rows, filled, alpha_min, alpha_max, min_transmittance, block, ids=None):
    """`_forward` of packed chunk-major rows, in one pass over blocks of `block` chunks, in order (a
    `lax.scan`): the CPU's way. With `ids` [K, B], `rows` is a table whose rows `ids` names, gathered
    block by block (a block with no splat is not gathered).

    Each block's alphas [B, block, S] are evaluated once and kept (they fit in a core's cache) for
    both its transmittance product and its weighted sums; the transmittance leaving the previous
    block's last chunk enters the block's chunks that continue that tile. A block with no splat (the
    unused chunk slots at the end of a view's lists) is passed over, not evaluated. The values equal
    `_forward`'s up to the order of the transmittance products (float32 rounding). K a multiple of
    `block` reads the inputs in place (others are padded with empty chunks).
    """
    k, s = pixels.shape[:2]
    c = rows.shape[-1] - _GEOMETRY
    blocks = -(-k // block)
    pad = blocks * block - k
    rows = jnp.asarray(rows)
    slots = rows if ids is None else ids  # [K, B, ...] sliced block by block
    if pad:
        pixels = jnp.pad(pixels, ((0, pad), (0, 0), (0, 0)))
        first = jnp.pad(first, (0, pad), constant_values=True)
        slots = jnp.pad(slots, ((0, pad),) + ((0, 0),) * (slots.ndim - 1))
        filled = jnp.pad(filled, ((0, pad), (0, 0)))

    def composite_block(carry, px, fst, r, f):
        mean2d, conic, opacity, sample = _unpack(r if ids is None else rows[r])  # [B, block, ...]
        alpha = jax.vmap(lambda *g: alphas(px, *g, alpha_min, alpha_max))(mean2d, conic, opacity, f.T)

        def through(t, a):
            return t * (1.0 - a), None

        product, _ = jax.lax.scan(through, jnp.ones((block, s), jnp.float32), alpha)  # [block, S]
        inclusive = segmented(jnp.multiply, fst, product)
        entering = jnp.concatenate([jnp.ones((1, s), jnp.float32), inclusive[:-1]])
        entering = jnp.where(fst[:, None], 1.0, entering)
        continues = (jnp.cumsum(fst) == 0)[:, None]  # the block's first run: the previous block's tile
        entering = jnp.where(continues, entering * carry, entering)

        def step(state, xs):
            transmittance, values = state
            a, v = xs
            after = transmittance * (1.0 - a)
            weight = jnp.where(after >= min_transmittance, a * transmittance, 0.0)  # [block, S]
            return (after, values + weight[..., None] * v[:, None, :]), None

        zeros = jnp.zeros((block, s, c), jnp.float32)
        (leaving, values), _ = jax.lax.scan(step, (entering, zeros), (alpha, sample))
        return leaving[-1], (values, leaving, entering)

    def skip(carry, px, fst, *_):  # no splat in the block: every alpha is 0, the transmittance passes
        continues = (jnp.cumsum(fst) == 0)[:, None]
        entering = jnp.where(continues, carry, jnp.ones((block, s), jnp.float32))
        return entering[-1], (jnp.zeros((block, s, c), jnp.float32), entering, entering)

    def body(carry, i):
        own = tuple(jax.lax.dynamic_slice_in_dim(a, i * block, block, 0) for a in (pixels, first, slots, filled))
        return jax.lax.cond(jnp.any(own[3]), composite_block, skip, carry, *own)

    _, out = jax.lax.scan(body, jnp.ones((s,), jnp.float32), jnp.arange(blocks, dtype=jnp.int32))
    return tuple(o.reshape((blocks * block,) + o.shape[2:])[:k] for o in out)


def _unpack(rows: Array):
    """(mean2d [B, K, 2], conic [B, K, 3], opacity [B, K], sample [B, K, C]) of rows [K, B, 6 + C]."""
    r = jnp.swapaxes(rows, 0, 1)
    return r[..., 0:2], r[..., 2:5], r[..., 5], r[..., _GEOMETRY:]


def _pack(mean2d: Array, conic: Array, opacity: Array, sample: Array) -> Array:
    """The rows [K, B, 6 + C] of slot-major arrays (`_unpack`'s inverse)."""
    return jnp.swapaxes(jnp.concatenate([mean2d, conic, opacity[..., None], sample], -1), 0, 1)


def _forward_rows(pixels, first, rows, filled, alpha_min, alpha_max, min_transmittance, ids=None):
    """(values, leaving, entering) of packed rows (or of the rows `ids` names in the table `rows`):
    `_forward_blocked` on a CPU (blocks of `CPU_BLOCK` chunks), `_forward` of the slot-major arrays
    elsewhere."""
    if jax.default_backend() == "cpu":
        return _forward_blocked(pixels, first, rows, filled, alpha_min, alpha_max, min_transmittance, CPU_BLOCK, ids)
    if ids is not None:
        rows = rows[ids]
    mean2d, conic, opacity, sample = _unpack(rows)
    return _forward(pixels, first, mean2d, conic, opacity, filled.T, sample, alpha_min, alpha_max, min_transmittance)


@functools.partial(jax.custom_vjp, nondiff_argnums=(4, 5, 6))
def _composite_vjp(pixels, first, rows, filled, alpha_min, alpha_max, min_transmittance):
    values, leaving, _ = _forward_rows(pixels, first, rows, filled, alpha_min, alpha_max, min_transmittance)
    return values, leaving


def _composite_fwd(pixels, first, rows, filled, alpha_min, alpha_max, min_transmittance):
    values, leaving, entering = _forward_rows(pixels, first, rows, filled, alpha_min, alpha_max, min_transmittance)
    return (values, leaving), (pixels, first, rows, filled, entering, values)


def _composite_bwd(alpha_min, alpha_max, min_transmittance, residuals, cotangents):
    pixels, first, rows, filled_rows, entering, values = residuals
    mean2d, conic, opacity, sample = _unpack(rows)
    filled = filled_rows.T
    g, _ = cotangents  # [K, S, 5]; `leaving` only ever feeds comparisons
    # Each chunk's own sum of w_j e_j, then R's share from the tile's later chunks: a segmented
    # suffix sum (the scan reversed, restarting at each tile's last chunk).
    own = jnp.sum(values * g, axis=-1)  # [K, S]
    last = jnp.concatenate([first[1:], jnp.ones((1,), bool)])
    later = segmented(jnp.add, last[::-1], own[::-1])[::-1] - own  # [K, S] exclusive suffix

    # The transmittance before each slot, forward again (stored for the reversed pass: on a CPU cheaper
    # than keeping it from the forward pass, whose scan then writes a [B, K, S] output at every step).
    def forward(transmittance, xs):
        alpha = alphas(pixels, *xs, alpha_min, alpha_max)
        return transmittance * (1.0 - alpha), transmittance

    _, before = jax.lax.scan(forward, entering, (mean2d, conic, opacity, filled))  # [B, K, S]
    dx = pixels[..., 0]
    dy = pixels[..., 1]

    def backward(suffix, xs):
        m, c, o, f, v, t = xs  # one slot of every chunk: [K, 2], [K, 3], [K], [K], [K, 5], [K, S]
        ddx = dx - m[:, None, 0]
        ddy = dy - m[:, None, 1]
        power = -0.5 * (c[:, None, 0] * ddx * ddx + c[:, None, 2] * ddy * ddy) - c[:, None, 1] * ddx * ddy
        raw = o[:, None] * jnp.exp(jnp.minimum(power, 0.0))
        alpha = jnp.minimum(alpha_max, raw)
        used = f[:, None] & (power <= 0.0) & (alpha >= alpha_min)
        alpha = jnp.where(used, alpha, 0.0)
        kept = t * (1.0 - alpha) >= min_transmittance
        weight = jnp.where(kept, alpha * t, 0.0)
        e = jnp.einsum("ksc,kc->ks", g, v)
        d_alpha = jnp.where(kept, t * e, 0.0) - suffix / (1.0 - alpha)
        d_v = jnp.einsum("ks,ksc->kc", weight, g)
        # alpha = o exp(power) where used and below the clamp (0 gradient where clamped or skipped).
        live = used & (raw < alpha_max)
        d_power = jnp.where(live, d_alpha * alpha, 0.0)
        d_o = jnp.sum(jnp.where(live, d_alpha * jnp.exp(jnp.minimum(power, 0.0)), 0.0), axis=1)
        d_m = jnp.stack(
            [
                jnp.sum(d_power * (c[:, None, 0] * ddx + c[:, None, 1] * ddy), 1),
                jnp.sum(d_power * (c[:, None, 1] * ddx + c[:, None, 2] * ddy), 1),
            ],
            -1,
        )
        d_c = jnp.stack(
            [
                jnp.sum(d_power * -0.5 * ddx * ddx, 1),
                jnp.sum(d_power * -ddx * ddy, 1),
                jnp.sum(d_power * -0.5 * ddy * ddy, 1),
            ],
            -1,
        )
        return suffix + weight * e, (d_m, d_c, d_o, d_v)

    _, (d_mean2d, d_conic, d_opacity, d_sample) = jax.lax.scan(
        backward, later, (mean2d, conic, opacity, filled, sample, before), reverse=True
    )
    return None, None, _pack(d_mean2d, d_conic, d_opacity, d_sample), None


_composite_vjp.defvjp(_composite_fwd, _composite_bwd)


class ChunkSplats(NamedTuple):
    """Each chunk's projected splats, nearest first, chunk by chunk (K chunks of B slots), packed so
    that one gather of a table of projected splats makes them.

    Attributes:
      rows: [K, B, 6 + C] per slot: the projected mean (x, y) in px, the inverse 2D covariance
        (a, b, c), the opacity, then the C values the splat adds, weighted (e.g. r, g, b, 1, depth).
        With `ids`: the table [N, 6 + C] of the projected splats, one row each.
      filled: bool [K, B], the slots that hold a splat.
      ids: int32 [K, B], each slot's row of the table `rows`, or None when `rows` are the slots'. The
        slots are then gathered where they are composited: on a CPU block by block, so that the blocks
        with no splat (the unused slots at the end of a view's lists) are never gathered.
    """

    rows: Array
    filled: Array
    ids: Optional[Array] = None


def composite_chunks(
    pixels: Array,
    first: Array,
    splats: ChunkSplats,
    alpha_min: float,
    alpha_max: float,
    min_transmittance: float,
    custom_gradient: bool = True,
):
    """The chunks' composited values and the transmittance leaving each (see the module docstring).

    Args:
      pixels: [K, S, 2] pixel centres of each chunk's tile.
      first: bool [K] the first chunk of its tile (unused chunks count as first).
      splats: each chunk's splats, nearest first (`ChunkSplats`: rows [K, B, 6 + C], filled [K, B], or a
        table [N, 6 + C] with the ids [K, B] of each slot's row).
      alpha_min, alpha_max, min_transmittance: the reference's 1/255, 0.99 and 1e-4.
      custom_gradient: the hand-written reverse-mode gradient (no forward mode), or JAX's own
        differentiation of the scans (both modes; slower in reverse).

    Returns:
      (values [K, S, C], transmittance leaving each chunk without the stop [K, S]).
    """
    rows, filled, ids = splats
    if custom_gradient:
        if ids is None:
            return _composite_vjp(pixels, first, rows, filled, alpha_min, alpha_max, min_transmittance)
        return _composite_table_vjp(pixels, first, rows, ids, filled, alpha_min, alpha_max, min_transmittance)
    if ids is not None:
        rows = rows[ids]
    mean2d, conic, opacity, sample = _unpack(rows)
    values, leaving, _ = _forward(
        pixels, first, mean2d, conic, opacity, filled.T, sample, alpha_min, alpha_max, min_transmittance
    )
    return values, leaving


@functools.partial(jax.custom_vjp, nondiff_argnums=(5, 6, 7))
def _composite_table_vjp(pixels, first, table, ids, filled, alpha_min, alpha_max, min_transmittance):
    """`_composite_vjp` of the rows `ids` [K, B] names in `table` [N, 6 + C], gathered where they are
    composited; its gradient is the rows' gradient added into the table (a gather's transpose)."""
    values, leaving, _ = _forward_rows(pixels, first, table, filled, alpha_min, alpha_max, min_transmittance, ids)
    return values, leaving


def _composite_table_fwd(pixels, first, table, ids, filled, alpha_min, alpha_max, min_transmittance):
    values, leaving, entering = _forward_rows(
        pixels, first, table, filled, alpha_min, alpha_max, min_transmittance, ids
    )
    return (values, leaving), (pixels, first, table, ids, filled, entering, values)


def _composite_table_bwd(alpha_min, alpha_max, min_transmittance, residuals, cotangents):
    pixels, first, table, ids, filled, entering, values = residuals
    residuals = (pixels, first, table[ids], filled, entering, values)
    d_rows = _composite_bwd(alpha_min, alpha_max, min_transmittance, residuals, cotangents)[2]
    return None, None, jnp.zeros_like(table).at[ids].add(d_rows), None, None


_composite_table_vjp.defvjp(_composite_table_fwd, _composite_table_bwd)
