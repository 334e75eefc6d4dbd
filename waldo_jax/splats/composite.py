"""Compositing a view's chunks of depth-sorted splats, with a hand-written reverse-mode gradient.

A chunk is B splats of one tile, nearest first; a tile's chunks follow each other in the K chunk slots
(`first` marks each tile's first). Every chunk is composited at its tile's S pixels at once, one splat
per step of a `lax.scan` over the B slots; the chunks of a tile are chained by the transmittance that
enters each (the product of its tile's earlier chunks' transmittances, a segmented scan). Per pixel:

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
from typing import NamedTuple

import jax
import jax.numpy as jnp

from waldo_jax.types import Array

__all__ = ["ChunkSplats", "alphas", "segmented", "composite_chunks"]


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


@functools.partial(jax.custom_vjp, nondiff_argnums=(7, 8, 9))
def _composite_vjp(pixels, first, mean2d, conic, opacity, filled, sample, alpha_min, alpha_max, min_transmittance):
    values, leaving, _ = _forward(
        pixels, first, mean2d, conic, opacity, filled, sample, alpha_min, alpha_max, min_transmittance
    )
    return values, leaving


def _composite_fwd(pixels, first, mean2d, conic, opacity, filled, sample, alpha_min, alpha_max, min_transmittance):
    values, leaving, entering = _forward(
        pixels, first, mean2d, conic, opacity, filled, sample, alpha_min, alpha_max, min_transmittance
    )
    return (values, leaving), (pixels, first, mean2d, conic, opacity, filled, sample, entering, values)


def _composite_bwd(alpha_min, alpha_max, min_transmittance, residuals, cotangents):
    pixels, first, mean2d, conic, opacity, filled, sample, entering, values = residuals
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
    return None, None, d_mean2d, d_conic, d_opacity, None, d_sample


_composite_vjp.defvjp(_composite_fwd, _composite_bwd)


class ChunkSplats(NamedTuple):
    """Each chunk's projected splats, nearest first, slot by slot (B slots of K chunks).

    Attributes:
      mean2d: [B, K, 2] projected means (px).
      conic: [B, K, 3] inverse 2D covariances (a, b, c).
      opacity: [B, K].
      filled: bool [B, K], the slots that hold a splat.
    """

    mean2d: Array
    conic: Array
    opacity: Array
    filled: Array


def composite_chunks(
    pixels: Array,
    first: Array,
    splats: ChunkSplats,
    sample: Array,
    alpha_min: float,
    alpha_max: float,
    min_transmittance: float,
    custom_gradient: bool = True,
):
    """The chunks' composited values and the transmittance leaving each (see the module docstring).

    Args:
      pixels: [K, S, 2] pixel centres of each chunk's tile.
      first: bool [K] the first chunk of its tile (unused chunks count as first).
      splats: each chunk's splats, nearest first, slot by slot (mean2d [B, K, 2], conic [B, K, 3],
        opacity [B, K], filled bool [B, K]).
      sample: [B, K, C] the values each splat adds, weighted (e.g. r, g, b, 1, depth).
      alpha_min, alpha_max, min_transmittance: the reference's 1/255, 0.99 and 1e-4.
      custom_gradient: the hand-written reverse-mode gradient (no forward mode), or JAX's own
        differentiation of the scans (both modes; slower in reverse).

    Returns:
      (values [K, S, C], transmittance leaving each chunk without the stop [K, S]).
    """
    mean2d, conic, opacity, filled = splats
    if custom_gradient:
        return _composite_vjp(
            pixels, first, mean2d, conic, opacity, filled, sample, alpha_min, alpha_max, min_transmittance
        )
    values, leaving, _ = _forward(
        pixels, first, mean2d, conic, opacity, filled, sample, alpha_min, alpha_max, min_transmittance
    )
    return values, leaving
