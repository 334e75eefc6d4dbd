"""The `waldo` command line (also `python -m waldo_jax`): one module per command.

Commands:
  waldo scene info PATH [--json]                       summary of a scene on disk (`scene`)
  waldo train SCENE_PATH --out RUN_DIR                 train an Instant-NGP field (`train`)
  waldo render procedural[:SEED] --out DIR             the procedural room's training views, PNGs + sheet (`render`)
  waldo render RUN_DIR --poses FILE|train --out DIR    render poses with a trained field (`render`)
  waldo explore SOURCE --criterion NAME --method M     search a scene (GRS / PIBS / EGPS), write results (`explore`)
  waldo path SOURCE --criterion NAME --keyframes K   search a camera path, export it (nerfstudio, NGP, MP4) (`path`)
  waldo demo [--out DIR] [--quick]                     the room end to end: train, search, report (`demo`)
  waldo score --criterion NAME IMAGE... [--json]        score image files with a criterion (`score`)
  waldo weights convert SRC DST                        criterion weights to the native .npz format (`weights`)
  waldo view PATH [--port N] [--export FILE.html]      a scene and a search in 3D in the browser (`view`)
  waldo --version                                      prints `waldo X.Y.Z` (`waldo_jax.version`)

Each command module has `add_command(subparsers)`, which registers its parser with the function that
runs it as `handler`. Bad input (a missing file, a malformed scene, an existing output folder) prints
one line `waldo: error: ...` on stderr and exits with status 1, without a traceback; so do bad arguments
(an unknown flag or choice: `waldo_jax.cli.conventions`, which also holds `--quiet` and progress). Ctrl-C and
SIGTERM print `waldo: interrupted` and exit with 130 / 143, leaving no unfinished output
(`waldo_jax.cli.interrupt`). Every command keeps XLA's compiled programs in a persistent cache
(`waldo_jax.environment.enable_compile_cache`; `WALDO_COMPILE_CACHE=off` or a folder), so a command
run again compiles little.
"""

from __future__ import annotations

import argparse
import os
import re
import signal
import sys
import warnings
from typing import List, Optional

from waldo_jax import io
from waldo_jax.cli import demo, explore, interrupt, path, render, scene, score, train, view, weights
from waldo_jax.cli.conventions import Parser
from waldo_jax.environment import enable_compile_cache
from waldo_jax.errors import WaldoError, check_seed, one_line
from waldo_jax.version import package_version

__all__ = ["main", "build_parser", "check_jax_platforms"]


def build_parser() -> argparse.ArgumentParser:
    """The argparse parser of the `waldo` command."""
    parser = Parser(prog="waldo", description="Explore NeRF scene spaces in JAX (Finding Waldo, MMSys'24).")
    parser.add_argument(
        "--version",
        action="version",
        version=f"waldo {package_version()}",
        help="print the version (waldo X.Y.Z) and exit",
    )
    commands = parser.add_subparsers(dest="command", metavar="COMMAND")
    commands.required = True
    for command in (scene, train, explore, path, score, weights, demo, render, view):
        command.add_command(commands)
    return parser


def main(argv: Optional[List[str]] = None) -> int:
    """Entry point of `waldo`; returns the exit status.

    `argv` None (the `waldo` process itself): SIGINT and SIGTERM end the process at once, cleanly,
    with status 130 / 143 (`waldo_jax.cli.interrupt`). With an `argv` (called in-process), an
    interrupt is cleaned up the same way and its status returned.
    """
    with interrupt.handled(exit_process=argv is None) as guard:
        try:
            return _run(argv)
        except KeyboardInterrupt as e:  # Ctrl-C, or SIGTERM as `interrupt.Interrupted`
            return guard.finish(getattr(e, "signum", signal.SIGINT))


def _run(argv: Optional[List[str]]) -> int:
    """Parses `argv` and runs its command; errors at the edges become one line and status 1."""
    parser = build_parser()
    created_before = len(io.created_output_dirs())
    show = warnings.showwarning
    # Warnings are one line each, like errors: "waldo: warning: ..." (not Python's file:line form).
    warnings.showwarning = _show_warning
    try:
        args = parser.parse_args(argv)  # bad arguments: `UsageError`, one line like any bad input
        if getattr(args, "seed", None) is not None:  # before anything is created, trained or written
            check_seed(args.seed, "--seed", getattr(args, "seeds", 1) or 1)
        enable_compile_cache()  # before the first compilation: JAX decides once whether it caches
        check_jax_platforms()
        return int(args.handler(args) or 0)
    except WaldoError as e:
        print(f"waldo: error: {one_line(str(e))}{_discarded(created_before)}", file=sys.stderr)
        return 1
    except MemoryError as e:  # an allocation no check foresaw (NumPy names its size): one line, the new folder removed
        said = one_line(str(e)) or "an allocation failed"
        print(f"waldo: error: out of memory: {said}{_discarded(created_before)}", file=sys.stderr)
        return 1
    except OSError as e:  # the machine refused (disk full, permissions): name the file, no traceback
        where = f"{e.filename}: " if e.filename else ""
        print(f"waldo: error: {where}{e.strerror or e}", file=sys.stderr)  # the files written so far stay
        return 1
    except Exception as e:  # XLA out of memory: an allocation no estimate foresaw, as NumPy's above
        said = _xla_out_of_memory(e)
        if said is None:
            raise
        print(f"waldo: error: out of memory: {said}{_discarded(created_before)}", file=sys.stderr)
        return 1
    finally:
        warnings.showwarning = show


def _xla_out_of_memory(error: BaseException) -> Optional[str]:
    """What an XLA allocation failure asked for, in words (JAX's `JaxRuntimeError` RESOURCE_EXHAUSTED, on
    any backend), or None for any other error. Checked by name, so that the CLI need not import JAX."""
    text = str(error)
    if type(error).__name__ != "JaxRuntimeError" or "RESOURCE_EXHAUSTED" not in text:
        return None
    asked = re.search(r"allocating (\d+) bytes", text)
    gib = int(asked.group(1)) / 2**30 if asked else None
    size = "memory" if gib is None else f"{gib:.1f} GiB" if gib < 1024 else f"{gib / 1024:.1f} TiB"
    return f"XLA could not allocate {size} for a computation this input sets (choose smaller sizes)"


_PACKAGE_DIR = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def _show_warning(message, category, filename, lineno, file=None, line=None) -> None:
    """Prints waldo's own warnings as one line each. A library's own (matplotlib's "identical low and high
    zlims" on a flat set of cameras) and NumPy's arithmetic warnings (an overflow in a cast, which the
    input check that follows reports by the input's name) are not waldo's to say: they are left out."""
    if issubclass(category, RuntimeWarning):
        return
    if not os.path.abspath(str(filename)).startswith(_PACKAGE_DIR + os.sep):
        return
    print(f"waldo: warning: {one_line(str(message))}", file=sys.stderr)


def _discarded(created_before: int) -> str:
    """Removes the output folders a command refused by a `WaldoError` (its input found wrong while it ran)
    created and has not declared finished, as an interrupt does (`io.discard_unfinished`), and says so
    for the error line. A failure of the machine (a full disk) keeps the whole files written before it."""
    removed = io.discard_unfinished(io.created_output_dirs()[created_before:])
    return f" (removed the unfinished output folder {', '.join(map(str, removed))})" if removed else ""


def check_jax_platforms() -> None:
    """Refuses a `JAX_PLATFORMS`, `JAX_PLATFORM_NAME` or `JAX_DEFAULT_DEVICE` naming a backend this machine
    cannot start (e.g. gpu without one), before any output folder is created: JAX would raise at its first
    computation, after the command began writing."""
    for name in ("JAX_PLATFORMS", "JAX_PLATFORM_NAME", "JAX_DEFAULT_DEVICE"):
        wanted = os.environ.get(name, "").strip()
        if not wanted:
            continue
        import jax

        try:  # any failure: JAX raises a RuntimeError for most, an AssertionError for JAX_PLATFORMS=cuda
            jax.devices() if name == "JAX_PLATFORMS" else jax.devices(wanted.lower())
        except Exception as e:
            reason = (str(e).strip().splitlines() or [type(e).__name__])[0] or type(e).__name__
            reason = reason.split(" (set JAX_PLATFORMS")[0]
            raise WaldoError(
                f"{name}={wanted}: this machine cannot start that backend ({reason[:200]}); "
                f"unset {name} to run on what it has"
            ) from None
