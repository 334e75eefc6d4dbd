"""The reverse-mode gradient of the marched renderer with respect to its rays (`render.marched`, gradient
"reverse"): what refining a camera pose needs from a trained NeRF.

The forward render's `while_loop`s (passes until every ray is done or opaque) cannot be transposed, so
the marched renderer's compositing is a `jax.custom_vjp` whose backward pass runs passes of its own. The
samples stay where the forward march put them (their distances t along each ray are constants) and
move with the ray, x = o + t d, so the gradient reaches the origin o and direction d, and through them
the pose; the samples a ray composited (its first n, up to early termination) are known from the
forward pass, so the backward needs no termination test. For ray r with samples i < n and the
cotangents g_rgb, g_depth, g_acc of its colour, depth and opacity (background b):

    L       = sum_i w_i v_i + const,   v_i = g_rgb . c_i + g_depth t_i + g_acc - g_rgb . b
    dL/dc_i = w_i g_rgb,   dL/dsigma_i = delta_i (T_{i+1} v_i - sum_{j > i} w_j v_j)

A pass composites a run of each ray's samples onto the optical depth it carries (`packed.composite_rows`,
differentiable); the samples of later passes see that optical depth, so the cotangent of a pass's
optical depth is -(the later passes' share of L) = (L so far) - L, with L from the forward's sums. Each
pass is then one `jax.vjp` of the field at its samples, in any order and pass size: memory is one
pass's, never the whole ray's. Names: `N` rays, `o` origins [N, 3], `d` directions [N, 3].
Why and what it costs: docs/design.md, "Search > Gradient refinement".
"""

from __future__ import annotations

from typing import Callable, NamedTuple, Tuple

import jax
import jax.numpy as jnp

from waldo_jax.render import packed
from waldo_jax.types import Array

__all__ = ["Passes", "composite_vjp"]


class _Backward(NamedTuple):
    """The backward passes' loop state."""

    rays: object  # the forward's per-ray pass state (the caller's type)
    done: Array  # float32 [N], sum of w * v over the samples composited so far
    d_origins: Array  # float32 [N, 3]
    d_directions: Array  # float32 [N, 3]


class Passes(NamedTuple):
    """How the forward composite ran its passes, in the caller's terms (`composite_vjp` runs them again).

    Attributes:
      pass_rows: (rows, layout, rays, o, d) -> `packed.RowSums` of one pass, differentiable in o and d.
      advance: (rays, layout, sums) -> rays after the pass (a ray is live while it has samples left).
      run: (one_pass, state, rays_of, first_rows) -> state: the passes (`marched._run_passes`).
    """

    pass_rows: Callable
    advance: Callable
    run: Callable


def composite_vjp(
    passes: Passes,
    start,
    origins: Array,
    directions: Array,
    sums: Tuple[Array, Array, Array],
    cotangents: Tuple[Array, Array, Array],
    background: Array,
    first_rows: int,
) -> Tuple[Array, Array]:
    """The gradient of a marched composite with respect to its rays' origins and directions.

    Args:
      passes: the forward's passes (one pass's row sums, the rays' advance, the loop over passes).
      start: the rays' state before the first pass.
      origins, directions: float32 [N, 3].
      sums: the forward's (rgb [N, 3] without the background, depth [N], acc [N]).
      cotangents: (g_rgb [N, 3], g_depth [N], g_acc [N]) of the rendered (rgb with the background,
        depth, acc).
      background: float32 [3].
      first_rows: the most rows a ray may take in its first pass.

    Returns:
      (d_origins [N, 3], d_directions [N, 3]).
    """
    rgb, depth, acc = sums
    g_rgb, g_depth, g_acc = cotangents
    g_acc = g_acc - g_rgb @ jnp.asarray(background, jnp.float32)  # rgb = sum w c + (1 - acc) b
    total = jnp.sum(g_rgb * rgb, axis=-1) + g_depth * depth + g_acc * acc  # [N], L up to a constant

    def one_pass(rows: int, layout: packed.RowLayout, state: _Backward) -> _Backward:
        part, pullback = jax.vjp(lambda o, d: passes.pass_rows(rows, layout, state.rays, o, d), origins, directions)
        done = state.done + jnp.sum(g_rgb * part.rgb, axis=-1) + g_depth * part.depth + g_acc * part.acc  # [N]
        d_o, d_d = pullback(packed.RowSums(rgb=g_rgb, depth=g_depth, acc=g_acc, optical_depth=done - total))
        return _Backward(
            passes.advance(state.rays, layout, part), done, state.d_origins + d_o, state.d_directions + d_d
        )

    init = _Backward(start, jnp.zeros_like(depth), jnp.zeros_like(origins), jnp.zeros_like(directions))
    final = passes.run(one_pass, init, lambda state: state.rays, first_rows)
    return final.d_origins, final.d_directions
