"""Vmapped over seeds, a criterion of rendered views renders one seed's population at a time
(`experiment.score_function`): the same scores bit for bit, and a program whose memory does not grow
with the seeds' renders (it did: the demo's 8-seed search on the NeRF's renders took 12.9 GiB)."""

import jax
import jax.numpy as jnp
import numpy as np

from waldo_jax.criteria import CriterionContext, make_criterion
from waldo_jax.pipeline import experiment, procedural_source
from waldo_jax.search.explore import program_memory


def _setup(seeds: int, population: int):
    source = procedural_source(0, 24, 8)
    criterion = make_criterion("colorfulness", CriterionContext(source=source.spec))
    c2w = jnp.asarray(source.train_c2w[: seeds * population].reshape(seeds, population, 4, 4))
    return source, criterion, c2w


def _memory(fn, c2w) -> int:
    return program_memory(jax.jit(jax.vmap(fn)).lower(c2w).compile())


def test_seeds_score_one_by_one_as_each_alone():
    source, criterion, c2w = _setup(seeds=2, population=4)
    score = experiment.score_function(source, criterion)
    together = np.asarray(jax.jit(jax.vmap(score))(c2w))
    alone = np.stack([np.asarray(jax.jit(score)(c2w[s])) for s in range(c2w.shape[0])])
    np.testing.assert_array_equal(together, alone)
    assert np.all(np.isfinite(together))


def test_the_renders_memory_does_not_grow_with_the_seeds():
    source, criterion, c2w = _setup(seeds=8, population=1)
    score = experiment.score_function(source, criterion)
    at_once = jax.tree_util.Partial(experiment._score_views, *score.args)  # the seeds rendered as one batch
    one, eight = _memory(score, c2w[:1]), _memory(score, c2w)
    if one is None:  # a backend without XLA's memory analysis
        return
    assert _memory(at_once, c2w) > 4 * _memory(at_once, c2w[:1])  # what one batch costs
    assert eight < 1.5 * one
    # A criterion of poses alone renders nothing: its seeds stay one batch.
    oracle = experiment.score_function(source, make_criterion("waldo_visible", CriterionContext(room=source.room)))
    assert oracle.func is experiment._score_views
