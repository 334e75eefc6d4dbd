"""The up and the layout of camera-less splat scenes (waldo_jax.splats.upright), on synthetic scenes
whose up is known, tilted by random rotations, and on the real donut."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from waldo_jax.splats.upright import FORMAT_UP, UprightConfig, estimate_upright, parse_up, ring_origins, visible_share

TRUE_UP = np.array([0.0, 0.0, 1.0])


def _quat_from_matrix(r: np.ndarray) -> np.ndarray:
    """(w, x, y, z) of a rotation matrix (the branch on the largest diagonal term, stable)."""
    m = r
    t = np.trace(m)
    if t > 0:
        s = math.sqrt(t + 1.0) * 2
        q = [0.25 * s, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s]
    else:
        i = int(np.argmax(np.diag(m)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = math.sqrt(1.0 + m[i, i] - m[j, j] - m[k, k]) * 2
        q = np.zeros(4)
        q[0] = (m[k, j] - m[j, k]) / s
        q[1 + i] = 0.25 * s
        q[1 + j] = (m[j, i] + m[i, j]) / s
        q[1 + k] = (m[k, i] + m[i, k]) / s
    return np.asarray(q, np.float64)


def _quat_mul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton product of (w, x, y, z) quaternions, [..., 4]."""
    aw, ax, ay, az = np.moveaxis(a, -1, 0)
    bw, bx, by, bz = np.moveaxis(b, -1, 0)
    return np.stack(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ],
        -1,
    )


class Scene:
    """Splat centres, opacities, log-scales and quaternions, built part by part in a z-up frame."""

    def __init__(self, seed: int):
        self.key = jax.random.key(seed)
        self.means, self.opacity, self.log_scales, self.quats = [], [], [], []

    def _draw(self, fn, *args, **kwargs) -> np.ndarray:
        self.key, key = jax.random.split(self.key)
        return np.asarray(fn(key, *args, **kwargs), np.float64)

    def plane(self, centre, u, v, half_u, half_v, count, opacity=0.9):
        """Flat splats on the rectangle centre + a u + b v, |a| <= half_u, |b| <= half_v."""
        u, v = np.asarray(u, float), np.asarray(v, float)
        n = np.cross(u, v)
        a = self._draw(jax.random.uniform, (count,), minval=-half_u, maxval=half_u)
        b = self._draw(jax.random.uniform, (count,), minval=-half_v, maxval=half_v)
        self.means.append(np.asarray(centre, float) + a[:, None] * u + b[:, None] * v)
        self.opacity.append(np.full(count, opacity))
        size = math.log(1.5 * math.sqrt(4 * half_u * half_v / count))
        self.log_scales.append(np.tile([size, size, size - 3.0], (count, 1)))
        self.quats.append(np.tile(_quat_from_matrix(np.stack([u, v, n], 1)), (count, 1)))

    def box(self, low, high, count, top=True):
        """Flat splats on the faces of an axis-aligned box (no bottom face; no top when `top` is False)."""
        low, high = np.asarray(low, float), np.asarray(high, float)
        c, h = 0.5 * (low + high), 0.5 * (high - low)
        x, y, z = np.eye(3)
        areas = {"x": h[1] * h[2], "y": h[0] * h[2], "z": h[0] * h[1]}
        faces = [
            (c + h[0] * x, y, z, h[1], h[2], areas["x"]),
            (c - h[0] * x, z, y, h[2], h[1], areas["x"]),
            (c + h[1] * y, z, x, h[2], h[0], areas["y"]),
            (c - h[1] * y, x, z, h[0], h[2], areas["y"]),
        ]
        if top:
            faces.append((c + h[2] * z, x, y, h[0], h[1], areas["z"]))
        total = sum(f[-1] for f in faces)
        for centre, u, v, hu, hv, area in faces:
            self.plane(centre, u, v, hu, hv, max(8, int(count * area / total)))

    def blob(self, centre, radii, count, opacity=0.8):
        """Round splats on an ellipsoid's surface."""
        d = self._draw(jax.random.normal, (count, 3))
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        self.means.append(np.asarray(centre, float) + d * np.asarray(radii, float))
        self.opacity.append(np.full(count, opacity))
        self.log_scales.append(np.full((count, 3), math.log(0.05 * min(radii))))
        self.quats.append(np.tile([1.0, 0.0, 0.0, 0.0], (count, 1)))

    def arrays(self, rotation=None):
        means, quats = np.concatenate(self.means), np.concatenate(self.quats)
        if rotation is not None:
            means = means @ rotation.T
            quats = _quat_mul(np.tile(_quat_from_matrix(rotation), (len(quats), 1)), quats)
        return means, np.concatenate(self.opacity), np.concatenate(self.log_scales), quats


def tabletop(seed=0) -> Scene:
    """A cropped tabletop capture: a 1.2 x 0.8 table top and a vase-like object standing on it."""
    s = Scene(seed)
    s.plane([0, 0, 0], [1, 0, 0], [0, 1, 0], 0.6, 0.4, 6000)
    s.blob([0.05, 0.0, 0.22], [0.12, 0.12, 0.22], 3000)
    s.box([0.25, -0.2, 0.0], [0.4, -0.05, 0.1], 800)
    return s


def room(seed=0) -> Scene:
    """A 4 x 4 x 2.5 room without its ceiling (as captures leave it), a table and a cupboard in it."""
    s = Scene(seed)
    s.plane([0, 0, 0], [1, 0, 0], [0, 1, 0], 2.0, 2.0, 8000)
    s.box([-2.0, -2.0, 0.0], [2.0, 2.0, 2.5], 12000, top=False)
    s.box([-0.5, -0.4, 0.0], [0.5, 0.4, 0.75], 1500)
    s.box([1.2, 1.3, 0.0], [1.9, 1.9, 1.8], 1500)
    return s


def guitar(floor: bool, seed=0) -> Scene:
    """A thin tall plate (a guitar's body, 0.35 x 1.0 x 0.08) standing upright, with or without its floor."""
    s = Scene(seed)
    if floor:
        s.plane([0, 0, 0], [1, 0, 0], [0, 1, 0], 1.0, 1.0, 5000)
    s.box([-0.18, -0.04, 0.0], [0.18, 0.04, 1.0], 4000)
    return s


def random_rotations(key, count: int) -> np.ndarray:
    """[count, 3, 3] rotations from normal quaternions (uniform on SO(3))."""
    q = np.asarray(jax.random.normal(key, (count, 4)), np.float64)
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    w, x, y, z = q.T
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
            np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
            np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
        ],
        1,
    )


def angle_deg(a, b) -> float:
    return math.degrees(math.acos(float(np.clip(np.dot(a, b) / np.linalg.norm(a) / np.linalg.norm(b), -1, 1))))


def _estimate(scene: Scene, rotation=None, **kwargs):
    means, opacity, log_scales, quats = scene.arrays(rotation)
    return estimate_upright(jax.random.key(0), means, opacity, (log_scales, quats), **kwargs)


@pytest.mark.slow
@pytest.mark.parametrize(
    "build", [tabletop, room, lambda: guitar(floor=True)], ids=["tabletop", "room", "guitar_floor"]
)
def test_up_of_tilted_copies_is_within_10_degrees(build):
    scene = build()
    rotations = random_rotations(jax.random.key(1), 4)
    for rotation in [np.eye(3), *rotations]:
        result = _estimate(scene, rotation)
        error = angle_deg(result.up, rotation @ TRUE_UP)
        assert error <= 10.0, (error, result.reason)
        assert result.rule == "support plane", result.reason


@pytest.mark.slow
def test_layout_tells_an_object_from_a_room():
    assert _estimate(tabletop()).layout == "object"
    inside = _estimate(room())
    assert inside.layout == "surround", inside.layout_reason
    assert inside.details["seen_from_inside"] > inside.details["seen_from_outside"]


@pytest.mark.slow
def test_an_objects_own_flat_face_is_not_its_support():
    """A standing plate without a floor: its face holds everything on one side and is wider than the
    plate is thick, but its body continues all along under it, so it is no support plane."""
    result = _estimate(guitar(floor=False))
    assert result.rule != "support plane"
    assert any("rests on" in r["rejected"] or "stands" in r["rejected"] for r in result.details["planes_rejected"])


@pytest.mark.slow
def test_a_format_axis_that_matches_the_longest_axis_is_taken():
    """The same plate in a y-down frame (as 3DGS/COLMAP files usually are): the prior picks its long axis."""
    to_y_down = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])  # z up -> -y up
    result = _estimate(guitar(floor=False), to_y_down, format_up=FORMAT_UP["3dgs-ply"])
    assert result.rule == "format axis", result.reason
    assert angle_deg(result.up, [0.0, -1.0, 0.0]) <= 10.0


@pytest.mark.slow
def test_given_up_and_layout_are_kept():
    result = _estimate(tabletop(), up=np.array([0.0, 2.0, 0.0]), layout="surround")
    np.testing.assert_allclose(result.up, [0.0, 1.0, 0.0])
    assert (result.rule, result.layout) == ("given", "surround")


@pytest.mark.slow
def test_same_key_same_decision():
    a, b = _estimate(tabletop()), _estimate(tabletop())
    np.testing.assert_array_equal(a.up, b.up)
    assert a.as_json() == b.as_json()


@pytest.mark.parametrize("text", ["0,0,0", "1,2", "a,b,c", "nan,0,1", "inf,0,0"])
def test_parse_up_refuses(text):
    with pytest.raises(ValueError, match="--up"):
        parse_up(text)


def test_parse_up_normalises():
    np.testing.assert_allclose(parse_up(" 0, 0 ,2"), [0.0, 0.0, 1.0])


@pytest.mark.slow
def test_visible_share_counts_occlusion():
    """Points inside a closed opaque box are hidden from outside and seen from inside."""
    s = Scene(0)
    s.box([-1, -1, -1], [1, 1, 1], 20000)
    s.plane([0, 0, -1], [1, 0, 0], [0, 1, 0], 1.0, 1.0, 4000)  # the bottom
    s.blob([0, 0, 0], [0.3, 0.3, 0.3], 4000)
    means, opacity, _, _ = s.arrays()
    outside = ring_origins(np.zeros(3), TRUE_UP, 4.0, 8, 30.0)
    inside = ring_origins(np.zeros(3), TRUE_UP, 0.6, 8, 0.0)
    seen_out = visible_share(means, opacity, outside)
    seen_in = visible_share(means, opacity, inside)
    blob_share = 4000 * 0.8 / float(opacity.sum())
    assert seen_out <= 1.0 - 0.9 * blob_share  # the blob inside the box is hidden
    assert seen_in >= seen_out + 0.5 * blob_share


def test_ring_origins_are_on_the_ring():
    centre = np.array([1.0, 2.0, 3.0])
    up = np.array([0.0, 1.0, 0.0])
    points = ring_origins(centre, up, 2.0, 6, 30.0)
    np.testing.assert_allclose(np.linalg.norm(points - centre, axis=1), 2.0)
    np.testing.assert_allclose((points - centre) @ up, 1.0)  # 2 sin 30


@pytest.mark.slow
def test_donut_up_is_its_iced_side():
    """The real donut (its icing faces +z: seen in renders from +z and -z) is found lying flat, +z up."""
    from test_splat_io import _require_data

    from waldo_jax.splats.io import load_splat_model

    model = load_splat_model(_require_data("splats/donut/point_cloud.ply"))
    s = model.splats
    valid = np.asarray(s.valid)
    result = estimate_upright(
        jax.random.key(0),
        np.asarray(s.means)[valid],
        np.asarray(jax.nn.sigmoid(s.logits))[valid],
        (np.asarray(s.log_scales)[valid], np.asarray(s.quats)[valid]),
        FORMAT_UP["3dgs-ply"],
    )
    assert angle_deg(result.up, TRUE_UP) <= 10.0, result.reason
    assert result.layout == "object", result.layout_reason
    assert jnp.isfinite(jnp.asarray(result.up)).all()


@pytest.mark.slow
@pytest.mark.parametrize("tilt", [(30.0, (1.0, 0.0, 0.0)), (120.0, (1.0, -1.0, 1.0))])
def test_a_tilted_donut_keeps_its_up(tilt):
    """The donut turned about the origin: its up turns along (a small flat patch of its side, which has the
    whole donut on one side as every tangent plane of a convex body, is no support: `max_overhang`)."""
    import sys
    from pathlib import Path

    from test_splat_io import _require_data

    from waldo_jax.pipeline.splat_sources import splat_upright
    from waldo_jax.splats.io import load_splat_model

    sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "benchmarks"))
    from upright_fitted import rotation, tilted

    r = rotation(*tilt)
    found = splat_upright(tilted(load_splat_model(_require_data("splats/donut/point_cloud.ply")), r))
    assert angle_deg(found.up, r @ np.asarray(TRUE_UP)) <= 10.0, found.reason


@pytest.mark.slow
def test_a_scene_above_max_splats_is_decided_on_a_thinning():
    """Past `max_splats` the decision runs on a uniform thinning (its work bounded: 30M splats took 76 s
    before it), and it is the same decision: the tabletop's plane and layout from a quarter of its splats.
    At or under the bound nothing is thinned, so smaller scenes decide bit for bit as before."""
    scene = tabletop()
    count = len(scene.arrays()[0])
    full = _estimate(scene)
    thinned = _estimate(scene, config=UprightConfig(max_splats=2500))
    assert thinned.details["thinned_from"] == count
    assert 2000 < thinned.details["splats_used"] < 2700
    assert thinned.rule == full.rule == "support plane", thinned.reason
    assert angle_deg(thinned.up, full.up) <= 3.0 and thinned.layout == full.layout
    same = _estimate(scene, config=UprightConfig(max_splats=count))
    assert "thinned_from" not in same.details and np.array_equal(same.up, full.up) and same.details == full.details
