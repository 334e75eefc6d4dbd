"""The procedural Waldo room: determinism, the visibility oracle, training cameras, rendering."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from waldo_jax.cameras import look_at
from waldo_jax.procedural import (
    DENSITY,
    RoomCameraConfig,
    make_room,
    room_field,
    room_scene,
    training_cameras,
    waldo_visibility,
    waldo_visibility_batch,
)
from waldo_jax.types import Intrinsics

UP = jnp.array([0.0, 1.0, 0.0])
INTR = Intrinsics.from_fov(64, 64, np.radians(60.0))


@pytest.fixture(scope="module")
def room():
    return make_room(0)


@pytest.fixture(scope="module")
def bare_room():
    """Walls, floor and Waldo only: nothing can stand between a camera and him."""
    return make_room(0, num_clutter=0, num_crates=0)


def side_camera(room, distance=1.6, height=0.5, angle=0.0):
    base = np.asarray(room.waldo_base)
    origin = base + np.array([distance * np.cos(angle), height, distance * np.sin(angle)])
    return look_at(jnp.asarray(origin), jnp.asarray(base + np.array([0.0, 0.5, 0.0])), UP)


@pytest.mark.slow
def test_same_seed_same_room_other_seed_other_room():
    a, b, c = make_room(3), make_room(3), make_room(4)
    for name in ("center", "size", "color", "waldo_points"):
        np.testing.assert_array_equal(np.asarray(getattr(a, name)), np.asarray(getattr(b, name)))
    assert not np.allclose(np.asarray(a.waldo_base), np.asarray(c.waldo_base))
    assert a.kind.shape == c.kind.shape  # shapes do not depend on the seed


@pytest.mark.slow
def test_primitives_sorted_by_kind(room):
    kinds = np.asarray(room.kind)
    assert np.all(np.diff(kinds) >= 0)
    assert room.num_boxes == int(np.sum(kinds == 0)) and room.num_spheres == int(np.sum(kinds == 1))


@pytest.mark.slow
def test_framed_unoccluded_waldo_is_fully_visible(bare_room):
    for angle in (0.0, 1.3, 2.9):
        vis = float(waldo_visibility(bare_room, side_camera(bare_room, angle=angle), INTR))
        assert vis > 0.95, (angle, vis)


@pytest.mark.slow
def test_waldo_behind_the_camera_is_invisible(bare_room):
    base = np.asarray(bare_room.waldo_base)
    origin = base + np.array([1.6, 0.5, 0.0])
    away = look_at(jnp.asarray(origin), jnp.asarray(origin + np.array([1.0, 0.0, 0.0])), UP)
    assert float(waldo_visibility(bare_room, away, INTR)) == 0.0


@pytest.mark.slow
def test_an_occluder_hides_waldo(bare_room, room):
    # The full room has crates around Waldo; from the bare room's viewpoint list, some side views
    # must lose visibility once the crates are there.
    angles = np.linspace(0, 2 * np.pi, 16, endpoint=False)
    bare = np.array([float(waldo_visibility(bare_room, side_camera(bare_room, 2.2, 0.3, a), INTR)) for a in angles])
    full = np.array([float(waldo_visibility(room, side_camera(room, 2.2, 0.3, a), INTR)) for a in angles])
    assert np.all(bare > 0.95)
    assert np.all(full <= bare + 1e-6)
    assert np.sum(full < 0.5) >= 4  # the pen blocks low views from several directions


@pytest.mark.slow
def test_cut_by_the_frame_is_partial(bare_room):
    base = np.asarray(bare_room.waldo_base)
    origin = base + np.array([1.2, 0.5, 0.0])
    # Aim so that Waldo sits on the left image border: about half of him is in frame.
    half_fov = np.radians(30.0)
    target = origin + np.array([-np.cos(half_fov), 0.0, np.sin(half_fov)])
    vis = float(waldo_visibility(bare_room, look_at(jnp.asarray(origin), jnp.asarray(target), UP), INTR))
    assert 0.2 < vis < 0.8


@pytest.mark.slow
def test_batch_equals_single(room):
    key = jax.random.key(0)
    origins = jax.random.uniform(key, (70, 3), minval=jnp.array([-3.0, 0.5, -3.0]), maxval=jnp.array([3.0, 1.7, 3.0]))
    c2w = jax.vmap(look_at, in_axes=(0, None, None))(origins, room.waldo_center, UP)
    batch = np.asarray(waldo_visibility_batch(room, c2w, INTR))
    single = np.array([float(waldo_visibility(room, c, INTR)) for c in c2w[:8]])
    np.testing.assert_allclose(batch[:8], single, atol=1e-5)
    assert np.all((batch >= 0) & (batch <= 1))
    assert batch.max() > 0.5  # looking straight at Waldo from inside the room often sees him


@pytest.mark.slow
def test_training_cameras_see_waldo_at_most_partly(room):
    config = RoomCameraConfig(max_visibility=0.5)
    c2w = training_cameras(jax.random.key(1), room, 16, INTR, config)
    assert c2w.shape == (16, 4, 4)
    vis = np.asarray(waldo_visibility_batch(room, jnp.asarray(c2w), INTR))
    assert np.all(vis <= 0.5)
    radius = np.linalg.norm(c2w[:, [0, 2], 3], axis=-1)
    assert np.all((radius >= 2.9 - 1e-5) & (radius <= 3.4 + 1e-5))


@pytest.mark.slow
def test_candidate_cameras_drawn_in_buckets_are_those_drawn_alone():
    from waldo_jax.procedural.cameras import _candidates, _candidates_in

    ranges = (np.float32((2.9, 3.4)), np.float32((1.0, 1.7)), np.float32(1.2), np.float32((0.2, 0.9)))
    for n in (7, 128, 200):
        key = jax.random.key(n)
        alone = np.asarray(_candidates_in(key, n, np.float32(n), *ranges))  # exactly n slots: the draw for n
        bucketed = _candidates(key, n, *ranges)  # 128 or 256 slots, cropped
        assert bucketed.shape == (n, 4, 4) and np.array_equal(bucketed, alone)
    programs = _candidates_in._cache_size()  # the bucket of 128 slots has run (n = 7 and 128 above)
    for n in (1, 60, 72, 127):  # other counts within it: no new program
        _candidates(jax.random.key(n), n, *ranges)
    assert _candidates_in._cache_size() == programs


@pytest.mark.slow
def test_too_strict_camera_filter_is_a_clear_error(room):
    with pytest.raises(ValueError, match="candidate cameras"):
        training_cameras(jax.random.key(1), room, 8, INTR, RoomCameraConfig(max_visibility=-1.0, oversample=1))


@pytest.mark.slow
def test_field_is_finite_and_bounded(room):
    points = jax.random.uniform(jax.random.key(2), (512, 3), minval=-5.0, maxval=5.0)
    sigma, rgb = jax.jit(jax.vmap(room_field, in_axes=(None, 0, None)))(room, points, jnp.array([0.0, 0.0, -1.0]))
    assert np.all(np.isfinite(sigma)) and np.all(np.isfinite(rgb))
    assert np.all((sigma >= 0) & (sigma <= DENSITY)) and np.all((rgb >= 0) & (rgb <= 1))
    field = jax.jit(room_field)
    inside_floor = field(room, jnp.array([0.0, -0.1, 0.0]), jnp.zeros(3))[0]
    in_the_air = field(room, jnp.array([3.5, 2.5, 3.5]), jnp.zeros(3))[0]
    assert float(inside_floor) > 0.99 * DENSITY and float(in_the_air) < 1e-3


@pytest.mark.slow
def test_room_scene_renders_views_where_waldo_shows_red_stripes():
    scene, room = room_scene(seed=0, num_views=4, resolution=24, num_samples=48)
    assert scene.images.shape == (4, 24, 24, 3) and scene.c2w.shape == (4, 4, 4)
    assert scene.format == "procedural" and scene.n_images == 4
    assert np.all(np.isfinite(scene.images)) and scene.images.min() >= 0 and scene.images.max() <= 1
    assert scene.images.std() > 0.05  # not a blank picture
    # A close, unobstructed-from-above render of Waldo shows his red jumper.
    from waldo_jax.procedural import room_render_config
    from waldo_jax.render import render_views

    base = np.asarray(room.waldo_base)
    cam = look_at(jnp.asarray(base + np.array([0.25, 1.6, 0.0])), jnp.asarray(base + np.array([0.0, 0.6, 0.0])), UP)
    image = np.asarray(
        render_views(
            room_field, room, cam[None], Intrinsics.from_fov(32, 32, 1.0), room_render_config(room, num_samples=96)
        ).rgb[0]
    )
    red = (image[..., 0] > 0.6) & (image[..., 1] < 0.25) & (image[..., 2] < 0.25)
    assert red.sum() >= 5
