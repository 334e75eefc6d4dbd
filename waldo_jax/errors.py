"""User-facing errors.

`WaldoError` is raised at the edges (files, configs, CLI arguments) with a message that names the
offending path or value. The CLI prints it as one line and exits non-zero, without a traceback.
Inside `jit`, failures are data (masks, -inf scores), never exceptions.
"""

from __future__ import annotations

import errno
import os
import stat
from pathlib import Path

__all__ = ["WaldoError", "SceneFormatError", "DataNotFoundError", "MAX_SEED", "check_seed", "MIN_RESOLUTION",
           "MAX_RESOLUTION", "check_resolution", "check_input_file"]

# The largest seed a run may use: seeds (and seed + K - 1 for K seeds) must fit a signed 32-bit integer,
# the integer type of JAX keys and of the JSON readers of results.
MAX_SEED = 2**31 - 1
# Image sides, everywhere a user picks one (--resolution, a poses file's w/h, a --target, a scored
# image): below 8 px no criterion sees anything; above 4096 px one view alone is 200 MB of float32
# and the int32 ray indices of a population overflow.
MIN_RESOLUTION = 8
MAX_RESOLUTION = 4096


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


def check_resolution(value, what: str = "--resolution") -> int:
    """`value` as an int if it lies in [MIN_RESOLUTION, MAX_RESOLUTION]; else a `WaldoError` naming
    `what` and the limits."""
    if isinstance(value, bool) or not isinstance(value, int) or not MIN_RESOLUTION <= value <= MAX_RESOLUTION:
        raise WaldoError(f"{what} must be an integer between {MIN_RESOLUTION} and {MAX_RESOLUTION} pixels, "
                         f"got {value!r}")
    return value


def check_input_file(path: str | os.PathLike, what: str = "file") -> Path:
    """`path` as a Path if it is a readable regular file (or a link to one); else an error that says
    what is wrong: `DataNotFoundError` when nothing is there, `WaldoError` for a directory, a FIFO or
    device, a symbolic-link loop, or a file that cannot be opened."""
    path = Path(path)
    try:
        mode = os.stat(path).st_mode
    except FileNotFoundError:
        raise DataNotFoundError(f"{path}: no such {what}") from None
    except OSError as e:
        if e.errno == errno.ELOOP:
            raise WaldoError(f"{path}: a symbolic link loop, where a {what} was expected") from None
        raise WaldoError(f"{path}: cannot read this {what} ({e.strerror or e})") from None
    if stat.S_ISDIR(mode):
        raise WaldoError(f"{path}: a directory, where a {what} was expected")
    if not stat.S_ISREG(mode):
        raise WaldoError(f"{path}: a FIFO, socket or device, where a {what} was expected")
    if not os.access(path, os.R_OK):
        raise WaldoError(f"{path}: cannot read this {what} (permission denied)")
    return path
