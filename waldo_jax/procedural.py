"""The procedural "Waldo room": an analytic radiance field with a known answer.

A seeded room (a checkered floor and four walls) cluttered with coloured boxes, spheres and
cylinders, and one small Waldo figure (blue legs, a red-and-white striped jumper, a head and a
striped bobble hat) hidden in a pen of crates. It needs no training: the radiance field is analytic
(densities from signed distance functions) and is rendered by `waldo_jax.render` like any other field.

It provides
  * `make_room(seed)`: the geometry as a pytree (`WaldoRoom`), which is also the field's params;
  * `room_field(room, x, d)`: the radiance field for one point;
  * `training_cameras(key, room, ...)`: cameras on a band around the room (inside the walls, looking
    towards its middle), kept only when they see Waldo at most partly (occluded, or cut by the
    frame), so that a search can improve on every training view;
  * `room_scene(seed, ...)`: those training views rendered as a `waldo_jax.types.Scene`;
  * `waldo_visibility(room, c2w, intrinsics)`: the exact oracle, the fraction of Waldo's projected
    area that is inside the frame and not occluded, from ray/primitive intersections with the
    analytic geometry (not from a render).

Units are metres; +y is up; the floor is the plane y = 0 and the room spans
[-ROOM_HALF, ROOM_HALF] in x and z.

Density model: sigma(x) = DENSITY * sigmoid(-sdf(x) / SURFACE_WIDTH), where sdf is the signed
distance to the union of all primitives; colour is that of the nearest primitive (with its pattern),
shaded by a fixed directional light using the SDF gradient as the normal. The oracle uses the hard
surfaces (sdf = 0) of the same primitives.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Optional, Tuple

import flax.struct
import jax
import jax.numpy as jnp
import numpy as np

from waldo_jax.cameras import look_at, project_points
from waldo_jax.types import Array, Intrinsics, PRNGKey, Scene

__all__ = [
    "WaldoRoom",
    "RoomCameraConfig",
    "make_room",
    "room_field",
    "room_sdf",
    "room_render_config",
    "training_cameras",
    "room_scene",
    "waldo_visibility",
    "waldo_visibility_batch",
]

ROOM_HALF = 4.0  # the room spans [-4, 4] in x and z
WALL_HEIGHT = 2.6
DENSITY = 400.0  # density inside solids, per metre
SURFACE_WIDTH = 0.01  # sigmoid width of the soft surface, metres
LIGHT_DIR = np.array([0.4, 1.0, 0.3]) / np.linalg.norm([0.4, 1.0, 0.3])
BACKGROUND = (0.78, 0.84, 0.92)

PATTERN_PLAIN, PATTERN_CHECKER, PATTERN_STRIPES = 0, 1, 2
WALDO_RED = (0.86, 0.08, 0.08)
WALDO_WHITE = (0.97, 0.97, 0.97)
STRIPE_WIDTH = 0.05

# Primitive kinds in the flat arrays of `WaldoRoom`.
KIND_BOX, KIND_SPHERE, KIND_CYLINDER = 0, 1, 2
_FAR = 1e30  # "no intersection" segment parameter (finite: no inf arithmetic under jit)


@flax.struct.dataclass
class WaldoRoom:
    """Geometry of one room; it is also the params pytree of `room_field`.

    Every primitive is a row of the flat arrays (K primitives), sorted by kind: `num_boxes` boxes,
    then `num_spheres` spheres, then the cylinders. Boxes use `size` as half extents;
    spheres use `size[0]` as radius; vertical cylinders use `size[0]` as radius and `size[1]` as half
    height. `center` is the primitive's centre.

    Attributes:
      kind: int32 [K], KIND_BOX / KIND_SPHERE / KIND_CYLINDER.
      center: float32 [K, 3].
      size: float32 [K, 3].
      color: float32 [K, 3] in [0, 1].
      pattern: int32 [K], PATTERN_PLAIN / PATTERN_CHECKER / PATTERN_STRIPES.
      is_waldo: bool [K], the primitives that make up Waldo.
      waldo_points: float32 [M, 3], surface samples of Waldo (for the oracle).
      waldo_normals: float32 [M, 3], their outward unit normals.
      waldo_areas: float32 [M], the surface area each sample stands for.
      waldo_base: float32 [3], the point on the floor where Waldo stands.
      num_boxes, num_spheres: how many rows are boxes and spheres (static).
      seed: the seed the room was built from (static).
    """

    kind: Array
    center: Array
    size: Array
    color: Array
    pattern: Array
    is_waldo: Array
    waldo_points: Array
    waldo_normals: Array
    waldo_areas: Array
    waldo_base: Array
    num_boxes: int = flax.struct.field(pytree_node=False, default=0)
    num_spheres: int = flax.struct.field(pytree_node=False, default=0)
    seed: int = flax.struct.field(pytree_node=False, default=0)

    @property
    def waldo_center(self) -> Array:
        """Centre of Waldo's figure (half his height above `waldo_base`)."""
        return self.waldo_base + jnp.array([0.0, 0.5, 0.0])

    @property
    def aabb(self) -> np.ndarray:
        """The room's box [2, 3] (walls included)."""
        pad = 0.35
        return np.array([[-ROOM_HALF - pad, -0.3, -ROOM_HALF - pad], [ROOM_HALF + pad, WALL_HEIGHT, ROOM_HALF + pad]],
                        np.float32)


# ---------------------------------------------------------------------------------------------
# Signed distances and the radiance field (one point each).


def _box_sdf(p: Array, center: Array, half: Array) -> Array:
    q = jnp.abs(p - center) - half
    outside = jnp.sqrt(jnp.sum(jnp.maximum(q, 0.0) ** 2) + 1e-12)
    return jnp.where(jnp.all(q <= 0.0), jnp.max(q), outside)


def _sphere_sdf(p: Array, center: Array, radius: Array) -> Array:
    return jnp.sqrt(jnp.sum((p - center) ** 2) + 1e-12) - radius


def _cylinder_sdf(p: Array, center: Array, radius: Array, half_height: Array) -> Array:
    d = p - center
    radial = jnp.sqrt(d[0] ** 2 + d[2] ** 2 + 1e-12) - radius
    vertical = jnp.abs(d[1]) - half_height
    q = jnp.stack([radial, vertical])
    outside = jnp.sqrt(jnp.sum(jnp.maximum(q, 0.0) ** 2) + 1e-12)
    return jnp.where(jnp.all(q <= 0.0), jnp.max(q), outside)


def _primitive_sdf(p: Array, kind: Array, center: Array, size: Array) -> Array:
    """Signed distance from p [3] to one primitive; kind selects the formula."""
    return jnp.select(
        [kind == KIND_BOX, kind == KIND_SPHERE],
        [_box_sdf(p, center, size), _sphere_sdf(p, center, size[0])],
        _cylinder_sdf(p, center, size[0], size[1]),
    )


def _all_sdf(room: WaldoRoom, p: Array) -> Array:
    """Signed distances [K] from p [3] to every primitive.

    Primitives are stored sorted by kind (boxes, spheres, cylinders; counts static), so each formula
    runs only on its own rows.
    """
    nb, ns = room.num_boxes, room.num_spheres
    box_c, box_h = room.center[:nb], room.size[:nb]
    q = jnp.abs(p - box_c) - box_h  # [nb, 3]
    box = jnp.where(
        jnp.all(q <= 0.0, axis=-1),
        jnp.max(q, axis=-1),
        jnp.sqrt(jnp.sum(jnp.maximum(q, 0.0) ** 2, axis=-1) + 1e-12),
    )
    sph_c, sph_r = room.center[nb:nb + ns], room.size[nb:nb + ns, 0]
    sphere = jnp.sqrt(jnp.sum((p - sph_c) ** 2, axis=-1) + 1e-12) - sph_r
    d = p - room.center[nb + ns:]  # [nc, 3]
    size = room.size[nb + ns:]
    radial = jnp.sqrt(d[:, 0] ** 2 + d[:, 2] ** 2 + 1e-12) - size[:, 0]
    vertical = jnp.abs(d[:, 1]) - size[:, 1]
    inside = (radial <= 0.0) & (vertical <= 0.0)
    cylinder = jnp.where(
        inside,
        jnp.maximum(radial, vertical),
        jnp.sqrt(jnp.maximum(radial, 0.0) ** 2 + jnp.maximum(vertical, 0.0) ** 2 + 1e-12),
    )
    return jnp.concatenate([box, sphere, cylinder])


def room_sdf(room: WaldoRoom, p: Array) -> Array:
    """Signed distance from one point p [3] to the union of the room's solids (negative inside)."""
    return jnp.min(_all_sdf(room, p))


def _albedo(room: WaldoRoom, index: Array, p: Array) -> Array:
    base = room.color[index]
    checker = (jnp.floor(p[0] / 0.5) + jnp.floor(p[2] / 0.5)) % 2.0
    checker_color = base * (0.72 + 0.28 * checker)
    stripe = jnp.floor((p[1] - room.waldo_base[1]) / STRIPE_WIDTH) % 2.0
    stripes_color = jnp.where(stripe < 0.5, jnp.array(WALDO_RED), jnp.array(WALDO_WHITE))
    return jnp.select(
        [room.pattern[index] == PATTERN_CHECKER, room.pattern[index] == PATTERN_STRIPES],
        [checker_color, stripes_color],
        base,
    )


def room_field(room: WaldoRoom, x: Array, d: Array) -> Tuple[Array, Array]:
    """The room's radiance field at one point.

    Args:
      room: the room (the field's params).
      x: world point [3].
      d: unit view direction [3] (unused: the room is Lambertian).

    Returns:
      sigma: density [] (per metre). rgb: colour [3] in [0, 1].
    """
    del d
    distances = _all_sdf(room, x)  # [K]
    nearest = jnp.argmin(distances)
    sigma = DENSITY * jax.nn.sigmoid(-distances[nearest] / SURFACE_WIDTH)
    # The shading normal is the gradient of the nearest primitive's distance alone (cheap).
    normal = jax.grad(_primitive_sdf)(x, room.kind[nearest], room.center[nearest], room.size[nearest])
    normal = normal / jnp.sqrt(jnp.sum(normal**2) + 1e-12)
    shade = 0.5 + 0.5 * jnp.maximum(jnp.dot(normal, jnp.asarray(LIGHT_DIR, jnp.float32)), 0.0)
    return sigma, jnp.clip(_albedo(room, nearest, x) * shade, 0.0, 1.0)


def room_render_config(room: WaldoRoom, num_samples: int = 128, **kwargs):
    """A `RenderConfig` suited to the room: its box, near 0.05, far 12 and the sky background."""
    from waldo_jax.render import RenderConfig

    return RenderConfig.create(near=0.05, far=12.0, aabb=room.aabb, background=BACKGROUND,
                               num_samples=num_samples, **kwargs)


# ---------------------------------------------------------------------------------------------
# Building a room.

_PALETTE = np.array([
    [0.20, 0.45, 0.80], [0.95, 0.70, 0.15], [0.25, 0.65, 0.35], [0.55, 0.30, 0.65],
    [0.90, 0.45, 0.25], [0.35, 0.75, 0.80], [0.80, 0.35, 0.50], [0.60, 0.55, 0.35],
    [0.45, 0.45, 0.50], [0.70, 0.80, 0.30],
], np.float32)


@dataclasses.dataclass
class _Builder:
    kind: list = dataclasses.field(default_factory=list)
    center: list = dataclasses.field(default_factory=list)
    size: list = dataclasses.field(default_factory=list)
    color: list = dataclasses.field(default_factory=list)
    pattern: list = dataclasses.field(default_factory=list)
    is_waldo: list = dataclasses.field(default_factory=list)

    def add(self, kind, center, size, color, pattern=PATTERN_PLAIN, waldo=False):
        size = list(size) + [0.0] * (3 - len(size))
        for name, value in zip(("kind", "center", "size", "color", "pattern", "is_waldo"),
                               (kind, center, size, color, pattern, waldo)):
            getattr(self, name).append(value)


def _waldo_parts(base: np.ndarray):
    """Waldo's primitives (kind, centre, size, colour, pattern), standing at `base` (about 1 m tall)."""
    x, y, z = base
    skin = (0.96, 0.78, 0.64)
    return [
        (KIND_CYLINDER, (x, y + 0.15, z), (0.085, 0.15), (0.15, 0.22, 0.62), PATTERN_PLAIN),  # legs
        (KIND_CYLINDER, (x, y + 0.475, z), (0.12, 0.175), WALDO_RED, PATTERN_STRIPES),  # jumper
        (KIND_SPHERE, (x, y + 0.74, z), (0.1,), skin, PATTERN_PLAIN),  # head
        (KIND_CYLINDER, (x, y + 0.875, z), (0.075, 0.055), WALDO_RED, PATTERN_STRIPES),  # hat
        (KIND_SPHERE, (x, y + 0.96, z), (0.04,), WALDO_WHITE, PATTERN_PLAIN),  # bobble
    ]


def _surface_samples(kind: int, center, size, density: float = 900.0):
    """Regular samples of one primitive's surface: points [n, 3], normals [n, 3], areas [n]."""
    c = np.asarray(center, np.float64)
    if kind == KIND_SPHERE:
        r = size[0]
        n = max(16, int(density * 4 * np.pi * r * r))
        i = np.arange(n) + 0.5
        polar = np.arccos(1 - 2 * i / n)
        azimuth = np.pi * (1 + 5**0.5) * i
        normals = np.stack([np.cos(azimuth) * np.sin(polar), np.cos(polar), np.sin(azimuth) * np.sin(polar)], -1)
        return c + r * normals, normals, np.full(n, 4 * np.pi * r * r / n)
    if kind == KIND_CYLINDER:
        r, h = size[0], size[1]
        n_theta = max(12, int(np.sqrt(density) * 2 * np.pi * r))
        n_y = max(4, int(np.sqrt(density) * 2 * h))
        theta = (np.arange(n_theta) + 0.5) / n_theta * 2 * np.pi
        ys = (np.arange(n_y) + 0.5) / n_y * 2 * h - h
        tt, yy = np.meshgrid(theta, ys)
        side_n = np.stack([np.cos(tt), np.zeros_like(tt), np.sin(tt)], -1).reshape(-1, 3)
        side_p = c + side_n * r + np.stack([np.zeros_like(yy), yy, np.zeros_like(yy)], -1).reshape(-1, 3)
        side_a = np.full(len(side_p), 2 * np.pi * r * 2 * h / len(side_p))
        n_r = max(2, int(np.sqrt(density) * r))
        rings = []
        for k in range(n_r):  # equal-area rings on each cap
            rho = r * np.sqrt((k + 0.5) / n_r)
            m = max(6, int(2 * np.pi * rho * np.sqrt(density)))
            ang = (np.arange(m) + 0.5) / m * 2 * np.pi
            rings.append(np.stack([rho * np.cos(ang), rho * np.sin(ang)], -1))
        disc = np.concatenate(rings)
        caps_p, caps_n = [], []
        for sign in (1.0, -1.0):
            caps_p.append(c + np.stack([disc[:, 0], np.full(len(disc), sign * h), disc[:, 1]], -1))
            caps_n.append(np.tile([0.0, sign, 0.0], (len(disc), 1)))
        caps_p, caps_n = np.concatenate(caps_p), np.concatenate(caps_n)
        caps_a = np.full(len(caps_p), 2 * np.pi * r * r / len(caps_p))
        return (np.concatenate([side_p, caps_p]), np.concatenate([side_n, caps_n]), np.concatenate([side_a, caps_a]))
    raise ValueError(f"no surface sampler for primitive kind {kind}")


def make_room(seed: int = 0, num_clutter: int = 12, num_crates: int = 4) -> WaldoRoom:
    """Builds the seeded room.

    Args:
      seed: the seed; the same seed always gives the same room.
      num_clutter: coloured primitives scattered over the room (the primitive count, and so the
        array shapes, depend only on this and `num_crates`).
      num_crates: crates in the pen around Waldo.

    Returns:
      A `WaldoRoom`.
    """
    key = jax.random.key(seed)
    k_waldo, k_crates, k_clutter = jax.random.split(key, 3)
    b = _Builder()
    # Floor slab and walls.
    b.add(KIND_BOX, (0.0, -0.15, 0.0), (ROOM_HALF + 0.3, 0.15, ROOM_HALF + 0.3), (0.82, 0.76, 0.66), PATTERN_CHECKER)
    wall = (0.90, 0.88, 0.84)
    for axis, sign in ((0, 1), (0, -1), (2, 1), (2, -1)):
        centre = [0.0, WALL_HEIGHT / 2, 0.0]
        centre[axis] = sign * (ROOM_HALF + 0.15)
        half = [ROOM_HALF + 0.3, WALL_HEIGHT / 2, ROOM_HALF + 0.3]
        half[axis] = 0.15
        b.add(KIND_BOX, centre, half, wall)

    # Waldo stands off-centre, in a pen of crates with gaps between them.
    u = np.asarray(jax.random.uniform(k_waldo, (2,)), np.float64)
    radius, angle = 0.4 + 0.8 * u[0], 2 * np.pi * u[1]
    base = np.array([radius * np.cos(angle), 0.0, radius * np.sin(angle)])
    waldo_parts = _waldo_parts(base)
    for kind, centre, size, colour, pattern in waldo_parts:
        b.add(kind, centre, size, colour, pattern, waldo=True)

    uc = np.asarray(jax.random.uniform(k_crates, (max(num_crates, 1), 4)), np.float64)
    start = 2 * np.pi * uc[0, 0]
    for i in range(num_crates):
        a = start + 2 * np.pi * (i + 0.2 * (uc[i, 1] - 0.5)) / num_crates
        dist = 0.5 + 0.08 * uc[i, 2]
        half_w = 0.2 + 0.06 * uc[i, 3]
        height = 0.85 + 0.3 * uc[i, 2]
        centre = base + np.array([dist * np.cos(a), height / 2, dist * np.sin(a)])
        b.add(KIND_BOX, centre, (half_w, height / 2, half_w), _PALETTE[(i * 3) % len(_PALETTE)] * 0.8 + 0.1)

    # Clutter: placed on a ring of the room away from Waldo's pen and the camera band.
    uk = np.asarray(jax.random.uniform(k_clutter, (num_clutter, 6)), np.float64)
    for i in range(num_clutter):
        kind = (KIND_BOX, KIND_SPHERE, KIND_CYLINDER)[i % 3]
        for attempt in range(8):  # deterministic re-draw from the same row when too close to Waldo
            v = (uk[i] + attempt * 0.6180339887) % 1.0
            r = 2.3 * np.sqrt(v[0])
            a = 2 * np.pi * v[1]
            xz = np.array([r * np.cos(a), r * np.sin(a)])
            if np.linalg.norm(xz - base[[0, 2]]) > 1.25:
                break
        colour = _PALETTE[int(v[2] * len(_PALETTE)) % len(_PALETTE)]
        s = 0.18 + 0.3 * v[3]
        if kind == KIND_BOX:
            h = 0.2 + 0.9 * v[4]
            b.add(kind, (xz[0], h / 2, xz[1]), (s, h / 2, s * (0.6 + 0.8 * v[5])), colour)
        elif kind == KIND_SPHERE:
            b.add(kind, (xz[0], s + 0.4 * v[4], xz[1]), (s,), colour)
            # a sphere floating off the floor stands on a thin post
            b.add(KIND_CYLINDER, (xz[0], (0.4 * v[4]) / 2, xz[1]), (0.03, (0.4 * v[4]) / 2 + 1e-3), (0.3, 0.3, 0.3))
        else:
            h = 0.4 + 1.4 * v[4]
            b.add(kind, (xz[0], h / 2, xz[1]), (0.6 * s, h / 2), colour)

    order = np.argsort(np.asarray(b.kind), kind="stable")  # boxes, spheres, cylinders
    arrays = dict(
        kind=np.asarray(b.kind, np.int32),
        center=np.asarray(b.center, np.float32),
        size=np.asarray(b.size, np.float32),
        color=np.asarray(b.color, np.float32),
        pattern=np.asarray(b.pattern, np.int32),
        is_waldo=np.asarray(b.is_waldo, bool),
    )
    arrays = {k: v[order] for k, v in arrays.items()}

    # Oracle samples: Waldo's surface, minus the parts buried inside his other parts.
    points, normals, areas = [], [], []
    for kind, centre, size, _, _ in waldo_parts:
        p, n, a = _surface_samples(kind, centre, size)
        points.append(p)
        normals.append(n)
        areas.append(a)
    points, normals, areas = np.concatenate(points), np.concatenate(normals), np.concatenate(areas)
    waldo_rows = np.flatnonzero(arrays["is_waldo"])
    sdf_to_parts = np.asarray(jax.vmap(lambda p: jax.vmap(_primitive_sdf, in_axes=(None, 0, 0, 0))(
        p, jnp.asarray(arrays["kind"][waldo_rows]), jnp.asarray(arrays["center"][waldo_rows]),
        jnp.asarray(arrays["size"][waldo_rows])))(jnp.asarray(points, jnp.float32)))
    on_surface = np.all(sdf_to_parts > -1e-4, axis=1) & (points[:, 1] > 1e-3)  # not buried, not on the floor
    return WaldoRoom(
        waldo_points=jnp.asarray(points[on_surface], jnp.float32),
        waldo_normals=jnp.asarray(normals[on_surface], jnp.float32),
        waldo_areas=jnp.asarray(areas[on_surface], jnp.float32),
        waldo_base=jnp.asarray(base, jnp.float32),
        num_boxes=int(np.sum(arrays["kind"] == KIND_BOX)),
        num_spheres=int(np.sum(arrays["kind"] == KIND_SPHERE)),
        seed=int(seed),
        **{k: jnp.asarray(v) for k, v in arrays.items()},
    )


# ---------------------------------------------------------------------------------------------
# The oracle: exact visibility of Waldo from the analytic geometry.


def _segment_hits(kind: Array, center: Array, size: Array, start: Array, end: Array) -> Array:
    """Whether the open segment start -> end [3] crosses the solid primitive (exact)."""
    v = end - start
    safe_v = jnp.where(jnp.abs(v) > 1e-12, v, 1e-12)

    def slab(lo, hi):
        t0, t1 = (lo - start) / safe_v, (hi - start) / safe_v
        return jnp.minimum(t0, t1), jnp.maximum(t0, t1)

    # Box: intersection of three slabs.
    near, far = slab(center - size, center + size)
    box_in, box_out = jnp.max(near), jnp.min(far)

    # Quadratic a s^2 + b s + c = 0 for the sphere and the cylinder's mantle.
    def quadratic(a, half_b, c):
        disc = half_b * half_b - a * c
        safe_a = jnp.where(jnp.abs(a) > 1e-12, a, 1.0)
        root = jnp.sqrt(jnp.maximum(disc, 0.0))
        lo, hi = (-half_b - root) / safe_a, (-half_b + root) / safe_a
        degenerate = jnp.abs(a) <= 1e-12  # no motion in the quadratic's plane: inside or not, always
        lo = jnp.where(degenerate, jnp.where(c < 0.0, -_FAR, _FAR), jnp.where(disc > 0.0, lo, _FAR))
        hi = jnp.where(degenerate, jnp.where(c < 0.0, _FAR, -_FAR), jnp.where(disc > 0.0, hi, -_FAR))
        return lo, hi

    d = start - center
    r = size[0]
    sph_in, sph_out = quadratic(jnp.dot(v, v), jnp.dot(v, d), jnp.dot(d, d) - r * r)
    cyl_in, cyl_out = quadratic(v[0] ** 2 + v[2] ** 2, v[0] * d[0] + v[2] * d[2], d[0] ** 2 + d[2] ** 2 - r * r)
    y_near, y_far = slab(center[1] - size[1], center[1] + size[1])
    cyl_in, cyl_out = jnp.maximum(cyl_in, y_near[1]), jnp.minimum(cyl_out, y_far[1])

    t_in = jnp.select([kind == KIND_BOX, kind == KIND_SPHERE], [box_in, sph_in], cyl_in)
    t_out = jnp.select([kind == KIND_BOX, kind == KIND_SPHERE], [box_out, sph_out], cyl_out)
    return (t_in < t_out) & (t_out > 0.0) & (t_in < 1.0)


def _waldo_solid_angles(room: WaldoRoom, c2w: Array, intrinsics: Intrinsics, near: float) -> Tuple[Array, Array]:
    """(seen, facing): Waldo's solid angle (steradians) that the camera sees, and that faces it."""
    c2w = jnp.asarray(c2w, jnp.float32)
    camera = c2w[:3, 3]
    to_camera = camera - room.waldo_points  # [M, 3]
    dist2 = jnp.sum(to_camera**2, axis=-1)
    cos = jnp.sum(room.waldo_normals * to_camera, axis=-1) / jnp.sqrt(dist2 + 1e-12)
    weight = room.waldo_areas * jnp.maximum(cos, 0.0) / jnp.maximum(dist2, 1e-6)  # [M] solid angles

    uv, depth = project_points(c2w, intrinsics, room.waldo_points)
    in_frame = (depth > near) & (uv[:, 0] >= 0) & (uv[:, 0] <= intrinsics.width) & (uv[:, 1] >= 0) & (
        uv[:, 1] <= intrinsics.height)

    starts = room.waldo_points + 1e-4 * room.waldo_normals  # off the surface, so its own solid is not hit
    hits = jax.vmap(lambda s: jax.vmap(_segment_hits, in_axes=(0, 0, 0, None, None))(
        room.kind, room.center, room.size, s, camera))(starts)  # [M, K]
    seen = in_frame & ~jnp.any(hits, axis=-1)
    return jnp.sum(jnp.where(seen, weight, 0.0)), jnp.sum(weight)


def waldo_visibility(room: WaldoRoom, c2w: Array, intrinsics: Intrinsics, near: float = 0.05) -> Array:
    """The oracle: the fraction of Waldo's projected area that is in frame and not occluded.

    Waldo's surface is represented by regular area-weighted samples. A sample counts towards the
    projected area when it faces the camera, with weight area * cos(angle) / distance^2 (its solid
    angle, so proportional to its projected pixels); it counts as seen when, in addition, it
    projects inside the image in front of the camera (beyond `near`) and the segment from it to the
    camera centre crosses no solid (walls, floor, clutter, crates, or Waldo's other parts).

    Args:
      room: the room.
      c2w: [4, 4] or [3, 4] camera-to-world matrix of one camera.
      intrinsics: its intrinsics (distortion included).
      near: minimum depth in front of the camera.

    Returns:
      visibility [] in [0, 1]: 0 when Waldo is behind the camera, out of frame or hidden; 1 when
      all of Waldo is in frame with nothing in between.
    """
    seen, facing = _waldo_solid_angles(room, c2w, intrinsics, near)
    return jnp.where(facing > 0.0, seen / jnp.maximum(facing, 1e-30), 0.0)


def waldo_coverage(room: WaldoRoom, c2w: Array, intrinsics: Intrinsics, near: float = 0.05) -> Array:
    """The share of the image covered by the visible part of Waldo (his "visible pixels" / all pixels).

    The seen solid angle of `waldo_visibility` times the pixels per steradian at the image centre
    (fx * fy), over the image's pixel count. It is largest when Waldo is close, unoccluded and
    whole in frame: moving closer enlarges him until the frame starts to cut him. Like the paper's
    salient-pixel criterion, but exact.

    Returns:
      coverage [] in [0, 1] (clipped; the small-angle pixel estimate can overshoot near the border).
    """
    seen, _ = _waldo_solid_angles(room, c2w, intrinsics, near)
    pixels = seen * intrinsics.fx * intrinsics.fy
    return jnp.clip(pixels / (intrinsics.width * intrinsics.height), 0.0, 1.0)


@jax.jit
def waldo_visibility_batch(room: WaldoRoom, c2w: Array, intrinsics: Intrinsics) -> Array:
    """`waldo_visibility` for a population of cameras c2w [P, 4, 4]; returns [P]."""
    return jax.vmap(waldo_visibility, in_axes=(None, 0, None))(room, c2w, intrinsics)


# ---------------------------------------------------------------------------------------------
# Training cameras and the training scene.


@dataclasses.dataclass(frozen=True)
class RoomCameraConfig:
    """Where the training cameras of the room go (a band inside the walls, looking inwards).

    Attributes:
      band_radius: (min, max) horizontal distance from the room's centre.
      band_height: (min, max) camera height.
      target_radius: look-at points lie within this distance of the centre ...
      target_height: ... at heights in this range.
      fov_x: horizontal field of view in radians.
      max_visibility: a camera is kept only if it sees at most this fraction of Waldo.
      oversample: candidate cameras drawn per kept camera.
    """

    band_radius: Tuple[float, float] = (2.9, 3.4)
    band_height: Tuple[float, float] = (1.0, 1.7)
    target_radius: float = 1.2
    target_height: Tuple[float, float] = (0.2, 0.9)
    fov_x: float = math.radians(60.0)
    max_visibility: float = 0.5
    oversample: int = 6


def training_cameras(key: PRNGKey, room: WaldoRoom, num_views: int, intrinsics: Intrinsics,
                     config: RoomCameraConfig = RoomCameraConfig()) -> np.ndarray:
    """Training cameras on a band around the room that see Waldo at most partly.

    Candidates are spread evenly in angle (with jitter) over the band, each looking at a random
    point near the centre; the first `num_views` candidates (in angular order) whose oracle
    visibility is at most `config.max_visibility` are kept.

    Args:
      key: PRNG key.
      room: the room.
      num_views: cameras to return.
      intrinsics: the cameras' intrinsics (the frame decides what "cut by the frame" means).
      config: the band.

    Returns:
      c2w: float32 [num_views, 4, 4].

    Raises:
      ValueError: when too few candidates qualify (ask for fewer views or a larger oversample).
    """
    n = num_views * config.oversample
    k_angle, k_radius, k_height, k_target = jax.random.split(key, 4)
    angle = 2 * jnp.pi * (jnp.arange(n) + jax.random.uniform(k_angle, (n,))) / n
    radius = jax.random.uniform(k_radius, (n,), minval=config.band_radius[0], maxval=config.band_radius[1])
    height = jax.random.uniform(k_height, (n,), minval=config.band_height[0], maxval=config.band_height[1])
    origins = jnp.stack([radius * jnp.cos(angle), height, radius * jnp.sin(angle)], -1)
    kt_r, kt_a, kt_h = jax.random.split(k_target, 3)
    t_r = config.target_radius * jnp.sqrt(jax.random.uniform(kt_r, (n,)))
    t_a = 2 * jnp.pi * jax.random.uniform(kt_a, (n,))
    t_h = jax.random.uniform(kt_h, (n,), minval=config.target_height[0], maxval=config.target_height[1])
    targets = jnp.stack([t_r * jnp.cos(t_a), t_h, t_r * jnp.sin(t_a)], -1)
    c2w = jax.vmap(look_at, in_axes=(0, 0, None))(origins, targets, jnp.array([0.0, 1.0, 0.0]))
    visibility = np.asarray(waldo_visibility_batch(room, c2w, intrinsics))
    keep = np.flatnonzero(visibility <= config.max_visibility)
    if len(keep) < num_views:
        raise ValueError(
            f"only {len(keep)} of {n} candidate cameras see Waldo at most {config.max_visibility:.0%}; "
            f"ask for fewer than {num_views} views or raise oversample"
        )
    # Spread the kept cameras over the whole band rather than taking the first ones in angle.
    chosen = keep[np.round(np.linspace(0, len(keep) - 1, num_views)).astype(int)]
    return np.asarray(c2w)[chosen].astype(np.float32)


def room_scene(seed: int = 0, num_views: int = 24, resolution: int = 64, num_samples: int = 128,
               camera_config: RoomCameraConfig = RoomCameraConfig(),
               room: Optional[WaldoRoom] = None) -> Tuple[Scene, WaldoRoom]:
    """The room's training views as a `Scene`, rendered with `waldo_jax.render.render_views`.

    Args:
      seed: seeds the room (unless `room` is given) and the cameras.
      num_views: number of training views.
      resolution: the views are resolution x resolution pixels.
      num_samples: samples per ray for the renders.
      camera_config: where the training cameras go.
      room: an already built room (else `make_room(seed)`).

    Returns:
      (scene, room).
    """
    from waldo_jax.render import render_views

    room = make_room(seed) if room is None else room
    intrinsics = Intrinsics.from_fov(resolution, resolution, camera_config.fov_x)
    key = jax.random.fold_in(jax.random.key(seed), 1)
    c2w = training_cameras(key, room, num_views, intrinsics, camera_config)
    config = room_render_config(room, num_samples=num_samples)
    images = np.asarray(render_views(room_field, room, jnp.asarray(c2w), intrinsics, config).rgb, np.float32)
    scene = Scene(
        images=images,
        c2w=np.asarray(c2w, np.float32),
        intrinsics=intrinsics,
        aabb=room.aabb,
        near=0.05,
        far=12.0,
        file_names=tuple(f"view_{i:03d}.png" for i in range(num_views)),
        format="procedural",
        name=f"procedural:{seed}",
        split="train",
        path="",
        background=np.asarray(BACKGROUND, np.float32),
        metadata={"seed": int(seed), "num_samples": int(num_samples),
                  "max_visibility": float(camera_config.max_visibility)},
    )
    return scene, room
