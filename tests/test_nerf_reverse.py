"""Reverse-mode gradients of the marched renderer (`render_marched(..., gradient="reverse")`,
`render.marched_vjp`): the same images as the forward renderer, and pose gradients equal to forward mode
and to finite differences, on an analytic field and on a trained NeRF."""

from __future__ import annotations

import dataclasses
import math

import waldo_jax  # noqa: F401  (XLA flags before the first computation)

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from waldo_jax.cameras import pose_to_c2w
from waldo_jax.render import RenderConfig, marched, marching, occupancy as occ
from waldo_jax.search.refine import values_and_gradients
from waldo_jax.types import Intrinsics, Pose

BOX = np.array([[-4.0] * 3, [4.0] * 3], np.float32)
INTRINSICS = Intrinsics.from_fov(9, 7, math.radians(60.0))  # 63 rays a view: blocks never divide evenly
# No box clipping and every cell occupied: the samples of a ray start at `near` whatever the pose, so
# finite differences see the same quadrature as the gradient (which keeps the sample distances fixed).
RENDER_CONFIG = RenderConfig.create(near=0.1, far=8.0, background=(0.1, 0.2, 0.3), ray_chunk=1)
GRID = occ.init_occupancy(BOX, resolution=8)
MARCH = marching.MarchConfig.for_grid(GRID, steps_per_diagonal=256, min_transmittance=0.0)
PACKINGS = [
    marched.Packing.for_backend("cpu"),  # one block, one field call a pass
    marched.Packing(rays_per_block=40, slots_per_ray=8, row_length=4, max_rows_per_ray=4),  # many passes
]
START = Pose(
    origin=jnp.array([[2.5, 0.4, -1.5], [-2.0, 0.8, 2.2]]),
    target=jnp.zeros((2, 3)),
    up=jnp.array([[0.0, 1.0, 0.0]] * 2),
)


def smooth_field(params, x, d):
    """A Gaussian blob of fog with colours that vary in space: smooth in x, so finite differences apply."""
    del d
    sigma = params["peak"] * jnp.exp(-jnp.sum((x - params["centre"]) ** 2) / 0.3)
    return sigma, 0.5 + 0.4 * jnp.sin(jnp.array([3.0, 5.0, 7.0]) * x + jnp.array([0.0, 1.0, 2.0]))


PARAMS = {"peak": jnp.float32(6.0), "centre": jnp.array([0.1, 0.0, -0.2])}
WEIGHTS = jax.random.normal(jax.random.key(0), (2, 7, 9, 3))


def objective(gradient, march=MARCH, packing=PACKINGS[0], params=PARAMS):
    """Offsets [2, 6] of (origin, look-at point) -> a scalar per pose of its colour, opacity and depth."""

    def values(offsets):
        poses = Pose(origin=START.origin + offsets[:, :3], target=START.target + offsets[:, 3:], up=START.up)
        out = marched.render_marched(
            smooth_field,
            params,
            marched.MarchSetup(GRID, RENDER_CONFIG, march),
            jax.vmap(pose_to_c2w)(poses),
            INTRINSICS,
            packing,
            gradient=gradient,
        ).output
        return (
            jnp.sum(out.rgb * WEIGHTS, axis=(1, 2, 3))
            + 0.3 * jnp.sum(out.acc, axis=(1, 2))
            + 0.01 * jnp.sum(out.depth, axis=(1, 2))
        )

    return values


def forward_gradient(values, offsets):
    _, tangents = jax.vmap(
        lambda e: jax.jvp(values, (offsets,), (jnp.broadcast_to(e, offsets.shape),)), out_axes=(None, 0)
    )(jnp.eye(6))
    return np.asarray(tangents).T  # [2, 6]


def reverse_gradient(values, offsets):
    value, pullback = jax.vjp(values, offsets)
    return np.asarray(pullback(jnp.ones_like(value))[0])


@pytest.mark.parametrize("packing", PACKINGS, ids=["cpu-default", "small-blocks"])
def test_reverse_equals_forward_and_finite_differences(packing):
    offsets = jnp.zeros((2, 6), jnp.float32)
    forward, reverse = objective("forward", packing=packing), objective("reverse", packing=packing)
    # The same images from the two programs (under jit the poses are traced, so each mode runs its own).
    np.testing.assert_array_equal(np.asarray(jax.jit(forward)(offsets)), np.asarray(jax.jit(reverse)(offsets)))
    g_forward, g_reverse = forward_gradient(forward, offsets), reverse_gradient(reverse, offsets)
    scale = np.max(np.abs(g_forward))
    assert scale > 0.1 and np.all(np.isfinite(g_reverse))
    np.testing.assert_allclose(g_reverse, g_forward, atol=2e-5 * scale)
    eps = 1e-3
    fd = np.zeros((2, 6))
    for k in range(6):
        step = np.zeros((2, 6), np.float32)
        step[:, k] = eps
        fd[:, k] = (np.asarray(forward(offsets + step)) - np.asarray(forward(offsets - step))) / (2 * eps)
    np.testing.assert_allclose(g_reverse, fd, atol=3e-3 * scale)


def test_an_untraced_call_runs_the_forward_program():
    """A call on concrete arrays cannot be differentiated: gradient="reverse" renders with the forward
    program (no second compilation) and the same images; traced, it differentiates in reverse mode."""
    offsets = jnp.zeros((2, 6), jnp.float32)
    packing = dataclasses.replace(PACKINGS[1], rays_per_block=48)  # a packing of this test's own: fresh programs
    forward, reverse = objective("forward", packing=packing), objective("reverse", packing=packing)
    images = np.asarray(forward(offsets))
    programs = marched._render_jit._cache_size()
    np.testing.assert_array_equal(np.asarray(reverse(offsets)), images)
    assert marched._render_jit._cache_size() == programs
    # Traced by jax.vjp it differentiates in reverse mode (the forward program has none: its while loops).
    g_reverse = reverse_gradient(reverse, offsets)
    np.testing.assert_allclose(g_reverse, forward_gradient(forward, offsets), atol=2e-5 * np.max(np.abs(g_reverse)))


def test_reverse_with_early_termination_and_dense_fog():
    """Rays that stop early (transmittance under the bound): the backward pass covers the samples each
    ray composited, no more, so it still equals forward mode; densities from 1e-3 to 1e4 stay finite."""
    offsets = jnp.zeros((2, 6), jnp.float32)
    march = MARCH.replace(min_transmittance=jnp.float32(1e-2))
    for peak in (1e-3, 6.0, 1e4):
        params = dict(PARAMS, peak=jnp.float32(peak))
        forward = objective("forward", march=march, packing=PACKINGS[1], params=params)
        reverse = objective("reverse", march=march, packing=PACKINGS[1], params=params)
        g_forward, g_reverse = forward_gradient(forward, offsets), reverse_gradient(reverse, offsets)
        assert np.all(np.isfinite(g_reverse)), peak
        np.testing.assert_allclose(g_reverse, g_forward, atol=2e-5 * max(np.max(np.abs(g_forward)), 1e-3))


def test_reverse_mode_only_and_refused_names():
    """The reverse renderer has no forward mode (its custom VJP), and a bad mode is named."""
    offsets = jnp.zeros((2, 6), jnp.float32)
    with pytest.raises(TypeError, match="custom_vjp"):
        jax.jvp(objective("reverse"), (offsets,), (offsets,))
    with pytest.raises(ValueError, match="gradient must be one of"):
        marched.render_marched(
            smooth_field,
            PARAMS,
            marched.MarchSetup(GRID, RENDER_CONFIG, MARCH),
            jnp.eye(4)[None],
            INTRINSICS,
            gradient="sideways",
        )


def test_trained_nerf_refine_gradients_agree(trained_lego_fast):
    """Through a trained hash-grid NeRF and a differentiable criterion, `values_and_gradients` in reverse
    mode equals forward mode (the refinement's gradient before), pose by pose."""
    from conftest import require_scene
    from waldo_jax.criteria import make_criterion
    from waldo_jax.nerf.checkpoint import load_checkpoint
    from waldo_jax.nerf.trained import TrainedField
    from waldo_jax.pipeline.sources import field_renderer
    from waldo_jax.scenes import load_scene
    from waldo_jax.search import training_poses

    checkpoint = load_checkpoint(trained_lego_fast[0])
    scene = load_scene(require_scene("lego_tiny"), split="train")
    intrinsics = scene.intrinsics.with_max_side(24)
    criterion = make_criterion("colorfulness").smooth()
    start = jax.tree.map(lambda a: a[:3], training_poses(scene.c2w))
    offsets = jnp.zeros((3, 6), jnp.float32)
    results = {}
    for mode in ("forward", "reverse"):
        field = TrainedField.create(
            checkpoint.params,
            checkpoint.occupancy,
            checkpoint.config,
            scene.near,
            scene.far,
            np.zeros(3, np.float32),
            scene.aabb,
        )
        render = field_renderer(field, gradient=mode)
        score = jax.tree_util.Partial(lambda r, c: criterion.evaluate(r(c, intrinsics)), render)
        results[mode] = jax.jit(lambda o, s=score, m=mode: values_and_gradients(s, start, jnp.float32(1.0), o, m))(
            offsets
        )
    (v_forward, g_forward), (v_reverse, g_reverse) = results["forward"], results["reverse"]
    np.testing.assert_allclose(np.asarray(v_reverse), np.asarray(v_forward), rtol=1e-6)  # XLA fuses each differently
    g_forward, g_reverse = np.asarray(g_forward), np.asarray(g_reverse)
    assert np.all(np.isfinite(g_reverse)) and np.max(np.abs(g_forward)) > 0
    np.testing.assert_allclose(g_reverse, g_forward, rtol=1e-3, atol=1e-4 * np.max(np.abs(g_forward)))
