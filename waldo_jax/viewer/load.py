"""PATH as a `ViewScene`: `load_view_scene` tells the kinds of PATH apart and hands each to its reader.

An output folder of `waldo explore` (`scene.explore_scene`; a `waldo demo`'s method folder with the demo's room,
`demo.demo_room`), of `waldo path` (`scene.path_scene`), of `waldo demo` (`demo.demo_scene`), or a SOURCE:
a splat scene, `procedural[:SEED]` or a NeRF run (`scene.source_geometry`). It sits above `scene` and `demo`
so that neither imports the other both ways.
"""

from __future__ import annotations

import math
import os
from pathlib import Path

from waldo_jax.viewer.fields import read_json
from waldo_jax.viewer.demo import demo_room, demo_scene, is_demo_output
from waldo_jax.viewer.scene import (
    DEFAULT_FOV_Y_DEG,
    Frustum,
    ViewerError,
    ViewScene,
    explore_scene,
    path_scene,
    ring_of,
    source_geometry,
)

__all__ = ["load_view_scene"]


def load_view_scene(path: str) -> ViewScene:
    """The `ViewScene` of PATH: an output folder of `waldo explore`, `waldo path` or `waldo demo`, or a SOURCE.

    Raises:
      ViewerError (or another `WaldoError` of the file it reads): PATH is missing, or a folder that is none of
        these nor a scene, or a results.json that is not an explore's or a path's.
    """
    from waldo_jax.pipeline.sources import parse_procedural

    text = str(path)
    if parse_procedural(text) is None and not Path(text).exists():
        raise ViewerError(f"PATH {text!r}: no such file or folder")
    folder = Path(text)
    # lexists: a results.json that is a folder, a FIFO or a dangling link is said as such (`read_json`), not
    # taken for a folder without one.
    if folder.is_dir() and os.path.lexists(folder / "results.json"):
        results = read_json(folder / "results.json", "results file")
        if isinstance(results, dict) and "limits" in results and "found" in results and "source" in results:
            return path_scene(folder, results)
        return explore_scene(folder, demo=demo_room(folder.resolve().parent))
    if folder.is_dir() and is_demo_output(folder):
        return demo_scene(folder)
    from waldo_jax.pipeline.splat_sources import is_splat_spec

    if folder.is_dir() and not is_splat_spec(text) and not (folder / "checkpoint.ckpt").is_file():
        raise ViewerError(
            f"PATH {text!r} is a folder but neither an output of `waldo explore` (no results.json) nor a scene "
            "(a 3DGS model folder, a `waldo train` run)"
        )
    notes = []
    splats, points, c2w, names, fov_y, aspect = source_geometry(text, notes)
    if c2w is None and splats is not None:
        c2w, names = ring_of(text)
        notes.append("the splats have no cameras: the training views drawn are `waldo explore`'s default ring")
    frustums = tuple(
        Frustum(f"/train/{i:04d}", "train", m, None, None, None, f"training view {names[i] if i < len(names) else i}")
        for i, m in enumerate(() if c2w is None else c2w)
    )
    fov_y = math.radians(DEFAULT_FOV_Y_DEG) if fov_y is None else fov_y
    return ViewScene(
        text, f"scene {text}", splats, points, frustums, fov_y, aspect or 1.0, notes=tuple(notes), source=text
    )
