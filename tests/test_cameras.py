"""Property tests of waldo_jax.cameras: look-at, pose round trips, quaternions, SLERP, intrinsics, rays.

The functions under test are jitted once at module level so that hypothesis examples reuse one
compilation each. Reference values come from NumPy/SciPy in float64, never from the code under test.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

# Importing waldo_jax first sets the XLA flag it needs before JAX starts its CPU backend.
from waldo_jax.cameras import (
    c2w_to_pose,
    camera_focus,
    camera_rays,
    distort,
    look_at,
    pixel_directions,
    pose_to_c2w,
    project_points,
    quaternion_slerp,
    quaternion_to_rotation,
    rotation_angle,
    rotation_to_quaternion,
    slerp_c2w,
    slerp_pose,
    undistort,
)
from waldo_jax.types import Intrinsics, Pose

import jax  # noqa: E402  (after waldo_jax, see above)
import jax.numpy as jnp  # noqa: E402


PROPERTY = settings(max_examples=40, deadline=None)
FEW = settings(max_examples=25, deadline=None)

# The fox scene's OPENCV coefficients (k1, k2, p1, p2).
FOX_DISTORTION = (0.0578, -0.0805, -0.00098, 0.000156)

# ------------------------------------------------------------------------------------------------
# Jitted functions under test (one compilation each for the whole module).

_look_at = jax.jit(look_at)
_pose_to_c2w = jax.jit(pose_to_c2w)
_c2w_to_pose = jax.jit(c2w_to_pose)
_to_quat = jax.jit(rotation_to_quaternion)
_to_rot = jax.jit(quaternion_to_rotation)
_slerp_c2w = jax.jit(slerp_c2w)
_slerp_pose = jax.jit(slerp_pose)
_quat_slerp = jax.jit(quaternion_slerp)
_rotation_angle = jax.jit(rotation_angle)
_distort = jax.jit(jax.vmap(distort, in_axes=(0, None)))
_undistort = jax.jit(jax.vmap(undistort, in_axes=(0, None)))
_camera_rays = jax.jit(camera_rays)
_project = jax.jit(project_points)
# project_points does not depend on the (static) image size: keep one compilation for all sizes.
_project_any_size = jax.jit(
    lambda c2w, fx, fy, cx, cy, dist, points: project_points(
        c2w, Intrinsics(width=1, height=1, fx=fx, fy=fy, cx=cx, cy=cy, distortion=dist), points
    )
)


def _project_with(c2w, k: Intrinsics, points):
    return _project_any_size(c2w, k.fx, k.fy, k.cx, k.cy, k.distortion, points)


# A fixed, generic weighting so that the "sum over outputs" loss has no symmetric cancellations.
_LOSS_WEIGHTS = np.linspace(-1.0, 2.0, 16, dtype=np.float32).reshape(4, 4)
_look_at_grad = jax.jit(jax.grad(lambda o, t, u: jnp.sum(look_at(o, t, u) * _LOSS_WEIGHTS), argnums=(0, 1, 2)))

# ------------------------------------------------------------------------------------------------
# Strategies and float64 helpers.

_coord = st.floats(-5.0, 5.0, allow_nan=False, allow_infinity=False, width=32)
vec3 = st.tuples(_coord, _coord, _coord).map(lambda v: np.asarray(v, np.float32))
_unit_coord = st.floats(-1.0, 1.0, allow_nan=False, width=32)
quat = (
    st.tuples(_unit_coord, _unit_coord, _unit_coord, _unit_coord)
    .map(np.asarray)
    .filter(lambda q: np.linalg.norm(q) > 0.1)
)
axis = st.tuples(_unit_coord, _unit_coord, _unit_coord).map(np.asarray).filter(lambda a: np.linalg.norm(a) > 0.1)


def _rotation_of(q_wxyz: np.ndarray) -> np.ndarray:
    """float64 rotation matrix of a (w, x, y, z) quaternion, from SciPy (x, y, z, w order)."""
    q = np.asarray(q_wxyz, np.float64)
    return Rotation.from_quat([q[1], q[2], q[3], q[0]]).as_matrix()


def _axis_angle(axis_vec: np.ndarray, angle: float) -> np.ndarray:
    a = np.asarray(axis_vec, np.float64)
    return Rotation.from_rotvec(a / np.linalg.norm(a) * angle).as_matrix()


def _half_turn(axis_vec: np.ndarray) -> np.ndarray:
    a = np.asarray(axis_vec, np.float64)
    a = a / np.linalg.norm(a)
    return 2.0 * np.outer(a, a) - np.eye(3)


def _angle64(ra: np.ndarray, rb: np.ndarray) -> float:
    """Geodesic angle between two rotations, in float64 and robust near 0 (SciPy's log map)."""
    rel = np.asarray(ra, np.float64).T @ np.asarray(rb, np.float64)
    return float(Rotation.from_matrix(rel).magnitude())


def _rigid(rotation: np.ndarray, origin: np.ndarray) -> np.ndarray:
    c2w = np.eye(4, dtype=np.float32)
    c2w[:3, :3] = rotation
    c2w[:3, 3] = origin
    return c2w


def _assert_valid_c2w(c2w, origin=None, atol=1e-5):
    c2w = np.asarray(c2w, np.float64)
    assert c2w.shape == (4, 4)
    assert np.all(np.isfinite(c2w))
    rotation = c2w[:3, :3]
    np.testing.assert_allclose(rotation.T @ rotation, np.eye(3), atol=atol)
    np.testing.assert_allclose(np.linalg.det(rotation), 1.0, atol=atol)
    np.testing.assert_array_equal(c2w[3], [0.0, 0.0, 0.0, 1.0])
    if origin is not None:
        np.testing.assert_allclose(c2w[:3, 3], origin, atol=1e-6)


def _unit(v):
    v = np.asarray(v, np.float64)
    return v / np.linalg.norm(v)


# ------------------------------------------------------------------------------------------------
# look_at


@PROPERTY
@given(origin=vec3, target=vec3, up=vec3)
def test_look_at_is_rigid_and_looks_at_the_target(origin, target, up):
    view = target.astype(np.float64) - origin
    assume(np.linalg.norm(view) > 0.1 and np.linalg.norm(up) > 0.1)
    # Keep away from up ∥ view (tested separately below).
    assume(np.linalg.norm(np.cross(_unit(view), _unit(up))) > 0.05)
    c2w = np.asarray(_look_at(origin, target, up), np.float64)
    _assert_valid_c2w(c2w, origin)
    np.testing.assert_allclose(c2w[:3, 2], -_unit(view), atol=1e-5)
    camera_up = c2w[:3, 1]
    assert np.dot(camera_up, up) >= 0.0
    # The camera's up axis is the given up made orthogonal to the view direction.
    expected_up = _unit(up - np.dot(up, _unit(view)) * _unit(view))
    np.testing.assert_allclose(camera_up, expected_up, atol=1e-4)
    # Right-handed frame: right = up x backward.
    np.testing.assert_allclose(c2w[:3, 0], np.cross(c2w[:3, 1], c2w[:3, 2]), atol=1e-5)


def test_look_at_identity_frame():
    # A camera at +z looking at the origin with +y up is the identity rotation (OpenGL convention).
    c2w = np.asarray(_look_at(np.float32([0, 0, 3]), np.zeros(3, np.float32), np.float32([0, 1, 0])))
    np.testing.assert_allclose(c2w, _rigid(np.eye(3), [0, 0, 3]), atol=1e-6)


_DEGENERATE = {
    "up_parallel": ([0.0, 0.0, 0.0], [0.0, 0.0, -2.0], [0.0, 0.0, -1.0]),
    "up_antiparallel": ([0.0, 0.0, 0.0], [0.0, 0.0, -2.0], [0.0, 0.0, 3.0]),
    "up_parallel_oblique": ([1.0, 2.0, 3.0], [2.0, 3.0, 4.0], [0.5, 0.5, 0.5]),
    "up_antiparallel_oblique": ([1.0, 2.0, 3.0], [2.0, 3.0, 4.0], [-2.0, -2.0, -2.0]),
    "look_down_y_up": ([0.0, 5.0, 0.0], [0.0, 0.0, 0.0], [0.0, 1.0, 0.0]),
    "look_up_y_up": ([0.0, -5.0, 0.0], [0.0, 0.0, 0.0], [0.0, 1.0, 0.0]),
    "origin_equals_target": ([1.0, -2.0, 0.5], [1.0, -2.0, 0.5], [0.0, 1.0, 0.0]),
    "origin_equals_target_zero_up": ([0.0, 0.0, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]),
    "zero_up": ([0.0, 0.0, 0.0], [1.0, 0.0, -1.0], [0.0, 0.0, 0.0]),
    "zero_up_looking_down": ([0.0, 2.0, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]),
    "tiny_view_offset": ([0.0, 0.0, 0.0], [1e-9, 0.0, 0.0], [0.0, 1.0, 0.0]),
    "tiny_up": ([0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1e-9, 0.0]),
    "up_parallel_plus_1e-9": ([0.0, 0.0, 0.0], [0.0, 0.0, -1.0], [1e-9, 1e-9, -1.0]),
    "up_parallel_plus_1e-7": ([0.0, 0.0, 0.0], [0.3, 0.4, -1.2], [0.3, 0.4 + 1e-7, -1.2]),
}


@pytest.mark.slow
@pytest.mark.parametrize("origin,target,up", list(_DEGENERATE.values()), ids=list(_DEGENERATE))
def test_look_at_degenerate_input_is_valid_deterministic_and_differentiable(origin, target, up):
    origin, target, up = (np.asarray(v, np.float32) for v in (origin, target, up))
    c2w = np.asarray(_look_at(origin, target, up))
    _assert_valid_c2w(c2w, origin)
    np.testing.assert_array_equal(c2w, np.asarray(_look_at(origin, target, up)))  # deterministic
    np.testing.assert_allclose(c2w, np.asarray(look_at(origin, target, up)), atol=1e-6)  # eager ~ jit
    view = target.astype(np.float64) - origin
    if np.linalg.norm(view) > 1e-6:
        np.testing.assert_allclose(c2w[:3, 2], -_unit(view), atol=1e-5)  # still looks at the target
    else:
        np.testing.assert_allclose(c2w[:3, 2], [0.0, 0.0, 1.0], atol=1e-6)  # documented: looks along -z
    for grad in _look_at_grad(origin, target, up):
        assert np.all(np.isfinite(np.asarray(grad))), grad


@FEW
@given(origin=vec3, target=vec3, scale=st.floats(-10.0, 10.0).filter(lambda s: abs(s) > 1e-3))
def test_look_at_up_parallel_to_view_gives_valid_rotation_and_finite_gradients(origin, target, scale):
    view = target.astype(np.float64) - origin
    assume(np.linalg.norm(view) > 0.1)
    up = (scale * view).astype(np.float32)  # parallel (scale > 0) or anti-parallel (scale < 0)
    c2w = np.asarray(_look_at(origin, target, up))
    _assert_valid_c2w(c2w, origin)
    np.testing.assert_allclose(c2w[:3, 2], -_unit(view), atol=1e-5)
    np.testing.assert_array_equal(c2w, np.asarray(_look_at(origin, target, up)))
    for grad in _look_at_grad(origin, target, up):
        assert np.all(np.isfinite(np.asarray(grad)))


def test_look_at_zero_up_falls_back_to_world_y():
    c2w = np.asarray(_look_at(np.zeros(3, np.float32), np.float32([1, 0, -1]), np.zeros(3, np.float32)))
    np.testing.assert_allclose(c2w[:3, 1], [0.0, 1.0, 0.0], atol=1e-6)


def test_look_at_nearly_parallel_up_stays_orthonormal():
    # Up vectors a little above the parallel cut-off (|cos| < 1 - 1e-6, i.e. angles > ~1.4e-3 rad)
    # go through a cross product of nearly parallel vectors: the frame must still be orthonormal.
    rng = np.random.default_rng(3)
    n = 256
    view = rng.normal(size=(n, 3))
    view /= np.linalg.norm(view, axis=1, keepdims=True)
    perp = np.cross(view, rng.normal(size=(n, 3)))
    perp /= np.linalg.norm(perp, axis=1, keepdims=True)
    angle = rng.uniform(1.45e-3, 5e-3, size=(n, 1))
    up = (np.cos(angle) * view + np.sin(angle) * perp).astype(np.float32)
    origin = rng.uniform(-3, 3, size=(n, 3)).astype(np.float32)
    target = (origin + 2.0 * view).astype(np.float32)
    c2w = np.asarray(jax.jit(jax.vmap(look_at))(origin, target, up), np.float64)
    rotation = c2w[:, :3, :3]
    gram = np.einsum("nji,njk->nik", rotation, rotation)
    # look_at orthogonalises up before the cross product, so nearly parallel input stays accurate.
    np.testing.assert_allclose(gram, np.broadcast_to(np.eye(3), gram.shape), atol=1e-5)
    assert np.all(np.einsum("ni,ni->n", c2w[:, :3, 1], up) > 0.0)


# ------------------------------------------------------------------------------------------------
# Pose <-> c2w round trips


@PROPERTY
@given(q=quat, origin=vec3, focus=st.floats(0.1, 20.0))
def test_c2w_to_pose_to_c2w_round_trip(q, origin, focus):
    c2w = _rigid(_rotation_of(q), origin)
    pose = _c2w_to_pose(c2w, focus)
    np.testing.assert_allclose(np.linalg.norm(np.asarray(pose.target) - origin), focus, rtol=1e-5)
    back = np.asarray(_pose_to_c2w(pose))
    np.testing.assert_allclose(back, c2w, atol=1e-5)


@PROPERTY
@given(origin=vec3, target=vec3, up=vec3)
def test_pose_to_c2w_to_pose_keeps_origin_view_and_focus(origin, target, up):
    view = target.astype(np.float64) - origin
    assume(np.linalg.norm(view) > 0.1 and np.linalg.norm(up) > 0.1)
    assume(np.linalg.norm(np.cross(_unit(view), _unit(up))) > 0.05)
    c2w = _pose_to_c2w(Pose(origin=origin, target=target, up=up))
    focus = np.linalg.norm(view)
    pose = _c2w_to_pose(c2w, np.float32(focus))
    np.testing.assert_allclose(pose.origin, origin, atol=1e-6)
    np.testing.assert_allclose(pose.target, target, atol=1e-4 * max(1.0, focus))
    # The recovered up is the camera's up axis: unit, orthogonal to the view, on the side of `up`.
    new_up = np.asarray(pose.up, np.float64)
    np.testing.assert_allclose(np.linalg.norm(new_up), 1.0, atol=1e-5)
    np.testing.assert_allclose(np.dot(new_up, _unit(view)), 0.0, atol=1e-5)
    assert np.dot(new_up, up) > 0.0
    np.testing.assert_allclose(_pose_to_c2w(pose), c2w, atol=1e-5)


# ------------------------------------------------------------------------------------------------
# Quaternions


def _assert_same_quaternion(q, reference_wxyz):
    q = np.asarray(q, np.float64)
    ref = np.asarray(reference_wxyz, np.float64)
    ref = ref / np.linalg.norm(ref)
    np.testing.assert_allclose(np.linalg.norm(q), 1.0, atol=1e-5)
    # q and -q are the same rotation; the library picks w >= 0, which for w = 0 leaves a choice.
    assert min(np.abs(q - ref).max(), np.abs(q + ref).max()) < 1e-5, (q, ref)


@PROPERTY
@given(q=quat)
def test_quaternion_round_trip_random_rotations(q):
    rotation = _rotation_of(q).astype(np.float32)
    q_out = np.asarray(_to_quat(rotation))
    assert q_out[0] >= 0.0
    _assert_same_quaternion(q_out, q)
    np.testing.assert_allclose(_to_rot(q_out), rotation, atol=1e-5)
    # And the other way: quaternion -> rotation matches SciPy's.
    np.testing.assert_allclose(_to_rot(np.asarray(q, np.float32)), _rotation_of(q), atol=1e-5)


@PROPERTY
@given(a=axis)
def test_quaternion_round_trip_half_turns(a):
    rotation = _half_turn(a).astype(np.float32)
    q_out = np.asarray(_to_quat(rotation))
    assert np.all(np.isfinite(q_out))
    _assert_same_quaternion(q_out, np.concatenate([[0.0], _unit(a)]))
    np.testing.assert_allclose(_to_rot(q_out), rotation, atol=1e-5)


@pytest.mark.parametrize(
    "rotation",
    [np.eye(3), _half_turn([1, 0, 0]), _half_turn([0, 1, 0]), _half_turn([0, 0, 1]), _half_turn([1, 1, 0])],
    ids=["identity", "half_x", "half_y", "half_z", "half_xy"],
)
def test_quaternion_round_trip_special_rotations(rotation):
    rotation = rotation.astype(np.float32)
    q_out = np.asarray(_to_quat(rotation))
    np.testing.assert_allclose(_to_rot(q_out), rotation, atol=1e-6)
    if np.allclose(rotation, np.eye(3)):
        np.testing.assert_allclose(q_out, [1.0, 0.0, 0.0, 0.0], atol=1e-7)


@PROPERTY
@given(qa=quat, qb=quat)
def test_rotation_angle_matches_reference(qa, qb):
    ra, rb = _rotation_of(qa), _rotation_of(qb)
    got = float(_rotation_angle(ra.astype(np.float32), rb.astype(np.float32)))
    # arccos of a float32 trace near +-1 has ~3e-4 absolute error.
    np.testing.assert_allclose(got, _angle64(ra, rb), atol=1e-3)


# ------------------------------------------------------------------------------------------------
# SLERP


@pytest.mark.slow
@PROPERTY
@given(qa=quat, qb=quat, oa=vec3, ob=vec3)
def test_slerp_end_points_are_the_inputs(qa, qb, oa, ob):
    a, b = _rigid(_rotation_of(qa), oa), _rigid(_rotation_of(qb), ob)
    np.testing.assert_allclose(_slerp_c2w(a, b, 0.0), a, atol=1e-5)
    np.testing.assert_allclose(_slerp_c2w(a, b, 1.0), b, atol=1e-5)
    # [3, 4] inputs give the same [4, 4] result.
    np.testing.assert_allclose(_slerp_c2w(a[:3], b[:3], 0.0), a, atol=1e-5)


_TS = (0.1, 0.25, 0.5, 0.7, 0.9)


@pytest.mark.slow
@PROPERTY
@given(qa=quat, a=axis, angle=st.floats(0.05, np.pi - 0.1), oa=vec3, ob=vec3)
def test_slerp_constant_angular_speed_and_linear_translation(qa, a, angle, oa, ob):
    ra = _rotation_of(qa)
    rb = ra @ _axis_angle(a, angle)
    ca, cb = _rigid(ra, oa), _rigid(rb, ob)
    total = _angle64(ra, rb)
    for t in _TS:
        c = np.asarray(_slerp_c2w(ca, cb, t), np.float64)
        _assert_valid_c2w(c)
        np.testing.assert_allclose(_angle64(ra, c[:3, :3]), t * total, atol=1e-4)
        np.testing.assert_allclose(_angle64(c[:3, :3], rb), (1 - t) * total, atol=1e-4)
        np.testing.assert_allclose(c[:3, 3], (1 - t) * oa.astype(np.float64) + t * ob, atol=1e-5)
        # The library's own angle agrees (looser: float32 arccos).
        np.testing.assert_allclose(
            _rotation_angle(ra.astype(np.float32), c[:3, :3].astype(np.float32)), t * total, atol=2e-3
        )


@pytest.mark.slow
@PROPERTY
@given(qa=quat, qb=quat)
def test_slerp_takes_the_shortest_arc(qa, qb):
    ra, rb = _rotation_of(qa), _rotation_of(qb)
    total = _angle64(ra, rb)
    for t in _TS:
        r = np.asarray(_slerp_c2w(_rigid(ra, np.zeros(3)), _rigid(rb, np.zeros(3)), t), np.float64)[:3, :3]
        from_a, to_b = _angle64(ra, r), _angle64(r, rb)
        assert from_a <= total + 1e-4 and from_a <= np.pi
        # On the geodesic between a and b: the two legs add up to the whole arc.
        np.testing.assert_allclose(from_a + to_b, total, atol=2e-4)


def test_slerp_shortest_arc_through_half_turn():
    # +170° and -170° about x are 20° apart via the half turn, 340° apart the long way round.
    ra, rb = _axis_angle([1, 0, 0], np.radians(170)), _axis_angle([1, 0, 0], np.radians(-170))
    mid = np.asarray(_slerp_c2w(_rigid(ra, np.zeros(3)), _rigid(rb, np.zeros(3)), 0.5))[:3, :3]
    np.testing.assert_allclose(mid, _half_turn([1, 0, 0]), atol=1e-5)
    # Same at the quaternion level with q1 given on the far hemisphere.
    q0 = np.float32([1.0, 0.0, 0.0, 0.0])
    q1 = -np.float32([np.cos(0.2), np.sin(0.2), 0.0, 0.0])  # 0.4 rad about x, written as -q
    q = np.asarray(_quat_slerp(q0, q1, 0.5))
    np.testing.assert_allclose(_to_rot(q), _axis_angle([1, 0, 0], 0.2), atol=1e-5)


@pytest.mark.slow
@PROPERTY
@given(origin=vec3, target=vec3, up=vec3, t=st.floats(0.0, 1.0))
def test_slerp_pose_with_itself_is_constant(origin, target, up, t):
    view = target.astype(np.float64) - origin
    assume(np.linalg.norm(view) > 0.1 and np.linalg.norm(up) > 0.1)
    assume(np.linalg.norm(np.cross(_unit(view), _unit(up))) > 0.05)
    pose = Pose(origin=origin, target=target, up=up)
    out = _slerp_pose(pose, pose, t)
    np.testing.assert_allclose(out.origin, origin, atol=1e-5)
    np.testing.assert_allclose(out.target, target, atol=1e-4 * max(1.0, np.linalg.norm(view)))
    np.testing.assert_allclose(_pose_to_c2w(out), _pose_to_c2w(pose), atol=1e-5)


@pytest.mark.slow
@PROPERTY
@given(oa=vec3, ta=vec3, ob=vec3, tb=vec3, t=st.floats(0.0, 1.0))
def test_slerp_pose_interpolates_focus_distance(oa, ta, ob, tb, t):
    up = np.float32([0.3, 1.0, -0.2])
    da, db = np.linalg.norm(ta.astype(np.float64) - oa), np.linalg.norm(tb.astype(np.float64) - ob)
    assume(da > 0.1 and db > 0.1)
    for o, tg in ((oa, ta), (ob, tb)):
        assume(np.linalg.norm(np.cross(_unit(tg.astype(np.float64) - o), _unit(up))) > 0.05)
    out = _slerp_pose(Pose(oa, ta, up), Pose(ob, tb, up), t)
    origin, target = np.asarray(out.origin, np.float64), np.asarray(out.target, np.float64)
    np.testing.assert_allclose(origin, (1 - t) * oa.astype(np.float64) + t * ob, atol=1e-5)
    np.testing.assert_allclose(np.linalg.norm(target - origin), (1 - t) * da + t * db, rtol=1e-5, atol=1e-5)
    # The target lies on the interpolated camera's view axis.
    c2w = np.asarray(_slerp_c2w(_pose_to_c2w(Pose(oa, ta, up)), _pose_to_c2w(Pose(ob, tb, up)), t))
    np.testing.assert_allclose(_unit(target - origin), -c2w[:3, 2], atol=1e-4)


# ------------------------------------------------------------------------------------------------
# Intrinsics


intrinsics_st = st.builds(
    lambda w, h, f, aspect, cx, cy, dist: Intrinsics.create(w, h, f, f * aspect, cx * w, cy * h, dist),
    st.integers(16, 400),
    st.integers(16, 400),
    st.floats(20.0, 500.0),
    st.floats(0.8, 1.25),
    st.floats(0.3, 0.7),
    st.floats(0.3, 0.7),
    st.sampled_from([None, FOX_DISTORTION]),
)


def _assert_projects_scaled(full: Intrinsics, small: Intrinsics, c2w, points):
    sx, sy = small.width / full.width, small.height / full.height
    uv_full, depth_full = _project_with(c2w, full, points)
    uv_small, depth_small = _project_with(c2w, small, points)
    np.testing.assert_allclose(depth_small, depth_full)
    np.testing.assert_allclose(uv_small, np.asarray(uv_full) * [sx, sy], rtol=1e-5, atol=1e-3)
    np.testing.assert_array_equal(np.asarray(small.distortion), np.asarray(full.distortion))


@PROPERTY
@given(
    intrinsics=intrinsics_st,
    size=st.tuples(st.integers(1, 800), st.integers(1, 800)),
    factor=st.floats(0.25, 8.0),
    resolution=st.integers(8, 1000),
)
def test_rescaled_intrinsics_project_to_scaled_pixels(intrinsics, size, factor, resolution):
    c2w = np.asarray(_look_at(np.float32([0.3, -0.2, 4.0]), np.float32([0.1, 0.2, 0.0]), np.float32([0, 1, 0])))
    points = np.random.default_rng(0).uniform(-0.5, 0.5, (16, 3)).astype(np.float32)
    _assert_projects_scaled(intrinsics, intrinsics.scaled(*size), c2w, points)
    down = intrinsics.downscaled(factor)
    assert (down.width, down.height) == (
        max(1, round(intrinsics.width / factor)),
        max(1, round(intrinsics.height / factor)),
    )
    _assert_projects_scaled(intrinsics, down, c2w, points)
    capped = intrinsics.with_max_side(resolution)
    assert max(capped.width, capped.height) == resolution
    _assert_projects_scaled(intrinsics, capped, c2w, points)


def test_downscaled_by_two_halves_every_parameter():
    k = Intrinsics.create(800, 600, 700.0, 710.0, 401.0, 299.0, FOX_DISTORTION)
    half = k.downscaled(2)
    assert (half.width, half.height) == (400, 300)
    np.testing.assert_allclose([half.fx, half.fy, half.cx, half.cy], [350.0, 355.0, 200.5, 149.5])
    np.testing.assert_array_equal(half.distortion, k.distortion)


@PROPERTY
@given(intrinsics=intrinsics_st)
def test_intrinsics_dict_round_trip(intrinsics):
    d = json.loads(json.dumps(intrinsics.to_dict()))
    back = Intrinsics.from_dict(d)
    assert (back.width, back.height) == (intrinsics.width, intrinsics.height)
    for name in ("fx", "fy", "cx", "cy", "distortion"):
        np.testing.assert_array_equal(np.asarray(getattr(back, name)), np.asarray(getattr(intrinsics, name)))


# ------------------------------------------------------------------------------------------------
# Distortion and rays


@pytest.mark.parametrize("distortion", [(0.0, 0.0, 0.0, 0.0), FOX_DISTORTION, (-0.2, 0.05, 0.002, -0.003)])
def test_undistort_inverts_distort(distortion):
    xy = np.random.default_rng(1).uniform(-0.7, 0.7, (200, 2)).astype(np.float32)
    dist = np.float32(distortion)
    distorted = np.asarray(_distort(xy, dist))
    if any(distortion):
        assert np.abs(distorted - xy).max() > 1e-3  # the distortion is not a no-op
    np.testing.assert_allclose(_undistort(distorted, dist), xy, atol=1e-5)
    np.testing.assert_allclose(_distort(np.asarray(_undistort(xy, dist)), dist), xy, atol=1e-5)


_CAMERAS = {
    "pinhole": Intrinsics.create(13, 9, 11.0, 12.0, 6.1, 4.7),
    "fox": Intrinsics.create(16, 12, 14.0, 14.5, 8.3, 5.6, FOX_DISTORTION),
}


@pytest.mark.slow
@pytest.mark.parametrize("name", list(_CAMERAS))
@FEW
@given(q=quat, origin=vec3)
def test_ray_through_pixel_centre_reprojects_to_it(name, q, origin):
    intrinsics = _CAMERAS[name]
    c2w = _rigid(_rotation_of(q), origin)
    origins, dirs = (np.asarray(a) for a in _camera_rays(c2w, intrinsics))
    h, w = intrinsics.shape
    assert dirs.shape == (h, w, 3) and origins.shape == (h, w, 3)
    np.testing.assert_allclose(np.linalg.norm(dirs, axis=-1), 1.0, atol=1e-6)
    np.testing.assert_allclose(origins, np.broadcast_to(origin, (h, w, 3)))
    points = (origins + 2.5 * dirs).reshape(-1, 3)
    uv, depth = _project(c2w, intrinsics, points)
    jj, ii = np.meshgrid(np.arange(h), np.arange(w), indexing="ij")
    centres = np.stack([ii + 0.5, jj + 0.5], axis=-1).reshape(-1, 2)
    np.testing.assert_allclose(uv, centres, atol=2e-3)
    assert np.all(np.asarray(depth) > 0.0)


def test_pixel_directions_with_distortion_differ_from_pinhole():
    # A corner pixel of the fox camera is bent by the distortion; the reprojection test above
    # would not notice if both camera_rays and project_points ignored it.
    fox, pinhole = _CAMERAS["fox"], _CAMERAS["fox"].replace(distortion=jnp.zeros(4))
    d_fox = np.asarray(pixel_directions(fox, 0.5, 0.5))
    d_pin = np.asarray(pixel_directions(pinhole, 0.5, 0.5))
    assert np.abs(d_fox - d_pin).max() > 1e-3
    np.testing.assert_allclose(d_fox[2], -1.0)


@FEW
@given(q=quat, origin=vec3)
def test_centre_ray_is_minus_z_and_image_orientation(q, origin):
    intrinsics = Intrinsics.create(5, 3, 4.0)  # cx = 2.5, cy = 1.5: the centre of pixel (2, 1)
    rotation = _rotation_of(q)
    _, dirs = _camera_rays(_rigid(rotation, origin), intrinsics)
    dirs = np.asarray(dirs, np.float64)
    np.testing.assert_allclose(dirs[1, 2], -rotation[:, 2], atol=1e-6)
    cam = dirs @ rotation  # back into the camera frame: R^T d
    assert np.all(cam[0, :, 1] > 0.0) and np.all(cam[-1, :, 1] < 0.0)  # top row looks up (+y)
    assert np.all(cam[:, 0, 0] < 0.0) and np.all(cam[:, -1, 0] > 0.0)  # left column looks left (-x)
    assert np.all(cam[..., 2] < 0.0)  # everything in front (-z)


@pytest.mark.slow
def test_camera_rays_vmap_over_poses_equals_per_camera_calls():
    intrinsics = _CAMERAS["fox"]
    rng = np.random.default_rng(2)
    c2ws = np.stack([_rigid(Rotation.random(random_state=i).as_matrix(), rng.uniform(-2, 2, 3)) for i in range(5)])
    origins, dirs = jax.jit(jax.vmap(lambda m: camera_rays(m, intrinsics)))(c2ws)
    assert dirs.shape == (5, intrinsics.height, intrinsics.width, 3)
    for i, c2w in enumerate(c2ws):
        o_i, d_i = _camera_rays(c2w, intrinsics)
        np.testing.assert_allclose(origins[i], o_i, atol=1e-6)
        np.testing.assert_allclose(dirs[i], d_i, atol=1e-6)
    # [3, 4] matrices work too.
    np.testing.assert_allclose(_camera_rays(c2ws[0][:3], intrinsics)[1], dirs[0], atol=1e-6)


# ------------------------------------------------------------------------------------------------
# camera_focus


@FEW
@given(
    centre=vec3,
    radius=st.floats(0.5, 10.0),
    n=st.integers(3, 24),
    elevation=st.floats(-1.2, 1.2),
    phase=st.floats(0.0, 2 * np.pi),
)
def test_camera_focus_recovers_common_target(centre, radius, n, elevation, phase):
    angles = phase + np.linspace(0.0, 2 * np.pi, n, endpoint=False)
    # A tilted ring: alternate cameras above and below so the axes are not coplanar.
    heights = radius * np.sin(elevation) * np.where(np.arange(n) % 2 == 0, 1.0, 0.5)
    ring = np.stack([radius * np.cos(angles), heights, radius * np.sin(angles)], axis=-1)
    origins = (centre + ring).astype(np.float32)
    up = np.float32([0.0, 1.0, 0.0])
    c2w = np.stack([np.asarray(_look_at(o, centre, up)) for o in origins])
    np.testing.assert_allclose(camera_focus(c2w), centre, atol=1e-3 * max(1.0, radius))
    np.testing.assert_allclose(camera_focus(c2w[:, :3]), centre, atol=1e-3 * max(1.0, radius))
