"""Tests of waldo_jax.render: the volume-rendering integral against closed forms, robustness sweeps,
and the batched `render_views` against a loop over `render_view`.

Tiny images (at most 5x3 pixels) and few samples keep the suite fast; every jitted entry point is
built once at module level and the fields take their numbers from `params`, so that one compilation
serves many cases.
"""

from __future__ import annotations

import numpy as np
import pytest

# Importing waldo_jax first sets the XLA flag it needs before JAX starts its CPU backend.
from waldo_jax.cameras import look_at
from waldo_jax.render import (
    MAX_DENSITY,
    RenderConfig,
    ray_aabb_interval,
    render_rays,
    render_view,
    render_views,
    sample_interval,
    volume_weights,
)
from waldo_jax.types import Intrinsics

import jax  # noqa: E402  (after waldo_jax, see above)
import jax.numpy as jnp  # noqa: E402

BACKGROUND = (0.2, 0.4, 0.9)
BACKGROUND32 = np.float32(BACKGROUND)  # what the renderer holds and returns bit for bit
SLAB_RGB = (1.0, 0.5, 0.0)

# ------------------------------------------------------------------------------------------------
# Fields and jitted entry points.


def slab_field(params, x, d):
    """Density params["sigma"] where params["lo"] <= x_0 <= params["hi"], else 0; constant colour."""
    del d
    inside = (x[0] >= params["lo"]) & (x[0] <= params["hi"])
    return jnp.where(inside, params["sigma"], 0.0), params["rgb"]


def ball_field(params, x, d):
    """Density params["sigma"] inside a ball of radius 0.7; colour varies with position and direction."""
    inside = jnp.sum(x * x) < 0.49
    rgb = jnp.clip(params["rgb"] + 0.3 * x + 0.1 * d, 0.0, 1.0)
    return jnp.where(inside, params["sigma"], 0.0), rgb


def _slab(sigma, lo, hi, rgb=SLAB_RGB):
    return {"sigma": jnp.float32(sigma), "lo": jnp.float32(lo), "hi": jnp.float32(hi), "rgb": jnp.float32(rgb)}


def _ball(sigma, rgb=(0.5, 0.5, 0.5)):
    return {"sigma": jnp.float32(sigma), "rgb": jnp.float32(rgb)}


_render_rays = jax.jit(render_rays, static_argnames=("field",))
_render_view = jax.jit(render_view, static_argnames=("field",))
_volume_weights = jax.jit(volume_weights)
_sample_interval = jax.jit(sample_interval, static_argnames=("num_samples",))
_ray_aabb_interval = jax.jit(ray_aabb_interval)
_weights_sum_grad = jax.jit(jax.grad(lambda sigma, delta: jnp.sum(volume_weights(sigma, delta))))

INTRINSICS = Intrinsics.create(5, 3, 4.0)  # 15 pixels: not a multiple of the ray chunk below
BOX = ((-1.0, -1.0, -1.0), (1.0, 1.0, 1.0))


def _config(near=0.0, far=10.0, aabb=None, num_samples=16, **kwargs):
    return RenderConfig.create(near=near, far=far, aabb=aabb, background=BACKGROUND, num_samples=num_samples, **kwargs)


def _rays(origins, directions):
    directions = np.asarray(directions, np.float64)
    directions = directions / np.linalg.norm(directions, axis=-1, keepdims=True)
    return jnp.asarray(np.asarray(origins, np.float32)), jnp.asarray(directions.astype(np.float32))


def _expected_rgb(acc, colour=SLAB_RGB):
    acc = np.asarray(acc, np.float64)[..., None]
    return acc * np.asarray(colour) + (1.0 - acc) * np.asarray(BACKGROUND)


# Rays along +x from x = 0, at a few lateral offsets (the slab field only looks at x_0).
_X_ORIGINS = [[0.0, 0.0, 0.0], [0.0, 0.3, -0.2], [0.0, -5.0, 2.0]]
_X_DIRS = [[1.0, 0.0, 0.0]] * 3


# ------------------------------------------------------------------------------------------------
# The integral against closed forms.


@pytest.mark.parametrize("sigma", [0.1, 1.0, 5.0])
def test_slab_covering_near_far_matches_closed_form_exactly(sigma):
    near, far = 1.0, 2.5
    config = _config(near=near, far=far, num_samples=16)
    origins, dirs = _rays(_X_ORIGINS, _X_DIRS)
    out = _render_rays(slab_field, _slab(sigma, near, far), origins, dirs, config)
    acc = 1.0 - np.exp(-sigma * (far - near))
    np.testing.assert_allclose(out.acc, np.full(3, acc), rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(out.rgb, np.broadcast_to(_expected_rgb(acc), (3, 3)), atol=1e-5)
    # The expected termination distance lies within the slab.
    mean_depth = np.asarray(out.depth) / np.asarray(out.acc)
    assert np.all((near < mean_depth) & (mean_depth < 0.5 * (near + far)))


@pytest.mark.slow
@pytest.mark.parametrize("sigma", [0.2, 3.0])
@pytest.mark.parametrize("stratified", [False, True], ids=["midpoints", "stratified"])
def test_slab_inside_long_interval_within_1e3_with_512_samples(sigma, stratified):
    # Bin edges do not line up with the slab: each edge bin is partly inside. The effective slab
    # length is off by less than one bin (2/512), so acc is off by < sigma exp(-sigma L) 2/512 < 1e-3.
    lo, hi = 0.37, 1.37
    config = _config(near=0.0, far=2.0, num_samples=512)
    origins, dirs = _rays(_X_ORIGINS, _X_DIRS)
    key = jax.random.key(7) if stratified else None
    out = _render_rays(slab_field, _slab(sigma, lo, hi), origins, dirs, config, key)
    acc = 1.0 - np.exp(-sigma * (hi - lo))
    np.testing.assert_allclose(out.acc, np.full(3, acc), atol=1e-3)
    np.testing.assert_allclose(out.rgb, np.broadcast_to(_expected_rgb(acc), (3, 3)), atol=1e-3)


@pytest.mark.slow
@pytest.mark.parametrize("sigma", [0.5, 2.0])
def test_slab_from_aabb_clipping_matches_closed_form(sigma):
    # Constant density everywhere; only the box [-1, 1]^3 bounds the samples.
    config = _config(near=0.0, far=10.0, aabb=BOX, num_samples=16)
    origins, dirs = _rays(
        [[-3.0, 0.2, 0.1], [-3.0, -3.0, 0.0], [0.0, 0.0, 0.0], [0.5, 3.0, -0.5]],
        [[1.0, 0.0, 0.0], [1.0, 1.0, 0.0], [0.0, 0.0, -1.0], [0.0, -1.0, 0.0]],
    )
    lengths = np.array([2.0, 2.0 * np.sqrt(2.0), 1.0, 2.0])  # chord inside the box (from inside: to exit)
    out = _render_rays(slab_field, _slab(sigma, -1e9, 1e9), origins, dirs, config)
    acc = 1.0 - np.exp(-sigma * lengths)
    np.testing.assert_allclose(out.acc, acc, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(out.rgb, _expected_rgb(acc), atol=1e-5)


def test_empty_space_gives_background():
    config = _config(near=0.0, far=4.0, num_samples=16)
    origins, dirs = _rays(_X_ORIGINS, _X_DIRS)
    out = _render_rays(slab_field, _slab(0.0, 1.0, 2.0), origins, dirs, config)
    np.testing.assert_array_equal(out.acc, np.zeros(3))
    np.testing.assert_array_equal(out.depth, np.zeros(3))
    np.testing.assert_array_equal(out.rgb, np.broadcast_to(BACKGROUND32, (3, 3)))


def test_opaque_wall_depth_within_one_bin():
    wall, near, far, num_samples = 2.3, 0.0, 8.0, 64
    bin_length = (far - near) / num_samples
    angles = np.array([0.0, 0.3, 0.6, 1.0])
    origins, dirs = _rays(np.zeros((4, 3)), np.stack([np.cos(angles), np.sin(angles), 0 * angles], -1))
    config = _config(near=near, far=far, num_samples=num_samples)
    out = _render_rays(slab_field, _slab(1e4, wall, 1e9), origins, dirs, config)
    np.testing.assert_allclose(out.acc, np.ones(4), atol=1e-5)
    np.testing.assert_allclose(out.depth, wall / np.cos(angles), atol=bin_length)
    np.testing.assert_allclose(out.rgb, np.broadcast_to(SLAB_RGB, (4, 3)), atol=1e-5)


# ------------------------------------------------------------------------------------------------
# Robustness: extreme and non-finite densities, grazing and missing rays, empty intervals.

_C2W = np.asarray(look_at(jnp.float32([0.3, 0.2, 3.0]), jnp.zeros(3), jnp.float32([0.0, 1.0, 0.0])))
_VIEW_CONFIG = _config(near=0.5, far=6.0, aabb=BOX, num_samples=16, ray_chunk=4)


def _view_loss(sigma, key=None):
    out = render_view(ball_field, _ball(sigma), _C2W, INTRINSICS, _VIEW_CONFIG, key)
    return jnp.mean((out.rgb - 0.3) ** 2), out


_loss_and_grad = jax.jit(jax.value_and_grad(_view_loss, has_aux=True))


@pytest.mark.slow
@pytest.mark.parametrize("sigma", [1e-6, 1e-3, 1.0, 1e3, 1e6, MAX_DENSITY])
@pytest.mark.parametrize("stratified", [False, True], ids=["midpoints", "stratified"])
def test_finite_outputs_and_gradients_across_densities(sigma, stratified):
    key = jax.random.key(3) if stratified else None
    (loss, out), grad = _loss_and_grad(jnp.float32(sigma), key)
    for leaf in (loss, out.rgb, out.depth, out.acc, grad):
        assert np.all(np.isfinite(np.asarray(leaf))), (sigma, leaf)
    acc = np.asarray(out.acc)
    assert np.all((acc >= 0.0) & (acc <= 1.0 + 1e-6))
    if sigma <= 1.0:  # translucent: the loss does depend on the density
        assert abs(float(grad)) > 0.0


@pytest.mark.slow
def test_density_gradient_matches_finite_difference():
    sigma, h = 1.0, 1e-2
    (_, _), grad = _loss_and_grad(jnp.float32(sigma), None)
    (plus, _), _ = _loss_and_grad(jnp.float32(sigma + h), None)
    (minus, _), _ = _loss_and_grad(jnp.float32(sigma - h), None)
    np.testing.assert_allclose(float(grad), (float(plus) - float(minus)) / (2 * h), rtol=2e-2)


@pytest.mark.slow
def test_non_finite_densities_from_the_field_give_finite_outputs():
    hit = np.asarray(_loss_and_grad(jnp.float32(1.0), None)[0][1].acc) > 0.0  # pixels seeing the ball
    assert hit.any() and (~hit).any()
    background = np.broadcast_to(BACKGROUND, INTRINSICS.shape + (3,))
    for bad in (np.nan, np.inf, -np.inf):
        (loss, out), _ = _loss_and_grad(jnp.float32(bad), None)
        for leaf in (loss, out.rgb, out.depth, out.acc):
            assert np.all(np.isfinite(np.asarray(leaf))), (bad, leaf)
        if np.isposinf(bad):  # +inf is clamped to MAX_DENSITY: opaque where the ball is
            np.testing.assert_allclose(np.asarray(out.acc)[hit], 1.0, atol=1e-6)
        else:  # NaN and -inf count as empty space
            np.testing.assert_array_equal(out.acc, np.zeros(INTRINSICS.shape))
            np.testing.assert_allclose(out.rgb, background, atol=1e-6)


@pytest.mark.slow
def test_non_finite_colours_from_the_field_give_finite_outputs():
    out = _render_view(ball_field, _ball(2.0, rgb=(np.nan, 0.5, 0.5)), _C2W, INTRINSICS, _VIEW_CONFIG)
    assert np.all(np.isfinite(np.asarray(out.rgb)))


_ray_loss_grad = jax.jit(
    jax.grad(lambda sigma, o, d, config: jnp.sum(render_rays(slab_field, _slab(sigma, -1e9, 1e9), o, d, config).rgb))
)


@pytest.mark.slow
def test_grazing_and_missing_rays():
    config = _config(near=0.0, far=10.0, aabb=BOX, num_samples=16)
    eps = 1e-6
    origins, dirs = _rays(
        [
            [-3.0, 1.0, 0.0],  # along the top face y = 1
            [-3.0, -1.0, 0.0],  # along the bottom face
            [-3.0, 1.0, 1.0],  # along an edge
            [-3.0, 1.0 - eps, 0.0],  # just inside
            [-3.0, 1.0 + eps, 0.0],  # just outside
            [-3.0, 2.0, 0.0],  # misses
            [3.0, 0.0, 0.0],  # box behind the camera
            [0.0, 2.0, 0.0],  # touches the edge (1, 1, z) at one point: zero-length interval
        ],
        [[1.0, 0.0, 0.0]] * 7 + [[1.0, -1.0, 0.0]],
    )
    sigma = 1.0
    out = _render_rays(slab_field, _slab(sigma, -1e9, 1e9), origins, dirs, config)
    for leaf in (out.rgb, out.depth, out.acc):
        assert np.all(np.isfinite(np.asarray(leaf)))
    acc = np.asarray(out.acc)
    assert np.all((acc >= 0.0) & (acc <= 1.0))
    for i in (0, 1, 2):  # on the boundary: either a full chord or nothing, nothing in between
        assert acc[i] < 1e-6 or abs(acc[i] - (1 - np.exp(-2 * sigma))) < 1e-5, acc[i]
    np.testing.assert_allclose(acc[3], 1.0 - np.exp(-2.0 * sigma), rtol=1e-5)
    for i in (4, 5, 6):  # misses: exactly the background
        assert acc[i] == 0.0 and float(out.depth[i]) == 0.0
        np.testing.assert_array_equal(out.rgb[i], BACKGROUND32)
    assert acc[7] < 1e-5
    grad = _ray_loss_grad(jnp.float32(sigma), origins, dirs, config)
    assert np.isfinite(float(grad))


@pytest.mark.slow
def test_zero_length_interval_gives_background_and_finite_gradients():
    # `create` rejects far <= near; build the config directly to get an empty [near, far].
    config = RenderConfig(
        num_samples=8,
        ray_chunk=8,
        use_aabb=False,
        near=jnp.float32(2.0),
        far=jnp.float32(2.0),
        aabb=jnp.float32(BOX),
        background=jnp.float32(BACKGROUND),
    )
    origins, dirs = _rays(_X_ORIGINS, _X_DIRS)
    for sigma in (1.0, 1e6, MAX_DENSITY):
        out = _render_rays(slab_field, _slab(sigma, -1e9, 1e9), origins, dirs, config)
        np.testing.assert_array_equal(out.acc, np.zeros(3))
        np.testing.assert_array_equal(out.rgb, np.broadcast_to(BACKGROUND32, (3, 3)))
        assert np.isfinite(float(_ray_loss_grad(jnp.float32(sigma), origins, dirs, config)))
    t_edges, t = _sample_interval(None, jnp.float32(2.0), jnp.float32(2.0), num_samples=8)
    np.testing.assert_array_equal(t_edges, np.full(9, 2.0))
    np.testing.assert_array_equal(t, np.full(8, 2.0))
    # A reversed interval is empty too.
    t_edges, _ = _sample_interval(None, jnp.float32(3.0), jnp.float32(1.0), num_samples=8)
    np.testing.assert_array_equal(t_edges, np.full(9, 3.0))


# ------------------------------------------------------------------------------------------------
# Building blocks.


@pytest.mark.slow
@pytest.mark.parametrize("seed", range(5))
def test_volume_weights_sum_to_at_most_one(seed):
    rng = np.random.default_rng(seed)
    num_samples = 64
    sigma = 10.0 ** rng.uniform(-6, 10, num_samples)
    sigma[rng.integers(0, num_samples, 8)] = 0.0
    sigma[rng.integers(0, num_samples, 2)] = np.nan
    sigma[rng.integers(0, num_samples, 2)] = np.inf
    delta = rng.uniform(0.0, 0.5, num_samples)
    w = np.asarray(_volume_weights(jnp.float32(sigma), jnp.float32(delta)), np.float64)
    assert np.all(np.isfinite(w)) and np.all(w >= 0.0)
    assert w.sum() <= 1.0 + 1e-6
    grad = _weights_sum_grad(jnp.float32(np.nan_to_num(sigma, posinf=MAX_DENSITY)), jnp.float32(delta))
    assert np.all(np.isfinite(np.asarray(grad)))


@pytest.mark.parametrize("sigma,delta", [(0.01, 0.1), (1.0, 0.05), (3.0, 0.2), (50.0, 0.01)])
def test_volume_weights_closed_form_for_constant_density(sigma, delta):
    num_samples = 32
    w = _volume_weights(jnp.full(num_samples, sigma, jnp.float32), jnp.full(num_samples, delta, jnp.float32))
    i = np.arange(num_samples)
    expected = np.exp(-sigma * delta * i) * (1.0 - np.exp(-sigma * delta))
    np.testing.assert_allclose(w, expected, rtol=1e-5, atol=1e-7)
    np.testing.assert_allclose(
        np.sum(np.asarray(w, np.float64)), 1 - np.exp(-sigma * delta * num_samples), rtol=1e-5, atol=1e-7
    )


@pytest.mark.parametrize("axis", [0, 1, 2])
@pytest.mark.parametrize("sign", [1.0, -1.0])
def test_ray_aabb_interval_axis_parallel(axis, sign):
    aabb = jnp.float32([[-1.0, -2.0, -0.5], [1.0, 2.0, 0.5]])
    half = np.array([1.0, 2.0, 0.5])
    e = np.eye(3)[axis]
    lateral = np.array([0.3, -0.4, 0.2]) * (1 - e)  # inside the box on the other two axes
    direction = jnp.float32(sign * e)
    # From outside, 3 units before the near face.
    origin = lateral - sign * (half[axis] + 3.0) * e
    t_enter, t_exit = _ray_aabb_interval(jnp.float32(origin), direction, aabb)
    np.testing.assert_allclose([t_enter, t_exit], [3.0, 3.0 + 2 * half[axis]], rtol=1e-6)
    # From inside: the entry lies behind the origin.
    t_enter, t_exit = _ray_aabb_interval(jnp.float32(lateral), direction, aabb)
    np.testing.assert_allclose([t_enter, t_exit], [-half[axis], half[axis]], rtol=1e-6)
    # Beside the box: a miss (exit before entry), with finite numbers.
    t_enter, t_exit = _ray_aabb_interval(jnp.float32(origin + 5.0 * (1 - e)), direction, aabb)
    assert np.isfinite(float(t_enter)) and np.isfinite(float(t_exit)) and float(t_exit) < float(t_enter)


@pytest.mark.slow
def test_stratified_samples_lie_inside_their_bins():
    num_samples = 16
    keys = jax.random.split(jax.random.key(0), 64)
    t_start = jnp.float32(np.random.default_rng(0).uniform(0.0, 2.0, 64))
    t_end = t_start + jnp.float32(np.random.default_rng(1).uniform(0.1, 5.0, 64))
    sample = jax.jit(jax.vmap(lambda k, a, b: sample_interval(k, a, b, num_samples)))
    t_edges, t = (np.asarray(a) for a in sample(keys, t_start, t_end))
    assert t_edges.shape == (64, num_samples + 1) and t.shape == (64, num_samples)
    np.testing.assert_allclose(t_edges[:, 0], t_start, rtol=1e-6)
    np.testing.assert_allclose(t_edges[:, -1], t_end, rtol=1e-6)
    assert np.all(t_edges[:, :-1] <= t) and np.all(t <= t_edges[:, 1:])
    midpoints = 0.5 * (t_edges[:, :-1] + t_edges[:, 1:])
    assert np.abs(t - midpoints).max() > 0.1 * np.diff(t_edges, axis=-1).min()  # jittered, not midpoints
    # Per-key streams differ, and the position inside the bin spans the bin.
    fraction = (t - t_edges[:, :-1]) / np.diff(t_edges, axis=-1)
    assert fraction.min() < 0.1 and fraction.max() > 0.9
    # Without a key: the midpoints.
    _, t_mid = _sample_interval(None, t_start[0], t_end[0], num_samples=num_samples)
    np.testing.assert_allclose(t_mid, midpoints[0], rtol=1e-6)


# ------------------------------------------------------------------------------------------------
# render_views


def _poses(num_poses: int) -> np.ndarray:
    angles = np.linspace(0.0, 2.0, num_poses)
    origins = np.stack([2.5 * np.sin(angles), 0.4 + 0.1 * angles, 2.5 * np.cos(angles)], -1).astype(np.float32)
    up = jnp.float32([0.0, 1.0, 0.0])
    return np.stack([np.asarray(look_at(o, jnp.float32([0.05, 0.0, -0.1]), up)) for o in origins])


_VIEWS_CONFIG = _config(near=0.5, far=6.0, aabb=BOX, num_samples=8, ray_chunk=4)
_VIEWS_PARAMS = _ball(1.5, rgb=(0.2, 0.6, 0.4))


@pytest.mark.slow
def test_render_views_equals_loop_over_render_view():
    # 3 poses of 15 pixels, rendered 4 rays at a time: the last chunk is padded.
    num_poses = 3
    c2w = _poses(num_poses)
    out = render_views(ball_field, _VIEWS_PARAMS, c2w, INTRINSICS, _VIEWS_CONFIG)
    assert out.rgb.shape == (num_poses, 3, 5, 3)
    assert out.depth.shape == out.acc.shape == (num_poses, 3, 5)
    acc = np.asarray(out.acc)
    assert acc.max() > 0.3 and acc.min() < 1e-3  # the views see both the ball and the background
    for i in range(num_poses):
        ref = _render_view(ball_field, _VIEWS_PARAMS, c2w[i], INTRINSICS, _VIEWS_CONFIG)
        for got, want in zip((out.rgb, out.depth, out.acc), (ref.rgb, ref.depth, ref.acc)):
            np.testing.assert_array_equal(got[i], want)  # every ray is computed alike: the same bits
    # [P, 3, 4] matrices give the same images.
    out34 = render_views(ball_field, _VIEWS_PARAMS, c2w[:, :3], INTRINSICS, _VIEWS_CONFIG)
    np.testing.assert_allclose(out34.rgb, out.rgb, atol=1e-6)


@pytest.mark.slow
def test_render_views_keys_determinism():
    c2w = _poses(3)

    def render(key=None):
        return render_views(ball_field, _VIEWS_PARAMS, c2w, INTRINSICS, _VIEWS_CONFIG, key)

    plain = render()
    np.testing.assert_array_equal(render().rgb, plain.rgb)
    np.testing.assert_array_equal(render().depth, plain.depth)
    keyed = render(jax.random.key(1))
    assert np.abs(np.asarray(keyed.depth) - np.asarray(plain.depth)).max() > 1e-4
    again = render(jax.random.key(1))
    np.testing.assert_array_equal(again.rgb, keyed.rgb)
    np.testing.assert_array_equal(again.depth, keyed.depth)
    other = render(jax.random.key(2))
    assert np.abs(np.asarray(other.depth) - np.asarray(keyed.depth)).max() > 1e-4
    # Each pose has its own sampling stream: two identical poses render differently with a key.
    same = np.stack([c2w[0], c2w[0], c2w[1]])
    twins = render_views(ball_field, _VIEWS_PARAMS, same, INTRINSICS, _VIEWS_CONFIG, jax.random.key(1))
    assert np.abs(np.asarray(twins.depth[0]) - np.asarray(twins.depth[1])).max() > 1e-4


@pytest.mark.slow
def test_render_views_accepts_legacy_uint32_keys():
    c2w = _poses(3)
    legacy = render_views(ball_field, _VIEWS_PARAMS, c2w, INTRINSICS, _VIEWS_CONFIG, jax.random.PRNGKey(0))
    assert np.all(np.isfinite(np.asarray(legacy.rgb)))


@pytest.mark.slow
def test_render_views_second_call_does_not_recompile():
    traces = []

    def counting_field(params, x, d):
        traces.append(1)  # runs only while JAX traces the function
        return ball_field(params, x, d)

    c2w = _poses(3)
    render_views(counting_field, _VIEWS_PARAMS, c2w, INTRINSICS, _VIEWS_CONFIG)
    first = len(traces)
    cache = render_views._cache_size()
    assert first > 0
    # New values for every array argument, same shapes and static settings: no new trace.
    config = _config(near=0.4, far=5.0, aabb=((-2, -2, -2), (2, 2, 2)), num_samples=8, ray_chunk=4).replace(
        background=jnp.float32([0.0, 0.0, 0.0])
    )
    out = render_views(
        counting_field,
        _ball(7.0, rgb=(0.9, 0.1, 0.1)),
        _poses(3)[::-1].copy(),
        INTRINSICS.replace(fx=jnp.float32(3.0)),
        config,
    )
    jax.block_until_ready(out)
    assert len(traces) == first
    assert render_views._cache_size() == cache
    # The counter does see a recompilation (a new number of poses).
    render_views(counting_field, _VIEWS_PARAMS, _poses(4), INTRINSICS, _VIEWS_CONFIG)
    assert len(traces) > first


@pytest.mark.slow
def test_render_views_does_not_depend_on_the_chunking():
    """The rays of all poses form one list cut into chunks; each ray is computed alike whatever the
    chunk size and its stratified samples come from its own key, so the images agree to the last bits
    (XLA may vectorise another chunk shape differently: a few ulps)."""
    c2w = _poses(3)
    for key in (None, jax.random.key(4)):
        small = render_views(ball_field, _VIEWS_PARAMS, c2w, INTRINSICS, _VIEWS_CONFIG, key)
        large = render_views(ball_field, _VIEWS_PARAMS, c2w, INTRINSICS, _VIEWS_CONFIG.replace(ray_chunk=7), key)
        for a, b in zip(jax.tree.leaves(small), jax.tree.leaves(large)):
            np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-6, atol=1e-7)
