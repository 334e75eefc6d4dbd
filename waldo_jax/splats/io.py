"""Splat scenes as folders and files: the reference 3DGS layout and the other splat formats.

The reference code (graphdeco-inria/gaussian-splatting) saves a trained model as a folder:

  <model>/point_cloud/iteration_<N>/point_cloud.ply    the splats, one per PLY vertex
                                                        (`waldo_jax.splats.formats.ply`);
  <model>/cameras.json                                  the cameras they were fitted to
                                                        (`waldo_jax.splats.cameras_json`).

`load_splat_model` reads that layout, a PLY alone, or one file of another splat format
(`waldo_jax.splats.formats`), with the cameras found beside it (`waldo_jax.splats.cameras`).
"""

from __future__ import annotations

import dataclasses
import os
import re
import warnings
from pathlib import Path
from typing import Optional, Tuple

import numpy as np

from waldo_jax.errors import SceneFormatError
from waldo_jax.splats.cameras import find_splat_cameras
from waldo_jax.splats.cameras_json import MAX_CAMERA_SIDE as MAX_CAMERA_SIDE
from waldo_jax.splats.cameras_json import SplatCameras as SplatCameras
from waldo_jax.splats.cameras_json import iteration_of
from waldo_jax.splats.cameras_json import read_cameras_json as read_cameras_json
from waldo_jax.splats.cameras_json import write_cameras_json
from waldo_jax.splats.formats import find_splat_file, read_splat_file, splat_format
from waldo_jax.splats.formats.common import SH_C0 as SH_C0
from waldo_jax.splats.formats.ply import read_splat_ply
from waldo_jax.splats.formats.ply import splat_ply_properties as splat_ply_properties
from waldo_jax.splats.formats.ply import write_splat_ply
from waldo_jax.splats.model import Splats
from waldo_jax.splats.upright import extent_problem, robust_bounds

__all__ = [
    "SplatCameras",
    "SplatModel",
    "splat_ply_properties",
    "read_splat_ply",
    "write_splat_ply",
    "read_cameras_json",
    "write_cameras_json",
    "load_splat_model",
    "write_splat_model",
    "cameras_facing_away",
]

_ITERATION = re.compile(r"iteration_(\d+)")


# ---------------------------------------------------------------------------------------------
# Model folders.


@dataclasses.dataclass(frozen=True, eq=False)
class SplatModel:
    """A splat scene loaded by `load_splat_model`.

    Attributes:
      splats: the splats.
      cameras: the cameras that come with it (`waldo_jax.splats.cameras.find_splat_cameras`), or None.
      ply_path: the PLY read.
      iteration: N of `point_cloud/iteration_N/`, or None outside that layout.
      source: where the scene came from, in words.
      degenerate: why every ring view of the splats would show nothing (all centres at one point), in
        words, else None; a warning said so when the model was loaded (for results.json's
        `source_info.degenerate`).
      bounds: (low, high) [3], the valid splats' robust bounds (`waldo_jax.splats.upright.robust_bounds`),
        computed once on loading for the ring of views and `waldo scene info`; None where not computed.
    """

    splats: Splats
    cameras: Optional[SplatCameras]
    ply_path: Path
    iteration: Optional[int]
    source: str
    degenerate: Optional[str] = None
    bounds: Optional[Tuple[np.ndarray, np.ndarray]] = None


def _find_ply(folder: Path) -> Tuple[Path, Optional[int]]:
    """The PLY of a model folder: the highest point_cloud/iteration_N/point_cloud.ply, else point_cloud.ply."""
    iterations = folder / "point_cloud" if (folder / "point_cloud").is_dir() else None
    if iterations is None and folder.name == "point_cloud":
        iterations = folder
    if iterations is not None:
        found = {
            int(m.group(1)): d / "point_cloud.ply"
            for d in iterations.iterdir()
            if (m := _ITERATION.fullmatch(d.name)) and (d / "point_cloud.ply").is_file()
        }
        if found:
            return found[max(found)], max(found)
    if (folder / "point_cloud.ply").is_file():
        return folder / "point_cloud.ply", iteration_of(folder / "point_cloud.ply")
    other = find_splat_file(folder)  # a .splat, .spz, .sog, compressed PLY or SOG meta.json
    if other is not None:
        return other, None
    holds = "; its point_cloud/ holds no iteration_<N>/point_cloud.ply" if iterations is not None else ""
    raise SceneFormatError(
        folder,
        "no splat scene here: looked for point_cloud/iteration_<N>/point_cloud.ply (the "
        f"reference 3DGS layout), one file of another splat format and point_cloud.ply{holds}",
    )


def load_splat_model(path: str | os.PathLike) -> SplatModel:
    """Loads a splat scene from a PLY file or a model folder.

    Accepts a `.ply` file (with the cameras.json beside it, or at the model root when the file lies
    in `point_cloud/iteration_N/`); a folder in the reference layout (`point_cloud/iteration_N/
    point_cloud.ply`, the highest N taken numerically, `cameras.json` at the root); its
    `point_cloud/` folder; or a folder holding `point_cloud.ply` directly. A scene without a
    camera file has `cameras` None (cameras.json, else a nerfstudio run, else a COLMAP model:
    `waldo_jax.splats.cameras.find_splat_cameras`).
    A file (or a folder's one file) of another splat format in
    `waldo_jax.splats.formats.FORMATS` (.splat, .spz, SOG, compressed PLY) loads too, `source` naming it.

    Raises:
      SceneFormatError: no such path, a folder in no such layout (listing what was looked for), or
        a malformed PLY or camera file (see `read_splat_ply`, `find_splat_cameras`).
    """
    path = Path(path).expanduser()
    if not path.exists():
        raise SceneFormatError(
            path,
            "no such file or folder"
            if not os.path.islink(path)
            else "a symbolic link that leads nowhere (a loop or a missing target)",
        )
    if path.is_dir():
        ply, iteration = _find_ply(path)
    else:
        ply, iteration = path, iteration_of(path)
    fmt = splat_format(ply)
    if fmt is None and ply.suffix.lower() == ".ply":
        fmt = "ply"  # a malformed PLY: read_splat_ply says what is wrong with it
    splat_file = None if fmt == "ply" else read_splat_file(ply)  # unknown: an error listing the formats
    splats = read_splat_ply(ply) if splat_file is None else splat_file.splats
    found = find_splat_cameras(ply)  # cameras.json, a nerfstudio run, a COLMAP model
    cameras = None if found is None else found[0]
    if iteration is not None:
        source = f"3DGS model {ply.parent.parent.parent}, iteration {iteration}"
    else:
        source = f"splat PLY {ply}" if splat_file is None else f"{splat_file.details}: {ply}"
    if found is not None:
        source += f", with {len(cameras)} cameras from {found[1]}"
    valid = np.asarray(splats.valid, bool)
    means = np.asarray(splats.means, np.float32)
    bounds = robust_bounds(means, valid)  # a pass over every splat: kept for the ring and `scene info`
    degenerate = extent_problem(means, valid, bounds)
    if degenerate is not None and cameras is None:
        degenerate += ": every render of a ring around it is the background alone"
        warnings.warn(f"{ply}: {degenerate}", stacklevel=2)
    else:
        degenerate = None
    if cameras is not None:
        behind = cameras_facing_away(cameras.c2w, means[valid])
        if behind:
            warnings.warn(f"{ply}: {behind} ({found[1]})", stacklevel=2)
    return SplatModel(splats, cameras, ply, iteration, source, degenerate, bounds)


def cameras_facing_away(c2w: np.ndarray, means: np.ndarray) -> Optional[str]:
    """Why every view from the cameras c2w [N, 4, 4] (OpenGL: looking down -z) would miss the splats' centres
    means [M, 3] (none in front of any camera), else None."""
    c2w = np.asarray(c2w, np.float64)
    points = np.asarray(means, np.float64)
    points = points[np.all(np.isfinite(points), axis=1)]
    if not len(points) or not len(c2w):
        return None
    for camera in c2w:  # usually the first camera has splats in front: one pass over the points
        forward = -camera[:3, 2]
        if np.any(points @ forward > float(camera[:3, 3] @ forward)):
            return None
    return (
        f"no splat centre is in front of any of the {len(c2w)} cameras: every view looks away from the splats "
        "(rotations in OpenGL axes where the file's convention is OpenCV's, x right, y down, z forward?)"
    )


def write_splat_model(
    folder: str | os.PathLike,
    splats: Splats,
    iteration: int,
    cameras: Optional[SplatCameras] = None,
    normals: bool = True,
) -> Path:
    """Writes a model folder in the reference layout.

    Writes `<folder>/point_cloud/iteration_<iteration>/point_cloud.ply` (see `write_splat_ply`) and,
    when `cameras` is given, `<folder>/cameras.json` (see `write_cameras_json`).

    Returns:
      The path of the PLY written.
    """
    if isinstance(iteration, bool) or not isinstance(iteration, (int, np.integer)) or iteration < 0:
        raise ValueError(f"iteration must be a non-negative integer, got {iteration!r}")
    folder = Path(folder)
    ply = write_splat_ply(folder / "point_cloud" / f"iteration_{int(iteration)}" / "point_cloud.ply", splats, normals)
    if cameras is not None:
        write_cameras_json(folder / "cameras.json", cameras.c2w, cameras.intrinsics, cameras.names)
    return ply
