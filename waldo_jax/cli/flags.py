"""The criterion flags that `waldo score` and `waldo explore` share, and the criterion they name.

`--criterion` takes a registered name or `weighted:NAME=W,...`; `--guard NAME:THRESHOLD` wraps it with
`constrained` (repeatable); `--weights DIR` replaces `WALDO_WEIGHTS`; `--target FILE` is the reference
image of the `waldo` finder. A command that loads a scene first calls `criterion_before_source`, so
that a bad criterion, guard, weights folder or target is refused before the scene is loaded, and a
`--weights` or `--target` that no criterion named uses is said in a warning line.
"""

from __future__ import annotations

import argparse
import warnings
from typing import Optional

from waldo_jax.criteria import CRITERIA, Criterion, CriterionContext
from waldo_jax.criteria.combine import build_criterion, spec_names
from waldo_jax.io import read_image
from waldo_jax.splats.upright import LAYOUTS, parse_up

__all__ = [
    "add_criterion_arguments",
    "criterion_before_source",
    "criterion_from_args",
    "add_splat_pose_arguments",
    "splat_pose_options",
]


def _up_argument(text: str):
    try:
        return parse_up(text)
    except ValueError as error:
        raise argparse.ArgumentTypeError(str(error).removeprefix("--up ")) from None


def add_splat_pose_arguments(parser: argparse.ArgumentParser) -> None:
    """`--cameras`, `--up` and `--orbit`: where a splat scene's training views come from."""
    parser.add_argument(
        "--cameras",
        default=None,
        metavar="PATH",
        help="splat scenes: the training poses from a transforms.json-like file, a COLMAP model or a "
        "nerfstudio run (default: the model's own cameras, else a ring of 24 views around the splats)",
    )
    parser.add_argument(
        "--up",
        type=_up_argument,
        default=None,
        metavar="X,Y,Z",
        help="splat scenes without cameras: the scene's up for the ring of views (default: read from the "
        "splats, see `waldo scene info`)",
    )
    parser.add_argument(
        "--orbit",
        choices=("auto", *LAYOUTS),
        default="auto",
        help="splat scenes without cameras: orbit the splats from outside (object) or stand inside them "
        "(surround); auto decides by which ring sees more of them",
    )


def splat_pose_options(args: argparse.Namespace) -> dict:
    """The keyword arguments of `load_source` that `add_splat_pose_arguments` set."""
    return {"cameras": args.cameras, "up": args.up, "orbit": None if args.orbit == "auto" else args.orbit}


def add_criterion_arguments(parser: argparse.ArgumentParser, default: Optional[str] = None) -> None:
    """`--criterion`, `--guard`, `--weights` and `--target` on `parser`."""
    names = ", ".join(sorted(CRITERIA))
    parser.add_argument(
        "--criterion", required=default is None, default=default, help=f"one of {names}, or weighted:NAME=W,NAME=W"
    )
    parser.add_argument(
        "--guard",
        action="append",
        default=[],
        metavar="NAME:THRESHOLD",
        help="a view failing this criterion's threshold gets the worst score, e.g. opacity:0.9 (repeatable)",
    )
    parser.add_argument(
        "--weights",
        default=None,
        metavar="DIR",
        help="weights folder in the ../shared/weights layout (default: WALDO_WEIGHTS, else $WALDO_DATA/weights)",
    )
    parser.add_argument(
        "--target", default=None, metavar="FILE", help="reference image of the object to find (criterion waldo)"
    )


def criterion_from_args(args: argparse.Namespace, room=None, source: str = "", train_c2w=None) -> Criterion:
    """The criterion the flags name (built with the room, training poses, weights folder and target they give)."""
    target = None
    names = spec_names(args.criterion, getattr(args, "guard", []) or [])
    # A --target that no criterion named reads is not read either (`criterion_before_source` warns of it).
    if getattr(args, "target", None) and any("target" in CRITERIA[name].reads for name in names):
        target = read_image(args.target, what="--target image", min_side=2)
    context = CriterionContext(
        room=room, weights_dir=getattr(args, "weights", None), target=target, source=source, train_c2w=train_c2w
    )
    return build_criterion(args.criterion, context, getattr(args, "guard", []) or [])


def criterion_before_source(args: argparse.Namespace) -> Optional[Criterion]:
    """The criterion the flags name, built before the source is loaded when it needs nothing from it.

    Checks the spec's text first (`spec_names`); a criterion that scores poses (the room's oracles)
    needs the source's room, so for it this returns None and the caller builds it with
    `criterion_from_args` once the source is loaded.

    Raises:
      CriterionError / DataNotFoundError / WeightsError / WaldoError: a bad spec, guard, weights
        folder or target image (naming the value or file).
    """
    names = spec_names(args.criterion, getattr(args, "guard", []) or [])
    given = (
        ("--weights", getattr(args, "weights", None), "weights_dir"),
        ("--target", getattr(args, "target", None), "target"),
    )
    for flag, value, field in given:
        if value and not any(field in CRITERIA[name].reads for name in names):
            users = ", ".join(sorted(name for name, spec in CRITERIA.items() if field in spec.reads))
            warnings.warn(f"{flag} has no effect: no criterion named here uses it (it is for {users})", stacklevel=2)
    if any(not CRITERIA[name].needs.render for name in names):
        return None
    return criterion_from_args(args, source=args.source)
