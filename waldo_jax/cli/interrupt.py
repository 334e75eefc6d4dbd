"""Ctrl-C (SIGINT) and SIGTERM end a `waldo` command cleanly: exit status 130 / 143, one line
`waldo: interrupted`, no traceback, no half-written file and no unfinished new output folder.

Why not Python's default. A KeyboardInterrupt ends `main`, then the interpreter finalises its modules
while XLA may still compile or run a program on its own threads (JAX waits for a compilation in a way
Ctrl-C interrupts, but the compilation goes on). Finalising destroys JAX's client (`PyClient`,
`PjRtClient`) and the devices under that work, and the compiling thread calls into a freed device:
SIGSEGV, exit 139, right after "waldo: interrupted". Besides, while the main thread waits inside XLA
(one jitted search runs for minutes in one call) Python runs no signal handler at all, so Ctrl-C
waited for the whole search; and SIGTERM killed the process without any cleanup.

So, within `handled(exit_process=True)` (the `waldo` process itself):
  * SIGINT and SIGTERM raise `Interrupted` (a KeyboardInterrupt) in the main thread, which unwinds as
    Ctrl-C does (atomic writes remove their temporary file, progress bars close); one raised where
    Python drops exceptions (a garbage-collection callback of JAX's, a __del__) is not printed but
    raised again where the main thread next runs Python code (`sys.unraisablehook`);
  * a watcher thread is woken through `signal.set_wakeup_fd` at once, even while the main thread waits
    in XLA, and finishes the job itself if the main thread has not within `GRACE_SECONDS`;
  * either way `Guard.finish` removes what the command left unfinished (`io.discard_unfinished`: the
    temporary files of writes in progress and the output folders the command created), prints the
    line, flushes and leaves with `os._exit`, which skips the interpreter's finalisation and so never
    tears JAX down under running work.
A signal the parent process set to be ignored (a background job of a non-interactive shell ignores
SIGINT) stays ignored. Called in-process (`exit_process=False`, tests), an interrupt is cleaned up
the same way and `finish` returns the status instead of ending the process.
"""

from __future__ import annotations

import _thread
import contextlib
import os
import signal
import sys
import threading
import time
from typing import Iterator, List

from waldo_jax import io

__all__ = ["EXIT_STATUS", "GRACE_SECONDS", "Interrupted", "Guard", "handled"]

EXIT_STATUS = {signal.SIGINT: 130, signal.SIGTERM: 143}  # 128 + the signal's number, as a shell reports it
GRACE_SECONDS = 1.0  # the main thread's time to unwind before the watcher ends the process itself


class Interrupted(KeyboardInterrupt):
    """SIGINT or SIGTERM, raised in the main thread (a KeyboardInterrupt, so it unwinds like Ctrl-C)."""

    def __init__(self, signum: int = signal.SIGINT):
        self.signum = int(signum)
        super().__init__(signal.Signals(self.signum).name)


class Guard:
    """The interrupt state of one command: what it created and how an interrupt ends it."""

    def __init__(self, exit_process: bool):
        self.exit_process = exit_process
        self._created_before = len(io.created_output_dirs())
        self._lock = threading.Lock()

    def finish(self, signum: int = signal.SIGINT) -> int:
        """Cleans up after an interrupt and prints one line; ends the process with 128 + signum when
        `exit_process`, else returns that status. Runs once: a second caller waits for the first."""
        self._lock.acquire()  # never released: the first caller ends the process (or returns, in-process)
        ignored = {}
        if threading.current_thread() is threading.main_thread():
            for other in EXIT_STATUS:  # a second Ctrl-C must not cut the cleanup short
                with contextlib.suppress(ValueError, OSError):
                    ignored[other] = signal.signal(other, signal.SIG_IGN)
        status = EXIT_STATUS.get(signum, 128 + int(signum))
        _close_progress_bars()
        removed = io.discard_unfinished(io.created_output_dirs()[self._created_before :])
        what = "" if signum == signal.SIGINT else f" by {signal.Signals(signum).name}"
        note = f" (removed the unfinished output folder {', '.join(map(str, removed))})" if removed else ""
        with contextlib.suppress(Exception):
            start = "\n" if getattr(sys.stderr, "line_open", False) else ""  # after a bar cut mid-line
            print(f"{start}waldo: interrupted{what}{note}", file=sys.stderr)
        if not self.exit_process:  # in-process: the caller's handlers back, not an "ignore" for good
            for other, handler in ignored.items():
                with contextlib.suppress(ValueError, OSError, TypeError):
                    signal.signal(other, handler)
            self._lock.release()
            return status
        for stream in (sys.stdout, sys.stderr):
            with contextlib.suppress(Exception):
                stream.flush()
        os._exit(status)


class _Stderr:
    """sys.stderr, remembering whether the last text written left a line open (a progress bar's does)."""

    def __init__(self, stream):
        self._stream = stream
        self.line_open = False

    def write(self, text):
        if text:
            self.line_open = not text.endswith("\n")
        return self._stream.write(text)

    def __getattr__(self, name):
        return getattr(self._stream, name)


def _close_progress_bars() -> None:
    """Closes open tqdm bars, so that the last line ends with a newline (only if tqdm is loaded)."""
    tqdm_std = sys.modules.get("tqdm.std")
    for bar in list(getattr(getattr(tqdm_std, "tqdm", None), "_instances", ()) or ()):
        with contextlib.suppress(Exception):
            bar.close()


@contextlib.contextmanager
def handled(exit_process: bool) -> Iterator[Guard]:
    """Runs a command with SIGINT and SIGTERM handled as the module docstring says; yields its `Guard`,
    whose `finish` the caller calls on `KeyboardInterrupt`. With `exit_process` False (or outside the
    main thread, where Python allows no handlers) no handler, wakeup fd or thread is installed."""
    guard = Guard(exit_process)
    if not exit_process or threading.current_thread() is not threading.main_thread():
        yield guard
        return
    raised = []

    def raise_interrupted(signum, frame) -> None:
        if not raised:  # once: a second Ctrl-C must not cut the unwinding short (the watcher ends it)
            raised.append(signum)
            raise Interrupted(signum)

    # A handler that raises where Python cannot propagate (a garbage-collection callback, a __del__)
    # has its exception printed as "Exception ignored" and dropped. Such an Interrupted is silenced
    # and, from another thread a moment later (from this one it would raise inside this hook), the
    # signal is simulated again: the main thread raises it where it next runs Python code (a main
    # thread waiting in XLA is ended by the watcher as before).
    previous_hook = sys.unraisablehook

    def unraisable(event) -> None:
        if isinstance(event.exc_value, Interrupted) and raised:
            again = threading.Timer(0.01, _thread.interrupt_main, args=(raised.pop(),))
            again.daemon = True
            again.start()
            return
        previous_hook(event)

    sys.unraisablehook = unraisable
    previous = {}
    for signum in EXIT_STATUS:
        handler = signal.getsignal(signum)
        if handler is not signal.SIG_IGN:  # an inherited "ignore" stays
            previous[signum] = signal.signal(signum, raise_interrupted)
    read_fd, write_fd = os.pipe()
    os.set_blocking(write_fd, False)
    previous_fd = signal.set_wakeup_fd(write_fd, warn_on_full_buffer=False)
    watcher = threading.Thread(
        target=_watch, args=(read_fd, guard, list(previous)), name="waldo-interrupt", daemon=True
    )
    watcher.start()
    stderr = sys.stderr = _Stderr(sys.stderr)
    try:
        yield guard
    finally:
        if sys.stderr is stderr:
            sys.stderr = stderr._stream
        if sys.unraisablehook is unraisable:
            sys.unraisablehook = previous_hook
        signal.set_wakeup_fd(previous_fd)
        for signum, handler in previous.items():
            signal.signal(signum, handler)
        os.close(write_fd)  # the watcher reads end-of-file and returns


def _watch(read_fd: int, guard: Guard, signals: List[int]) -> None:
    """Waits for the signal numbers the C-level handler writes to the wakeup fd; after the first of
    `signals`, gives the main thread GRACE_SECONDS to finish and then finishes in its place."""
    try:
        while True:
            data = os.read(read_fd, 64)
            if not data:
                return
            caught = [s for s in data if s in signals]
            if caught:
                time.sleep(GRACE_SECONDS)
                guard.finish(caught[0])
                return
    finally:
        os.close(read_fd)
