"""The flags of different shots and of the view archive, shared by `waldo explore` and `waldo demo`.

`--min-separation DEG`: the top-k written are the best views pairwise at least DEG degrees apart
(`waldo_jax.search.views`; 0: the paper's top-k). `--grid AZxEL` and `--distance-edges A,B,...`: the
cells of the view archive (`waldo_jax.search.archive.ViewGrid`) that every run reports and MAP-Elites
searches. Each value is checked here and refused with one line naming the flag.
"""

from __future__ import annotations

import argparse
import re

from waldo_jax.cli.conventions import is_ascii_number
from waldo_jax.errors import WaldoError, check_float32
from waldo_jax.search.archive import ViewGrid
from waldo_jax.search.views import DEFAULT_MIN_SEPARATION

__all__ = ["add_shot_arguments", "shot_separation", "view_grid"]

_DEFAULT_GRID = ViewGrid()


def add_shot_arguments(parser: argparse.ArgumentParser, grid: bool = True) -> None:
    """`--min-separation` (and, with `grid`, `--grid` and `--distance-edges`) on `parser`."""
    parser.add_argument(
        "--min-separation",
        type=float,
        default=DEFAULT_MIN_SEPARATION,
        metavar="DEG",
        help="the top-k are the best views pairwise at least DEG degrees apart (camera centres seen from the "
        "scene's focus, viewing directions, distance ratio); 0 gives the paper's top-k",
    )
    if not grid:
        return
    parser.add_argument(
        "--grid",
        default=f"{_DEFAULT_GRID.azimuth_cells}x{_DEFAULT_GRID.elevation_cells}",
        metavar="AZxEL",
        help="cells of the view archive: azimuth sectors x elevation bands around the scene's focus",
    )
    parser.add_argument(
        "--distance-edges",
        default=",".join(f"{e:g}" for e in _DEFAULT_GRID.distance_edges),
        metavar="D,D,...",
        help="the archive's distance bands, cut at these multiples of the training cameras' distance to the "
        "focus ('' for one band)",
    )


def shot_separation(args: argparse.Namespace) -> float:
    """--min-separation as a float in [0, 180]; a `WaldoError` naming the flag otherwise."""
    return check_float32(args.min_separation, "--min-separation", minimum=0.0, maximum=180.0)


def view_grid(args: argparse.Namespace) -> ViewGrid:
    """The `ViewGrid` of --grid and --distance-edges (defaults when the parser has neither)."""
    text = getattr(args, "grid", None)
    if text is None:
        return _DEFAULT_GRID
    match = re.fullmatch(r"\s*(\d{1,3})\s*[xX]\s*(\d{1,3})\s*", str(text), re.ASCII)
    if not match:
        raise WaldoError(f"--grid must be AZxEL, two whole numbers such as 8x4, got {text!r}")
    edges_text = str(getattr(args, "distance_edges", "") or "").strip()
    try:
        parts = edges_text.split(",") if edges_text else []
        if not all(map(is_ascii_number, parts)):
            raise ValueError(edges_text)
        edges = tuple(float(part) for part in parts)
    except ValueError:
        raise WaldoError(
            f"--distance-edges must be comma-separated numbers such as 0.75,1.33, got {edges_text!r}"
        ) from None
    for edge in edges:  # the grid's edges are float32 under jit: 1e39 is infinite there, 1e-50 zero
        check_float32(edge, "--distance-edges", positive=edge > 0)
    try:
        return ViewGrid(azimuth_cells=int(match.group(1)), elevation_cells=int(match.group(2)), distance_edges=edges)
    except ValueError as e:
        message = str(e).replace("ViewGrid.distance_edges", "--distance-edges")
        for field in ("ViewGrid.azimuth_cells", "ViewGrid.elevation_cells"):
            message = message.replace(field, "--grid")
        raise WaldoError(message) from None
