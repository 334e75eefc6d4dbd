"""The room: its geometry (`WaldoRoom`, also the field's params), `make_room(seed)`, and the analytic
radiance field `room_field(room, x, d)` from signed distance functions (docs/design.md, "Procedural room").
"""

from __future__ import annotations

import dataclasses
from typing import Optional, Tuple

import flax.struct
import jax
import jax.numpy as jnp
import numpy as np

from waldo_jax.types import Array

__all__ = [
    "WaldoRoom",
    "make_room",
    "room_field",
    "waldo_field",
    "room_sdf",
    "ROOM_HALF",
    "WALL_HEIGHT",
    "DENSITY",
    "BACKGROUND",
    "KIND_BOX",
    "KIND_SPHERE",
    "KIND_CYLINDER",
    "FAR",
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
FAR = 1e30  # "no intersection" segment parameter (finite: no inf arithmetic under jit)


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
      waldo_scale: float32 [], his size (and his pen's) over the default's (1: about 1 m tall).
      stripe_width: float32 [], the width of his red and white stripes in metres (5 cm at size 1).
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
    waldo_scale: Array
    stripe_width: Array
    num_boxes: int = flax.struct.field(pytree_node=False, default=0)
    num_spheres: int = flax.struct.field(pytree_node=False, default=0)
    seed: int = flax.struct.field(pytree_node=False, default=0)

    @property
    def waldo_center(self) -> Array:
        """Centre of Waldo's figure (half his height above `waldo_base`)."""
        return self.waldo_base + jnp.array([0.0, 0.5, 0.0]) * self.waldo_scale

    @property
    def aabb(self) -> np.ndarray:
        """The room's box [2, 3] (walls included)."""
        pad = 0.35
        return np.array(
            [[-ROOM_HALF - pad, -0.3, -ROOM_HALF - pad], [ROOM_HALF + pad, WALL_HEIGHT, ROOM_HALF + pad]], np.float32
        )


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


@jax.jit
def _sdf_to_primitives(points: Array, kind: Array, center: Array, size: Array) -> Array:
    """Signed distances [M, K] of points [M, 3] to K primitives."""
    return jax.vmap(lambda p: jax.vmap(_primitive_sdf, in_axes=(None, 0, 0, 0))(p, kind, center, size))(points)


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
    sph_c, sph_r = room.center[nb : nb + ns], room.size[nb : nb + ns, 0]
    sphere = jnp.sqrt(jnp.sum((p - sph_c) ** 2, axis=-1) + 1e-12) - sph_r
    d = p - room.center[nb + ns :]  # [nc, 3]
    size = room.size[nb + ns :]
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
    stripe = jnp.floor((p[1] - room.waldo_base[1]) / room.stripe_width) % 2.0
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


def waldo_field(room: WaldoRoom, x: Array, d: Array) -> Tuple[Array, Array]:
    """`room_field`'s density with colour (1, 1, 1) on Waldo's primitives and (0, 0, 0) elsewhere: rendered
    on a black background, a pixel's value is the share of its ray's weight that lands on Waldo (his mask)."""
    del d
    distances = _all_sdf(room, x)  # [K]
    nearest = jnp.argmin(distances)
    sigma = DENSITY * jax.nn.sigmoid(-distances[nearest] / SURFACE_WIDTH)
    return sigma, jnp.broadcast_to(room.is_waldo[nearest].astype(jnp.float32), (3,))


# ---------------------------------------------------------------------------------------------
# Building a room.

_PALETTE = np.array(
    [
        [0.20, 0.45, 0.80],
        [0.95, 0.70, 0.15],
        [0.25, 0.65, 0.35],
        [0.55, 0.30, 0.65],
        [0.90, 0.45, 0.25],
        [0.35, 0.75, 0.80],
        [0.80, 0.35, 0.50],
        [0.60, 0.55, 0.35],
        [0.45, 0.45, 0.50],
        [0.70, 0.80, 0.30],
    ],
    np.float32,
)


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
        for name, value in zip(
            ("kind", "center", "size", "color", "pattern", "is_waldo"), (kind, center, size, color, pattern, waldo)
        ):
            getattr(self, name).append(value)


def _waldo_parts(base: np.ndarray, scale: float = 1.0):
    """Waldo's primitives (kind, centre, size, colour, pattern), standing at `base` (about `scale` m tall)."""
    x, y, z = base
    skin = (0.96, 0.78, 0.64)
    parts = [
        (KIND_CYLINDER, 0.15, (0.085, 0.15), (0.15, 0.22, 0.62), PATTERN_PLAIN),  # legs
        (KIND_CYLINDER, 0.475, (0.12, 0.175), WALDO_RED, PATTERN_STRIPES),  # jumper
        (KIND_SPHERE, 0.74, (0.1,), skin, PATTERN_PLAIN),  # head
        (KIND_CYLINDER, 0.875, (0.075, 0.055), WALDO_RED, PATTERN_STRIPES),  # hat
        (KIND_SPHERE, 0.96, (0.04,), WALDO_WHITE, PATTERN_PLAIN),  # bobble
    ]
    return [
        (kind, (x, y + scale * height, z), tuple(scale * v for v in size), colour, pattern)
        for kind, height, size, colour, pattern in parts
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


def _add_floor_and_walls(b: _Builder) -> None:
    """The floor slab (checkered) and the four walls."""
    b.add(KIND_BOX, (0.0, -0.15, 0.0), (ROOM_HALF + 0.3, 0.15, ROOM_HALF + 0.3), (0.82, 0.76, 0.66), PATTERN_CHECKER)
    wall = (0.90, 0.88, 0.84)
    for axis, sign in ((0, 1), (0, -1), (2, 1), (2, -1)):
        centre = [0.0, WALL_HEIGHT / 2, 0.0]
        centre[axis] = sign * (ROOM_HALF + 0.15)
        half = [ROOM_HALF + 0.3, WALL_HEIGHT / 2, ROOM_HALF + 0.3]
        half[axis] = 0.15
        b.add(KIND_BOX, centre, half, wall)


def _waldo_base(key) -> np.ndarray:
    """Where Waldo stands: off-centre, 0.4 to 1.2 m from the middle of the floor. float64 [3]."""
    u = np.asarray(jax.random.uniform(key, (2,)), np.float64)
    radius, angle = 0.4 + 0.8 * u[0], 2 * np.pi * u[1]
    return np.array([radius * np.cos(angle), 0.0, radius * np.sin(angle)])


def _add_crates(b: _Builder, key, base: np.ndarray, num_crates: int, scale: float = 1.0) -> None:
    """A pen of `num_crates` crates around `base`, with gaps between them (sized with Waldo: `scale`)."""
    uc = np.asarray(jax.random.uniform(key, (max(num_crates, 1), 4)), np.float64)
    start = 2 * np.pi * uc[0, 0]
    for i in range(num_crates):
        a = start + 2 * np.pi * (i + 0.2 * (uc[i, 1] - 0.5)) / num_crates
        dist = scale * (0.5 + 0.08 * uc[i, 2])
        half_w = scale * (0.2 + 0.06 * uc[i, 3])
        height = scale * (0.85 + 0.3 * uc[i, 2])
        centre = base + np.array([dist * np.cos(a), height / 2, dist * np.sin(a)])
        b.add(KIND_BOX, centre, (half_w, height / 2, half_w), _PALETTE[(i * 3) % len(_PALETTE)] * 0.8 + 0.1)


def _add_clutter(b: _Builder, key, base: np.ndarray, num_clutter: int, clearance: float = 1.25) -> None:
    """`num_clutter` boxes, spheres (on posts) and cylinders on a ring away from Waldo's pen (`clearance` m
    from him) and the camera band."""
    uk = np.asarray(jax.random.uniform(key, (num_clutter, 6)), np.float64)
    for i in range(num_clutter):
        kind = (KIND_BOX, KIND_SPHERE, KIND_CYLINDER)[i % 3]
        for attempt in range(8):  # deterministic re-draw from the same row when too close to Waldo
            v = (uk[i] + attempt * 0.6180339887) % 1.0
            r = 2.3 * np.sqrt(v[0])
            a = 2 * np.pi * v[1]
            xz = np.array([r * np.cos(a), r * np.sin(a)])
            if np.linalg.norm(xz - base[[0, 2]]) > clearance:
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


def _primitive_arrays(b: _Builder) -> dict:
    """The builder's rows as NumPy arrays {kind, center, size, color, pattern, is_waldo}, sorted by kind
    (boxes, spheres, cylinders; stable)."""
    order = np.argsort(np.asarray(b.kind), kind="stable")
    arrays = dict(
        kind=np.asarray(b.kind, np.int32),
        center=np.asarray(b.center, np.float32),
        size=np.asarray(b.size, np.float32),
        color=np.asarray(b.color, np.float32),
        pattern=np.asarray(b.pattern, np.int32),
        is_waldo=np.asarray(b.is_waldo, bool),
    )
    return {k: v[order] for k, v in arrays.items()}


def _waldo_surface(waldo_parts, arrays: dict):
    """The oracle's samples of Waldo's surface, minus the parts buried inside his other parts or on the
    floor: points [M, 3], normals [M, 3], areas [M] (NumPy)."""
    points, normals, areas = [], [], []
    for kind, centre, size, _, _ in waldo_parts:
        p, n, a = _surface_samples(kind, centre, size)
        points.append(p)
        normals.append(n)
        areas.append(a)
    points, normals, areas = np.concatenate(points), np.concatenate(normals), np.concatenate(areas)
    waldo_rows = np.flatnonzero(arrays["is_waldo"])
    sdf_to_parts = np.asarray(
        _sdf_to_primitives(
            jnp.asarray(points, jnp.float32),
            arrays["kind"][waldo_rows],
            arrays["center"][waldo_rows],
            arrays["size"][waldo_rows],
        )
    )
    on_surface = np.all(sdf_to_parts > -1e-4, axis=1) & (points[:, 1] > 1e-3)  # not buried, not on the floor
    return points[on_surface], normals[on_surface], areas[on_surface]


def make_room(
    seed: int = 0,
    num_clutter: int = 12,
    num_crates: int = 4,
    waldo_scale: float = 1.0,
    stripe_width: Optional[float] = None,
) -> WaldoRoom:
    """Builds the seeded room.

    Args:
      seed: the seed; the same seed always gives the same room.
      num_clutter: coloured primitives scattered over the room (the primitive count, and so the
        array shapes, depend only on this and `num_crates`).
      num_crates: crates in the pen around Waldo.
      waldo_scale: Waldo's size and his pen's over the default's (1: about 1 m tall in the 8 m room); the
        rest of the room and where things stand do not change with it.
      stripe_width: his stripes' width in metres (default: 5 cm times `waldo_scale`).

    Returns:
      A `WaldoRoom`.
    """
    if not 0.25 <= waldo_scale <= 2.0:
        raise ValueError(f"waldo_scale must be in [0.25, 2], got {waldo_scale!r}")
    stripe_width = STRIPE_WIDTH * waldo_scale if stripe_width is None else stripe_width
    if not 0.005 <= stripe_width <= 1.0:
        raise ValueError(f"stripe_width must be in [0.005, 1] metres, got {stripe_width!r}")
    key = jax.random.key(seed)
    k_waldo, k_crates, k_clutter = jax.random.split(key, 3)
    b = _Builder()
    _add_floor_and_walls(b)
    # Waldo stands off-centre, in a pen of crates with gaps between them.
    base = _waldo_base(k_waldo)
    waldo_parts = _waldo_parts(base, waldo_scale)
    for kind, centre, size, colour, pattern in waldo_parts:
        b.add(kind, centre, size, colour, pattern, waldo=True)
    _add_crates(b, k_crates, base, num_crates, waldo_scale)
    _add_clutter(b, k_clutter, base, num_clutter, 1.25 * max(waldo_scale, 1.0))

    arrays = _primitive_arrays(b)
    points, normals, areas = _waldo_surface(waldo_parts, arrays)
    return WaldoRoom(
        waldo_points=jnp.asarray(points, jnp.float32),
        waldo_normals=jnp.asarray(normals, jnp.float32),
        waldo_areas=jnp.asarray(areas, jnp.float32),
        waldo_base=jnp.asarray(base, jnp.float32),
        waldo_scale=jnp.float32(waldo_scale),
        stripe_width=jnp.float32(stripe_width),
        num_boxes=int(np.sum(arrays["kind"] == KIND_BOX)),
        num_spheres=int(np.sum(arrays["kind"] == KIND_SPHERE)),
        seed=int(seed),
        **{k: jnp.asarray(v) for k, v in arrays.items()},
    )
