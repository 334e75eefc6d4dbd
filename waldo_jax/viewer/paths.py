"""The viewer's "Export this path": the camera path on screen as the files `waldo path` writes.

The path is a `waldo path` output's own frames, or, for an explore output (a demo's method), its top-k shots
in rank order as keyframes, joined by `FRAMES_PER_SHOT` frames each (`cameras.slerp_c2w`: rotations SLERPed,
centres linear), one second per shot at `SHOTS_FPS`. It is written with the writers of `waldo path`
(`scenes.camera_paths.nerfstudio_camera_path`, `instant_ngp_camera_path`; the scene's own frame, as `waldo path`
without --nerfstudio-transforms) as camera_path.json and instant_ngp_path.json into a new folder
`viewer_path_NN` of the output folder: the first free NN, created exclusively, so no earlier export is
overwritten. `waldo render SOURCE --poses .../camera_path.json` renders it.

Poses are OpenGL camera-to-world [4, 4].
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import List, Optional, Tuple

import numpy as np

from waldo_jax.errors import WaldoError
from waldo_jax.viewer.scene import ViewerError, ViewScene

__all__ = ["FRAMES_PER_SHOT", "SHOTS_FPS", "export_camera_path", "path_of", "shots_path"]

FRAMES_PER_SHOT = 12  # frames from one top-k shot to the next
SHOTS_FPS = 12.0
_MAX_EXPORTS = 1000


def shots_path(keyframes: np.ndarray, frames_per_shot: int = FRAMES_PER_SHOT) -> np.ndarray:
    """The camera path through keyframes c2w [K, 4, 4]: `frames_per_shot` frames from each to the next and the
    last keyframe, float64 [(K - 1) * frames_per_shot + 1, 4, 4]; frame i * frames_per_shot is keyframe i."""
    import jax
    import jax.numpy as jnp

    from waldo_jax.cameras import slerp_c2w

    keyframes = np.asarray(keyframes, np.float64)
    if len(keyframes) < 2:
        return keyframes.copy()
    t = jnp.arange(frames_per_shot) / frames_per_shot  # [S] in [0, 1)
    between = jax.vmap(lambda a, b: jax.vmap(lambda s: slerp_c2w(a, b, s))(t))(
        jnp.asarray(keyframes[:-1]), jnp.asarray(keyframes[1:])
    )  # [K - 1, S, 4, 4]
    frames = np.asarray(between, np.float64).reshape(-1, 4, 4)
    frames[::frames_per_shot] = keyframes[:-1]  # the shots exactly, not float32's rounding of them
    return np.concatenate([frames, keyframes[-1:]])


def path_of(scene: ViewScene, group: str = "") -> Tuple[np.ndarray, float, str]:
    """(frames c2w float64 [F, 4, 4], frames per second, what it is in words) of the path shown for `scene`:
    a camera path's frames, else the top-k shots of `group` ("" outside a demo) by rank as keyframes.

    Raises:
      ViewerError: the scene has neither a camera path nor top-k shots (of that group).
    """
    if scene.camera_path is not None and len(scene.camera_path):
        frames = np.asarray(scene.camera_path, np.float64)
        return frames, scene.path_fps, f"the camera path ({len(frames)} frames)"
    shots = sorted((f for f in scene.frustums if f.kind == "topk" and f.group == group), key=lambda f: f.topk_rank)
    if not shots:
        raise ViewerError(f"{scene.path}: no camera path and no top-k shots{f' of {group}' if group else ''} to export")
    frames = shots_path(np.stack([f.c2w for f in shots]))
    what = f"the {len(shots)} top-k shots{f' of {group.upper()}' if group else ''} in rank order as keyframes"
    return frames, SHOTS_FPS, f"{what}, {FRAMES_PER_SHOT} frames from one to the next"


def _run_camera(scene: ViewScene, folder: Path):
    """The run's camera and world from its poses.json, read once (explore and path outputs write one): its
    intrinsics, else its resolution and fov_y; the world it records (`PosesFile.world`), else None."""
    from waldo_jax.scenes import load_poses_file
    from waldo_jax.types import Intrinsics

    width, height = scene.resolution or (max(1, round(64 * scene.aspect)), 64)
    focal = 0.5 * height / math.tan(0.5 * scene.fov_y)
    fallback = Intrinsics.create(int(width), int(height), focal, focal)
    try:
        poses = load_poses_file(folder / "poses.json", fallback)
    except (WaldoError, OSError, ValueError):
        return fallback, None
    return poses.intrinsics, poses.world


def _new_folder(output: Path) -> Path:
    """`output/viewer_path_NN` for the first NN not taken, created here (exclusively: never an earlier one)."""
    for number in range(1, _MAX_EXPORTS):
        folder = output / f"viewer_path_{number:02d}"
        try:
            folder.mkdir()
        except FileExistsError:
            continue
        return folder
    raise ViewerError(f"{output}: viewer_path_01 .. viewer_path_{_MAX_EXPORTS - 1} all exist; move some away")


def export_camera_path(scene: ViewScene, group: str = "", output: Optional[Path] = None) -> List[Path]:
    """Writes the path shown for `scene` (`path_of`) as nerfstudio's camera_path.json and Instant-NGP's
    instant_ngp_path.json into a new folder `viewer_path_NN` of `output` (default: the scene's output folder).

    Returns:
      The two files written.

    Raises:
      ViewerError: nothing to export, or no output folder (a SOURCE alone).
    """
    from waldo_jax import io
    from waldo_jax.scenes.camera_paths import NgpFrame, instant_ngp_camera_path, nerfstudio_camera_path

    output = Path(output) if output is not None else scene.output
    if output is None or not Path(output).is_dir():
        raise ViewerError(f"{scene.path}: no output folder to write a camera path into")
    frames, fps, what = path_of(scene, group)
    run = Path(scene.output or output) / group  # the run whose poses.json has the camera and the world
    intrinsics, world = _run_camera(scene, run)
    info = {"criterion": scene.criterion, "source": scene.source, "exported_by": "waldo view", "path": what}
    if world is not None:  # the run's world goes with its poses: `render --poses` elsewhere says so
        info["source_world"] = world
    folder = _new_folder(Path(output))
    nerfstudio = folder / "camera_path.json"
    io.write_json(nerfstudio, nerfstudio_camera_path(frames, intrinsics, fps, extra=info))
    ngp = folder / "instant_ngp_path.json"
    frame = NgpFrame.of_info(scene.source_info)
    io.write_json(ngp, instant_ngp_camera_path(frames, intrinsics, fps, extra=info, frame=frame))
    return [nerfstudio, ngp]
