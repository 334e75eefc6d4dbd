"""`waldo weights convert SRC DST [--model NAME ...] [--force]`: criterion weights to native .npz files."""

from __future__ import annotations

import argparse
import time
from typing import Sequence

import numpy as np

import waldo_jax.criteria  # noqa: F401  (registers the converters)
from waldo_jax import io
from waldo_jax.cli.conventions import Progress, add_quiet, path_argument
from waldo_jax.errors import WaldoError
from waldo_jax.weights import CONVERTERS, convert_all, load_model

__all__ = ["add_command", "cmd_weights_convert"]


def add_command(subparsers) -> None:
    """Registers `weights convert` on an argparse subparsers object."""
    p = subparsers.add_parser("weights", help="criterion weights: convert to the fast native format")
    cmds = p.add_subparsers(dest="weights_command", metavar="COMMAND")
    cmds.required = True
    c = cmds.add_parser(
        "convert",
        help="convert a weights folder to native .npz files",
        description="Read the original weights files of SRC (torch pickles, OpenCV YAML, MATLAB .mat, in the "
        "../shared/weights layout) and write DST/<model>/<model>.npz for each model, checking every "
        "shape. Criteria load DST faster with --weights DST (or WALDO_WEIGHTS=DST).",
    )
    c.add_argument("src", type=path_argument, metavar="SRC", help="weights folder in the ../shared/weights layout")
    c.add_argument("dst", metavar="DST", help="output folder")  # checked as every output folder is
    c.add_argument("--model", action="append", default=None, help="convert only this model (repeatable)")
    c.add_argument("--force", action="store_true", help="replace existing converted files")
    add_quiet(c, "line per model")
    c.set_defaults(handler=cmd_weights_convert)


def cmd_weights_convert(args: argparse.Namespace) -> int:
    """`waldo weights convert`: writes DST/<model>/<model>.npz for each model and checks it loads."""
    dst = io.check_output_dir(args.dst, force=True)  # an existing folder is fine: each model's file is checked
    models = args.model
    if not args.force:
        for model in models or CONVERTERS:
            existing = dst / model / f"{model}.npz"
            if existing.exists():
                raise WaldoError(f"{existing} exists; pass --force to replace it")
    start = time.perf_counter()
    progress = Progress(args.quiet)
    with progress:
        progress.phase(f"converting {args.src}")
        written = convert_all(args.src, dst, models)
    for model, path in written.items():
        t0 = time.perf_counter()
        tree, _ = load_model(model, dst)
        seconds = time.perf_counter() - t0
        count = sum(int(np.size(leaf)) for leaf in _leaves(tree))
        if not args.quiet:
            print(
                f"{model:8s} {count:9d} values -> {path} ({path.stat().st_size / 1e6:.2f} MB, loads in {seconds:.3f} s)"
            )
    print(f"converted {len(written)} model(s) in {time.perf_counter() - start:.1f} s")
    return 0


def _leaves(tree) -> Sequence[np.ndarray]:
    if isinstance(tree, dict):
        return [leaf for value in tree.values() for leaf in _leaves(value)]
    return [tree]
