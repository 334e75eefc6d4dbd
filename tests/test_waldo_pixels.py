"""Waldo in the pictures (issue 42): his pixel mask, the PSNR over his pixels, his size and stripes in the
room, and training cameras chosen to cover his surface."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from waldo_jax.cameras import look_at
from waldo_jax.metrics import masked_psnr
from waldo_jax.procedural import RoomCameraConfig, make_room, waldo_mask, waldo_surface_seen, waldo_visibility_batch
from waldo_jax.procedural.cameras import training_cameras
from waldo_jax.procedural.visibility import waldo_samples_seen, waldo_visibility
from waldo_jax.types import Intrinsics

INTR = Intrinsics.from_fov(32, 32, np.radians(60.0))


def test_masked_psnr_counts_only_the_masked_pixels():
    truth = np.zeros((2, 4, 4, 3))
    rendered = truth.copy()
    rendered[:, :2] = 0.1  # an error of 0.1 on every channel of the top half
    rendered[:, 2:] = 0.9  # a large error outside the mask
    mask = np.zeros((2, 4, 4))
    mask[0, :2] = 1.0  # image 0: the top half; image 1: no pixel
    psnr = masked_psnr(rendered, truth, mask)
    assert psnr[0] == pytest.approx(20.0, abs=1e-9)  # -10 log10(0.01)
    assert np.isnan(psnr[1])


@pytest.mark.slow
def test_default_room_is_unchanged_by_the_new_arguments_and_scale_grows_waldo():
    base = make_room(1)
    same = make_room(1, waldo_scale=1.0, stripe_width=0.05)
    for a, b in zip(jax.tree_util.tree_leaves(base), jax.tree_util.tree_leaves(same)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    big = make_room(1, waldo_scale=1.5)
    extent = lambda r: np.ptp(np.asarray(r.waldo_points)[:, 1])  # noqa: E731
    assert extent(big) == pytest.approx(1.5 * extent(base), rel=0.02)
    np.testing.assert_allclose(big.waldo_base, base.waldo_base)  # he stands where he stood
    assert float(big.stripe_width) == pytest.approx(0.075)
    for bad in ({"waldo_scale": 3.0}, {"waldo_scale": 0.1}, {"stripe_width": 0.0}):
        with pytest.raises(ValueError, match=str(next(iter(bad.values())))):
            make_room(1, **bad)


@pytest.mark.slow
def test_waldo_mask_is_where_he_is_seen():
    room = make_room(1)
    centre = np.asarray(room.waldo_center)
    eye = centre + np.array([0.0, 0.3, 1.6])
    facing = look_at(jnp.asarray(eye), jnp.asarray(centre), jnp.array([0.0, 1.0, 0.0]))
    away = look_at(jnp.asarray(eye), jnp.asarray(eye + np.array([0.0, 0.0, 1.0])), jnp.array([0.0, 1.0, 0.0]))
    c2w = jnp.stack([facing, away])
    mask = waldo_mask(room, c2w, INTR)
    visible = np.asarray(waldo_visibility_batch(room, c2w, INTR))
    assert mask.shape == (2, 32, 32) and mask.min() >= 0.0 and mask.max() <= 1.0 + 1e-6
    assert visible[1] == 0.0 and not (mask[1] > 0.5).any()
    assert visible[0] > 0.5 and (mask[0] > 0.5).sum() > 20
    # He stands at the image centre of a camera looking at him.
    rows, cols = np.nonzero(mask[0] > 0.5)
    assert abs(rows.mean() - 15.5) < 6 and abs(cols.mean() - 15.5) < 4


@pytest.mark.slow
def test_samples_seen_agree_with_surface_seen():
    room = make_room(1)
    c2w = jnp.asarray(training_cameras(jax.random.key(0), room, 6, INTR))
    seen = np.asarray(waldo_samples_seen(room, c2w, INTR))  # [P, M]
    area = np.asarray(room.waldo_areas, np.float64)
    share = float((seen.any(0) * area).sum() / area.sum())
    assert share == pytest.approx(float(waldo_surface_seen(room, c2w, INTR)), abs=1e-5)


@pytest.mark.slow
def test_covering_cameras_see_more_of_waldo_and_still_at_most_half():
    room = make_room(1)
    config = RoomCameraConfig()
    key = jax.random.key(3)
    plain = training_cameras(key, room, 12, INTR, config)
    covering = training_cameras(key, room, 12, INTR, config.__class__(cover_views=6))
    again = training_cameras(key, room, 12, INTR, config.__class__(cover_views=6))
    np.testing.assert_array_equal(covering, again)  # same key, same cameras
    assert covering.shape == (12, 4, 4)
    visible = np.asarray(waldo_visibility_batch(room, jnp.asarray(covering), INTR))
    assert visible.max() <= config.max_visibility + 1e-6  # no view sees more than half of him
    assert float(waldo_surface_seen(room, jnp.asarray(covering), INTR)) > float(
        waldo_surface_seen(room, jnp.asarray(plain), INTR)
    )


def test_field_of_view_in_degrees_is_refused():
    with pytest.raises(ValueError, match="radians"):
        Intrinsics.from_fov(32, 32, 60.0)


@pytest.mark.slow
def test_held_out_views_are_as_many_as_asked_with_the_training_share_covering():
    """`held_out_scene` returns `count` views (it once returned `cover_views` of them when asked for fewer),
    of which the training views' share covers Waldo; more covering views than views is refused."""
    from waldo_jax.procedural import held_out_scene, room_scene

    room = make_room(1)
    config = RoomCameraConfig(cover_views=4)
    scene, room = room_scene(1, num_views=12, resolution=16, camera_config=config, room=room)
    test = held_out_scene(room, 1, 3, scene, config)
    assert test.images.shape == (3, 16, 16, 3) and test.c2w.shape == (3, 4, 4)
    assert held_out_scene(room, 1, 6, scene, config).n_images == 6  # 2 of them covering (4 x 6 / 12)
    with pytest.raises(ValueError, match="cover_views"):
        training_cameras(jax.random.key(0), room, 3, INTR, config)


def test_eager_oracles_share_one_program_across_population_sizes():
    """Eager calls of the batched oracles pad their cameras to `POSE_BUCKET` (one program for every size
    up to it) and give each camera the value it has alone in a batch of its own size."""
    from waldo_jax.procedural import visibility

    room = make_room(1)
    c2w = np.asarray(training_cameras(jax.random.key(0), room, 9, INTR))
    full = waldo_visibility_batch(room, c2w, INTR)
    programs = visibility._visibility_batch._cache_size()
    for count in (1, 4, 9):
        np.testing.assert_array_equal(waldo_visibility_batch(room, c2w[:count], INTR), full[:count])
    assert visibility._visibility_batch._cache_size() == programs
    unpadded = np.asarray(jax.jit(jax.vmap(waldo_visibility, in_axes=(None, 0, None)))(room, jnp.asarray(c2w), INTR))
    np.testing.assert_array_equal(full, unpadded)
    seen = waldo_samples_seen(room, c2w, INTR)
    np.testing.assert_array_equal(waldo_samples_seen(room, c2w[:2], INTR), seen[:2])
    # Traced (here the room, under jit), nothing is padded and the value is the same.
    traced = jax.jit(lambda r: waldo_visibility_batch(r, jnp.asarray(c2w), INTR))(room)
    np.testing.assert_array_equal(np.asarray(traced), full)
