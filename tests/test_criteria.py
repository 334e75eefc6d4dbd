"""Criteria: the registry, the room's oracles (exact cases) and colourfulness (analytic values)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from waldo_jax.cameras import look_at
from waldo_jax.criteria import CRITERIA, CriterionContext, CriterionError, make_criterion
from waldo_jax.procedural import make_room, waldo_coverage, waldo_visibility
from waldo_jax.types import Intrinsics

INTR = Intrinsics.from_fov(32, 32, np.radians(60.0))
UP = jnp.array([0.0, 1.0, 0.0])


@pytest.fixture(scope="module")
def bare_room():
    return make_room(3, num_clutter=0, num_crates=0)


def test_registry_names_and_errors():
    assert {"waldo_oracle", "waldo_visible", "colorfulness"} <= set(CRITERIA)
    with pytest.raises(CriterionError, match="unknown criterion 'nope'.*colorfulness"):
        make_criterion("nope")
    with pytest.raises(CriterionError, match="needs the procedural Waldo room.*fox"):
        make_criterion("waldo_oracle", CriterionContext(source="fox"))
    for name, spec in CRITERIA.items():
        assert spec.direction in ("max", "min") and spec.inputs in ("images", "renders", "poses"), name


@pytest.mark.slow
def test_oracle_criteria_score_poses_like_the_oracle(bare_room):
    oracle = make_criterion("waldo_oracle", CriterionContext(room=bare_room))
    visible = make_criterion("waldo_visible", CriterionContext(room=bare_room))
    centre = np.asarray(bare_room.waldo_center)
    inwards = -np.asarray(bare_room.waldo_base) * np.array([1.0, 0.0, 1.0])
    inwards /= np.linalg.norm(inwards)  # from Waldo towards the room's middle: inside the walls
    origins = centre + np.array([0.0, 0.3, 0.0]) + np.array([d * inwards for d in (3.0, 2.4, 1.8, 1.4)])
    c2w = jax.vmap(look_at, in_axes=(0, None, None))(jnp.asarray(origins), jnp.asarray(centre), UP)
    cov = np.asarray(jax.jit(oracle.score_poses)(c2w, INTR))
    vis = np.asarray(visible.score_poses(c2w, INTR))
    np.testing.assert_allclose(cov, [float(waldo_coverage(bare_room, m, INTR)) for m in c2w], rtol=1e-5)
    np.testing.assert_allclose(vis, [float(waldo_visibility(bare_room, m, INTR)) for m in c2w], rtol=1e-5)
    assert np.all(vis > 0.95)  # nothing in the bare room hides him
    assert np.all(np.diff(cov) > 0)  # closer, unoccluded and whole in frame: more of the image is Waldo
    # He is about 1 m tall and 0.24 m wide: from 3 m with a 60 degree lens he covers ~1 % of the image.
    assert 0.003 < cov[0] < 0.03
    with pytest.raises(CriterionError, match="scores camera poses"):
        oracle.score_images(np.zeros((1, 8, 8, 3), np.float32))


@pytest.mark.slow
def test_coverage_drops_when_waldo_leaves_the_frame(bare_room):
    centre = np.asarray(bare_room.waldo_center)
    origin = centre + np.array([1.5, 0.3, 0.0])
    facing = look_at(jnp.asarray(origin), jnp.asarray(centre), UP)
    away = look_at(jnp.asarray(origin), jnp.asarray(origin + np.array([1.0, 0.0, 0.0])), UP)
    assert float(waldo_coverage(bare_room, facing, INTR)) > 0.02
    assert float(waldo_coverage(bare_room, away, INTR)) == 0.0


def test_colorfulness_analytic_values():
    crit = make_criterion("colorfulness")
    grey = np.full((8, 8, 3), 0.4, np.float32)
    red = np.zeros((8, 8, 3), np.float32)
    red[..., 0] = 1.0
    half = red.copy()
    half[:, 4:] = 0.0  # red | black: rg and yb each take two values
    scores = np.asarray(jax.jit(crit.score_images)(np.stack([grey, red, half])))
    # grey: rg = yb = 0. red: rg = 255, yb = 127.5, no spread -> 0.3 * hypot(255, 127.5).
    # half: rg in {255, 0}, yb in {127.5, 0}: std 127.5 and 63.75, means 127.5 and 63.75.
    expected_half = np.hypot(127.5, 63.75) + 0.3 * np.hypot(127.5, 63.75)
    np.testing.assert_allclose(scores, [0.0, 0.3 * np.hypot(255.0, 127.5), expected_half], rtol=1e-5, atol=1e-4)
    with pytest.raises(CriterionError, match="scores images"):
        crit.score_poses(jnp.eye(4)[None], INTR)
    with pytest.raises(CriterionError, match=r"images \[P, H, W, 3\]"):
        crit.score_images(np.zeros((8, 8, 3), np.float32))
