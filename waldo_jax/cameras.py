"""Camera maths: poses, look-at, SLERP, projection and ray generation.

Conventions (NeRF/OpenGL, as in `waldo_jax.types`): a camera looks along its local -z axis, +y is up
and +x right; `c2w` is a camera-to-world matrix [4, 4] (a [3, 4] one is accepted where noted) whose
columns are right, up, backward and the camera origin. Pixel centres sit at (i + 0.5, j + 0.5).

The search methods of the paper ("Finding Waldo", MMSys'24) describe a pose by its origin, look-at
point and up vector (`waldo_jax.types.Pose`); `pose_to_c2w` and `c2w_to_pose` convert both ways.

Every function here is written for one camera and is jit-, vmap- and grad-safe: degenerate input
(an up vector parallel to the view direction, a target equal to the origin, a zero up vector) gives a
deterministic valid rotation and never a NaN, value or gradient.
"""

from __future__ import annotations

from typing import Tuple

import jax
import jax.numpy as jnp
import numpy as np

from waldo_jax.types import Array, Intrinsics, Pose

__all__ = [
    "look_at",
    "pose_to_c2w",
    "c2w_to_pose",
    "rotation_to_quaternion",
    "quaternion_to_rotation",
    "quaternion_slerp",
    "slerp_c2w",
    "slerp_pose",
    "rotation_angle",
    "distort",
    "undistort",
    "pixel_directions",
    "camera_rays",
    "pixel_ray",
    "project_points",
    "camera_focus",
    "scene_up",
]

_EPS = 1e-8
_WORLD_AXES = np.eye(3, dtype=np.float32)


def _safe_normalize(v: Array, fallback: Array) -> Tuple[Array, Array]:
    """Unit vector of `v` [3], or `fallback` when |v| is ~0; also returns whether v was usable."""
    sq = jnp.sum(v * v)
    ok = sq > _EPS**2
    v_safe = jnp.where(ok, v, fallback)  # keeps the norm below away from zero, gradients too
    return v_safe / jnp.sqrt(jnp.sum(v_safe * v_safe)), ok


def _least_aligned_axis(direction: Array) -> Array:
    """The world axis least aligned with a unit `direction` [3] (first one on ties): a safe helper up."""
    return jnp.asarray(_WORLD_AXES)[jnp.argmin(jnp.abs(direction))]


@jax.jit
def look_at(origin: Array, target: Array, up: Array) -> Array:
    """Camera-to-world matrix of a camera at `origin` looking at `target` (jitted: called from host
    code, or vmapped there, it is one compiled program per shape).

    Args:
      origin: camera centre, [3].
      target: look-at point, [3]. If it equals the origin the camera looks along world -z.
      up: approximate up vector, [3]. It is orthogonalised against the view direction. If it is zero
        or parallel to the view direction, a fallback is used (world +y for a zero up vector when
        that is not parallel too, else the world axis least aligned with the view direction), so the
        result is always a valid rotation.

    Returns:
      c2w: [4, 4] with columns right, up, backward (= -view direction) and origin.
    """
    origin = jnp.asarray(origin, jnp.float32)
    forward, _ = _safe_normalize(jnp.asarray(target, jnp.float32) - origin, jnp.array([0.0, 0.0, -1.0]))
    default_up = jnp.where(jnp.abs(forward[1]) < 0.99, jnp.array([0.0, 1.0, 0.0]), _least_aligned_axis(forward))
    up_dir, _ = _safe_normalize(jnp.asarray(up, jnp.float32), default_up)
    # Parallel up: fall back to the axis least aligned with the view direction.
    # Orthogonalise up against the view direction first: the cross product of nearly parallel
    # float32 vectors alone loses precision.
    up_ortho = up_dir - jnp.dot(up_dir, forward) * forward
    right, ok = _safe_normalize(jnp.cross(forward, up_ortho), jnp.zeros(3))
    fallback_right, _ = _safe_normalize(jnp.cross(forward, _least_aligned_axis(forward)), jnp.array([1.0, 0.0, 0.0]))
    right = jnp.where(ok & (jnp.abs(jnp.dot(forward, up_dir)) < 1.0 - 1e-6), right, fallback_right)
    true_up = jnp.cross(right, forward)
    rotation = jnp.stack([right, true_up, -forward], axis=-1)  # [3, 3], columns
    top = jnp.concatenate([rotation, origin[:, None]], axis=-1)  # [3, 4]
    return jnp.concatenate([top, jnp.array([[0.0, 0.0, 0.0, 1.0]])], axis=0)


def pose_to_c2w(pose: Pose) -> Array:
    """`look_at` of a `Pose` holding one camera ([3] fields); vmap it for a population."""
    return look_at(pose.origin, pose.target, pose.up)


def c2w_to_pose(c2w: Array, focus_distance: Array | float = 1.0) -> Pose:
    """Decomposes a camera-to-world matrix into origin, look-at point and up vector.

    Args:
      c2w: [4, 4] or [3, 4] camera-to-world matrix.
      focus_distance: distance along the view direction at which the look-at point is placed.

    Returns:
      A `Pose` with origin [3], target = origin + focus_distance * view direction [3] and the
      camera's up axis [3]. `pose_to_c2w` of it gives back `c2w` (for a rigid `c2w`).
    """
    c2w = jnp.asarray(c2w, jnp.float32)
    origin = c2w[:3, 3]
    return Pose(origin=origin, target=origin - focus_distance * c2w[:3, 2], up=c2w[:3, 1])


def rotation_to_quaternion(rotation: Array) -> Array:
    """Unit quaternion (w, x, y, z) of a rotation matrix [3, 3], with w >= 0.

    Uses the branch with the largest pivot (Shepperd's method), chosen with `where`, so it is stable
    for every rotation, including half turns.
    """
    m = jnp.asarray(rotation, jnp.float32)
    m00, m01, m02 = m[0, 0], m[0, 1], m[0, 2]
    m10, m11, m12 = m[1, 0], m[1, 1], m[1, 2]
    m20, m21, m22 = m[2, 0], m[2, 1], m[2, 2]
    pivots = jnp.stack(
        [
            1.0 + m00 + m11 + m22,
            1.0 + m00 - m11 - m22,
            1.0 - m00 + m11 - m22,
            1.0 - m00 - m11 + m22,
        ]
    )
    candidates = jnp.stack(
        [
            jnp.stack([pivots[0], m21 - m12, m02 - m20, m10 - m01]),
            jnp.stack([m21 - m12, pivots[1], m01 + m10, m02 + m20]),
            jnp.stack([m02 - m20, m01 + m10, pivots[2], m12 + m21]),
            jnp.stack([m10 - m01, m02 + m20, m12 + m21, pivots[3]]),
        ]
    )  # [4, 4]
    best = jnp.argmax(pivots)
    q = candidates[best] / (2.0 * jnp.sqrt(jnp.maximum(pivots[best], _EPS)))
    q = q / jnp.linalg.norm(q)
    return jnp.where(q[0] < 0.0, -q, q)


def quaternion_to_rotation(q: Array) -> Array:
    """Rotation matrix [3, 3] of a quaternion (w, x, y, z) [4] (normalised first)."""
    q = q / jnp.sqrt(jnp.maximum(jnp.sum(q * q), _EPS))
    w, x, y, z = q[0], q[1], q[2], q[3]
    return jnp.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def quaternion_slerp(q0: Array, q1: Array, t: Array | float) -> Array:
    """Spherical linear interpolation of unit quaternions [4] along the shorter arc; t in [0, 1].

    Nearly identical rotations fall back to normalised linear interpolation (no 0/0).
    """
    dot = jnp.dot(q0, q1)
    q1 = jnp.where(dot < 0.0, -q1, q1)
    dot = jnp.abs(dot)
    close = dot > 1.0 - 1e-6
    theta = jnp.arccos(jnp.clip(jnp.where(close, 0.0, dot), -1.0, 1.0))
    sin_theta = jnp.sin(theta)
    w0 = jnp.where(close, 1.0 - t, jnp.sin((1.0 - t) * theta) / jnp.where(close, 1.0, sin_theta))
    w1 = jnp.where(close, t, jnp.sin(t * theta) / jnp.where(close, 1.0, sin_theta))
    q = w0 * q0 + w1 * q1
    return q / jnp.sqrt(jnp.maximum(jnp.sum(q * q), _EPS))


def slerp_c2w(c2w_a: Array, c2w_b: Array, t: Array | float) -> Array:
    """Interpolates two camera-to-world matrices: rotation SLERP, linear translation.

    Args:
      c2w_a, c2w_b: [4, 4] or [3, 4] rigid transforms (t = 0 gives a, t = 1 gives b).
      t: interpolation parameter in [0, 1].

    Returns:
      c2w: [4, 4]; its rotation moves at constant angular speed from a's to b's.
    """
    q = quaternion_slerp(rotation_to_quaternion(c2w_a[:3, :3]), rotation_to_quaternion(c2w_b[:3, :3]), t)
    origin = (1.0 - t) * c2w_a[:3, 3] + t * c2w_b[:3, 3]
    top = jnp.concatenate([quaternion_to_rotation(q), origin[:, None]], axis=-1)
    return jnp.concatenate([top, jnp.array([[0.0, 0.0, 0.0, 1.0]], top.dtype)], axis=0)


def slerp_pose(pose_a: Pose, pose_b: Pose, t: Array | float) -> Pose:
    """SLERP between two `Pose`s ([3] fields): the camera frames are interpolated with `slerp_c2w`,
    the look-at point lies on the interpolated view axis at the linearly interpolated focus distance."""
    dist_a = jnp.linalg.norm(pose_a.target - pose_a.origin)
    dist_b = jnp.linalg.norm(pose_b.target - pose_b.origin)
    c2w = slerp_c2w(pose_to_c2w(pose_a), pose_to_c2w(pose_b), t)
    return c2w_to_pose(c2w, (1.0 - t) * dist_a + t * dist_b)


def rotation_angle(rotation_a: Array, rotation_b: Array) -> Array:
    """Geodesic angle in radians between two rotations [3, 3] (safe at 0 and pi)."""
    cos = 0.5 * (jnp.trace(rotation_a.T @ rotation_b) - 1.0)
    return jnp.arccos(jnp.clip(cos, -1.0, 1.0))


def distort(xy: Array, distortion: Array) -> Array:
    """Applies OpenCV radial-tangential distortion (k1, k2, p1, p2) to normalised coordinates [..., 2]."""
    k1, k2, p1, p2 = distortion[0], distortion[1], distortion[2], distortion[3]
    x, y = xy[..., 0], xy[..., 1]
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k1 + k2 * r2)
    xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
    yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
    return jnp.stack([xd, yd], axis=-1)


def undistort(xy_distorted: Array, distortion: Array, iterations: int = 10) -> Array:
    """Inverts `distort` for one point [2] by Newton's method (a fixed number of steps, jit-friendly).

    The Jacobian is the exact 2x2 one of `distort`; a singular Jacobian leaves the point unchanged.
    With zero distortion the first step is exact.
    """

    def step(_, xy):
        residual = distort(xy, distortion) - xy_distorted
        jac = jax.jacfwd(distort)(xy, distortion)  # [2, 2]
        det = jac[0, 0] * jac[1, 1] - jac[0, 1] * jac[1, 0]
        safe_det = jnp.where(jnp.abs(det) > 1e-12, det, 1.0)
        dx = (jac[1, 1] * residual[0] - jac[0, 1] * residual[1]) / safe_det
        dy = (jac[0, 0] * residual[1] - jac[1, 0] * residual[0]) / safe_det
        update = jnp.where(jnp.abs(det) > 1e-12, jnp.stack([dx, dy]), 0.0)
        return xy - update

    return jax.lax.fori_loop(0, iterations, step, xy_distorted)


def pixel_directions(intrinsics: Intrinsics, u: Array, v: Array) -> Array:
    """Camera-frame direction [3] (z = -1, not normalised) through pixel position (u, v).

    (u, v) are continuous pixel coordinates; the centre of pixel (i, j) is (i + 0.5, j + 0.5).
    """
    xy = jnp.stack([(u - intrinsics.cx) / intrinsics.fx, (v - intrinsics.cy) / intrinsics.fy])
    xy = undistort(xy, intrinsics.distortion)
    return jnp.stack([xy[0], -xy[1], -jnp.ones_like(xy[0])])


def camera_rays(c2w: Array, intrinsics: Intrinsics) -> Tuple[Array, Array]:
    """Rays through every pixel centre of one camera.

    Args:
      c2w: [4, 4] or [3, 4] camera-to-world matrix.
      intrinsics: the camera's `Intrinsics` (its width and height set the output shape).

    Returns:
      origins: [H, W, 3] (all equal to the camera centre).
      directions: [H, W, 3] unit directions in world coordinates.
    """
    c2w = jnp.asarray(c2w, jnp.float32)
    u = jnp.arange(intrinsics.width, dtype=jnp.float32) + 0.5
    v = jnp.arange(intrinsics.height, dtype=jnp.float32) + 0.5
    uu, vv = jnp.meshgrid(u, v, indexing="xy")  # [H, W]
    dirs_cam = jax.vmap(jax.vmap(lambda a, b: pixel_directions(intrinsics, a, b)))(uu, vv)  # [H, W, 3]
    dirs = dirs_cam @ c2w[:3, :3].T  # [H, W, 3]
    dirs = dirs / jnp.linalg.norm(dirs, axis=-1, keepdims=True)
    origins = jnp.broadcast_to(c2w[:3, 3], dirs.shape)
    return origins, dirs


def pixel_ray(c2w: Array, intrinsics: Intrinsics, pixel: Array) -> Tuple[Array, Array]:
    """The ray through the centre of ONE pixel, named by its flat index.

    Args:
      c2w: [4, 4] or [3, 4] camera-to-world matrix.
      intrinsics: the camera's `Intrinsics`.
      pixel: int [], row-major flat index `row * width + col` in [0, height * width).

    Returns:
      origin: [3], the camera centre. direction: [3], unit, in world coordinates (as `camera_rays`).
    """
    c2w = jnp.asarray(c2w, jnp.float32)
    row, col = pixel // intrinsics.width, pixel % intrinsics.width
    dir_cam = pixel_directions(intrinsics, col.astype(jnp.float32) + 0.5, row.astype(jnp.float32) + 0.5)  # [3]
    direction = jnp.sum(c2w[:3, :3] * dir_cam[None, :], axis=1)  # [3]
    return c2w[:3, 3], direction / jnp.linalg.norm(direction)


def project_points(c2w: Array, intrinsics: Intrinsics, points: Array) -> Tuple[Array, Array]:
    """Projects world points into one camera (with its distortion).

    Args:
      c2w: [4, 4] or [3, 4] camera-to-world matrix (rigid).
      intrinsics: the camera's `Intrinsics`.
      points: [N, 3] world points.

    Returns:
      uv: [N, 2] continuous pixel coordinates (meaningless where depth <= 0).
      depth: [N] distance in front of the camera along its view axis (> 0 means in front).
    """
    rotation, origin = c2w[:3, :3], c2w[:3, 3]
    cam = (points - origin) @ rotation  # [N, 3]; = R^T (p - o)
    depth = -cam[:, 2]
    safe_depth = jnp.where(jnp.abs(depth) > _EPS, depth, _EPS)
    xy = jnp.stack([cam[:, 0] / safe_depth, -cam[:, 1] / safe_depth], axis=-1)  # image y points down
    xy = distort(xy, intrinsics.distortion)
    uv = jnp.stack([xy[:, 0] * intrinsics.fx + intrinsics.cx, xy[:, 1] * intrinsics.fy + intrinsics.cy], axis=-1)
    return uv, depth


def camera_focus(c2w: np.ndarray) -> np.ndarray:
    """The point closest (least squares) to all cameras' optical axes: where they look (host, NumPy).

    A small pull towards the mean camera origin keeps it finite when the axes are parallel.

    Args:
      c2w: [N, 4, 4] or [N, 3, 4] camera-to-world matrices.

    Returns:
      float64 [3], world coordinates.
    """
    c2w = np.asarray(c2w, np.float64)
    origins = c2w[:, :3, 3]
    dirs = -c2w[:, :3, 2]
    dirs = dirs / np.linalg.norm(dirs, axis=-1, keepdims=True)
    projectors = np.eye(3)[None] - dirs[:, :, None] * dirs[:, None, :]  # [N, 3, 3], off each axis
    ridge = 1e-4 * len(origins)
    lhs = projectors.sum(0) + ridge * np.eye(3)
    rhs = np.einsum("nij,nj->i", projectors, origins) + ridge * origins.mean(0)
    return np.linalg.solve(lhs, rhs)


def scene_up(c2w: np.ndarray) -> np.ndarray:
    """The scene's up direction float64 [3] (unit): the normalised mean of the cameras' up vectors
    c2w[:, :3, 1] (OpenGL cameras: +y is the image's up), as nerfstudio's and multinerf's "up"
    orientation takes it. +z when there are no cameras or their up vectors cancel out (host, NumPy).

    Args:
      c2w: float [N, 4, 4] (or [N, 3, 4]) camera-to-world poses, the training cameras.
    """
    c2w = np.asarray(c2w, np.float64)
    mean = c2w[:, :3, 1].mean(axis=0) if len(c2w) else np.zeros(3)
    norm = float(np.linalg.norm(mean))
    return mean / norm if norm > 1e-6 else np.array([0.0, 0.0, 1.0])
