"""`load_source`: a SOURCE string to its `Source` (the room, a NeRF run, or a splat scene)."""

from __future__ import annotations

import os
from typing import Callable, Optional

import numpy as np

from waldo_jax.pipeline.sources import (
    DEFAULT_PROCEDURAL_VIEWS,
    Source,
    SourceError,
    parse_procedural,
    procedural_source,
    run_source,
)
from waldo_jax.pipeline.splat_sources import is_splat_spec, splat_source

__all__ = ["check_source_spec", "load_source"]


def check_source_spec(spec: str) -> None:
    """A SourceError for a SOURCE that names nothing: empty text, or neither procedural[:SEED] nor an
    existing file or folder (before any reader reports a checkpoint it looked for inside it)."""
    if not str(spec).strip():
        raise SourceError("SOURCE is empty: give procedural[:SEED], a NeRF run folder or a splat scene")
    if parse_procedural(spec) is None and not os.path.lexists(spec):
        hint = (
            " (the procedural room is spelt procedural, in lower case)" if spec.lower().startswith("procedural") else ""
        )
        raise SourceError(
            f"SOURCE {spec!r} does not exist: no file or folder of that name, and not procedural[:SEED]{hint}"
        )


def load_source(
    spec: str,
    resolution: Optional[int] = None,
    views: Optional[int] = None,
    cameras: Optional[str] = None,
    up: Optional[np.ndarray] = None,
    orbit: Optional[str] = None,
    images: bool = True,
    check: Optional[Callable[[int, int, int], None]] = None,
) -> Source:
    """The Source of a SOURCE string: `procedural[:SEED]`, a NeRF run directory, or a splat scene
    (a `.ply`, a reference 3DGS folder or a splat run; `waldo_jax.pipeline.splat_sources`).

    `views` (default `DEFAULT_PROCEDURAL_VIEWS`) is for the procedural room only: a run's training
    views are those it was trained on, and passing `views` with a run is an error, not ignored.
    `cameras` (a transforms.json-like poses file, a COLMAP model or a nerfstudio run) gives a splat
    scene its training poses; `up` and `orbit` place the ring of views of a splat scene without cameras
    (`splat_source`). `images=False` leaves a run's or a splat scene's training images out (None), for
    callers that only render. `check(width, height, n_train)` is called with the renders' size and the
    training views' count before any image is rendered or read (`experiment.epoch_check`: a size the
    search cannot hold is refused before the source's own work).

    Raises:
      SourceError: a bad spec, a missing run directory, a bad checkpoint, `views` with a run,
        `cameras` with anything but a splat scene (or another `WaldoError` of the file it reads).
    """
    check_source_spec(spec)
    seed = parse_procedural(spec)
    splat = seed is None and is_splat_spec(spec)
    if cameras is not None and not splat:
        raise SourceError(f"--cameras gives a splat scene its poses; {spec} has its own")
    if (up is not None or orbit is not None) and not splat:
        raise SourceError(f"--up/--orbit place the ring of views of a splat scene without cameras; {spec} has its own")
    if seed is not None:
        return procedural_source(seed, resolution, DEFAULT_PROCEDURAL_VIEWS if views is None else views, check=check)
    if views is not None:
        raise SourceError(f"--views is for procedural sources; {spec} explores from the views it was trained on")
    if splat:
        return splat_source(spec, resolution, cameras, up=up, orbit=orbit, images=images, check=check)
    return run_source(spec, resolution, images=images, check=check)
