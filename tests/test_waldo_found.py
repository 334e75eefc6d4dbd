"""`waldo_found` ("Waldo whole, as large as possible") on analytic cases, and pose criteria in combinations."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from waldo_jax.cameras import look_at
from waldo_jax.criteria import CriterionContext, CriterionError, build_criterion, constrained, make_criterion, weighted
from waldo_jax.criteria.oracle import FOUND_SOFTNESS, found_score
from waldo_jax.procedural import FOUND_VISIBILITY, WaldoRoom, make_room, waldo_coverage, waldo_view, waldo_visibility
from waldo_jax.procedural.room import KIND_BOX
from waldo_jax.types import Intrinsics

INTR = Intrinsics.from_fov(32, 32, np.radians(60.0))
UP = jnp.array([0.0, 1.0, 0.0])


@pytest.fixture(scope="module")
def bare_room():
    """Walls, floor and Waldo only: nothing stands between a camera and him."""
    return make_room(3, num_clutter=0, num_crates=0)


def _with_box(room: WaldoRoom, center, half) -> WaldoRoom:
    """`room` with one more box (boxes come first in the flat arrays)."""
    row = dict(
        kind=jnp.array([KIND_BOX], jnp.int32),
        center=jnp.asarray([center], jnp.float32),
        size=jnp.asarray([half], jnp.float32),
        color=jnp.full((1, 3), 0.5, jnp.float32),
        pattern=jnp.zeros((1,), jnp.int32),
        is_waldo=jnp.zeros((1,), bool),
    )
    joined = {k: jnp.concatenate([v, getattr(room, k)]) for k, v in row.items()}
    return room.replace(num_boxes=room.num_boxes + 1, **joined)


def _inwards(room):
    """A horizontal unit vector from Waldo towards the room's middle (cameras there stay inside the walls)."""
    v = -np.asarray(room.waldo_base) * np.array([1.0, 0.0, 1.0])
    return v / np.linalg.norm(v)


def _facing(room, distance, height=0.0):
    """Cameras [len(distance), 4, 4] in front of Waldo, at his centre's height + `height`, aimed at it."""
    centre = np.asarray(room.waldo_center)
    origins = np.stack([centre + np.array([0.0, height, 0.0]) + d * _inwards(room) for d in np.atleast_1d(distance)])
    return jax.vmap(look_at, in_axes=(0, None, None))(jnp.asarray(origins), jnp.asarray(centre), UP)


@pytest.mark.slow
def test_whole_and_large_scores_high_half_hidden_scores_low(bare_room):
    found = make_criterion("waldo_found", CriterionContext(room=bare_room))
    assert found.inputs == "poses" and found.direction == "max" and found.value_range == (0.0, 2.0)
    c2w = _facing(bare_room, [3.0, 2.4, 1.9])
    scores = np.asarray(found.score_poses(c2w, INTR))
    vis = np.array([float(waldo_visibility(bare_room, c, INTR)) for c in c2w])
    cov = np.array([float(waldo_coverage(bare_room, c, INTR)) for c in c2w])
    assert np.all(vis >= FOUND_VISIBILITY)
    np.testing.assert_allclose(scores, 1.0 + cov, rtol=1e-5)  # found: 1 + his share of the image
    assert np.all(np.diff(scores) > 0)  # whole and closer: larger, better

    # A box between the camera and Waldo's lower half: the same camera now sees about half of him.
    centre = np.asarray(bare_room.waldo_center)
    wall_at = centre + 0.8 * _inwards(bare_room)
    hidden = _with_box(bare_room, (wall_at[0], 0.28, wall_at[2]), (0.6, 0.28, 0.6))
    hidden_found = make_criterion("waldo_found", CriterionContext(room=hidden))
    half = float(hidden_found.score_poses(c2w[1:2], INTR)[0])
    half_vis = float(waldo_visibility(hidden, c2w[1], INTR))
    assert 0.2 < half_vis < 0.8
    assert half == pytest.approx(half_vis, rel=1e-5)  # not found: the visible fraction, below 1
    assert half < 1.0 < scores[0]  # every whole view beats every half-hidden one, whatever its size

    # Too close: the frame cuts him, so he is not found however large he is.
    close = _facing(bare_room, [0.45])
    close_vis = float(waldo_visibility(bare_room, close[0], INTR))
    assert close_vis < FOUND_VISIBILITY
    assert float(found.score_poses(close, INTR)[0]) == pytest.approx(close_vis, rel=1e-5)


@pytest.mark.slow
def test_waldo_view_is_both_oracles_in_one_pass(bare_room):
    c2w = _facing(bare_room, [2.0, 0.6], height=0.3)
    for c in c2w:
        vis, cov = waldo_view(bare_room, c, INTR)
        assert float(vis) == pytest.approx(float(waldo_visibility(bare_room, c, INTR)), rel=1e-6)
        assert float(cov) == pytest.approx(float(waldo_coverage(bare_room, c, INTR)), rel=1e-6)


@pytest.mark.slow
def test_smooth_stand_in_is_close_and_climbs_towards_a_larger_whole_view(bare_room):
    found = make_criterion("waldo_found", CriterionContext(room=bare_room))
    smooth = found.smooth()
    c2w = _facing(bare_room, [2.4])
    exact = float(found.score_poses(c2w, INTR)[0])
    assert float(smooth.score_poses(c2w, INTR)[0]) == pytest.approx(exact, abs=0.02)

    def value(distance):
        origin = jnp.asarray(bare_room.waldo_center) + distance * jnp.asarray(_inwards(bare_room), jnp.float32)
        c = look_at(origin, bare_room.waldo_center, UP)[None]
        return smooth.apply(smooth.params, c, INTR)[0]

    slope = float(jax.grad(value)(2.4))
    assert np.isfinite(slope) and slope < 0.0  # stepping closer raises the score
    # The step at the bar: far below it the score is the visibility, far above 1 + coverage.
    v = jnp.array([0.5, FOUND_VISIBILITY - 0.1, FOUND_VISIBILITY + 0.1, 1.0])
    c = jnp.full(4, 0.05)
    np.testing.assert_allclose(found_score(v, c), [0.5, 0.8, 1.05, 1.05], atol=1e-6)
    np.testing.assert_allclose(found_score(v, c, FOUND_SOFTNESS), found_score(v, c), atol=0.01)


@pytest.mark.slow
def test_pose_criteria_combine_with_each_other(bare_room):
    context = CriterionContext(room=bare_room)
    oracle, visible = make_criterion("waldo_oracle", context), make_criterion("waldo_visible", context)
    c2w = _facing(bare_room, [2.4, 0.45])
    cov = np.asarray(oracle.score_poses(c2w, INTR))
    vis = np.asarray(visible.score_poses(c2w, INTR))
    assert vis[0] >= 0.9 > vis[1]

    guarded = constrained(oracle, visible, 0.9)
    assert guarded.inputs == "poses" and guarded.name == "waldo_oracle|waldo_visible>=0.9"
    np.testing.assert_allclose(guarded.score_poses(c2w, INTR), np.where(vis >= 0.9, cov, 0.0), rtol=1e-5, atol=1e-7)
    assert guarded.differentiable  # both parts have smooth stand-ins
    assert np.all(np.isfinite(np.asarray(guarded.smooth().score_poses(c2w, INTR))))
    same = build_criterion("waldo_oracle", context, guards=["waldo_visible:0.9"])
    np.testing.assert_allclose(same.score_poses(c2w, INTR), guarded.score_poses(c2w, INTR))

    mean = weighted([oracle, visible], [1.0, 3.0])
    assert mean.inputs == "poses"
    np.testing.assert_allclose(mean.score_poses(c2w, INTR), 0.25 * cov + 0.75 * vis, rtol=1e-5)
    parsed = build_criterion("weighted:waldo_oracle=1,waldo_visible=3", context)
    np.testing.assert_allclose(parsed.score_poses(c2w, INTR), mean.score_poses(c2w, INTR), rtol=1e-6)


@pytest.mark.slow
def test_pose_and_view_criteria_combine_into_a_posed_criterion(bare_room):
    context = CriterionContext(room=bare_room)
    visible = make_criterion("waldo_visible", context)
    guarded = constrained(visible, make_criterion("opacity"), 0.5)
    assert guarded.inputs == "posed"
    c2w = _facing(bare_room, [2.4, 2.0])
    vis = np.asarray(visible.score_poses(c2w, INTR))
    rgba = np.ones((2, 4, 4, 4), np.float32)
    rgba[1, ..., 3] = 0.1  # the second view is nearly empty: the guard fails it
    np.testing.assert_allclose(guarded.score_posed(rgba, c2w, INTR), [vis[0], 0.0], rtol=1e-5)
    with pytest.raises(CriterionError, match="together with their camera poses"):
        guarded.score_images(rgba)
    both = weighted([visible, make_criterion("opacity")], [1.0, 1.0])
    assert both.inputs == "posed"
    np.testing.assert_allclose(both.score_posed(rgba, c2w, INTR), 0.5 * vis + 0.5 * np.array([1.0, 0.1]), rtol=1e-5)
    # A combination inside a combination keeps working.
    nested = constrained(guarded, make_criterion("opacity"), 0.9)
    assert nested.inputs == "posed"
    np.testing.assert_allclose(nested.score_posed(rgba, c2w, INTR), [vis[0], 0.0], rtol=1e-5)


@pytest.mark.slow
def test_posed_criterion_scores_through_the_pipeline():
    """A search scores a "posed" combination by rendering and passing the poses (`score_function`)."""
    from waldo_jax.pipeline import initial_scores, load_source, score_function

    source = load_source("procedural:1", 16)
    context = CriterionContext(room=source.room)
    guarded = build_criterion("waldo_visible", context, guards=["opacity:0.5"])
    assert guarded.inputs == "posed"
    c2w = jnp.asarray(source.train_c2w[:3])
    vis = np.asarray(make_criterion("waldo_visible", context).score_poses(c2w, source.intrinsics))
    scores = np.asarray(jax.jit(score_function(source, guarded))(c2w))
    np.testing.assert_allclose(scores, vis, rtol=1e-5)  # the room's views are opaque: the guard passes
    initial, what = initial_scores(source, guarded, "images")
    assert what == "images" and initial.shape == (source.n_train,)
    np.testing.assert_allclose(initial[:3], vis, rtol=1e-5)


@pytest.mark.slow
def test_egps_finds_waldo_whole_with_waldo_found():
    """In a room whose search space holds views of Waldo whole (seed 1), EGPS at the low budget finds one
    in every seed with `waldo_found`, where `waldo_oracle`'s best view shows him cut or half hidden."""
    from waldo_jax.pipeline import load_source, run_explore
    from waldo_jax.procedural import waldo_visibility_batch
    from waldo_jax.search import ExploreConfig

    source = load_source("procedural:1", 32)
    best = {}
    for name in ("waldo_found", "waldo_oracle"):
        criterion = make_criterion(name, CriterionContext(room=source.room))
        run = run_explore(source, criterion, ExploreConfig(method="egps", budget="low"), seeds=4)
        c2w = jnp.asarray(np.stack([np.asarray(r.top_c2w[0]) for r in run.results]))
        best[name] = np.asarray(waldo_visibility_batch(source.room, c2w, source.intrinsics))
    assert np.all(best["waldo_found"] >= FOUND_VISIBILITY), best
    assert np.mean(best["waldo_oracle"]) < FOUND_VISIBILITY, best


@pytest.mark.slow
def test_demo_closeups_aim_at_waldo_and_zoom_to_his_size(bare_room):
    """`waldo demo`'s close-ups: same camera centres, Waldo's centre at the image centre, zoomed so that he
    fills about `CLOSEUP_FILL` of the height (twice as far: twice the zoom), the image size unchanged."""
    from waldo_jax.cameras import project_points
    from waldo_jax.pipeline.demo import CLOSEUP_FILL, closeup_cameras
    from waldo_jax.pipeline.sources import room_renderer

    centre = np.asarray(bare_room.waldo_points).mean(axis=0)
    aside = np.asarray(look_at(jnp.asarray(centre + 3.0 * _inwards(bare_room)), jnp.asarray(centre) + 1.0, UP))
    near = np.asarray(_facing(bare_room, [2.0]))
    cameras, zoomed, zoom = closeup_cameras(bare_room, np.stack([aside, near[0]]), INTR)
    np.testing.assert_allclose(cameras[:, :3, 3], [aside[:3, 3], near[0, :3, 3]], atol=1e-6)
    for camera in cameras:
        uv, depth = project_points(jnp.asarray(camera), zoomed, jnp.asarray(centre)[None])
        np.testing.assert_allclose(np.asarray(uv[0]), [INTR.width / 2, INTR.height / 2], atol=1e-3)
        assert float(depth[0]) > 0
    assert (zoomed.width, zoomed.height) == (INTR.width, INTR.height)
    _, _, far_zoom = closeup_cameras(bare_room, np.asarray(_facing(bare_room, [4.0])), INTR)
    _, _, near_zoom = closeup_cameras(bare_room, near, INTR)
    np.testing.assert_allclose(far_zoom, 2.0 * near_zoom, rtol=1e-4)
    points = np.asarray(bare_room.waldo_points)
    uv, _ = project_points(
        jnp.asarray(closeup_cameras(bare_room, near, INTR)[0][0]),
        zoomed.replace(fx=INTR.fx * near_zoom, fy=INTR.fy * near_zoom),
        jnp.asarray(points),
    )
    extent = float(np.ptp(np.asarray(uv[:, 1])))
    assert 0.5 * CLOSEUP_FILL * INTR.height < extent < 1.1 * CLOSEUP_FILL * INTR.height  # about: perspective
    # A scene's renderer takes the zoomed intrinsics: the same camera renders a different (closer) image.
    render = room_renderer(bare_room)
    camera = jnp.asarray(cameras[1:])
    plain, closer = render(camera, INTR), render(camera, zoomed)
    assert closer.intrinsics is zoomed and closer.rgba.shape == (1, INTR.height, INTR.width, 4)
    assert not np.allclose(np.asarray(plain.rgba), np.asarray(closer.rgba), atol=1e-2)
    # A NaN pose is skipped by the zoom (the median of the others); none finite gives zoom 1.
    nan_pose = np.full((1, 4, 4), np.nan, np.float32)
    assert closeup_cameras(bare_room, np.concatenate([near, nan_pose]), INTR)[2] == near_zoom
    assert closeup_cameras(bare_room, nan_pose, INTR)[2] == 1.0


@pytest.mark.slow
def test_surface_seen_by_cameras(bare_room):
    """`waldo_surface_seen`: one camera in front sees about half of Waldo's surface; four around him see
    most of it (not his soles and undersides); a box between camera and Waldo hides all; more cameras never
    see less."""
    from waldo_jax.procedural import waldo_surface_seen

    front = np.asarray(_facing(bare_room, [2.5]))
    one = float(waldo_surface_seen(bare_room, jnp.asarray(front), INTR))
    assert 0.3 < one < 0.6
    centre = np.asarray(bare_room.waldo_center)
    around = []
    for angle in np.radians([0.0, 90.0, 180.0, 270.0]):
        origin = centre + 1.5 * np.array([np.cos(angle), 0.6, np.sin(angle)])
        around.append(np.asarray(look_at(jnp.asarray(origin), jnp.asarray(centre), UP)))
    four = float(waldo_surface_seen(bare_room, jnp.asarray(np.stack(around)), INTR))
    assert four > 0.8 and four >= float(waldo_surface_seen(bare_room, jnp.asarray(np.stack(around[:2])), INTR))
    wall = centre + 1.2 * _inwards(bare_room)
    hidden = _with_box(bare_room, wall, [0.6, 1.5, 0.6])
    assert float(waldo_surface_seen(hidden, jnp.asarray(front), INTR)) == 0.0
