"""Criteria on the command line: `waldo score`, `waldo weights convert`, and the shared criterion flags.

    waldo score --criterion NAME IMAGE... [--json] [--weights DIR] [--target FILE] [--guard NAME:T]
    waldo weights convert SRC DST [--model NAME ...] [--force]

`--criterion` takes a registered name or `weighted:NAME=W,...`; `--guard NAME:THRESHOLD` wraps it with
`constrained` (repeatable); `--weights DIR` replaces `WALDO_WEIGHTS`; `--target FILE` is the reference
image of the `waldo` finder. `waldo explore` takes the same flags.

`waldo score` scores each image file at its own size (images of one size in one batched call) and
prints `score  file` lines, or with `--json` exactly one object
`{"criterion": NAME, "direction": "max"|"min", "scores": [...]}` with the scores in input order.
RGBA files give their alpha to criteria that use opacity; other files count as opaque.
"""

from __future__ import annotations

import argparse
import json
import os
import time
import warnings
from pathlib import Path
from typing import Optional, Sequence

import numpy as np

from waldo_jax.errors import MAX_RESOLUTION, MIN_RESOLUTION, WaldoError, check_input_file

__all__ = ["add_criterion_arguments", "criterion_from_args", "read_image", "add_score_command",
           "add_weights_command", "cmd_score", "cmd_weights_convert"]


def add_criterion_arguments(parser: argparse.ArgumentParser, default: Optional[str] = None) -> None:
    """`--criterion`, `--guard`, `--weights` and `--target` on `parser`."""
    from waldo_jax.criteria import CRITERIA

    names = ", ".join(sorted(CRITERIA))
    parser.add_argument("--criterion", required=default is None, default=default,
                        help=f"one of {names}, or weighted:NAME=W,NAME=W" + (f" (default {default})" if default else ""))
    parser.add_argument("--guard", action="append", default=[], metavar="NAME:THRESHOLD",
                        help="a view failing this criterion's threshold gets the worst score, e.g. opacity:0.9 "
                             "(repeatable)")
    parser.add_argument("--weights", default=None, metavar="DIR",
                        help="weights folder in the ../shared/weights layout (default: WALDO_WEIGHTS, else "
                             "$WALDO_DATA/weights)")
    parser.add_argument("--target", default=None, metavar="FILE",
                        help="reference image of the object to find (criterion waldo)")


def read_image(path: str | os.PathLike, keep_alpha: bool = False, what: str = "image file",
               min_side: int = MIN_RESOLUTION) -> np.ndarray:
    """An image file as float32 [H, W, 3] in [0, 1] ([H, W, 4] with its alpha if `keep_alpha` and it has one).

    Sides must lie in [min_side, MAX_RESOLUTION] (read from the header, before any decoding; a scored
    image needs MIN_RESOLUTION, a --target crop 2), and every value must be finite.

    Raises:
      DataNotFoundError: no such file. WaldoError: not a regular file, not a readable image, too
        small or too large, or with NaN / infinite values (the message names the file).
    """
    import imageio.v3 as iio
    from PIL import Image

    path = check_input_file(path, what)
    try:
        with Image.open(path) as header:  # the size without decoding: an 8000x8000 file costs nothing
            width, height = header.size
    except Exception:  # not a format Pillow knows: imageio may still read it; its size is checked below
        width = height = None
    if width is not None:
        _check_image_size(path, width, height, min_side)
    try:
        with warnings.catch_warnings():  # imageio's plugin probing warns about deprecated plugins on junk files
            warnings.simplefilter("ignore", DeprecationWarning)
            image = np.asarray(iio.imread(path))
    except Exception as exc:  # imageio raises many types, some with installation advice on later lines
        first = (str(exc).strip().splitlines() or [type(exc).__name__])[0]
        raise WaldoError(f"{path}: not a readable image ({first[:160]})") from None
    if image.ndim == 2:
        image = np.repeat(image[..., None], 3, axis=-1)
    if image.ndim != 3 or image.shape[-1] not in (1, 3, 4):
        raise WaldoError(f"{path}: expected a grey, RGB or RGBA image, got an array of shape {image.shape}")
    _check_image_size(path, image.shape[1], image.shape[0], min_side)
    if image.shape[-1] == 1:
        image = np.repeat(image, 3, axis=-1)
    scale = float(np.iinfo(image.dtype).max) if np.issubdtype(image.dtype, np.integer) else 1.0
    image = image.astype(np.float32) / scale
    if not np.all(np.isfinite(image)):
        raise WaldoError(f"{path}: the image has {int(np.sum(~np.isfinite(image)))} NaN or infinite values")
    if image.shape[-1] == 4 and not keep_alpha:
        image = image[..., :3]
    return image


def _check_image_size(path: Path, width: int, height: int, min_side: int) -> None:
    if not (min_side <= min(width, height) and max(width, height) <= MAX_RESOLUTION):
        raise WaldoError(f"{path}: the image is {width}x{height}; sides must lie between {min_side} and "
                         f"{MAX_RESOLUTION} pixels")


def criterion_from_args(args: argparse.Namespace, room=None, source: str = ""):
    """The criterion the flags name (built with the room, weights folder and target they give)."""
    from waldo_jax.criteria import CriterionContext
    from waldo_jax.criteria.combine import build_criterion

    target = None
    if getattr(args, "target", None):
        target = read_image(args.target, what="--target image", min_side=2)
    context = CriterionContext(room=room, weights_dir=getattr(args, "weights", None), target=target, source=source)
    return build_criterion(args.criterion, context, getattr(args, "guard", []) or [])


def add_score_command(subparsers) -> None:
    p = subparsers.add_parser(
        "score", help="score image files with a criterion",
        description="Score image files with a criterion of the registry (each at its own size). Prints "
                    "'score  file' lines, or with --json one object {criterion, direction, scores} in input order.")
    p.add_argument("images", nargs="+", metavar="IMAGE", help="image files (PNG, JPEG, ...)")
    add_criterion_arguments(p)
    p.add_argument("--json", action="store_true", help="print exactly one JSON object")
    p.set_defaults(handler=cmd_score)


def cmd_score(args: argparse.Namespace) -> int:
    import jax

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


def add_weights_command(subparsers) -> None:
    p = subparsers.add_parser("weights", help="criterion weights: convert to the fast native format")
    cmds = p.add_subparsers(dest="weights_command", metavar="COMMAND")
    cmds.required = True
    c = cmds.add_parser(
        "convert", help="convert a weights folder to native .npz files",
        description="Read the original weights files of SRC (torch pickles, OpenCV YAML, MATLAB .mat, in the "
                    "../shared/weights layout) and write DST/<model>/<model>.npz for each model, checking every "
                    "shape. Criteria load DST faster with --weights DST (or WALDO_WEIGHTS=DST).")
    c.add_argument("src", metavar="SRC", help="weights folder in the ../shared/weights layout")
    c.add_argument("dst", metavar="DST", help="output folder")
    c.add_argument("--model", action="append", default=None, help="convert only this model (repeatable)")
    c.add_argument("--force", action="store_true", help="replace existing converted files")
    c.set_defaults(handler=cmd_weights_convert)


def cmd_weights_convert(args: argparse.Namespace) -> int:
    import waldo_jax.criteria  # noqa: F401  (registers the converters)
    from waldo_jax.weights import CONVERTERS, convert_all, load_model

    dst = Path(args.dst)
    models = args.model
    if not args.force:
        for model in models or CONVERTERS:
            existing = dst / model / f"{model}.npz"
            if existing.exists():
                raise WaldoError(f"{existing} exists; pass --force to replace it")
    start = time.perf_counter()
    written = convert_all(args.src, dst, models)
    for model, path in written.items():
        t0 = time.perf_counter()
        tree, _ = load_model(model, dst)
        seconds = time.perf_counter() - t0
        count = sum(int(np.size(leaf)) for leaf in _leaves(tree))
        print(f"{model:8s} {count:9d} values -> {path} ({path.stat().st_size / 1e6:.2f} MB, loads in {seconds:.3f} s)")
    print(f"converted {len(written)} model(s) in {time.perf_counter() - start:.1f} s")
    return 0


def _leaves(tree) -> Sequence[np.ndarray]:
    if isinstance(tree, dict):
        return [leaf for value in tree.values() for leaf in _leaves(value)]
    return [tree]
