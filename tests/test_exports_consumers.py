"""`waldo path`'s exports read the way nerfstudio and Instant-NGP read them (tests/consumer_parsers.py).

For a nerfstudio scene with `applied_transform` (face), an Instant-NGP scene (fox), a Blender scene
(lego_tiny), the procedural room and a from_mitsuba scene, the exports of a small path (three training
views, then nine frames of waldo's spline through them) go through the consumers' readers: nerfstudio's
dataparser (what world its model's cameras live in, and the dataparser_transforms.json it saves),
`ns-render camera-path`, the viewer's "Load Path", Instant-NGP's loader, its camera path and `run.py`'s
frame times. Every frame's world pose must come back as the pose waldo rendered, within
`POSITION_TOL` scene units and `ANGLE_TOL` degrees (the bound docs/design.md states), and each
training view must land on the consumer's own camera for that image. Controls show that the checks
bite: the old exports (no applied transform undone, NGP's default cubic B-spline) fail them. One small
end-to-end `waldo path` on the room, with an odd --video-resolution, checks the CLI's files.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from types import SimpleNamespace
from typing import Any, Dict, Tuple

import imageio.v3 as iio
import jax.numpy as jnp
import numpy as np
import pytest

import consumer_parsers as cp
from conftest import require_scene
from waldo_jax.cameras import camera_focus
from waldo_jax.cli import main
from waldo_jax.errors import WaldoError
from waldo_jax.pipeline.path_run import check_nerfstudio_export
from waldo_jax.pipeline.sources import export_info
from waldo_jax.scenes import load_scene
from waldo_jax.scenes.camera_paths import (
    NgpFrame,
    instant_ngp_camera_path,
    nerfstudio_camera_path,
    read_camera_path,
    read_dataparser_transform,
)
from waldo_jax.search.path import path_c2w
from waldo_jax.search.population import training_poses

POSITION_TOL = 1e-3  # scene units
ANGLE_TOL = 0.05  # degrees
FPS = 6.0  # 12 frames at 6 fps: run.py renders them with --video_n_seconds 2 --video_fps 6


# ---------------------------------------------------------------------------------------------
# Helpers.


def _errors(expected: np.ndarray, got: np.ndarray, unit: float = 1.0) -> Tuple[float, float]:
    """(largest position error / unit, largest rotation error in degrees) of camera matrices [F, 3|4, 4]."""
    expected, got = np.asarray(expected, np.float64), np.asarray(got, np.float64)
    position = np.linalg.norm(expected[:, :3, 3] - got[:, :3, 3], axis=-1) / unit
    # ||R1 - R2||_F = 2 sqrt(2) sin(angle / 2): well conditioned near 0, where acos of the trace is not.
    chord = np.linalg.norm(expected[:, :3, :3] - got[:, :3, :3], axis=(1, 2)) / (2.0 * math.sqrt(2.0))
    return float(position.max()), float(np.degrees(2.0 * np.arcsin(np.clip(chord, 0.0, 1.0))).max())


def _within(errors: Tuple[float, float], what: str) -> None:
    position, degrees = errors
    assert position <= POSITION_TOL and degrees <= ANGLE_TOL, f"{what}: {position:.3g} units, {degrees:.3g} degrees"


def _key(file_path: str) -> str:
    """A frame's image path as both sides spell it ("./train/r_0" and "train/r_0.png" -> "train/r_0")."""
    return Path(file_path).with_suffix("").as_posix()


def _path_frames(scene, count: int = 3, frames: int = 9) -> Tuple[np.ndarray, list]:
    """Three training views (their names) followed by `frames` frames of waldo's spline through them."""
    pick = np.linspace(0, scene.n_images - 1, count).round().astype(int)
    train = np.asarray(scene.c2w[pick], np.float64)
    keyframes = training_poses(jnp.asarray(scene.c2w[pick]), jnp.asarray(camera_focus(np.asarray(scene.c2w))))
    spline = np.asarray(path_c2w(keyframes, frames), np.float64)
    return np.concatenate([train, spline]), [scene.file_names[i] for i in pick]


def _exports(scene, c2w: np.ndarray, dataparser_file: Dict[str, Any]) -> Tuple[Dict[str, Any], Dict[str, Any]]:
    """waldo's two exports of frames c2w, as `write_path_outputs` builds them for this scene, through JSON text."""
    info = export_info(scene.format, scene.metadata, scene.aabb, scene.path)
    applied = info["nerfstudio_applied_transform"]
    ns = nerfstudio_camera_path(
        c2w,
        scene.intrinsics,
        FPS,
        read_dataparser_transform(dataparser_file),
        applied_transform=None if applied is None else np.asarray(applied),
        applied_scale=info["nerfstudio_applied_scale"],
    )
    frame = NgpFrame.create(info["ngp_scale"], info["ngp_offset"], info["ngp_from_mitsuba"])
    ngp = instant_ngp_camera_path(c2w, scene.intrinsics, FPS, frame=frame)
    ns, ngp = json.loads(json.dumps(ns)), json.loads(json.dumps(ngp))
    for export in (ns, ngp):  # and waldo's own reader (`waldo render --poses`) gets the frames back
        np.testing.assert_allclose(read_camera_path(export, scene.intrinsics)[0], c2w, atol=2e-5)
    return ns, ngp


def _check_nerfstudio(export: Dict[str, Any], parsed: Dict[str, Any], c2w: np.ndarray, names, intrinsics) -> None:
    """ns-render's cameras and the viewer's keyframes of `export` against waldo's frames c2w (scene frame)."""
    expected = parsed["transform"] @ c2w  # the dataparser's own map of a transforms.json pose ...
    expected[:, :3, 3] *= parsed["scale"]  # ... into the model's world
    cameras = cp.ns_get_path_from_json(export)
    _within(_errors(expected, cameras["c2w"], unit=parsed["scale"]), "ns-render camera pose")
    # Each training view lands on the model's own camera for that image.
    index = {_key(p): i for i, p in enumerate(parsed["file_paths"])}
    own = parsed["poses"][[index[_key(n)] for n in names]]
    _within(_errors(own, cameras["c2w"][: len(names)], unit=parsed["scale"]), "training view vs the model's camera")
    np.testing.assert_allclose(cameras["fy"], float(intrinsics.fy), rtol=1e-6)
    assert (cameras["width"], cameras["height"]) == (intrinsics.width, intrinsics.height)
    assert cameras["video_fps"] == pytest.approx(FPS)
    # The viewer loads one keyframe per frame, where ns-render's frames are, meeting them at i / fps.
    loaded = cp.ns_viewer_load_path(export)
    viewer = np.stack([cp.ns_viewer_keyframe_matrix(k) for k in loaded["keyframes"]])
    _within(_errors(expected, viewer, unit=parsed["scale"]), "viewer keyframe pose")
    np.testing.assert_allclose(cp.ns_viewer_keyframe_seconds(loaded), np.arange(len(c2w)) / FPS, atol=1e-9)
    assert not any(k["override_fov_enabled"] for k in loaded["keyframes"])
    assert all(k["aspect"] == pytest.approx(intrinsics.width / intrinsics.height) for k in loaded["keyframes"])


def _ngp_played(export: Dict[str, Any]) -> list:
    """The keyframe NGP's camera has when run.py opens the shutter of each frame, with the file's run.py flags."""
    flags = export["waldo"]["run_py"]
    seconds, fps = int(flags[flags.index("--video_n_seconds") + 1]), int(flags[flags.index("--video_fps") + 1])
    path = cp.ngp_load_camera_path(export)
    return [cp.ngp_eval_camera_path(path, start) for start, _ in cp.ngp_run_py_frame_times(seconds, fps)]


def _check_ngp(
    export: Dict[str, Any],
    file_frame: Dict[str, Any],
    c2w_file: np.ndarray,
    names,
    training_ngp: Dict[str, np.ndarray],
    intrinsics,
) -> None:
    """run.py's frames of `export` against waldo's frames as the transforms file writes them (c2w_file)."""
    played = _ngp_played(export)
    assert len(played) == len(c2w_file)
    ngp = np.stack([cp.ngp_keyframe_matrix(k) for k in played])
    back = np.stack([cp.ngp_matrix_to_nerf(m, file_frame) for m in ngp])
    _within(_errors(c2w_file, back), "run.py frame pose")
    own = np.stack([training_ngp[_key(n)] for n in names])
    _within(_errors(own, ngp[: len(names)], unit=file_frame["scale"]), "training view vs NGP's own camera")
    for k in played:
        assert cp.ngp_fov_focal_length(k["fov"], intrinsics.height) == pytest.approx(float(intrinsics.fy), rel=1e-6)


def _ngp_training(folder: Path, jsons, file_frame) -> Dict[str, np.ndarray]:
    """NGP's camera matrix of every training frame of the loaded JSONs, by image path."""
    return {
        _key(f["file_path"]): cp.ngp_nerf_matrix_to_ngp(np.asarray(f["transform_matrix"]), file_frame)
        for meta in jsons
        for f in meta["frames"]
    }


# ---------------------------------------------------------------------------------------------
# The scenes.


def _scene(name: str):
    return load_scene(require_scene(name), downscale=8, max_images=6)


def test_face_nerfstudio_scene_with_applied_transform():
    folder = require_scene("face")
    scene = _scene("face")
    assert scene.metadata["nerfstudio_applied"]["source"] == "applied_transform"
    c2w, names = _path_frames(scene)
    parsed = cp.ns_nerfstudio_dataparser(folder)
    ns, ngp = _exports(scene, c2w, parsed["dataparser_transforms"])
    _check_nerfstudio(ns, parsed, c2w, names, scene.intrinsics)
    meta = json.loads((folder / "transforms.json").read_text())
    frame = cp.ngp_load_nerf_frame([meta])
    _check_ngp(ngp, frame, c2w, names, _ngp_training(folder, [meta], frame), scene.intrinsics)
    # Control: the dataparser transform used as if it mapped transforms.json's frame (the old export)
    # puts the cameras about 180 degrees and a unit or more away from the model's.
    old = json.loads(
        json.dumps(
            nerfstudio_camera_path(
                c2w, scene.intrinsics, FPS, read_dataparser_transform(parsed["dataparser_transforms"])
            )
        )
    )
    expected = parsed["transform"] @ c2w
    expected[:, :3, 3] *= parsed["scale"]
    position, degrees = _errors(expected, cp.ns_get_path_from_json(old)["c2w"])
    assert position > 0.5 and degrees > 90


def test_fox_instant_ngp_scene():
    folder = require_scene("fox")
    with pytest.warns(UserWarning, match="skipped 17 of 67"):
        scene = _scene("fox")
    c2w, names = _path_frames(scene)
    parsed = cp.ns_nerfstudio_dataparser(folder)  # nerfstudio-data reads NGP's transforms.json too
    ns, ngp = _exports(scene, c2w, parsed["dataparser_transforms"])
    _check_nerfstudio(ns, parsed, c2w, names, scene.intrinsics)
    meta = json.loads((folder / "transforms.json").read_text())
    frame = cp.ngp_load_nerf_frame([meta])
    assert frame["scale"] == pytest.approx(0.33) and frame["aabb_scale"] == 4
    _check_ngp(ngp, frame, c2w, names, _ngp_training(folder, [meta], frame), scene.intrinsics)
    # Control: NGP's default cubic B-spline on the same keyframes leaves our frames.
    cubic = {**ngp, "spline_order": 3}
    played = np.stack([cp.ngp_matrix_to_nerf(cp.ngp_keyframe_matrix(k), frame) for k in _ngp_played(cubic)])
    position, degrees = _errors(c2w, played)
    assert position > POSITION_TOL or degrees > ANGLE_TOL


def test_lego_tiny_blender_scene():
    folder = require_scene("lego_tiny")
    scene = load_scene(folder, split="train", max_images=6)
    c2w, names = _path_frames(scene)
    parsed = cp.ns_blender_dataparser(folder, "train")
    ns, ngp = _exports(scene, c2w, parsed["dataparser_transforms"])
    _check_nerfstudio(ns, parsed, c2w, names, scene.intrinsics)
    meta = json.loads((folder / "transforms_train.json").read_text())
    frame = cp.ngp_load_nerf_frame([meta])
    _check_ngp(ngp, frame, c2w, names, _ngp_training(folder, [meta], frame), scene.intrinsics)


def _tiny_transforms(folder: Path, extra: Dict[str, Any], n: int = 4) -> Dict[str, Any]:
    """A 16x16 scene of n views on a circle (OpenGL c2w looking at the origin), with `extra` keys."""
    frames = []
    for i in range(n):
        angle = 2 * math.pi * i / n
        eye = np.array([3 * math.cos(angle), 0.5 * i, 3 * math.sin(angle)])
        back = eye / np.linalg.norm(eye)
        right = np.cross([0.0, 1.0, 0.0], back)
        right /= np.linalg.norm(right)
        m = np.eye(4)
        m[:3, :3] = np.stack([right, np.cross(back, right), back], axis=1)
        m[:3, 3] = eye
        name = f"images/{i:03d}.png"
        (folder / "images").mkdir(parents=True, exist_ok=True)
        iio.imwrite(folder / name, np.full((16, 16, 3), 40 * i, np.uint8))
        frames.append({"file_path": name, "transform_matrix": m.tolist()})
    meta = {"fl_x": 20.0, "fl_y": 20.0, "cx": 8.0, "cy": 8.0, "w": 16, "h": 16, "frames": frames, **extra}
    (folder / "transforms.json").write_text(json.dumps(meta))
    return meta


@pytest.mark.parametrize(
    "extra",
    [
        {"from_mitsuba": True},
        {"from_mitsuba": True, "scale": 0.2, "offset": [0.4, 0.5, 0.6]},
        {"scale": 0.25, "offset": 0.3, "aabb_scale": 2},
        {"aabb": [[-2.0, -1.0, -3.0], [4.0, 1.0, 3.0]]},
    ],
)
def test_instant_ngp_keys_as_ngp_reads_them(tmp_path, extra):
    """`scale`, `offset`, `aabb` and `from_mitsuba` give the box and the exports NGP's loader gives."""
    meta = _tiny_transforms(tmp_path, extra)
    scene = load_scene(tmp_path)
    frame = cp.ngp_load_nerf_frame([meta])
    # The box: NGP's marching cube 0.5 +- aabb_scale / 2 mapped back to the file's world.
    half = 0.5 * frame["aabb_scale"]
    cube = np.stack([np.full(3, 0.5 - half), np.full(3, 0.5 + half)])
    np.testing.assert_allclose(scene.aabb, (cube - frame["offset"]) / frame["scale"], rtol=1e-5, atol=1e-5)
    # The cameras: a Mitsuba file's camera axes become OpenGL's, so NGP's matrix of a loaded pose is
    # NGP's matrix of the file's.
    training = _ngp_training(tmp_path, [meta], frame)
    c2w, names = _path_frames(scene, count=3, frames=9)
    _, ngp = _exports(scene, c2w, {"transform": np.eye(4)[:3].tolist(), "scale": 1.0})
    file_c2w = c2w @ np.diag([-1.0, 1.0, -1.0, 1.0]) if frame["from_mitsuba"] else c2w
    _check_ngp(ngp, frame, file_c2w, names, training, scene.intrinsics)


def test_nerfstudio_colmap_default_and_applied_scale(tmp_path):
    """No `applied_transform` but a colmap/sparse/0 folder: nerfstudio's legacy COLMAP transform; and
    `applied_scale`, which nerfstudio folds into the saved scale but not into its cameras."""
    _tiny_transforms(tmp_path, {"camera_model": "OPENCV", "applied_scale": 2.5})
    (tmp_path / "colmap" / "sparse" / "0").mkdir(parents=True)
    scene = load_scene(tmp_path)
    assert scene.metadata["nerfstudio_applied"]["source"] == "nerfstudio's COLMAP default"
    np.testing.assert_array_equal(scene.applied_transform, cp.NS_COLMAP_DEFAULT_APPLIED_TRANSFORM)
    c2w, names = _path_frames(scene)
    parsed = cp.ns_nerfstudio_dataparser(tmp_path)
    assert parsed["dataparser_transforms"]["scale"] == pytest.approx(2.5 * parsed["scale"])
    ns, _ = _exports(scene, c2w, parsed["dataparser_transforms"])
    _check_nerfstudio(ns, parsed, c2w, names, scene.intrinsics)


def test_a_checkpoint_without_the_applied_transform_reads_it_from_its_scene_or_refuses(tmp_path):
    """Checkpoints saved before waldo recorded `nerfstudio_applied` re-read their scene file; without
    it, `--nerfstudio-transforms` is refused before the search (the export could not undo it)."""
    _tiny_transforms(tmp_path, {"camera_model": "OPENCV", "applied_transform": cp.NS_COLMAP_DEFAULT_APPLIED_TRANSFORM})
    scene = load_scene(tmp_path)
    old = {k: v for k, v in scene.metadata.items() if k != "nerfstudio_applied"}
    info = export_info("nerfstudio", old, scene.aabb, str(tmp_path))
    assert info["nerfstudio_applied_transform"] == [list(r) for r in cp.NS_COLMAP_DEFAULT_APPLIED_TRANSFORM]
    gone = export_info("nerfstudio", old, scene.aabb, str(tmp_path / "elsewhere"))
    assert gone["nerfstudio_applied_source"] == "unknown"
    source = SimpleNamespace(info={**gone, "scene_path": "elsewhere"}, spec="runs/old")
    check_nerfstudio_export(source, None)  # no --nerfstudio-transforms: nothing to undo
    with pytest.raises(WaldoError, match="runs/old does not record its scene's applied_transform"):
        check_nerfstudio_export(source, (np.eye(4), 1.0))


# ---------------------------------------------------------------------------------------------
# The room, end to end.


@pytest.mark.filterwarnings("ignore:os.fork:RuntimeWarning")  # imageio-ffmpeg reads the MP4 in a subprocess
def test_waldo_path_on_the_room_round_trips_through_the_consumers(tmp_path, capsys):
    data = tmp_path / "room"  # what NGP and nerfstudio would be trained on
    assert (
        main(["render", "procedural:1", "--views", "8", "--resolution", "16", "--samples", "16", "--out", str(data)])
        == 0
    )
    meta = json.loads((data / "transforms.json").read_text())
    frame = cp.ngp_load_nerf_frame([meta])
    assert frame["scale"] == pytest.approx(1 / 8.7, rel=1e-5)  # the room's aabb, not NGP's default 0.33
    # waldo's loader honours `aabb` too: the box is NGP's unit cube mapped back (the room's +-4.35).
    room = load_scene(data)
    np.testing.assert_allclose(
        room.aabb, (np.stack([np.zeros(3), np.ones(3)]) - frame["offset"]) / frame["scale"], rtol=1e-5, atol=1e-4
    )
    np.testing.assert_allclose(room.aabb[:, [0, 2]], [[-4.35, -4.35], [4.35, 4.35]], atol=1e-4)
    parsed = cp.ns_nerfstudio_dataparser(data)
    dataparser = tmp_path / "dataparser_transforms.json"
    dataparser.write_text(json.dumps(parsed["dataparser_transforms"]))

    out = tmp_path / "path"
    capsys.readouterr()
    assert (
        main(
            [
                "path",
                "procedural:1",
                "--out",
                str(out),
                "--seed",
                "2",
                "--resolution",
                "16",
                "--video-resolution",
                "33",
                "--views",
                "8",
                "--keyframes",
                "3",
                "--frames",
                "8",
                "--epochs",
                "2",
                "--initial-paths",
                "5",
                "--paths-per-epoch",
                "4",
                "--max-speed",
                "0.5",
                "--max-turn",
                "60",
                "--nerfstudio-transforms",
                str(dataparser),
            ]
        )
        == 0
    )
    err = capsys.readouterr().err
    assert "path.mp4: 33x33 frames padded to 34x34" in err
    video = iio.imread(out / "path.mp4")
    assert video.shape[:3] == (8, 34, 34)
    assert iio.imread(out / "path.gif").shape[1:3] == (33, 33)
    results = json.loads((out / "results.json").read_text())
    assert results["video"]["mp4_size"] == [34, 34] and results["video"]["frame_size"] == [33, 33]

    # What waldo rendered: poses.json's frames at the video's intrinsics.
    rendered = json.loads((out / "poses.json").read_text())
    c2w = np.stack([np.asarray(f["transform_matrix"]) for f in rendered["frames"]])
    intrinsics = type("K", (), {"width": rendered["w"], "height": rendered["h"], "fy": rendered["fl_y"]})
    assert (intrinsics.width, intrinsics.height) == (33, 33)
    ns = json.loads((out / "camera_path.json").read_text())
    expected = parsed["transform"] @ c2w
    expected[:, :3, 3] *= parsed["scale"]
    cameras = cp.ns_get_path_from_json(ns)
    _within(_errors(expected, cameras["c2w"], unit=parsed["scale"]), "room: ns-render camera pose")
    np.testing.assert_allclose(cameras["fy"], intrinsics.fy, rtol=1e-6)
    assert cameras["video_fps"] == pytest.approx(12.0)
    viewer = np.stack([cp.ns_viewer_keyframe_matrix(k) for k in cp.ns_viewer_load_path(ns)["keyframes"]])
    _within(_errors(expected, viewer, unit=parsed["scale"]), "room: viewer keyframe pose")

    ngp = json.loads((out / "instant_ngp_path.json").read_text())
    assert ngp["waldo"]["run_py"][ngp["waldo"]["run_py"].index("--video_fps") + 1] == "8"  # 8 frames at 12 fps
    played = _ngp_played(ngp)
    back = np.stack([cp.ngp_matrix_to_nerf(cp.ngp_keyframe_matrix(k), frame) for k in played])
    _within(_errors(c2w, back), "room: run.py frame pose")
