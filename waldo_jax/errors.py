"""User-facing errors.

`WaldoError` is raised at the edges (files, configs, CLI arguments) with a message that names the
offending path or value. The CLI prints it as one line and exits non-zero, without a traceback.
Inside `jit`, failures are data (masks, -inf scores), never exceptions.
"""

from __future__ import annotations

import os

__all__ = ["WaldoError", "SceneFormatError", "DataNotFoundError", "MAX_SEED", "check_seed"]

# The largest seed a run may use: seeds (and seed + K - 1 for K seeds) must fit a signed 32-bit integer,
# the integer type of JAX keys and of the JSON readers of results.
MAX_SEED = 2**31 - 1


class WaldoError(Exception):
    """An error caused by the user's input, reported as one clear line."""


class SceneFormatError(WaldoError):
    """A scene on disk is malformed: the message names the file and the problem."""

    def __init__(self, path: str | os.PathLike, problem: str):
        self.path = os.fspath(path)
        self.problem = problem
        super().__init__(f"{self.path}: {problem}")


class DataNotFoundError(WaldoError, FileNotFoundError):
    """A data or weights file the project expects is missing."""


def check_seed(seed, what: str = "--seed", count: int = 1) -> int:
    """`seed` as an int if it and the `count` seeds from it (seed, seed + 1, ...) lie in [0, MAX_SEED];
    else a `WaldoError` naming `what` and the limit."""
    if isinstance(seed, bool) or not isinstance(seed, int):
        raise WaldoError(f"{what} must be an integer, got {seed!r}")
    last = seed + max(int(count), 1) - 1
    if seed < 0 or last > MAX_SEED:
        span = f" (with {count} seeds, up to {last})" if count > 1 else ""
        raise WaldoError(f"{what} must be between 0 and {MAX_SEED}, got {seed}{span}")
    return seed
