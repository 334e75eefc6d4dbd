"""Shared test fixtures.

Tests that need the third-party data in `$WALDO_DATA` (default `../shared`) use `require_scene` /
`require_weights`: they skip with a clear reason when the data is absent, and fail instead when
`WALDO_REQUIRE_DATA=1` (as `.ci/run` sets it).
"""

from __future__ import annotations

import contextlib
import os
import shutil
import signal
import tempfile
from pathlib import Path
from typing import Callable

os.environ.setdefault("JAX_ENABLE_X64", "0")
# XLA's legacy CPU fusion emitters and LLVM's optimisation level 1 (`waldo_jax._xla_flags`,
# docs/design.md "Faster CPU compiles on request"): the suite compiles ~5,000 programs and runs short
# ones, so on the 2-core CPU it takes about a fifth less time (the emitters), then a tenth less (level 1).
# Set before waldo_jax is imported (below), inherited by the subprocesses (notebooks, sharding,
# benchmarks). `WALDO_FAST_COMPILE=0 pytest ...` runs the suite with XLA's defaults;
# tests/test_xla_guard.py checks both settings give the same answers.
os.environ.setdefault("WALDO_FAST_COMPILE", "1")
# One persistent XLA compilation cache for the whole run (created in `pytest_configure` below, shared
# by the xdist workers and every subprocess they start): the CLI, notebook and benchmark tests start
# processes that compile the same programs again. Programs that compile in under 0.2 s are not
# stored (writing them costs about what compiling does). The cache key covers XLA_FLAGS, so the
# default-emitter runs of tests/test_xla_guard.py compile their own programs.
os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", "0.2")

import pytest
from filelock import FileLock

from waldo_jax import paths


def _missing(what: str):
    if paths.require_data():
        pytest.fail(f"{what} is missing and WALDO_REQUIRE_DATA=1", pytrace=False)
    pytest.skip(f"{what} not found (set WALDO_DATA to the folder holding scenes/ and weights/)")


@contextlib.contextmanager
def within(seconds: int = 20):
    """Raises TimeoutError in the test when the code under it blocks longer than `seconds` (a read of a
    FIFO that a missing check would wait on for ever), instead of hanging the suite."""

    def expire(signum, frame):
        raise TimeoutError(f"blocked for more than {seconds} s")

    previous = signal.signal(signal.SIGALRM, expire)
    signal.alarm(seconds)
    try:
        yield
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, previous)


def require_scene(name: str):
    """Path of `$WALDO_DATA/scenes/<name>`, skipping (or failing under WALDO_REQUIRE_DATA) when absent."""
    data = paths.data_dir()
    path = None if data is None else data / "scenes" / name
    if path is None or not path.exists():
        _missing(f"scene {name!r} ({path or 'WALDO_DATA unset and no ../shared'})")
    return path


def require_weights(relpath: str):
    """Path of `$WALDO_WEIGHTS/<relpath>`, skipping (or failing under WALDO_REQUIRE_DATA) when absent."""
    base = paths.weights_dir()
    path = None if base is None else base / relpath
    if path is None or not path.exists():
        _missing(f"weights file {relpath!r} ({path or 'WALDO_WEIGHTS unset'})")
    return path


def built_once(tmp_path_factory, name: str, build: Callable[[Path], None]) -> Path:
    """A folder that `build(folder)` fills once per test session, shared by all pytest-xdist workers.

    A module-scoped fixture runs once per *worker*: under `pytest -n 2` both workers would train the
    same NeRF side by side, each at half speed. Here the first worker builds (with both cores to
    itself) while the other waits on a file lock and then reads the finished folder. A build that
    raises leaves no `.done` mark, so the next worker tries again and reports its own failure.
    Callers must treat the folder as read-only.
    """
    root = tmp_path_factory.getbasetemp()
    if os.environ.get("PYTEST_XDIST_WORKER"):
        root = root.parent  # the session's base folder, common to every worker
    folder, done = root / name, root / f"{name}.done"
    with FileLock(str(root / f"{name}.lock")):
        if not done.exists():
            shutil.rmtree(folder, ignore_errors=True)
            folder.mkdir()
            build(folder)
            done.touch()
    return folder


@pytest.fixture(scope="session")
def trained_lego_fast(tmp_path_factory):
    """lego_tiny trained once per session with the fast preset (250 steps, all 90 views, a small hash
    grid, the render step calibrated on 3 of the 10 held-out views): a real field with surfaces and empty space.

    Shared by the convergence test (test_train, which reads the run's summary) and the renderer tests
    on a trained field (test_marched, which read the checkpoint). Returns (checkpoint path, summary):
    the summary holds the `TrainResult`'s psnr_test, steps, n_train, n_test, history, render_step_curve,
    render_step_scale, rays_per_second and seconds (the training's wall time).
    """
    import dataclasses
    import json
    import time

    import jax

    from waldo_jax.nerf import train as tr
    from waldo_jax.nerf.checkpoint import save_checkpoint
    from waldo_jax.nerf.config import TrainConfig
    from waldo_jax.scenes import load_scene

    path = require_scene("lego_tiny")

    def build(folder):
        train_scene = load_scene(path, split="train")
        test_scene = load_scene(path, split="test")
        config = TrainConfig.preset(
            "fast", train_scene, steps=250, chunk=50, num_samples=128, samples_per_batch=2**14, eval_samples=128
        )
        hashgrid = dataclasses.replace(config.field.hashgrid, L=8, T=2**14)
        config = config.replace(field=dataclasses.replace(config.field, hashgrid=hashgrid))
        start = time.perf_counter()
        result = tr.train(jax.random.key(0), train_scene, config, test_scene, progress=False)
        seconds = time.perf_counter() - start
        save_checkpoint(folder / "lego.ckpt", result.params, result.config, train_scene, result.occupancy)
        summary = {
            "psnr_test": result.psnr_test,
            "steps": result.steps,
            "n_train": result.n_train,
            "n_test": result.n_test,
            "history": result.history,
            "render_step_curve": result.render_step_curve,
            "render_step_scale": result.config.render_step_scale,
            "sampler": config.sampler,
            "rays_per_second": result.rays_per_second,
            "seconds": seconds,
        }
        (folder / "summary.json").write_text(json.dumps(summary, default=float))

    folder = built_once(tmp_path_factory, "trained_lego_fast", build)
    return folder / "lego.ckpt", json.loads((folder / "summary.json").read_text())


# Test files by their time on the 2-core CPU, heaviest first (each over about 15 s there, fixtures
# included; the rest keep their order after them). They are the slow tier as a whole (marked `slow`
# below); in the other files a test that takes seconds carries `@pytest.mark.slow` itself, so that
# the fast tier, `pytest -n 2 -m "not slow" tests`, stays within a minute on 2 cores (a fast-tier run
# names the unmarked tests over `FAST_TIER_LIMIT_S` at its end: `pytest_terminal_summary`). pyproject's
# `--dist loadfile` hands whole files to the pytest-xdist workers, so a file's module fixtures and
# compiled programs are built once, and `--no-loadscope-reorder` keeps this order (pytest-xdist 3.8
# otherwise sorts the files by their number of tests): taking the heavy files first keeps one worker
# from running a long file alone at the end. test_marched builds the lego_tiny training that
# test_train then reads.
HEAVY_FIRST = (
    "test_device_check.py",
    "test_splat_cli.py",
    "test_explore_cli.py",
    "test_splat_render.py",
    "test_nerf_reverse.py",
    "test_interrupt.py",
    "test_exports_consumers.py",
    "test_paper_tables.py",
    "test_marched.py",
    "test_search_path.py",
    "test_criteria_all.py",
    "test_notebooks.py",
    "test_finder.py",
    "test_train.py",
    "test_bad_input.py",
    "test_cli_conventions.py",
    "test_csnet.py",
    "test_search_beyond.py",
    "test_sharding.py",
    "test_xla_guard.py",
    "test_multiprocess.py",
)


def pytest_configure(config):
    """The run's compilation cache: a fresh folder made by the controlling process, before the xdist
    workers start (they and their subprocesses inherit it), removed at the end. A cache folder the
    user set (JAX_COMPILATION_CACHE_DIR) is used as it is and kept."""
    if os.environ.get("PYTEST_XDIST_WORKER") or os.environ.get("JAX_COMPILATION_CACHE_DIR"):
        return
    import jax

    folder = tempfile.mkdtemp(prefix="waldo-jax-test-compile-cache-")
    os.environ["JAX_COMPILATION_CACHE_DIR"] = folder
    jax.config.update("jax_compilation_cache_dir", folder)  # this process, when it runs tests itself
    config.stash[_CACHE_KEY] = folder


def pytest_unconfigure(config):
    folder = config.stash.get(_CACHE_KEY, None)
    if folder:
        shutil.rmtree(folder, ignore_errors=True)


_CACHE_KEY = pytest.StashKey[str]()


# `WALDO_TEST_COMPILE_LOG=FILE pytest ...` appends one JSON line per test to FILE: its wall time, the
# seconds JAX spent in this process tracing, lowering and compiling (JAX's own monitoring events;
# subprocesses not included), and under `programs` each program XLA was asked for, as [name, the
# persistent cache's key, loaded from the cache, seconds XLA compiled it]. For the suite-time work
# (`benchmarks/suite_profile.py` reads it): which tests are compile-bound, and which programs are
# compiled more than once in a run.
_COMPILE_LOG = os.environ.get("WALDO_TEST_COMPILE_LOG")
_compile_seconds: dict = {}
_programs: list = []

if _COMPILE_LOG:
    import jax.monitoring
    from jax._src import compiler as _compiler  # private: the cache's read and write, wrapped to log keys

    def _on_duration(event, seconds, **kwargs):
        if event.startswith("/jax/core/compile/"):
            name = event.rsplit("/", 1)[-1]
            _compile_seconds[name] = _compile_seconds.get(name, 0.0) + seconds

    jax.monitoring.register_event_duration_secs_listener(_on_duration)
    _read, _write = _compiler._cache_read, _compiler._cache_write

    def _logged_read(module_name, cache_key, *args, **kwargs):
        executable, seconds = _read(module_name, cache_key, *args, **kwargs)
        if executable is not None:
            _programs.append([module_name, cache_key, True, seconds])
        return executable, seconds

    def _logged_write(cache_key, compile_time_secs, module_name, *args, **kwargs):
        _programs.append([module_name, cache_key, False, round(compile_time_secs, 3)])
        return _write(cache_key, compile_time_secs, module_name, *args, **kwargs)

    _compiler._cache_read, _compiler._cache_write = _logged_read, _logged_write

    @pytest.hookimpl(hookwrapper=True)
    def pytest_runtest_protocol(item, nextitem):
        import json
        import time

        _compile_seconds.clear()
        _programs.clear()
        start = time.perf_counter()
        yield
        record = {"test": item.nodeid, "seconds": round(time.perf_counter() - start, 2)}
        record.update({k: round(v, 2) for k, v in _compile_seconds.items()})
        record["programs"] = list(_programs)
        with FileLock(_COMPILE_LOG + ".lock"), open(_COMPILE_LOG, "a") as log:
            log.write(json.dumps(record) + "\n")


# A test of the fast tier (not marked `slow`) over this many seconds, setup and teardown included, is
# named at the end of a fast-tier run, to be marked `@pytest.mark.slow`: the tier is the edit-test loop.
# (The first test of a worker that builds a NeRF field pays its compiles, about 5 s; that is allowed.)
FAST_TIER_LIMIT_S = 8.0


def pytest_terminal_summary(terminalreporter, exitstatus, config):
    if "not slow" not in (config.option.markexpr or ""):
        return
    seconds: dict = {}
    for reports in terminalreporter.stats.values():
        for report in reports:
            if getattr(report, "when", None) in ("setup", "call", "teardown"):
                seconds[report.nodeid] = seconds.get(report.nodeid, 0.0) + report.duration
    over = sorted(((s, nodeid) for nodeid, s in seconds.items() if s > FAST_TIER_LIMIT_S), reverse=True)
    if over:
        terminalreporter.write_sep("-", f"fast-tier tests over {FAST_TIER_LIMIT_S} s: mark them @pytest.mark.slow")
        for s, nodeid in over:
            terminalreporter.write_line(f"{s:6.1f} s  {nodeid}")


def pytest_collection_modifyitems(config, items):
    for item in items:  # the fast tier, `pytest -m "not slow"`, leaves the heavy files out whole
        if item.path.name in HEAVY_FIRST:
            item.add_marker(pytest.mark.slow)
    rank = {name: index for index, name in enumerate(HEAVY_FIRST)}
    items.sort(key=lambda item: rank.get(item.path.name, len(rank)))  # stable: a file's own order is kept
