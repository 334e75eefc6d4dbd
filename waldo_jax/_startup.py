"""Ctrl-C and SIGTERM while the `waldo` command starts: imported first by `waldo_jax/__init__.py`.

Importing JAX and jaxlib takes a second or two. A SIGINT then raised a KeyboardInterrupt wherever Python
was: in an import (a traceback of 30 lines) or in one of JAX's garbage-collection callbacks, where Python
drops it ("Exception ignored in ...") and the command went on to finish. Nothing has been created while
the package imports, so for the `waldo` process (its console script, or `python -m waldo_jax`) the two
signals end it at once here, with the statuses and the line of `waldo_jax.cli.interrupt`, which takes
over when the command begins. A signal the parent set to be ignored stays ignored; a library user's
process (a notebook, a script importing waldo_jax) keeps its own handlers.
"""

from __future__ import annotations

import os
import signal
import sys

# 128 + the signal's number, as a shell reports it (`waldo_jax.cli.interrupt.EXIT_STATUS`).
_STATUS = {signal.SIGINT: 130, signal.SIGTERM: 143}


def is_waldo_command() -> bool:
    """Whether this process is the `waldo` command: its console script, or `python -m waldo_jax[.cli]`."""
    script = os.path.basename(sys.argv[0]) if sys.argv else ""
    orig = list(getattr(sys, "orig_argv", []))
    modules = (["-m", "waldo_jax"], ["-m", "waldo_jax.cli"])
    return script in ("waldo", "waldo.exe") or any(orig[i : i + 2] in modules for i in range(len(orig) - 1))


def _end(signum, frame) -> None:  # pragma: no cover - runs in a process being interrupted
    try:
        sys.stderr.write("waldo: interrupted\n")
        sys.stderr.flush()
    finally:
        os._exit(_STATUS.get(signum, 1))


def guard_startup() -> None:
    """For the `waldo` command only: SIGINT and SIGTERM end the process at once while it starts."""
    if not is_waldo_command():
        return
    for signum in _STATUS:
        if signal.getsignal(signum) is not signal.SIG_IGN:
            signal.signal(signum, _end)
