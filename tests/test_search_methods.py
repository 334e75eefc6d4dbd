"""GRS, PIBS and EGPS proposals (waldo_jax.search), checked against the paper's Algorithm 1.

Tiny populations (6 to 12 views) on a ring of cameras; every `ask` is jitted once per config.
Reference values are computed with NumPy (float64) from the population, not by the code under test.
"""

from __future__ import annotations

import numpy as np
import pytest

# Importing waldo_jax first sets the XLA flag it needs before JAX starts its CPU backend.
from waldo_jax.cameras import look_at, slerp_pose
from waldo_jax.search import egps, grs, pibs
from waldo_jax.search.population import init_population, training_poses, write_children
from waldo_jax.types import Pose

import jax  # noqa: E402  (after waldo_jax, see above)
import jax.numpy as jnp  # noqa: E402


_look_at = jax.jit(jax.vmap(look_at))
_init = jax.jit(init_population, static_argnames=("capacity", "direction"))


def ring_c2w(n: int, radius: float = 3.0) -> np.ndarray:
    """n cameras on a wavy ring, looking at jittered points near the centre (deterministic)."""
    angle = 2 * np.pi * np.arange(n) / n
    origins = np.stack([radius * np.cos(angle), 1.0 + 0.4 * np.sin(3 * angle), radius * np.sin(angle)], -1)
    targets = np.stack([0.3 * np.cos(2 * angle), 0.5 + 0.2 * np.cos(angle), 0.3 * np.sin(5 * angle)], -1)
    ups = np.stack([0.1 * np.sin(angle), np.ones(n), 0.1 * np.cos(2 * angle)], -1)
    return np.asarray(_look_at(*(jnp.asarray(x, jnp.float32) for x in (origins, targets, ups))))


def make_population(scores, capacity):
    """A population of len(scores) ring views (max direction) with `capacity` slots."""
    scores = np.asarray(scores, np.float32)
    c2w = ring_c2w(len(scores))
    return _init(
        training_poses(c2w), jnp.asarray(scores), capacity=capacity, direction="max", train_c2w=jnp.asarray(c2w)
    )


_ask = {
    "grs": jax.jit(grs.ask, static_argnames=("config",)),
    "pibs": jax.jit(pibs.ask, static_argnames=("config",)),
    "egps": jax.jit(egps.ask, static_argnames=("config",)),
}
_write = jax.jit(write_children)
_slerp = jax.jit(jax.vmap(slerp_pose))


def np_pose(pose: Pose, i=None):
    get = (lambda x: np.asarray(x, np.float64)) if i is None else (lambda x: np.asarray(x[i], np.float64))
    return get(pose.origin), get(pose.target), get(pose.up)


def unit(v):
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


# ------------------------------------------------------------------------------------------------
# GRS


@pytest.mark.slow
def test_grs_children_follow_the_training_cameras():
    population = make_population(np.linspace(0.0, 1.0, 8), capacity=8)
    children, mask, after = _ask["grs"](jax.random.key(0), population, grs.Params(), grs.Config(256), 1)
    origin, target, up = np_pose(children)
    train_origin = np.asarray(population.origin, np.float64)
    train_target = np.asarray(population.target)
    train_up = np.asarray(population.up, np.float64)

    assert np.all(np.asarray(mask))
    low, high = train_origin.min(0), train_origin.max(0)
    assert np.all(origin >= low) and np.all(origin <= high)
    # It really samples the box: each axis covers most of its range.
    assert np.all((origin.max(0) - origin.min(0)) > 0.9 * (high - low))
    # Look-at points are exactly (bit for bit) training look-at points, and all of them get used.
    member = np.all(np.asarray(children.target)[:, None, :] == train_target[None], axis=-1)  # [256, 8]
    assert np.all(member.any(1))
    assert member.any(0).all()
    np.testing.assert_allclose(up, np.broadcast_to(unit(train_up.mean(0)), up.shape), atol=1e-6)
    np.testing.assert_array_equal(np.asarray(after.explored), np.asarray(population.explored))


# ------------------------------------------------------------------------------------------------
# PIBS: 6 ring views, 4 slots per epoch, top_c = 4 (6 pairs), capacity 18 (one compilation).

PIBS_CONFIG = pibs.Config(4, top_c=4)
PIBS_CAPACITY = 18


def find_pair(population, child_origin, child_target, child_up, candidates):
    """The (a, b, t) among candidate slot pairs whose SLERP arc passes through the child, else None."""
    origin, target, up = (np.asarray(x) for x in (population.origin, population.target, population.up))
    for a, b in candidates:
        direction = origin[b].astype(np.float64) - origin[a]
        t = float(np.dot(child_origin - origin[a], direction) / np.dot(direction, direction))
        if not -1e-3 < t < 1 + 1e-3:
            continue
        pose_a = Pose(*(jnp.asarray(x[a])[None] for x in (origin, target, up)))
        pose_b = Pose(*(jnp.asarray(x[b])[None] for x in (origin, target, up)))
        ro, rt, ru = np_pose(_slerp(pose_a, pose_b, jnp.asarray([t], jnp.float32)), 0)
        if (
            np.allclose(ro, child_origin, atol=1e-4)
            and np.allclose(rt, child_target, atol=1e-4)
            and np.allclose(unit(ru), unit(child_up), atol=1e-4)
        ):
            return a, b, t
    return None


@pytest.mark.slow
def test_pibs_interpolates_unexplored_pairs_and_exhausts_them():
    scores = np.array([0.1, 0.9, 0.5, 0.7, 0.3, 0.8], np.float32)
    n, epochs = PIBS_CONFIG.children_per_epoch, 3
    population = make_population(scores, PIBS_CAPACITY)
    top = list(np.argsort(-scores, kind="stable")[:4])  # slots 1, 5, 3, 2
    candidates = [(top[i], top[j]) for i in range(4) for j in range(i + 1, 4)]  # rank order

    used_pairs, masks, ts = [], [], []
    for epoch in range(1, epochs + 1):
        children, mask, population = _ask["pibs"](jax.random.key(epoch), population, pibs.Params(), PIBS_CONFIG, epoch)
        mask = np.asarray(mask)
        masks.append(mask)
        pairs, epoch_ts = [], []
        for i in np.flatnonzero(mask):
            found = find_pair(population, *np_pose(children, i), candidates)
            assert found is not None, f"epoch {epoch} child {i} is not on the SLERP arc of a top_c pair"
            a, b, t = found
            assert 1e-3 < t < 1 - 1e-3  # strictly between the pair
            pairs.append((a, b))
            epoch_ts.append(t)
        used_pairs.append(set(pairs))
        ts.append(sorted(epoch_ts))
        # Children scored below everything: the top_c (and so the pair set) stays the same.
        population = _write(
            population,
            children,
            _look_at(children.origin, children.target, children.up),
            jnp.full(n, -1.0),
            jnp.asarray(mask),
            epoch,
            6 + (epoch - 1) * n,
        )

    # Epoch 1: 6 pairs for 4 slots, step round(4 / 6) = 1: the first 4 pairs in rank order, t = 1/2.
    assert masks[0].all() and used_pairs[0] == set(candidates[:4])
    np.testing.assert_allclose(ts[0], [0.5] * 4, atol=1e-3)
    # Epoch 2: the 2 remaining pairs, step round(4 / 2) = 2: t = 1/3 and 2/3 on each.
    assert masks[1].all() and used_pairs[1] == set(candidates[4:])
    np.testing.assert_allclose(ts[1], [1 / 3, 1 / 3, 2 / 3, 2 / 3], atol=1e-3)
    assert not used_pairs[0] & used_pairs[1]  # no pair used twice
    # Epoch 3: every top_c pair is explored: all slots masked (default fallback "none").
    assert not masks[2].any()

    explored = np.asarray(population.explored)
    np.testing.assert_array_equal(explored, explored.T)  # both orders marked
    marked = {(int(a), int(b)) for a, b in zip(*np.nonzero(explored)) if a < b}
    assert marked == {tuple(sorted(p)) for p in candidates}
    assert np.asarray(population.valid).sum() == 6 + 8  # masked children are not kept


@pytest.mark.slow
def test_pibs_skips_failed_scores_and_masks_spare_slots():
    # 3 finite views: 3 pairs for 4 slots, step round(4 / 3) = 1: 3 children and 1 masked slot.
    scores = np.array([0.4, np.nan, 0.1, np.nan, 0.2, np.nan], np.float32)
    population = make_population(scores, PIBS_CAPACITY)
    _, mask, after = _ask["pibs"](jax.random.key(0), population, pibs.Params(), PIBS_CONFIG, 1)
    assert np.asarray(mask).tolist() == [True, True, True, False]
    explored = np.asarray(after.explored)
    assert not explored[[1, 3, 5]].any() and not explored[:, [1, 3, 5]].any()
    assert explored.sum() == 2 * 3


@pytest.mark.slow
def test_pibs_more_pairs_than_slots_marks_only_used_pairs():
    # 6 pairs for 2 slots: round(2 / 6) = 0 is raised to 1; the 4 pairs not used stay unexplored.
    population = make_population(np.array([0.1, 0.9, 0.5, 0.7, 0.3, 0.8], np.float32), PIBS_CAPACITY)
    _, mask, after = _ask["pibs"](jax.random.key(0), population, pibs.Params(), pibs.Config(2, top_c=4), 1)
    assert np.asarray(mask).all()
    explored = np.asarray(after.explored)
    assert explored.sum() == 2 * 2 and explored[1, 5] and explored[1, 3]


@pytest.mark.slow
def test_pibs_grs_fallback_fills_exhausted_slots():
    population = make_population(np.array([0.1, 0.9, 0.5, 0.7, 0.3, 0.8], np.float32), PIBS_CAPACITY)
    population = population.replace(explored=jnp.ones((PIBS_CAPACITY, PIBS_CAPACITY), bool))
    _, mask, _ = _ask["pibs"](jax.random.key(3), population, pibs.Params(), PIBS_CONFIG, 1)
    assert not np.asarray(mask).any()
    config = pibs.Config(4, top_c=4, fallback="grs")
    children, mask, _ = _ask["pibs"](jax.random.key(3), population, pibs.Params(), config, 1)
    assert np.asarray(mask).all()
    # The fallback children are GRS poses: training look-at points and the mean training up.
    train_target = np.asarray(population.target)[:6]
    assert np.all(np.asarray(children.target)[:, None] == train_target[None], axis=-1).any(1).all()
    np.testing.assert_allclose(
        np.asarray(children.up),
        np.broadcast_to(unit(np.asarray(population.up, np.float64)[:6].mean(0)), (4, 3)),
        atol=1e-6,
    )
    with pytest.raises(ValueError, match="fallback"):
        pibs.Config(4, fallback="random")


# ------------------------------------------------------------------------------------------------
# EGPS: 8 ring views, capacity 8, 2000 children (one compilation).

EGPS_CONFIG = egps.Config(2000)
NAN = np.nan


def egps_children(scores, params=None, seed=0):
    population = make_population(np.asarray(scores, np.float32), 8)
    params = egps.Params() if params is None else params
    children, mask, _ = _ask["egps"](jax.random.key(seed), population, params, EGPS_CONFIG, 1)
    return population, children, np.asarray(mask)


@pytest.mark.slow
def test_egps_children_inside_widened_parent_box():
    # Four usable views: the better half is exactly the two best (slots 1 and 3): every child's parents.
    population, children, mask = egps_children([0.2, 0.9, 0.1, 0.7, NAN, NAN, NAN, NAN])
    assert mask.all()
    origin, target, up = np_pose(children)
    pop_o, pop_t, pop_u = (np.asarray(x, np.float64) for x in (population.origin, population.target, population.up))
    for child, field in ((origin, pop_o), (target, pop_t)):
        p1, p2 = field[1], field[3]
        nabla = np.abs(0.1 * (p1 - p2))
        low, high = np.minimum(p1, p2), np.maximum(p1, p2)
        assert np.all(child >= low - nabla - 1e-5) and np.all(child <= high + nabla + 1e-5)
        outside = (child < low - 1e-6) | (child > high + 1e-6)  # only mutation leaves the box
        # P(a component leaves the box) = 2 x 0.05 (mutation) x 0.1 (crossover within nabla of the edge).
        assert 0.004 < outside.mean() < 0.02, outside.mean()
    np.testing.assert_allclose(up, np.broadcast_to(unit(pop_u[1] + pop_u[3]), up.shape), atol=1e-6)


@pytest.mark.slow
def test_egps_without_mutation_stays_in_the_box():
    params = egps.Params(nabla_scale=jnp.asarray(0.0, jnp.float32))
    population, children, _ = egps_children([0.2, 0.9, 0.1, 0.7, NAN, NAN, NAN, NAN], params)
    pop_o = np.asarray(population.origin, np.float64)
    origin = np.asarray(children.origin, np.float64)
    assert np.all(origin >= np.minimum(pop_o[1], pop_o[3])) and np.all(origin <= np.maximum(pop_o[1], pop_o[3]))


@pytest.mark.slow
def test_egps_parents_come_from_the_better_half():
    # The 4 best views sit on the z >= 0 half of the ring, the 4 worst on the z < 0 half: a child of
    # a worse parent would land well below z = 0; children of the better half stay in its box.
    population, children, _ = egps_children([0.9, 0.8, 0.7, 0.6, 0.1, 0.2, 0.3, 0.4], seed=1)
    better = np.asarray(population.origin, np.float64)[:4]
    origin = np.asarray(children.origin, np.float64)
    spread = better.max(0) - better.min(0)
    assert np.all(origin >= better.min(0) - 0.1 * spread - 1e-5)
    assert np.all(origin <= better.max(0) + 0.1 * spread + 1e-5)
    assert origin[:, 2].min() < 0.05 * spread[2]  # ... while really spanning the better half


@pytest.mark.slow
def test_egps_masks_when_no_two_parents():
    _, children, mask = egps_children([NAN, 0.3, NAN, NAN, NAN, NAN, NAN, NAN])
    assert not mask.any()
    assert np.all(np.isfinite(np.asarray(children.origin)))


@pytest.mark.slow
def test_egps_rank_biased_parent_selection():
    fitness = jnp.asarray([0.5, 0.9, -jnp.inf, 0.1, 0.7, 0.3, 0.2, 0.8, 0.6, 0.4], jnp.float32)
    weights, can_breed = egps.parent_weights(fitness, jnp.float32(1.0))
    assert bool(can_breed)
    # 9 finite views: better half h = 4 (slots 1, 7, 4, 8) with weights proportional to 4, 3, 2, 1.
    expected = np.zeros(10)
    expected[[1, 7, 4, 8]] = np.array([4, 3, 2, 1]) / 10
    np.testing.assert_allclose(np.asarray(weights) / np.sum(np.asarray(weights)), expected, atol=1e-6)
    uniform, _ = egps.parent_weights(fitness, jnp.float32(0.0))
    np.testing.assert_allclose(np.asarray(uniform)[[1, 7, 4, 8]], 1.0)
    assert np.asarray(uniform)[[0, 2, 3, 5, 6, 9]].sum() == 0.0

    draws = 20_000
    u = jax.random.uniform(jax.random.key(0), (draws, 2))
    p1, p2 = jax.jit(jax.vmap(egps.select_parents, in_axes=(0, None, None)))(u, weights, fitness)
    p1, p2 = np.asarray(p1), np.asarray(p2)
    assert np.all(p1 != p2)
    assert np.all(np.isin(p1, [1, 7, 4, 8])) and np.all(np.isin(p2, [1, 7, 4, 8]))
    assert np.all(np.asarray(fitness)[p1] > np.asarray(fitness)[p2])  # parent1 is the better one
    # P(slot chosen as either parent) = p_i + sum_{j != i} p_j p_i / (1 - p_j).
    p = expected[[1, 7, 4, 8]]
    chosen = p + np.array([sum(p[j] * p[i] / (1 - p[j]) for j in range(4) if j != i) for i in range(4)])
    freq = np.array([np.mean((p1 == s) | (p2 == s)) for s in (1, 7, 4, 8)])
    np.testing.assert_allclose(freq, chosen, atol=0.01)


def test_egps_mutation_frequencies():
    draws = 20_000
    u = jax.random.uniform(jax.random.key(7), (draws, 3))
    delta = np.asarray(
        jax.jit(jax.vmap(egps.mutation_delta, in_axes=(0, None, None)))(u, jnp.ones(3), egps.Params().mutation_probs)
    )  # [draws, 3] in {-1, 0, 1}
    assert set(np.unique(delta)) <= {-1.0, 0.0, 1.0}
    for component in range(3):
        freq = [np.mean(delta[:, component] == v) for v in (-1.0, 0.0, 1.0)]
        np.testing.assert_allclose(freq, [0.05, 0.9, 0.05], atol=0.01)


@pytest.mark.slow
def test_egps_params_are_vmappable():
    population = make_population(np.array([0.2, 0.9, 0.1, 0.7, NAN, NAN, NAN, NAN], np.float32), 8)
    params = egps.Params(
        nabla_scale=jnp.asarray([0.0, 0.5]),
        rank_bias=jnp.asarray([1.0, 1.0]),
        mutation_probs=jnp.asarray([[0.05, 0.9, 0.05], [0.5, 0.0, 0.5]]),
    )
    sweep = jax.jit(jax.vmap(egps.ask, in_axes=(None, None, 0, None, None)), static_argnames=("config",))
    children, _, _ = sweep(jax.random.key(0), population, params, egps.Config(500), 1)
    pop_o = np.asarray(population.origin, np.float64)
    low, high = np.minimum(pop_o[1], pop_o[3]), np.maximum(pop_o[1], pop_o[3])
    origin = np.asarray(children.origin, np.float64)  # [2, 500, 3]
    assert np.all((origin[0] >= low) & (origin[0] <= high))
    # Parents 1 and 3 differ in x only; a +-0.5 (p1 - p2) step leaves the box half of the time.
    x = origin[1, :, 0]
    assert 0.4 < np.mean((x < low[0]) | (x > high[0])) < 0.6
