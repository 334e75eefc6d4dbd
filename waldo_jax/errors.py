"""User-facing errors, and the checks of numbers where they enter the program.

`WaldoError` is raised at the edges (files, configs, CLI arguments) with a message that names the
offending path or value. The CLI prints it as one line and exits non-zero, without a traceback.
Inside `jit`, failures are data (masks, -inf scores), never exceptions.

Every number read from a file or a flag that reaches a division, a cast to float32 / int32, a shape
or an allocation passes one of `check_float32`, `check_int`, `check_resolution` or `check_seed` where
it enters: float64 and Python ints accept values (1e-300, 1e39, 10**12) that float32 / int32 turn into
0, infinity or a wrapped integer far from the check.
"""

from __future__ import annotations

import errno
import math
import os
import re
import stat
from pathlib import Path
from typing import Callable, Optional

import numpy as np

__all__ = [
    "MAX_TRAIN_STEPS",
    "WaldoError",
    "SceneFormatError",
    "DataNotFoundError",
    "NumberError",
    "ConfigError",
    "MAX_SEED",
    "MAX_INT32",
    "check_seed",
    "MIN_RESOLUTION",
    "MAX_RESOLUTION",
    "check_resolution",
    "check_input_file",
    "read_input_file",
    "check_float32",
    "is_finite_number",
    "check_int",
    "MemoryBudgetError",
    "host_memory_bytes",
    "check_memory",
    "one_line",
    "with_article",
]

# The largest seed a run may use: seeds (and seed + K - 1 for K seeds) must fit a signed 32-bit integer,
# the integer type of JAX keys and of the JSON readers of results.
MAX_SEED = 2**31 - 1
# The largest count (steps, epochs, views...) a run may use: counts become int32 arrays under jit.
MAX_INT32 = 2**31 - 1
# The most steps a training may take (a NeRF's or a splat fit's): 300 times Instant-NGP's 35,000. The work
# grows with it, and so does the history a run keeps (a record per chunk of 50 steps, about
# 750 bytes with its JSON: 2e9 steps would keep 30 GB); int32 alone let `--steps 2000000000` start a
# training of 170,000 hours.
MAX_TRAIN_STEPS = 10**7
_FLOAT32_MAX = float(np.finfo(np.float32).max)
_FLOAT32_TINY = float(np.finfo(np.float32).smallest_subnormal)
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


class ConfigError(WaldoError, ValueError):
    """A setting that does not exist where it was given (e.g. an option a search method does not have):
    the message names it and where it was given."""


class NumberError(WaldoError, ValueError):
    """A number that cannot be used: not a number, not finite, out of range, or one that float32 or
    int32 cannot hold (the message names it and its limits)."""


def is_finite_number(value) -> bool:
    """Whether `value` is a real number (an int or a float, not a bool) with a finite float value. JSON
    allows integers of any length: one past float64's range (10**400) is not finite, where `math.isfinite`
    raises OverflowError on it."""
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, float, np.integer, np.floating)):
        return False
    try:
        return math.isfinite(value)
    except OverflowError:
        return False


def check_float32(
    value, what: str, positive: bool = False, minimum: float | None = None, maximum: float | None = None
) -> float:
    """`value` as a Python float if it is a real number (not a bool) that stays finite in float32 and
    lies in [minimum, maximum]; with `positive`, one that is > 0 in float32 as well (1e-300 rounds to 0
    there, 1e39 to infinity). Else a `NumberError` naming `what`."""
    shown = _shown(value)
    try:
        number = math.nan if isinstance(value, (bool, str, bytes)) else float(value)
    except (TypeError, ValueError, OverflowError):
        number = math.nan
    if not (math.isfinite(number) and abs(number) <= _FLOAT32_MAX):
        raise NumberError(f"{what} must be a finite number (float32 holds |x| <= {_FLOAT32_MAX:.4g}), got {shown}")
    if number != 0 and np.float32(number) == 0 and not positive:  # 1e-300 is 0 there: no threshold, no scale
        raise NumberError(f"{what} must be 0 or a number float32 holds (|x| >= {_FLOAT32_TINY:.3g}), got {shown}")
    if positive and not number > 0:
        raise NumberError(f"{what} must be a positive number, got {shown}")
    if positive and not np.float32(number) > 0:
        raise NumberError(
            f"{what} must be a positive number that float32 holds (>= {_FLOAT32_TINY:.3g}), got "
            f"{shown}, which rounds to 0"
        )
    if (minimum is not None and number < minimum) or (maximum is not None and number > maximum):
        span = (
            f"between {minimum:g} and {maximum:g}"
            if minimum is not None and maximum is not None
            else f">= {minimum:g}"
            if minimum is not None
            else f"<= {maximum:g}"
        )
        raise NumberError(f"{what} must be {span}, got {shown}")
    return number


def _shown(value) -> str:
    """`repr(value)`, shortened to 40 characters (an integer of 400 digits is not a message)."""
    text = repr(value)
    return text if len(text) <= 40 else text[:37] + "..."


def check_int(value, what: str, minimum: int = 1, maximum: int = MAX_INT32) -> int:
    """`value` as an int if it is an integer (not a bool) in [minimum, maximum] (default: a positive
    int32); else a `NumberError` naming `what` and the limits."""
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or not minimum <= value <= maximum:
        raise NumberError(f"{what} must be an integer between {minimum} and {maximum}, got {_shown(value)}")
    return int(value)


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
        raise WaldoError(
            f"{what} must be an integer between {MIN_RESOLUTION} and {MAX_RESOLUTION} pixels, got {value!r}"
        )
    return value


_CONTROL = re.compile(r"[\x00-\x1f\x7f-\x9f]")


def one_line(text: str) -> str:
    """`text` with its control characters (a newline or terminal escape in a file name it quotes) written
    as escapes, so that a message stays the one line it is meant to be and moves no cursor."""
    return _CONTROL.sub(lambda m: m.group().encode("unicode_escape").decode("ascii"), text)


def with_article(what: str) -> str:
    """`what` after "a" or "an" ("an image file", "a poses file"), for messages that say what was expected."""
    return f"{'an' if what[:1].lower() in 'aeiou' else 'a'} {what}"


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
            raise WaldoError(f"{path}: a symbolic link loop, where {with_article(what)} was expected") from None
        raise WaldoError(f"{path}: cannot read this {what} ({e.strerror or e})") from None
    if stat.S_ISDIR(mode):
        raise WaldoError(f"{path}: a directory, where {with_article(what)} was expected")
    if not stat.S_ISREG(mode):
        raise WaldoError(f"{path}: a FIFO, socket or device, where {with_article(what)} was expected")
    if not os.access(path, os.R_OK):
        raise WaldoError(f"{path}: cannot read this {what} (permission denied)")
    return path


def read_input_file(
    path: str | os.PathLike,
    what: str = "file",
    error: Optional[Callable[[str], Exception]] = None,
    text: bool = False,
    max_bytes: Optional[int] = None,
):
    """The bytes (or, with `text`, the UTF-8 text) of an input file, once it is a readable regular file
    (`check_input_file`) no larger than the memory this machine has free (`host_memory_bytes`): a file
    larger than that would be killed by Linux mid-read, not refused. `max_bytes` bounds a format whose
    files are small by nature and whose parser takes many times a file's size (YAML: about 400 times).
    `error(problem)` makes the exception for a file too large or unreadable (default: a `WaldoError`
    naming `path`)."""

    def fail(problem: str) -> Exception:
        return WaldoError(f"{path}: {problem}") if error is None else error(problem)

    try:
        path = check_input_file(path, what)
    except WaldoError as e:  # no file, a folder, a FIFO, a link loop: said by `error` where given
        if error is None:
            raise
        said = str(e)
        raise error(said[len(f"{path}: ") :] if said.startswith(f"{path}: ") else said) from None
    try:
        size = path.stat().st_size
        if max_bytes is not None and size > max_bytes:
            raise fail(f"{what} of {size / 2**20:,.1f} MiB; more than {max_bytes / 2**20:g} MiB is not one")
        available = host_memory_bytes()
        if available and size > available:
            raise fail(
                f"{what} of {size / 2**30:,.1f} GiB, more than the {available / 2**30:.1f} GiB this machine has "
                "free to read it"
            )
        return path.read_text(encoding="utf-8") if text else path.read_bytes()
    except OSError as e:
        raise fail(f"cannot read this {what} ({e.strerror or e})") from None


class MemoryBudgetError(WaldoError, MemoryError):
    """Work set by input (a count read from a flag or a file) whose memory this machine does not have:
    the message names the input, the amount and the memory it would take."""


def host_memory_bytes() -> int:
    """Memory this process can still take on the host: Linux's MemAvailable (and a cgroup's limit less its
    use, and an address-space limit less the process's virtual size, where lower), else the physical
    memory; 0 where none can be read (no check then)."""
    available = []
    try:
        with open("/proc/meminfo", encoding="ascii") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    available.append(int(line.split()[1]) * 1024)
    except (OSError, ValueError, IndexError):
        pass
    try:
        limit = Path("/sys/fs/cgroup/memory.max").read_text().strip()
        if limit.isdigit():
            available.append(int(limit) - int(Path("/sys/fs/cgroup/memory.current").read_text().strip()))
    except (OSError, ValueError):
        pass
    address_space = _address_space_left()
    if address_space is not None:
        available.append(address_space)
    if not available:
        try:
            available.append(int(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")))
        except (AttributeError, ValueError, OSError):
            return 0
    return max(min(available), 1)  # 0 would mean "unknown": nothing left is 1 byte


def _address_space_left() -> Optional[int]:
    """What an address-space limit (`ulimit -v`, RLIMIT_AS) leaves this process: the limit less its
    virtual size now; None without such a limit (or where neither can be read)."""
    try:
        import resource

        soft, _ = resource.getrlimit(resource.RLIMIT_AS)
        if soft == resource.RLIM_INFINITY:
            return None
        with open("/proc/self/status", encoding="ascii") as f:
            size = next(int(line.split()[1]) * 1024 for line in f if line.startswith("VmSize:"))
        return int(soft) - size
    except (ImportError, OSError, ValueError, IndexError, StopIteration):
        return None


def check_memory(need: float, what: str, hint: str) -> None:
    """Raises MemoryBudgetError when `need` bytes (what `what` would allocate) exceed the host memory at
    hand (`host_memory_bytes`); `hint` says which input to change."""
    available = host_memory_bytes()
    if available and need > available:
        raise MemoryBudgetError(
            f"{what} would take {need / 2**30:,.1f} GiB, more than the {available / 2**30:.1f} GiB this "
            f"machine has free; {hint}"
        )
