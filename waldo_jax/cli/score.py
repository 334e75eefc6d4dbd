"""`waldo score --criterion NAME IMAGE... [--json] [--weights DIR] [--target FILE] [--guard NAME:T]`.

Scores each image file at its own size (images of one size in one batched call) and prints
`score  file` lines, or with `--json` exactly one object
`{"criterion": NAME, "direction": "max"|"min", "scores": [...]}` with the scores in input order.
RGBA files give their alpha to criteria that use opacity; other files count as opaque.
"""

from __future__ import annotations

import argparse
import json

import jax
import numpy as np

from waldo_jax.cli.flags import add_criterion_arguments, criterion_from_args
from waldo_jax.errors import WaldoError
from waldo_jax.io import read_image

__all__ = ["add_command", "cmd_score"]


def add_command(subparsers) -> None:
    """Registers `score` on an argparse subparsers object."""
    p = subparsers.add_parser(
        "score", help="score image files with a criterion",
        description="Score image files with a criterion of the registry (each at its own size). Prints "
                    "'score  file' lines, or with --json one object {criterion, direction, scores} in input order.")
    p.add_argument("images", nargs="+", metavar="IMAGE", help="image files (PNG, JPEG, ...)")
    add_criterion_arguments(p)
    p.add_argument("--json", action="store_true", help="print exactly one JSON object")
    p.set_defaults(handler=cmd_score)


def cmd_score(args: argparse.Namespace) -> int:
    """`waldo score`: prints the criterion's score of each image file."""
    criterion = criterion_from_args(args)
    if criterion.inputs == "poses":
        raise WaldoError(f"criterion {criterion.name!r} scores camera poses of the procedural room, not image files")
    images = [read_image(path, keep_alpha=criterion.inputs == "renders") for path in args.images]
    scores = np.zeros(len(images), np.float64)
    score = jax.jit(criterion.score_images)
    by_shape: dict = {}
    for i, image in enumerate(images):
        by_shape.setdefault(image.shape, []).append(i)
    for shape, indices in by_shape.items():  # one batched call per image size
        batch = np.stack([images[i] for i in indices])
        scores[indices] = np.asarray(score(batch), np.float64)
    if args.json:
        print(json.dumps({"criterion": criterion.name, "direction": criterion.direction,
                          "scores": [float(s) for s in scores]}))
        return 0
    better = "higher" if criterion.direction == "max" else "lower"
    print(f"# {criterion.name} ({better} is better): {criterion.description}")
    for path, value in zip(args.images, scores):
        print(f"{value:12.6g}  {path}")
    return 0
