"""The compositing of chunked tile lists (waldo_jax.splats.composite): the CPU's one pass over blocks
of chunks against the two-pass scans and against a float64 loop over each tile's list, written here.

The chunk lists are random and built to reach every path of the blocked pass: tiles whose chunks run
across block boundaries (the transmittance carried from one block to the next), a tile with a whole
block of empty chunks in its middle (a block passed over, whose carry must go through it), part-full
last chunks, unused chunks at the end, and a chunk count that is not a multiple of the block (padding).
"""

from __future__ import annotations

import functools

import jax
import numpy as np
import pytest

from waldo_jax.splats import composite

ALPHA_MIN, ALPHA_MAX, MIN_T = 1.0 / 255.0, 0.99, 1e-4
B, TS = 4, 4  # slots per chunk, tile side (S = 16 pixels)
S = TS * TS


def _lists(seed: int):
    """(pixels [K, S, 2], first [K], rows [K, B, 11], filled [K, B]) of random tiles' chunk lists."""
    rng = np.random.default_rng(seed)
    runs = [1, 7, 12, 2, 3, 1, 5]  # chunks per tile; the 12-chunk one (chunks 8-19) has an empty middle
    first, tile_of, filled = [], [], []
    for t, n in enumerate(runs):
        for j in range(n):
            first.append(j == 0)
            tile_of.append(t)
            f = np.ones(B, bool)
            if j == n - 1:
                f[rng.integers(1, B + 1) :] = False  # a part-full last chunk
            if n == 12 and 4 <= j < 8:
                f[:] = False  # a whole block (of 4) of empty chunks inside a tile
            filled.append(f)
    for _ in range(9):  # unused chunk slots at the end
        first.append(True)
        tile_of.append(0)
        filled.append(np.zeros(B, bool))
    k = len(first)
    corner = np.stack([np.array(tile_of) * TS, np.zeros(k)], -1).astype(np.float32)
    j, i = np.meshgrid(np.arange(TS), np.arange(TS), indexing="ij")
    offsets = np.stack([i.reshape(-1), j.reshape(-1)], -1).astype(np.float32) + 0.5
    pixels = corner[:, None, :] + offsets[None]
    mean2d = corner[:, None, :] + rng.uniform(-1.0, TS + 1.0, (k, B, 2))
    scale = rng.uniform(0.6, 3.0, (k, B, 2))
    rho = rng.uniform(-0.6, 0.6, (k, B))
    det = (scale[..., 0] * scale[..., 1]) ** 2 * (1 - rho**2)
    cov_xy = rho * scale[..., 0] * scale[..., 1]
    conic = np.stack([scale[..., 1] ** 2 / det, -cov_xy / det, scale[..., 0] ** 2 / det], -1)
    opacity = rng.uniform(0.05, 0.995, (k, B))  # some above the 0.99 clamp
    values = np.concatenate([rng.uniform(0, 1, (k, B, 3)), np.ones((k, B, 1)), rng.uniform(1, 5, (k, B, 1))], -1)
    rows = np.concatenate([mean2d, conic, opacity[..., None], values], -1).astype(np.float32)
    return pixels, np.array(first), rows, np.stack(filled)


def _reference(pixels, first, rows, filled):
    """A float64 loop over every tile's list: per chunk (values, leaving without the stop, entering)."""
    k = len(first)
    out_values = np.zeros((k, S, rows.shape[-1] - 6))
    leaving, entering = np.ones((k, S)), np.ones((k, S))
    transmittance = np.ones(S)
    for c in range(k):
        if first[c]:
            transmittance = np.ones(S)
        entering[c] = transmittance
        for b in range(B):
            if not filled[c, b]:
                continue
            (mx, my), (a, bb, cc), o, v = rows[c, b, :2], rows[c, b, 2:5], rows[c, b, 5], rows[c, b, 6:]
            dx, dy = pixels[c, :, 0] - mx, pixels[c, :, 1] - my
            power = -0.5 * (a * dx * dx + cc * dy * dy) - bb * dx * dy
            alpha = np.minimum(ALPHA_MAX, o * np.exp(np.minimum(power, 0.0)))
            alpha = np.where((power <= 0) & (alpha >= ALPHA_MIN), alpha, 0.0)
            after = transmittance * (1 - alpha)
            weight = np.where(after >= MIN_T, alpha * transmittance, 0.0)
            out_values[c] += weight[:, None] * v[None, :]
            transmittance = after
        leaving[c] = transmittance
    return out_values, leaving, entering


@functools.partial(jax.jit, static_argnames=("block",))
def _blocked(pixels, first, rows, filled, block):
    return composite._forward_blocked(pixels, first, rows, filled, ALPHA_MIN, ALPHA_MAX, MIN_T, block)


@jax.jit
def _two_pass(pixels, first, rows, filled):
    mean2d, conic, opacity, sample = composite._unpack(rows)
    return composite._forward(pixels, first, mean2d, conic, opacity, filled.T, sample, ALPHA_MIN, ALPHA_MAX, MIN_T)


@pytest.mark.parametrize("seed", [0, 1])
def test_blocked_pass_equals_two_passes_and_the_float64_loop(seed):
    """Blocks of 4 (K a multiple after padding: 40 chunks, so 10 blocks, one all empty inside a tile),
    5 (padded), 64 (one block): values, leaving and entering equal the two-pass scans to float32 rounding
    (the transmittance products are taken in another order) and the float64 loop over each tile."""
    pixels, first, rows, filled = _lists(seed)
    assert len(first) == 40
    want = _reference(pixels, first, rows, filled)
    two = _two_pass(pixels, first, rows, filled)
    # The lists stop pixels (else the early stop would be untested) and light every chunk of a busy tile.
    assert np.any(want[1] < MIN_T) and np.all(np.any(want[0][:3, :, 3] > 0, axis=-1))
    for block in (4, 5, 64):
        got = _blocked(pixels, first, rows, filled, block=block)
        for name, g, t, w in zip(("values", "leaving", "entering"), got, two, want):
            np.testing.assert_allclose(np.asarray(g), np.asarray(t), rtol=1e-5, atol=2e-6, err_msg=f"{name}, {block}")
            np.testing.assert_allclose(np.asarray(g), w, rtol=1e-4, atol=1e-5, err_msg=f"{name} vs float64, {block}")


def test_blocked_pass_skips_empty_blocks():
    """A block with no filled slot is passed over (lax.cond's skip branch): made unevaluable by NaN
    geometry in its empty slots, which the evaluated branch would turn into NaN values, it leaves the
    outputs finite and equal to the same lists with zeros there."""
    pixels, first, rows, filled = _lists(0)
    poisoned = rows.copy()
    empty_block = ~filled.reshape(10, 4, B).any(axis=(1, 2))
    assert empty_block.sum() >= 2  # the tile's empty middle block and the unused tail
    poisoned.reshape(10, 4, B, -1)[empty_block] = np.nan
    clean = _blocked(pixels, first, rows, filled, block=4)
    got = _blocked(pixels, first, poisoned, filled, block=4)
    for g, c in zip(got, clean):
        assert np.all(np.isfinite(np.asarray(g)))
        np.testing.assert_array_equal(np.asarray(g), np.asarray(c))


def test_rows_named_in_a_table_equal_the_rows_gathered_bit_for_bit():
    """`ChunkSplats(table, filled, ids)` (the slots gathered where they are composited: block by block on
    a CPU) gives the same values, transmittances and table gradient, bit for bit, as the slots gathered
    first, `ChunkSplats(table[ids], filled)`; a block whose slots are all empty is passed over (its ids
    may name a row of NaNs and nothing changes)."""
    pixels, first, rows, filled = _lists(1)
    k = len(first)
    rng = np.random.default_rng(3)
    # The table: every filled slot's row, shuffled, plus rows no slot names.
    table = np.concatenate([rows[filled], rng.uniform(0, 1, (5, rows.shape[-1])).astype(np.float32)])
    perm = rng.permutation(len(table))
    table = table[perm]
    ids = np.zeros((k, B), np.int32)
    ids[filled] = np.argsort(perm)[: int(filled.sum())]
    g = rng.normal(size=(k, S, rows.shape[-1] - 6)).astype(np.float32)

    def run(form):
        def loss(t):
            gathered = form == "gathered"
            splats = composite.ChunkSplats(t[ids], filled) if gathered else composite.ChunkSplats(t, filled, ids)
            values, leaving = composite.composite_chunks(pixels, first, splats, ALPHA_MIN, ALPHA_MAX, MIN_T)
            return (values * g).sum(), (values, leaving)

        return jax.jit(jax.value_and_grad(loss, has_aux=True))(table)

    (_, (v_gathered, l_gathered)), d_gathered = run("gathered")
    (_, (v_table, l_table)), d_table = run("table")
    np.testing.assert_array_equal(np.asarray(v_table), np.asarray(v_gathered))
    np.testing.assert_array_equal(np.asarray(l_table), np.asarray(l_gathered))
    np.testing.assert_array_equal(np.asarray(d_table), np.asarray(d_gathered))
    assert np.any(np.asarray(d_table)[:, :6] != 0)  # the gradient reaches the geometry
    # A block (of 4 chunks here) with no filled slot is passed over: its ids may name a row of NaNs.
    got = composite._forward_blocked(pixels, first, table, filled, ALPHA_MIN, ALPHA_MAX, MIN_T, 4, ids)
    empty4 = ~filled.reshape(10, 4, B).any(axis=(1, 2))
    assert empty4.sum() >= 2
    wild4 = ids.copy().reshape(10, 4, B)
    table_nan = np.concatenate([table, np.full((1, table.shape[1]), np.nan, np.float32)])
    wild4[empty4] = len(table)  # the NaN row: evaluating it would poison the values
    poisoned = composite._forward_blocked(
        pixels, first, table_nan, filled, ALPHA_MIN, ALPHA_MAX, MIN_T, 4, wild4.reshape(k, B)
    )
    for p_, g_ in zip(poisoned, got):
        assert np.all(np.isfinite(np.asarray(p_)))
        np.testing.assert_array_equal(np.asarray(p_), np.asarray(g_))


def test_rows_named_in_a_table_are_gathered_only_inside_the_evaluated_branch():
    """The point of the table form on a CPU: the table's rows are read only in the branch that composites a
    block holding a splat (inside the block loop's `lax.cond`), never for all K x B slots up front."""
    pixels, first, rows, filled = _lists(0)
    table = rows[filled]
    ids = np.zeros(filled.shape, np.int32)
    ids[filled] = np.arange(len(table))
    jaxpr = jax.make_jaxpr(
        lambda t: composite._forward_blocked(pixels, first, t, filled, ALPHA_MIN, ALPHA_MAX, MIN_T, 4, ids)
    )(table)
    where = []  # for each gather from the table: whether it lies inside a cond's branch

    def walk(jx, in_branch):
        for eqn in jx.eqns:
            if eqn.primitive.name == "gather" and eqn.invars[0].aval.shape == table.shape:
                where.append(in_branch)
            for param in eqn.params.values():
                for sub in param if isinstance(param, (tuple, list)) else (param,):
                    inner = getattr(sub, "jaxpr", None)
                    if inner is not None:
                        walk(getattr(inner, "jaxpr", inner), in_branch or eqn.primitive.name == "cond")

    walk(jaxpr.jaxpr, False)
    assert where and all(where), where


def test_pairs_whose_tile_no_splat_pixel_reaches_are_left_out_and_no_other():
    """`render._reaches_tile` (which pairs of a splat's tile box are composited) against a float64 brute
    force over each tile's pixel centres: every (splat, tile) where some pixel's alpha reaches alpha_min
    is kept, and tilted needles' and round splats' empty corner tiles (a third of the box here) are left out."""
    from waldo_jax.splats.render import SplatRenderConfig, _reaches_tile, _support_q

    rng = np.random.default_rng(0)
    n, ts = 400, 8
    config = SplatRenderConfig(tile_size=ts)
    angle = rng.uniform(0, np.pi, n)
    sx, sy = rng.uniform(0.5, 12.0, n), rng.uniform(0.5, 3.0, n)  # needles to round, half axes in px
    rot = np.stack([np.stack([np.cos(angle), -np.sin(angle)], -1), np.stack([np.sin(angle), np.cos(angle)], -1)], -2)
    cov = rot @ (np.stack([sx, sy], -1)[:, :, None] ** 2 * np.eye(2)) @ np.swapaxes(rot, 1, 2)  # [n, 2, 2]
    inv = np.linalg.inv(cov)
    mean = rng.uniform(8.0, 56.0, (n, 2))
    opacity = rng.uniform(0.01, 1.0, n)
    q_max = 2.0 * np.log(opacity / config.alpha_min)
    half = np.sqrt(q_max[:, None] * np.stack([cov[:, 0, 0], cov[:, 1, 1]], -1))
    splat, tx, ty = [], [], []
    for i in range(n):  # every tile of the support's box
        lo, hi = np.floor((mean[i] - half[i]) / ts).astype(int), np.floor((mean[i] + half[i]) / ts).astype(int)
        for y in range(lo[1], hi[1] + 1):
            for x in range(lo[0], hi[0] + 1):
                splat.append(i), tx.append(x), ty.append(y)
    splat, tx, ty = np.array(splat), np.array(tx), np.array(ty)
    conic = np.stack([inv[:, 0, 0], inv[:, 0, 1], inv[:, 1, 1]], -1)
    support = np.asarray(_support_q(opacity.astype(np.float32), config))
    columns = tuple(np.concatenate([mean, conic, support[:, None]], -1).astype(np.float32).T)
    kept = np.asarray(_reaches_tile(columns, splat, tx, ty, ts))
    offsets = np.stack(np.meshgrid(np.arange(ts), np.arange(ts)), -1).reshape(-1, 2) + 0.5  # pixel centres
    d = np.stack([tx, ty], -1)[:, None, :] * ts + offsets[None] - mean[splat][:, None, :]  # [M, S, 2]
    q = np.einsum("msi,mij,msj->ms", d, inv[splat], d)
    reaches = np.any(opacity[splat][:, None] * np.exp(-0.5 * q) >= config.alpha_min, axis=1)
    assert np.all(kept[reaches]), "a pair with a pixel at or above alpha_min was left out"
    assert 0.2 < 1.0 - kept.mean() and np.mean(kept == reaches) > 0.98, (kept.mean(), reaches.mean())
