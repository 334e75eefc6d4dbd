"""Shared test fixtures.

Tests that need the third-party data in `$WALDO_DATA` (default `../shared`) use `require_scene` /
`require_weights`: they skip with a clear reason when the data is absent, and fail instead when
`WALDO_REQUIRE_DATA=1` (as `.ci/run` sets it).
"""

from __future__ import annotations

import os
import shutil
from pathlib import Path
from typing import Callable

os.environ.setdefault("JAX_ENABLE_X64", "0")

import pytest
from filelock import FileLock

from waldo_jax import paths


def _missing(what: str):
    if paths.require_data():
        pytest.fail(f"{what} is missing and WALDO_REQUIRE_DATA=1", pytrace=False)
    pytest.skip(f"{what} not found (set WALDO_DATA to the folder holding scenes/ and weights/)")


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
