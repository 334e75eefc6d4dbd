"""Cameras of splat scenes in other layouts (waldo_jax.scenes.colmap, waldo_jax.splats.cameras): COLMAP
sparse models, nerfstudio splatfacto runs, and the lookup order of `find_splat_cameras`."""

from __future__ import annotations

import json
import math
import os
import re
import time
import struct

import numpy as np
import pytest

from consumer_parsers import ns_nerfstudio_dataparser
from waldo_jax.cameras import project_points
from waldo_jax.errors import SceneFormatError
from waldo_jax.scenes.colmap import (
    COLMAP_CAMERA_MODELS,
    PINHOLE_LIKE_MODELS,
    ColmapCamera,
    ColmapImage,
    colmap_pose,
    qvec_of_rotation,
    read_colmap_model,
    rotation_of_qvec,
    write_colmap_model,
)
from waldo_jax.splats.cameras import find_splat_cameras, read_camera_source, read_colmap_cameras
from waldo_jax.splats.io import load_splat_model, read_splat_ply, write_cameras_json, write_splat_ply
from waldo_jax.splats.model import make_splats
from waldo_jax.types import Intrinsics
from test_splat_io import _require_data


def _rotation(axis, angle: float) -> np.ndarray:
    """Rodrigues: the rotation by `angle` radians about `axis`."""
    a = np.asarray(axis, np.float64) / np.linalg.norm(axis)
    k = np.array([[0.0, -a[2], a[1]], [a[2], 0.0, -a[0]], [-a[1], a[0], 0.0]])
    return np.eye(3) + math.sin(angle) * k + (1.0 - math.cos(angle)) * (k @ k)


def _cameras(n: int) -> np.ndarray:
    """n varied, deterministic OpenGL camera-to-world matrices [n, 4, 4] (angles up to 180 degrees)."""
    c2w = np.tile(np.eye(4), (n, 1, 1))
    for i in range(n):
        c2w[i, :3, :3] = _rotation([1.0, 0.3 * i - 1.0, 0.5 + 0.1 * i], 0.4 + 2.7 * i / max(n - 1, 1))
        c2w[i, :3, 3] = [2.0 * math.cos(i), 1.5 * math.sin(0.7 * i), 0.3 * i - 1.0]
    return c2w


def _one_focal(model: str) -> bool:
    """COLMAP's models with one focal length f (models.h): f, cx, cy, ..."""
    return model.startswith("SIMPLE_") or model in ("RADIAL", "RADIAL_FISHEYE")


def _params(model: str, i: int) -> tuple:
    """Parameters of a camera of `model` in its order: focal length(s), an off-centre principal point,
    non-zero distortion."""
    f, fy, cx, cy = 500.0 + i, 520.0 + i, 330.5 - i, 238.25 + i
    n = COLMAP_CAMERA_MODELS[model][1]
    head = (f, cx, cy) if _one_focal(model) else (f, fy, cx, cy)
    extra = tuple(0.01 * (j + 1) for j in range(n - len(head)))
    return (640.0, 480.0) if model == "EQUIRECTANGULAR" else head + extra


# ---------------------------------------------------------------------------------------------
# COLMAP.


def test_quaternion_round_trip_and_convention():
    for i, c2w in enumerate(_cameras(12)):
        q = qvec_of_rotation(c2w[:3, :3])
        assert q[0] >= 0 and abs(np.linalg.norm(q) - 1) < 1e-12
        np.testing.assert_allclose(rotation_of_qvec(q), c2w[:3, :3], atol=1e-12, err_msg=str(i))
    # (w, x, y, z) = (cos 45, 0, sin 45, 0): 90 degrees about +y, x -> -z.
    np.testing.assert_allclose(
        rotation_of_qvec([math.sqrt(0.5), 0, math.sqrt(0.5), 0]), [[0, 0, 1], [0, 1, 0], [-1, 0, 0]], atol=1e-12
    )
    # A rotation of 180 degrees (trace -1) keeps its precision.
    half_turn = _rotation([1.0, 2.0, 3.0], math.pi)
    np.testing.assert_allclose(rotation_of_qvec(qvec_of_rotation(half_turn)), half_turn, atol=1e-12)


@pytest.mark.parametrize("scale", [1e-300, 1e300])
def test_a_quaternion_of_any_finite_size_keeps_its_direction(scale):
    """A quaternion's squares once overflowed (1e300: the identity came back, with a warning naming no
    file) or underflowed; its direction is what counts. Zero and non-finite ones are refused."""
    np.testing.assert_allclose(rotation_of_qvec([scale, scale, 0, 0]), rotation_of_qvec([1, 1, 0, 0]), atol=1e-12)
    for bad in ([0, 0, 0, 0], [math.inf, 0, 0, 0], [math.nan, 1, 0, 0]):
        with pytest.raises(ValueError, match="zero or not finite"):
            rotation_of_qvec(bad)


@pytest.mark.parametrize("binary", [True, False], ids=["bin", "txt"])
def test_colmap_round_trip_all_pinhole_models(tmp_path, binary):
    models = sorted(PINHOLE_LIKE_MODELS)
    cameras = [ColmapCamera(i + 1, m, 640 + 8 * i, 480, _params(m, i)) for i, m in enumerate(models)]
    c2w = _cameras(2 * len(models))
    images = []
    for i, m in enumerate(c2w):
        q, t = colmap_pose(m)
        images.append(ColmapImage(100 - i, tuple(q), tuple(t), cameras[i % len(cameras)].camera_id, f"img_{i:02d}.jpg"))
    folder = write_colmap_model(tmp_path / "sparse" / "0", cameras, images[::-1], binary=binary)
    ext = ".bin" if binary else ".txt"
    assert sorted(p.name for p in folder.iterdir()) == sorted(f"{s}{ext}" for s in ("cameras", "images", "points3D"))

    raw_cameras, raw_images = read_colmap_model(folder)
    assert list(raw_cameras.values()) == cameras  # exact: doubles in binary, repr in text
    assert raw_images == images[::-1]

    with pytest.warns(UserWarning, match="distortion of 6 camera"):
        read = read_colmap_cameras(tmp_path)  # the scene folder: sparse/0 is found
    assert read.names == tuple(f"img_{i:02d}.jpg" for i in range(len(c2w)))  # sorted by name
    np.testing.assert_allclose(read.c2w, c2w, atol=2e-6)
    for i, intrinsics in enumerate(read.intrinsics):
        camera = cameras[i % len(cameras)]
        d = intrinsics.to_dict()
        p = camera.params
        fx, fy, cx, cy = (p[0], p[0], p[1], p[2]) if _one_focal(camera.model) else p[:4]
        assert (d["width"], d["height"]) == (camera.width, camera.height)
        assert [d["fx"], d["fy"], d["cx"], d["cy"]] == [np.float32(v) for v in (fx, fy, cx, cy)], camera.model
        assert not intrinsics.has_distortion  # dropped, with the warning


def test_colmap_all_models_read_raw_and_non_pinholes_refused(tmp_path):
    cameras = [ColmapCamera(i + 1, m, 640, 480, _params(m, i)) for i, m in enumerate(COLMAP_CAMERA_MODELS)]
    image = ColmapImage(1, (1.0, 0.0, 0.0, 0.0), (0.0, 0.0, 0.0), 0, "a.png")
    for binary in (True, False):
        folder = write_colmap_model(tmp_path / str(binary), cameras, [image], binary=binary)
        assert list(read_colmap_model(folder)[0].values()) == cameras
    assert {COLMAP_CAMERA_MODELS[m][0] for m in COLMAP_CAMERA_MODELS} == set(range(18))
    for camera in cameras:
        if camera.model in PINHOLE_LIKE_MODELS:
            continue
        folder = write_colmap_model(tmp_path / camera.model, [camera], [image._replace(camera_id=camera.camera_id)])
        with pytest.raises(SceneFormatError, match=f"cameras.bin: camera {camera.camera_id} is a {camera.model}"):
            read_colmap_cameras(folder)


def test_hand_made_colmap_text(tmp_path):
    """A pose worked out by hand: q = 90 degrees about y, t = (1, 2, 3), an off-centre principal point."""
    (tmp_path / "cameras.txt").write_text(
        "# Camera list with one line of data per camera:\n#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]\n"
        "7 PINHOLE 640 480 500 510 300.5 260.25\n"
    )
    h = math.sqrt(0.5)
    (tmp_path / "images.txt").write_text(
        "# Image list with two lines of data per image:\n"
        f"3 {h} 0 {h} 0 1 2 3 7 left view.png\n"
        "10.5 20.5 -1 30.0 40.0 12\n"
    )
    cameras = read_colmap_cameras(tmp_path / "images.txt")
    assert cameras.names == ("left view.png",)
    # world-to-camera R maps x -> -z, z -> x: the camera's right (x), down (y) and forward (z) axes are
    # R's rows (0, 0, 1), (0, 1, 0), (-1, 0, 0); its centre -R^T t = (3, -2, -1). OpenGL: up = -down,
    # backward = -forward.
    expected = np.array([[0, 0, 1, 3], [0, -1, 0, -2], [1, 0, 0, -1], [0, 0, 0, 1]], np.float32)
    np.testing.assert_allclose(cameras.c2w[0], expected, atol=1e-6)
    d = cameras.intrinsics[0].to_dict()
    assert (d["width"], d["height"], d["fx"], d["fy"], d["cx"], d["cy"]) == (640, 480, 500, 510, 300.5, 260.25)
    # COLMAP's own projection (x = R X + t, u = fx x / z + cx) against ours through the c2w read.
    rotation = np.array([[0.0, 0, 1], [0, 1, 0], [-1, 0, 0]])
    points = np.array([[-2.0, -2.5, -0.5], [0.5, -1.0, -3.0], [-7.0, 1.0, 2.0]])
    cam = points @ rotation.T + [1.0, 2.0, 3.0]
    colmap_uv = np.stack([500 * cam[:, 0] / cam[:, 2] + 300.5, 510 * cam[:, 1] / cam[:, 2] + 260.25], -1)
    uv, depth = project_points(cameras.c2w[0], cameras.intrinsics[0], points.astype(np.float32))
    np.testing.assert_allclose(np.asarray(depth), cam[:, 2], rtol=1e-5)
    np.testing.assert_allclose(np.asarray(uv), colmap_uv, rtol=1e-5)


def _image(image_id: int, c2w: np.ndarray, camera_id: int, name: str) -> ColmapImage:
    """The COLMAP image of an OpenGL camera-to-world matrix."""
    q, t = colmap_pose(c2w)
    return ColmapImage(image_id, tuple(q), tuple(t), camera_id, name)


def _model(tmp_path, binary=True):
    cameras = [ColmapCamera(1, "PINHOLE", 64, 48, (50.0, 50.0, 32.0, 24.0))]
    images = [_image(i + 1, m, 1, f"{i}.png") for i, m in enumerate(_cameras(3))]
    return write_colmap_model(tmp_path / "model", cameras, images, binary=binary)


def _truncate(name, keep):
    def edit(folder):
        data = (folder / name).read_bytes()
        (folder / name).write_bytes(data[:keep])
        return folder

    return edit


def _replace_bytes(name, offset, packed):
    def edit(folder):
        data = bytearray((folder / name).read_bytes())
        data[offset : offset + len(packed)] = packed
        (folder / name).write_bytes(bytes(data))
        return folder

    return edit


def _remove(name):
    def edit(folder):
        (folder / name).unlink()
        return folder / ("cameras.bin" if name == "images.bin" else "images.bin")

    return edit


def _write(name, text):
    def edit(folder):
        (folder / name).write_text(text)
        return folder

    return edit


@pytest.mark.parametrize(
    "binary, edit, file, message",
    [
        (True, _truncate("cameras.bin", -3), "cameras.bin", "truncated: camera 1's 4 PINHOLE parameters"),
        (True, _truncate("images.bin", -1), "images.bin", "truncated"),
        (True, _truncate("images.bin", 4), "images.bin", "truncated: the image count"),
        (True, _truncate("cameras.bin", 0), "cameras.bin", "empty file"),
        (True, _replace_bytes("cameras.bin", 12, struct.pack("<i", 99)), "cameras.bin", "unknown camera model id 99"),
        (True, _replace_bytes("images.bin", 8 + 60, struct.pack("<I", 5)), "images.bin", "camera 5 is not in"),
        (True, _remove("images.bin"), "images.bin", "no such file"),
        (
            False,
            _write("cameras.txt", "1 WEIRD 64 48 50 32 24\n"),
            "cameras.txt",
            "line 1: unknown camera model 'WEIRD'",
        ),
        (
            False,
            _write("cameras.txt", "1 PINHOLE 64 48 50 32 24\n"),
            "cameras.txt",
            "PINHOLE camera has 4 parameters, got 3",
        ),
        (False, _write("images.txt", "1 1 0 0 0 0 0 0 1\n"), "images.txt", "line 1: expected IMAGE_ID"),
        (False, _write("images.txt", "1 1 0 0 zero 0 0 0 1 a.png\n\n"), "images.txt", "line 1: expected float"),
        (False, _write("images.txt", "1 0 0 0 0 0 0 0 1 a.png\n\n"), "images.txt", "zero or non-finite quaternion"),
    ],
    ids=lambda v: v if isinstance(v, str) and len(v) < 16 else None,
)
def test_bad_colmap_models(tmp_path, binary, edit, file, message):
    target = edit(_model(tmp_path, binary))
    with pytest.raises(SceneFormatError, match=message) as e:
        read_colmap_cameras(target)
    assert e.value.path.endswith(file)


def test_no_colmap_model_here(tmp_path):
    with pytest.raises(SceneFormatError, match="no COLMAP model here") as e:
        read_colmap_cameras(tmp_path)
    assert e.value.path == str(tmp_path)
    assert read_camera_source(tmp_path) is None  # --cameras: then it is read as a poses file


# ---------------------------------------------------------------------------------------------
# nerfstudio runs.

# config.yml as `ns-train splatfacto --data data/scene` saves it (yaml.dump of its dataclasses), cut down.
_CONFIG_YML = """\
!!python/object:nerfstudio.engine.trainer.TrainerConfig
_target: !!python/name:nerfstudio.engine.trainer.Trainer ''
data: &id001 !!python/object/apply:pathlib.PosixPath
{data}
experiment_name: scene
gradient_accumulation_steps: {{}}
load_dir: null
machine: !!python/object:nerfstudio.configs.base_config.MachineConfig
  device_type: cuda
  dist_url: auto
method_name: splatfacto
optimizers:
  means:
    optimizer: !!python/object:nerfstudio.engine.optimizers.AdamOptimizerConfig
      _target: &id002 !!python/name:torch.optim.adam.Adam ''
      eps: 1.0e-15
      lr: 0.00016
output_dir: !!python/object/apply:pathlib.PosixPath
- outputs
pipeline: !!python/object:nerfstudio.pipelines.base_pipeline.VanillaPipelineConfig
  _target: !!python/name:nerfstudio.pipelines.base_pipeline.VanillaPipeline ''
  datamanager: !!python/object:nerfstudio.data.datamanagers.full_images_datamanager.FullImageDatamanagerConfig
    _target: !!python/object/apply:_operator.getitem
    - !!python/name:nerfstudio.data.datamanagers.full_images_datamanager.FullImageDatamanager ''
    - !!python/name:nerfstudio.data.datasets.base_dataset.InputDataset ''
    cache_images: gpu
    camera_res_scale_factor: 1.0
    data: *id001
    dataparser: !!python/object:{parser}
      _target: !!python/name:nerfstudio.data.dataparsers.nerfstudio_dataparser.Nerfstudio ''
      auto_scale_poses: true
      center_method: poses
      data: !!python/object/apply:pathlib.PosixPath []
{colmap}      orientation_method: up
      scale_factor: 1.0
    eval_image_indices: !!python/tuple
    - 0
  model: !!python/object:nerfstudio.models.splatfacto.SplatfactoModelConfig
    _target: !!python/name:nerfstudio.models.splatfacto.SplatfactoModel ''
    background_color: random
    sh_degree: 3
timestamp: 2024-05-01_120000
viewer: !!python/object:nerfstudio.configs.base_config.ViewerConfig
  quit_on_train_completion: true
"""
_NS_PARSER = "nerfstudio.data.dataparsers.nerfstudio_dataparser.NerfstudioDataParserConfig"
_COLMAP_PARSER = "nerfstudio.data.dataparsers.colmap_dataparser.ColmapDataParserConfig"


def _config_yml(data_parts, parser=_NS_PARSER, colmap=""):
    return _CONFIG_YML.format(data="\n".join(f"- {p}" for p in data_parts), parser=parser, colmap=colmap)


def _transforms(applied: bool):
    """A nerfstudio transforms.json: OpenGL c2w, an off-centre principal point, frames out of order."""
    c2w = _cameras(5)
    c2w[:, :3, 3] = c2w[:, :3, 3] * 3.0 + [4.0, -2.0, 1.0]
    meta = {
        "camera_model": "OPENCV",
        "w": 160,
        "h": 120,
        "fl_x": 150.0,
        "fl_y": 152.0,
        "cx": 83.0,
        "cy": 57.5,
        "frames": [
            {"file_path": f"images/frame_{i:05d}.png", "transform_matrix": m.tolist()} for i, m in enumerate(c2w)
        ][::-1],
    }
    if applied:
        meta["applied_transform"] = [[0.0, 1.0, 0.0, 0.5], [1.0, 0.0, 0.0, -0.25], [0.0, 0.0, -1.0, 2.0]]
    return meta, c2w


def _splats_at(points):
    n = len(points)
    return make_splats(
        means=np.asarray(points, np.float32),
        log_scales=np.full((n, 3), -3.0, np.float32),
        quats=np.tile(np.float32([1, 0, 0, 0]), (n, 1)),
        logits=np.zeros(n, np.float32),
        sh=np.zeros((n, 1, 3), np.float32),
    )


def _splatfacto_project(tmp_path, applied=True, where="inside"):
    """data/scene (transforms.json) and outputs/scene/splatfacto/<timestamp>/ (config.yml,
    dataparser_transforms.json as nerfstudio's dataparser makes them) with splats exported at the data
    frame's points `world`, moved into the dataparser frame."""
    project = tmp_path / "project"
    data = project / "data" / "scene"
    data.mkdir(parents=True)
    meta, c2w = _transforms(applied)
    (data / "transforms.json").write_text(json.dumps(meta))
    ns = ns_nerfstudio_dataparser(data)
    run = project / "outputs" / "scene" / "splatfacto" / "2024-05-01_120000"
    run.mkdir(parents=True)
    (run / "config.yml").write_text(_config_yml(["data", "scene"]))
    (run / "dataparser_transforms.json").write_text(json.dumps(ns["dataparser_transforms"]))
    # Points in front of the cameras, in transforms.json's frame, then as nerfstudio's model holds them.
    world = np.stack([m[:3, 3] - 2.0 * m[:3, 2] + 0.3 * m[:3, 0] for m in c2w])
    model_points = ns["scale"] * (world @ ns["transform"][:3, :3].T + ns["transform"][:3, 3])
    folder = {"inside": run, "exports": run / "exports", "beside": project}[where]
    ply = write_splat_ply(folder / "splat.ply", _splats_at(model_points), normals=False)
    return ply, run, meta, c2w, world, ns


@pytest.mark.parametrize("applied", [False, True], ids=["plain", "applied_transform"])
def test_splatfacto_cameras_land_in_the_splats_frame(tmp_path, applied):
    ply, run, meta, c2w, world, ns = _splatfacto_project(tmp_path, applied)
    transform = np.asarray(ns["dataparser_transforms"]["transform"])
    assert abs(ns["dataparser_transforms"]["scale"] - 1.0) > 0.1 and np.linalg.norm(transform[:, 3]) > 0.1
    assert np.max(np.abs(transform[:3, :3] - np.eye(3))) > 0.1  # a non-trivial transform
    model = load_splat_model(ply)
    cameras = model.cameras
    assert "nerfstudio run" in model.source and str(run) in model.source
    # nerfstudio's own cameras (its dataparser, re-implemented in consumer_parsers), sorted by file path.
    assert cameras.names == tuple(ns["file_paths"])
    np.testing.assert_allclose(cameras.c2w[:, :3], ns["poses"], atol=1e-5)
    # Each splat projects from its moved camera where the data-frame point does from the data's camera.
    means = np.asarray(model.splats.means)
    for i in range(len(c2w)):
        j = cameras.names.index(f"images/frame_{i:05d}.png")
        original = Intrinsics.create(160, 120, 150.0, 152.0, 83.0, 57.5)
        uv0, d0 = project_points(c2w[i].astype(np.float32), original, world[i : i + 1].astype(np.float32))
        uv1, d1 = project_points(cameras.c2w[j], cameras.intrinsics[j], means[i : i + 1])
        np.testing.assert_allclose(np.asarray(uv1), np.asarray(uv0), atol=1e-3)
        np.testing.assert_allclose(np.asarray(d1), ns["scale"] * np.asarray(d0), rtol=1e-5)
        assert cameras.intrinsics[j].to_dict() == original.to_dict()


@pytest.mark.parametrize("where", ["exports", "beside"])
def test_splatfacto_ply_exported_near_the_run(tmp_path, where):
    ply, run, *_ = _splatfacto_project(tmp_path, where=where)
    found = find_splat_cameras(ply)
    assert found is not None and found[1].startswith(f"nerfstudio run {run}")
    # --cameras names the run or its config.yml.
    for spec in (run, run / "config.yml"):
        cameras, _ = read_camera_source(spec)
        np.testing.assert_array_equal(cameras.c2w, found[0].c2w)


def test_splatfacto_with_colmap_dataparser(tmp_path):
    """nerfstudio's colmap dataparser: the saved transform maps COLMAP's world directly."""
    data = tmp_path / "data"
    c2w = _cameras(3)
    images = [_image(i + 1, m, 1, f"{i}.png") for i, m in enumerate(c2w)]
    write_colmap_model(
        data / "colmap" / "sparse" / "0", [ColmapCamera(1, "PINHOLE", 64, 48, (50.0, 51.0, 30.0, 25.0))], images
    )
    run = tmp_path / "elsewhere" / "run"
    run.mkdir(parents=True)
    config = _config_yml(
        [str(data)],
        _COLMAP_PARSER,
        "      colmap_path: !!python/object/apply:pathlib.PosixPath\n      - colmap\n      - sparse\n      - '0'\n",
    )
    (run / "config.yml").write_text(config)
    transform = np.concatenate([_rotation([0.2, 1.0, -0.4], 1.1), [[0.5], [-1.0], [2.0]]], axis=1)
    (run / "dataparser_transforms.json").write_text(json.dumps({"transform": transform.tolist(), "scale": 0.25}))
    write_splat_ply(run / "splat.ply", _splats_at(np.zeros((1, 3))), normals=False)
    cameras, source = find_splat_cameras(run / "splat.ply")
    expected = np.concatenate([transform, [[0, 0, 0, 1]]]) @ c2w
    expected[:, :3, 3] *= 0.25
    np.testing.assert_allclose(cameras.c2w, expected, atol=2e-6)
    assert str(data / "colmap" / "sparse" / "0") in source


def test_bad_splatfacto_runs(tmp_path):
    ply, run, *_ = _splatfacto_project(tmp_path)
    (run / "config.yml").write_text(_config_yml(["data", "gone"]))
    # Asked for (--cameras): an error naming the config. Found by looking around: a warning, no cameras.
    with pytest.raises(SceneFormatError, match=r"names the data data/gone, which is not here") as e:
        read_camera_source(run)
    assert e.value.path == str(run / "config.yml")
    with pytest.warns(UserWarning, match=r"names the data data/gone, which is not here.*cameras are not read"):
        assert load_splat_model(ply).cameras is None
    (run / "config.yml").write_text("pipeline: [unclosed\n")
    with pytest.raises(SceneFormatError, match="not a readable YAML file") as e:
        load_splat_model(ply)
    assert e.value.path == str(run / "config.yml")
    # A config of nested lists past CONFIG_MAX_BYTES (8 MB had taken 147 s and 3.3 GB): refused unread.
    (run / "config.yml").write_text(
        _config_yml(["data", "scene"]) + "junk: [" + ",".join(["[[[1]]]"] * 600_000) + "]\n"
    )
    start = time.perf_counter()
    with pytest.raises(SceneFormatError, match=r"nerfstudio config of 4\.6 MiB; more than 4 MiB is not one") as e:
        read_camera_source(run)
    assert e.value.path == str(run / "config.yml") and time.perf_counter() - start < 1.0
    (run / "config.yml").write_text("!!python/object/apply:os.system ['touch pwned']\n")
    with pytest.raises(SceneFormatError, match="expected nerfstudio's config"):
        load_splat_model(ply)  # the tag is read as data, never run
    assert not (tmp_path / "pwned").exists() and not os.path.exists("pwned")
    (run / "config.yml").write_text(_config_yml(["data", "scene"]))
    (run / "dataparser_transforms.json").write_text(json.dumps({"transform": [[1, 0, 0]], "scale": 1}))
    with pytest.raises(
        SceneFormatError, match=re.escape("dataparser transform must be a 3x4 matrix, got shape [1, 3]")
    ) as e:
        load_splat_model(ply)
    assert e.value.path == str(run / "dataparser_transforms.json")


def test_part_of_a_run_or_model_given_as_cameras_says_what_is_missing(tmp_path):
    """`--cameras` naming a nerfstudio run without one of its two files, or a COLMAP model without its
    images file, had been "a directory, where a poses file was expected"; a config.yml that is a FIFO,
    "no such file"."""
    _, run, *_ = _splatfacto_project(tmp_path)
    (run / "dataparser_transforms.json").unlink()
    with pytest.raises(
        SceneFormatError, match=r"no such file \(a nerfstudio run holds config.yml and dataparser_transforms.json\)"
    ) as e:
        read_camera_source(run)
    assert e.value.path == str(run / "dataparser_transforms.json")
    camera = ColmapCamera(1, "PINHOLE", 64, 48, (50.0, 52.0, 30.0, 20.0))
    model = write_colmap_model(tmp_path / "model", [camera], [_image(1, _cameras(1)[0], 1, "v.png")], binary=True)
    (model / "images.bin").unlink()
    with pytest.raises(SceneFormatError, match="a COLMAP model without images.bin or images.txt.*cameras.bin"):
        read_camera_source(model)
    fifo = tmp_path / "fifo_run"
    fifo.mkdir()
    (fifo / "dataparser_transforms.json").write_text("{}")
    os.mkfifo(fifo / "config.yml")
    for spec in (fifo / "config.yml", fifo):
        with pytest.raises(SceneFormatError, match="a FIFO, socket or device, where a file was expected") as e:
            read_camera_source(spec)
        assert e.value.path == str(fifo / "config.yml")
    assert read_camera_source(tmp_path / "model" / "nothing_here") is None  # not a run or model: a poses file's


# ---------------------------------------------------------------------------------------------
# The lookup, and the real donut.


def test_lookup_order(tmp_path):
    ply = write_splat_ply(tmp_path / "point_cloud.ply", _splats_at(np.zeros((2, 3))))
    assert find_splat_cameras(ply) is None and load_splat_model(ply).cameras is None
    c2w = _cameras(4)
    write_colmap_model(
        tmp_path / "sparse" / "0",
        [ColmapCamera(1, "SIMPLE_PINHOLE", 64, 48, (40.0, 32.0, 24.0))],
        [_image(i, m, 1, f"c{i}") for i, m in enumerate(c2w)],
    )
    cameras, source = find_splat_cameras(ply)
    assert source == f"COLMAP model {tmp_path / 'sparse' / '0'} (images.bin)" and len(cameras) == 4
    write_cameras_json(tmp_path / "cameras.json", c2w[:2], Intrinsics.create(32, 32, 30.0), ["a", "b"])
    model = load_splat_model(ply)
    assert len(model.cameras) == 2 and model.source.endswith("with 2 cameras from cameras.json")


def test_real_donut_colmap_cameras_match_cameras_json(tmp_path):
    donut = _require_data("splats/donut/point_cloud.ply")
    from waldo_jax.pipeline.splat_sources import ring_cameras

    splats = read_splat_ply(donut)
    intrinsics = Intrinsics.create(320, 240, 280.0, 290.0)
    c2w, _ = ring_cameras(np.asarray(splats.means), np.asarray(splats.valid), intrinsics, count=8)
    names = [f"view_{i}" for i in range(len(c2w))]
    with_json, with_colmap = tmp_path / "json", tmp_path / "colmap"
    for folder in (with_json, with_colmap):
        folder.mkdir()
        os.symlink(donut, folder / "point_cloud.ply")
    write_cameras_json(with_json / "cameras.json", c2w, intrinsics, names)
    reference = load_splat_model(with_json)
    assert reference.cameras is not None and reference.source.endswith("cameras from cameras.json")
    # The same cameras as COLMAP writes them (cameras.json's centred pinhole as a PINHOLE camera).
    d = intrinsics.to_dict()
    camera = ColmapCamera(1, "PINHOLE", d["width"], d["height"], (d["fx"], d["fy"], d["cx"], d["cy"]))
    poses = [colmap_pose(m) for m in reference.cameras.c2w]
    images = [ColmapImage(i + 1, tuple(q), tuple(t), 1, name) for i, ((q, t), name) in enumerate(zip(poses, names))]
    write_colmap_model(with_colmap / "sparse" / "0", [camera], images)
    model = load_splat_model(with_colmap)
    assert "COLMAP model" in model.source and model.splats.count == reference.splats.count
    assert model.cameras.names == reference.cameras.names
    np.testing.assert_allclose(model.cameras.c2w, reference.cameras.c2w, atol=1e-6)
    assert [i.to_dict() for i in model.cameras.intrinsics] == [i.to_dict() for i in reference.cameras.intrinsics]


@pytest.mark.slow
def test_splat_source_reads_colmap_cameras(tmp_path):
    """`--cameras` takes a COLMAP model; a scene's own COLMAP model is said in `source_info.poses`."""
    from waldo_jax.pipeline.splat_sources import splat_source

    ply = write_splat_ply(tmp_path / "scene" / "point_cloud.ply", _splats_at([[0.0, 0.0, -1.0], [0.1, 0.0, -1.2]]))
    camera = ColmapCamera(1, "PINHOLE", 64, 48, (50.0, 52.0, 30.0, 20.0))
    c2w = _cameras(2)
    images = [_image(i + 1, m, 1, f"v{i}.png") for i, m in enumerate(c2w)]
    model = write_colmap_model(tmp_path / "elsewhere", [camera], images, binary=False)
    source = splat_source(str(ply), resolution=32, cameras=str(model / "images.txt"), images=False)
    assert source.info["poses"] == f"--cameras {model / 'images.txt'}: COLMAP model {model} (images.txt)"
    np.testing.assert_allclose(source.train_c2w, c2w, atol=2e-6)
    assert source.train_names == ("v0.png", "v1.png")
    d = source.intrinsics.to_dict()  # the COLMAP camera at 32 px: its off-centre principal point scaled
    assert (d["width"], d["height"], d["fx"], d["cx"], d["cy"]) == (32, 24, 25.0, 15.0, 10.0)
    # A principal point far off the image renders every view empty: warned of, as a poses file's is.
    off = ColmapCamera(1, "PINHOLE", 64, 48, (50.0, 52.0, -1e6, 20.0))
    far = write_colmap_model(tmp_path / "far", [off], images, binary=True)
    with pytest.warns(UserWarning, match=r"principal point \(cx, cy\) = \(-1e\+06, 20\) lies outside the 64x48"):
        splat_source(str(ply), resolution=32, cameras=str(far), images=False)
    write_colmap_model(tmp_path / "scene" / "sparse", [camera], images[:1])
    source = splat_source(str(ply), resolution=32, images=False)
    assert source.info["poses"] == f"COLMAP model {tmp_path / 'scene' / 'sparse'} (images.bin)"
    assert len(source.train_c2w) == 1
