"""Where data and weights live.

The scenes and pretrained weights are third-party files that are never part of the repository.
They are read from:
  * `WALDO_DATA` (default: `../shared` beside the repository, when it exists), holding `scenes/`;
  * `WALDO_WEIGHTS` (default: `$WALDO_DATA/weights`).
"""

from __future__ import annotations

import os
from pathlib import Path

from waldo_jax.errors import DataNotFoundError

__all__ = ["data_dir", "weights_dir", "scene_path", "require_data"]

_REPO_ROOT = Path(__file__).resolve().parent.parent


def data_dir() -> Path | None:
    """The data directory, or None when neither `WALDO_DATA` is set nor `../shared` exists."""
    env = os.environ.get("WALDO_DATA")
    if env:
        return Path(env).expanduser()
    default = _REPO_ROOT.parent / "shared"
    return default if default.is_dir() else None


def weights_dir() -> Path | None:
    """The weights directory: `WALDO_WEIGHTS`, else `$WALDO_DATA/weights`, else None."""
    env = os.environ.get("WALDO_WEIGHTS")
    if env:
        return Path(env).expanduser()
    data = data_dir()
    return None if data is None else data / "weights"


def require_data() -> bool:
    """True when a missing data file must fail instead of skipping (`WALDO_REQUIRE_DATA=1`, as in CI)."""
    return os.environ.get("WALDO_REQUIRE_DATA", "").strip().lower() in ("1", "true", "yes")


def scene_path(name: str) -> Path:
    """Path of a named scene under `$WALDO_DATA/scenes`, with a clear error when it is absent."""
    data = data_dir()
    if data is None:
        raise DataNotFoundError(
            f"scene {name!r} needs the data directory: set WALDO_DATA to the folder holding scenes/ "
            "(default ../shared beside the repository)"
        )
    path = data / "scenes" / name
    if not path.exists():
        raise DataNotFoundError(f"scene {name!r} not found: expected the folder {path}")
    return path
