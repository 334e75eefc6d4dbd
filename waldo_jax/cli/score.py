"""`waldo score --criterion NAME IMAGE... [--json] [--weights DIR] [--target FILE] [--guard NAME:T]`,
or `waldo score --criterion NAME --source SOURCE [--poses FILE|train] [--resolution R] [--json]`.

Scores each image file at its own size (images of one size in one batched call) and prints
`score  file` lines, or with `--json` exactly one object
`{"criterion": NAME, "direction": "max"|"min", "scores": [...]}` with the scores in input order.
RGBA files give their alpha to criteria that use opacity; other files count as opaque. With
`--source`, the views of SOURCE (any SOURCE of `waldo explore`: the room, a NeRF run, a splat scene)
at the poses of a transforms.json-like file, or at its training poses, are rendered and scored, as a
search scores them (with the accumulated opacity for the criteria that use it).
"""

from __future__ import annotations

import argparse
import json
import os
import warnings

import jax
import numpy as np

from pathlib import Path

from waldo_jax.cli.conventions import Progress, add_quiet, path_argument
from waldo_jax.cli.flags import add_criterion_arguments, criterion_before_source, criterion_from_args
from waldo_jax.errors import MAX_RESOLUTION, MIN_RESOLUTION, WaldoError, check_input_file
from waldo_jax.io import read_image

__all__ = ["add_command", "cmd_score"]


def add_command(subparsers) -> None:
    """Registers `score` on an argparse subparsers object."""
    p = subparsers.add_parser(
        "score",
        help="score image files with a criterion",
        description="Score image files with a criterion of the registry (each at its own size). Prints "
        "'score  file' lines, or with --json one object {criterion, direction, scores} in input order.",
    )
    p.add_argument("images", type=path_argument, nargs="*", metavar="IMAGE", help="image files (PNG, JPEG, ...)")
    p.add_argument(
        "--source",
        default=None,
        metavar="SOURCE",
        help="score renders of SOURCE (procedural[:SEED], a RUN_DIR, a splat scene) instead of files",
    )
    p.add_argument(
        "--poses",
        default=None,  # None: "train", and a --poses given beside image files can be told from it
        metavar="FILE|train",
        help="with --source: a transforms.json-like poses file, or 'train' for its training poses (default: train)",
    )
    p.add_argument("--resolution", type=int, default=None, help="with --source: longer side of the renders")
    add_criterion_arguments(p)
    p.add_argument("--json", action="store_true", help="print exactly one JSON object")
    add_quiet(p)
    p.set_defaults(handler=cmd_score)


def cmd_score(args: argparse.Namespace) -> int:
    """`waldo score`: prints the criterion's score of each image file."""
    if (args.source is None) == (not args.images):
        raise WaldoError("give IMAGE files or --source SOURCE (one of the two)")
    if args.source is not None:
        return _score_source(args)
    ignored = [flag for flag in ("--poses", "--resolution") if getattr(args, flag[2:]) is not None]
    if ignored:  # flags of renders: image files are scored as they are
        verb, it = ("has", "it is") if len(ignored) == 1 else ("have", "they are")
        warnings.warn(f"{' and '.join(ignored)} {verb} no effect on IMAGE files ({it} for --source)", stacklevel=2)
    criterion = criterion_before_source(args)  # None: a criterion of poses (of the procedural room)
    if criterion is None:
        raise WaldoError(f"criterion {args.criterion!r} scores camera poses of the procedural room, not image files")
    # Every file is checked and sized from its header first; the images are then decoded a batch at a time,
    # at most SCORE_BATCH_BYTES of them (all of them at once took 0.8 GB a 4096x4096 photo, without a bound).
    by_size: dict = {}
    for i, path in enumerate(args.images):
        by_size.setdefault(_header_size(path) or ("file", i), []).append(i)
    scores = np.zeros(len(args.images), np.float64)
    score = jax.jit(criterion.score_images)
    with Progress(args.quiet) as progress:
        progress.phase(
            f"scoring with {criterion.name} (compiling once per image size)", total=len(args.images), unit="image"
        )
        for size, indices in by_size.items():  # batched calls per image size
            pixels = 1 if size[0] == "file" else size[0] * size[1]
            batch = max(1, SCORE_BATCH_BYTES // (16 * pixels))  # float32 RGBA
            for start in range(0, len(indices), batch):
                chunk = indices[start : start + batch]
                images = [read_image(args.images[i], keep_alpha=criterion.needs.opacity) for i in chunk]
                by_shape: dict = {}
                for i, image in zip(chunk, images):
                    by_shape.setdefault(image.shape, []).append((i, image))
                for pairs in by_shape.values():
                    scores[[i for i, _ in pairs]] = np.asarray(score(np.stack([im for _, im in pairs])), np.float64)
                progress.advance(len(chunk))
    return _print(args, criterion, scores, args.images)


# The most image data `waldo score` decodes at once (float32), whatever the number of files.
SCORE_BATCH_BYTES = 512 << 20


def _header_size(path) -> tuple | None:
    """(width, height) of an image file from its header, its sides checked (`read_image`'s rule), or None
    where Pillow cannot read the header (imageio may still read the file: it is then scored alone)."""
    from PIL import Image

    check_input_file(path, "image file")
    try:
        with Image.open(path) as header:
            width, height = header.size
    except Exception:
        return None
    if not (MIN_RESOLUTION <= min(width, height) and max(width, height) <= MAX_RESOLUTION):
        raise WaldoError(
            f"{path}: the image is {width}x{height}; sides must lie between {MIN_RESOLUTION} and "
            f"{MAX_RESOLUTION} pixels"
        )
    return (width, height)


def _print(args: argparse.Namespace, criterion, scores, labels) -> int:
    if args.json:
        print(
            json.dumps(
                {"criterion": criterion.name, "direction": criterion.direction, "scores": [float(s) for s in scores]}
            )
        )
        return 0
    better = "higher" if criterion.direction == "max" else "lower"
    print(f"# {criterion.name} ({better} is better): {criterion.description}")
    for label, value in zip(labels, scores):
        print(f"{value:12.6g}  {label}")
    return 0


def _score_source(args: argparse.Namespace) -> int:
    """`waldo score --source SOURCE`: renders the poses with SOURCE and scores them as a search does."""
    from waldo_jax.pipeline import load_source, score_function
    from waldo_jax.scenes import read_poses_file

    if args.poses is None:
        args.poses = "train"
    if args.poses != "train":  # a folder or a FIFO said as such before SOURCE loads, not after (a NeRF: seconds)
        if not os.path.lexists(args.poses):
            raise WaldoError(f"{args.poses}: no such poses file (or pass --poses train)")
        check_input_file(args.poses, "poses file")
    criterion = criterion_before_source(args)
    progress = Progress(args.quiet)
    with progress:
        progress.phase(f"loading {args.source}")
        source = load_source(args.source, args.resolution)
    if criterion is None:  # a poses criterion: the room's oracles need the source
        criterion = criterion_from_args(args, room=source.room, source=source.spec, train_c2w=source.train_c2w)
    if args.poses == "train":
        c2w, labels = source.train_c2w, list(source.train_names)
    else:
        c2w, intrinsics, files = read_poses_file(Path(args.poses), source.intrinsics)
        if (intrinsics.width, intrinsics.height) != (source.intrinsics.width, source.intrinsics.height):
            side = max(source.intrinsics.width, source.intrinsics.height)
            raise WaldoError(
                f"{args.poses}: its cameras are {intrinsics.width}x{intrinsics.height}, SOURCE renders "
                f"{source.intrinsics.width}x{source.intrinsics.height} (--resolution {side}): "
                "pass the --resolution of the file's longer side"
            )
        labels = [f or f"pose {i}" for i, f in enumerate(files)]
    with progress:
        progress.phase(f"rendering and scoring {len(c2w)} views (compiling first)")
        scores = np.asarray(jax.jit(lambda c: score_function(source, criterion)(c))(np.asarray(c2w, np.float32)))
    return _print(args, criterion, scores, labels)
