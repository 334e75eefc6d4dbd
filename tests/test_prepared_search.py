"""Searches prepared on threads at once (`prepare_explore`, as `waldo demo` does) run as `run_explore` runs them."""

from __future__ import annotations

import concurrent.futures

import waldo_jax  # noqa: F401  (XLA flags before the first computation)

import jax
import numpy as np
import pytest

from waldo_jax.criteria import CriterionContext, make_criterion
from waldo_jax.pipeline import load_source
from waldo_jax.pipeline.experiment import prepare_explore, run_explore, run_prepared
from waldo_jax.search import ExploreConfig

METHODS = ("grs", "pibs", "egps")


@pytest.mark.slow
def test_searches_prepared_on_threads_equal_run_explore():
    """Three methods prepared side by side on three threads (their compiles overlapping), then run one by
    one, give bit for bit what `run_explore` gives for each, run after them on the main thread."""
    source = load_source("procedural:1", 16)
    criterion = make_criterion("waldo_found", CriterionContext(room=source.room))
    configs = [ExploreConfig(method=m, budget="low", epochs=2) for m in METHODS]
    with concurrent.futures.ThreadPoolExecutor(max_workers=len(configs)) as pool:
        futures = [pool.submit(prepare_explore, source, criterion, c, 5, 2) for c in configs]
        prepared = [f.result() for f in futures]
    assert all(p.seconds > 0 and p.config.children_per_epoch > 0 for p in prepared)
    threaded = [run_prepared(p) for p in prepared]
    for config, run in zip(configs, threaded):
        again = run_explore(source, criterion, config, seed=5, seeds=2)
        assert run.seeds == again.seeds == [5, 6]
        assert set(run.seconds) == {"setup", "search", "render_topk", "total"}
        for a, b in zip(jax.tree.leaves(run.results), jax.tree.leaves(again.results)):
            np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
        np.testing.assert_array_equal(run.top_images, again.top_images)
        np.testing.assert_array_equal(run.scores_train, again.scores_train)
