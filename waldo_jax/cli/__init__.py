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

Each command module has `add_command(subparsers)`, which registers its parser with the function that
runs it as `handler`. Bad input (a missing file, a malformed scene, an existing output folder) prints
one line `waldo: error: ...` on stderr and exits with status 1, without a traceback.
"""

from __future__ import annotations

import argparse
import sys
import warnings
from typing import List, Optional

from waldo_jax.cli import demo, explore, path, render, scene, score, train, weights
from waldo_jax.errors import WaldoError, check_seed

__all__ = ["main", "build_parser"]


def build_parser() -> argparse.ArgumentParser:
    """The argparse parser of the `waldo` command."""
    parser = argparse.ArgumentParser(
        prog="waldo",
        description="Explore NeRF scene spaces in JAX (Finding Waldo, MMSys'24).",
    )
    commands = parser.add_subparsers(dest="command", metavar="COMMAND")
    commands.required = True
    for command in (scene, train, explore, path, score, weights, demo, render):
        command.add_command(commands)
    return parser


def main(argv: Optional[List[str]] = None) -> int:
    """Entry point of `waldo`; returns the exit status."""
    parser = build_parser()
    args = parser.parse_args(argv)
    show = warnings.showwarning
    # Warnings are one line each, like errors: "waldo: warning: ..." (not Python's file:line form).
    warnings.showwarning = lambda message, *rest, **kw: print(f"waldo: warning: {message}", file=sys.stderr)
    try:
        if getattr(args, "seed", None) is not None:  # before anything is created, trained or written
            check_seed(args.seed, "--seed", getattr(args, "seeds", 1) or 1)
        return int(args.handler(args) or 0)
    except WaldoError as e:
        print(f"waldo: error: {e}", file=sys.stderr)
        return 1
    except OSError as e:  # the machine refused (disk full, permissions): name the file, no traceback
        where = f"{e.filename}: " if e.filename else ""
        print(f"waldo: error: {where}{e.strerror or e}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print("waldo: interrupted", file=sys.stderr)
        return 130
    finally:
        warnings.showwarning = show

