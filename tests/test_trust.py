"""`trust`: the training cameras' coverage of a view, from poses alone, and its use as a guard."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import waldo_jax  # noqa: F401
from waldo_jax.cameras import look_at
from waldo_jax.criteria import CRITERIA, CriterionContext, CriterionError, build_criterion, make_criterion
from waldo_jax.criteria.trust import trust_params, trust_scores
from waldo_jax.procedural import make_room
from waldo_jax.types import Intrinsics

UP = jnp.array([0.0, 1.0, 0.0])
INTRINSICS = Intrinsics.create(32, 32, fx=32 / (2 * math.tan(math.radians(30.0))))  # 60 degrees


def _ring(count=12, radius=3.0, height=1.2):
    """Training cameras c2w [count, 4, 4] on a ring round the origin, looking at it."""
    angles = np.linspace(0.0, 2 * np.pi, count, endpoint=False)
    origins = np.stack([radius * np.cos(angles), np.full(count, height), radius * np.sin(angles)], axis=-1)
    return np.stack([np.asarray(look_at(o, jnp.zeros(3), UP)) for o in origins]).astype(np.float32)


@pytest.fixture(scope="module")
def ring():
    return _ring()


@pytest.fixture(scope="module")
def criterion(ring):
    return make_criterion("trust", CriterionContext(train_c2w=ring))


def _camera(origin, target=(0.0, 0.0, 0.0)):
    return np.asarray(look_at(jnp.asarray(origin, jnp.float32), jnp.asarray(target, jnp.float32), UP))


def test_registered_as_a_smooth_pose_criterion(criterion):
    spec = CRITERIA["trust"]
    assert (spec.inputs, spec.direction, spec.smooth) == ("poses", "max", True)
    assert criterion.value_range == (0.0, 1.0) and criterion.differentiable


@pytest.mark.slow
def test_training_poses_score_one_and_far_or_averted_views_zero(criterion, ring):
    np.testing.assert_allclose(criterion.score_poses(ring, INTRINSICS), 1.0)
    averted = _camera(ring[0, :3, 3], 2 * ring[0, :3, 3])  # at a training camera, looking out of the ring
    far = _camera((30.0, 1.2, 0.0))  # ten times the training distance
    close = _camera((0.3, 0.2, 0.0), (-1.0, 0.2, 0.0))  # a tenth of it
    scores = np.asarray(criterion.score_poses(np.stack([averted, far, close]), INTRINSICS))
    np.testing.assert_allclose(scores, 0.0, atol=1e-6)


@pytest.mark.slow
def test_trust_falls_as_a_camera_moves_away(criterion, ring):
    origin = ring[0, :3, 3]
    steps = np.linspace(1.0, 0.15, 12)  # from the training camera towards the centre: ever closer
    closer = np.stack([_camera(origin * s) for s in steps])
    heights = np.linspace(1.2, 5.5, 12)  # upwards, looking at the centre from ever higher
    higher = np.stack([_camera((origin[0], h, origin[2])) for h in heights])
    for poses in (closer, higher):
        for c in (criterion, criterion.smooth()):
            scores = np.asarray(c.score_poses(poses, INTRINSICS))
            assert np.all(np.diff(scores) <= 0.01), scores  # the stand-in's sigmoids: a slight rise near 1
            assert scores[0] > 0.9 and scores[-1] < 0.1, scores


@pytest.mark.slow
def test_jit_vmap_and_smooth_stand_in(criterion, ring):
    key = jax.random.key(0)
    offsets = 0.8 * jax.random.normal(key, (48, 3))
    targets = 0.5 * jax.random.normal(jax.random.fold_in(key, 1), (48, 3))
    origins = jnp.asarray(ring[np.arange(48) % len(ring), :3, 3]) + offsets
    population = jax.vmap(lambda o, t: look_at(o, t, UP))(origins, targets)  # [48, 4, 4]
    exact = np.asarray(criterion.score_poses(population, INTRINSICS))  # one jitted, vmapped call
    assert exact.shape == (48,) and 0.1 < exact.mean() < 0.9 and np.all((exact >= 0) & (exact <= 1))
    np.testing.assert_allclose(exact[:3], criterion.score_poses(population[:3], INTRINSICS), atol=1e-6)
    smooth = np.asarray(criterion.smooth().score_poses(population, INTRINSICS))
    assert np.mean(np.abs(smooth - exact)) < 0.08, np.mean(np.abs(smooth - exact))
    grad = jax.jit(
        jax.grad(lambda o: criterion.smooth_apply(criterion.params, look_at(o, jnp.zeros(3), UP)[None], INTRINSICS)[0])
    )(origins[3])
    assert np.all(np.isfinite(np.asarray(grad)))
    # the parameters are leaves: a sweep vmaps over them (a tighter angle never trusts more)
    angles = jnp.radians(jnp.array([5.0, 15.0, 30.0, 60.0]))
    base = trust_params(ring)[:4]
    swept = np.asarray(jax.jit(jax.vmap(lambda a: trust_scores(base + (a,), population, INTRINSICS)))(angles))
    assert swept.shape == (4, 48) and np.all(np.diff(swept, axis=0) >= -1e-6) and swept[0].mean() < swept[-1].mean()


@pytest.mark.slow
def test_guards_pose_and_view_criteria(ring):
    room = make_room(1)
    context = CriterionContext(room=room, train_c2w=ring)
    found = build_criterion("waldo_found", context)
    guarded = build_criterion("waldo_found", context, ["trust:0.5"])
    assert guarded.name == "waldo_found|trust>=0.5" and guarded.inputs == "poses" and guarded.differentiable
    poses = np.stack([ring[0], ring[5], _camera((30.0, 1.2, 0.0)), _camera(ring[0, :3, 3], 2 * ring[0, :3, 3])])
    np.testing.assert_allclose(
        guarded.score_poses(poses, INTRINSICS)[:2], found.score_poses(poses[:2], INTRINSICS), atol=1e-6
    )
    np.testing.assert_allclose(guarded.score_poses(poses, INTRINSICS)[2:], 0.0)  # waldo_found's worst score
    posed = build_criterion("opacity", context, ["trust:0.5"])
    assert posed.inputs == "posed"
    rgba = np.ones((4, 8, 8, 4), np.float32)
    np.testing.assert_allclose(posed.score_posed(rgba, poses, INTRINSICS), [1.0, 1.0, 0.0, 0.0])


@pytest.mark.slow
def test_missing_training_cameras_refused_in_one_line():
    with pytest.raises(CriterionError, match=r"needs the source's training camera poses \(source: fox\)") as info:
        make_criterion("trust", CriterionContext(source="fox"))
    assert "\n" not in str(info.value)
    with pytest.raises(CriterionError, match="training camera poses"):
        build_criterion("waldo_found", CriterionContext(room=make_room(1)), ["trust:0.5"])
