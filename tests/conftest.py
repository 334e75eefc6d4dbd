"""Shared test fixtures.

Tests that need the third-party data in `$WALDO_DATA` (default `../shared`) use `require_scene` /
`require_weights`: they skip with a clear reason when the data is absent, and fail instead when
`WALDO_REQUIRE_DATA=1` (as `.ci/run` sets it).
"""

from __future__ import annotations

import os

os.environ.setdefault("JAX_ENABLE_X64", "0")

import pytest

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
