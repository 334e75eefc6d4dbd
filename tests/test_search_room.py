"""End to end on the procedural Waldo room, scored by the exact visibility oracle (no rendering).

The 20 training cameras of `procedural.training_cameras` each see at most half of Waldo. EGPS at the
paper's low budget (20 + 5 x 51 = 275 views) must find a view that sees more of him than every
training view for at least 8 of 10 seeds, all seeds in one vmapped call.
"""

from __future__ import annotations

import numpy as np
import pytest

# Importing waldo_jax first sets the XLA flag it needs before JAX starts its CPU backend.
from waldo_jax.procedural import make_room, training_cameras, waldo_visibility_batch
from waldo_jax.search import ExploreConfig, Initial, explore_seeds
from waldo_jax.types import Intrinsics

import jax  # noqa: E402  (after waldo_jax, see above)
import jax.numpy as jnp  # noqa: E402


def _visibility(room, intrinsics, c2w):
    return waldo_visibility_batch(room, c2w, intrinsics)


@pytest.mark.slow
def test_egps_finds_waldo_better_than_every_training_view():
    room = make_room(0)
    intrinsics = Intrinsics.from_fov(16, 16, np.radians(60.0))
    c2w = training_cameras(jax.random.key(1), room, 20, intrinsics)
    # Score them padded to the 6 x 20 candidates training_cameras scored: its compilation is reused.
    train_scores = np.asarray(waldo_visibility_batch(room, jnp.asarray(np.resize(c2w, (120, 4, 4))), intrinsics))[:20]
    assert train_scores.max() <= 0.5

    score_fn = jax.tree_util.Partial(_visibility, room, intrinsics)  # room and intrinsics stay traced
    config = ExploreConfig(method="egps", budget="low")
    assert config.capacity(20) == 275
    seeds = explore_seeds(
        jax.random.split(jax.random.key(0), 10), score_fn, Initial(c2w=c2w, scores=train_scores), config=config
    )
    best = np.asarray(seeds.results.metrics.best)[:, -1]  # [10]
    assert np.sum(best > train_scores.max()) >= 8, (best, train_scores.max())
    # The returned top views are the best ones and their scores are the oracle's.
    top = np.asarray(seeds.results.top_scores)
    np.testing.assert_allclose(top[:, 0], best)
    rescored = np.asarray(waldo_visibility_batch(room, seeds.results.top_c2w[0], intrinsics))
    np.testing.assert_allclose(rescored, top[0], atol=1e-6)
    assert float(seeds.cvir_mean) > 0.0 and float(seeds.mcvir_mean) > 0.0


@pytest.mark.slow
def test_egps_beats_grs_on_mcvir_at_the_demo_settings():
    """`waldo demo`'s claim, without its NeRF: room 0, its 32 training cameras, waldo_oracle, 8 seeds."""
    from waldo_jax.criteria import CriterionContext, make_criterion
    from waldo_jax.pipeline.demo import SETTINGS
    from waldo_jax.pipeline import seed_keys

    settings = SETTINGS["full"]
    room = make_room(0)
    intrinsics = Intrinsics.from_fov(settings.resolution, settings.resolution, np.radians(60.0))
    c2w = training_cameras(jax.random.fold_in(jax.random.key(0), 1), room, settings.views, intrinsics)
    oracle = make_criterion("waldo_oracle", CriterionContext(room=room))
    score_fn = jax.tree_util.Partial(lambda crit, intr, m: crit.score_poses(m, intr), oracle, intrinsics)
    initial = Initial(c2w=c2w, scores=np.asarray(oracle.score_poses(jnp.asarray(c2w), intrinsics)))
    keys = seed_keys(0, settings.seeds)
    mcvir = {
        m: float(explore_seeds(keys, score_fn, initial, config=ExploreConfig(method=m, budget="low")).mcvir_mean)
        for m in ("grs", "egps")
    }
    assert mcvir["egps"] > mcvir["grs"] > 0.0, mcvir
