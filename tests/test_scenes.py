"""Tests of waldo_jax.scenes: the real scenes in $WALDO_DATA and tiny synthetic fixtures."""

from __future__ import annotations

import json
import os
import re
import struct
import warnings
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pytest

from conftest import require_scene, within
from waldo_jax.errors import SceneFormatError, WaldoError
from waldo_jax.scenes import (
    SceneArgumentError,
    camera_bounds,
    camera_focus,
    detect_format,
    load_scene,
    read_ply_points,
)

# ------------------------------------------------------------------------------------------------
# Helpers.


def _load_recording(*args, **kwargs):
    """load_scene plus the list of warnings it issued."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        scene = load_scene(*args, **kwargs)
    return scene, list(caught)


def _assert_rigid(c2w, tol=1e-4):
    rotation = c2w[:, :3, :3].astype(np.float64)
    eye = np.broadcast_to(np.eye(3), rotation.shape)
    np.testing.assert_allclose(np.swapaxes(rotation, 1, 2) @ rotation, eye, atol=tol)
    np.testing.assert_allclose(np.linalg.det(rotation), 1.0, atol=tol)
    np.testing.assert_allclose(c2w[:, 3], np.broadcast_to([0, 0, 0, 1], (len(c2w), 4)), atol=tol)


def _assert_plausible(scene, n, height, width):
    assert scene.images.shape == (n, height, width, 3)
    assert scene.images.dtype == np.float32 and scene.c2w.dtype == np.float32
    assert scene.c2w.shape == (n, 4, 4) and len(scene.file_names) == n
    assert 0.0 <= scene.images.min() and scene.images.max() <= 1.0
    assert scene.images[::8].std() > 0.05  # real content, not a constant fill
    _assert_rigid(scene.c2w)
    k = scene.intrinsics
    assert (k.width, k.height) == (width, height)
    fov_x = 2 * np.degrees(np.arctan(0.5 * width / float(k.fx)))
    assert 20 < fov_x < 120
    assert 0.9 < float(k.fx) / float(k.fy) < 1.1
    assert 0.3 * width < float(k.cx) < 0.7 * width and 0.3 * height < float(k.cy) < 0.7 * height
    assert scene.aabb.shape == (2, 3) and scene.aabb.dtype == np.float32
    assert np.all(scene.aabb[0] < scene.aabb[1])
    assert 0 < scene.near < scene.far
    assert all((Path(scene.path) / name).is_file() for name in scene.file_names)


def _inside(points, aabb):
    return np.all((points >= aabb[0]) & (points <= aabb[1]), axis=-1)


def _write_image(path, height=8, width=8, channels=3, value=None):
    path.parent.mkdir(parents=True, exist_ok=True)
    if value is None:
        rng = np.random.default_rng(len(str(path)))
        data = rng.integers(0, 256, (height, width, channels), dtype=np.uint8)
    else:
        data = np.full((height, width, channels), value, np.uint8)
    iio.imwrite(path, data if channels > 1 else data[..., 0])
    return data


def _pose(tx=0.0, ty=0.0, tz=4.0):
    return [[1.0, 0.0, 0.0, tx], [0.0, 1.0, 0.0, ty], [0.0, 0.0, 1.0, tz], [0.0, 0.0, 0.0, 1.0]]


def _transforms_scene(folder, n=3, extra=None, frames=None, sizes=None):
    """A tiny instant-ngp scene: n 8x8 PNGs and a transforms.json."""
    folder.mkdir(parents=True, exist_ok=True)
    if frames is None:
        frames = [{"file_path": f"images/{i:03d}.png", "transform_matrix": _pose(tx=0.1 * i)} for i in range(n)]
    for i, frame in enumerate(frames):
        h, w = sizes[i] if sizes else (8, 8)
        if isinstance(frame.get("file_path"), str):
            _write_image(folder / frame["file_path"], h, w)
    meta = {"fl_x": 8.0, "fl_y": 8.0, "cx": 4.0, "cy": 4.0, "w": 8, "h": 8, "aabb_scale": 1, "frames": frames}
    meta.update(extra or {})
    (folder / "transforms.json").write_text(json.dumps(meta))
    return folder / "transforms.json"


# ------------------------------------------------------------------------------------------------
# The real scenes (skipped without data, failing under WALDO_REQUIRE_DATA=1).


@pytest.fixture(scope="module")
def fox():
    return _load_recording(require_scene("fox"), downscale=8)


@pytest.fixture(scope="module")
def face():
    return load_scene(require_scene("face"))


@pytest.fixture(scope="module")
def garden():
    return load_scene(require_scene("garden"))


@pytest.fixture(scope="module")
def fern():
    return load_scene(require_scene("fern"))


@pytest.fixture(scope="module")
def lego():
    return load_scene(require_scene("lego_tiny"))


@pytest.mark.slow
def test_fox(fox):
    scene, caught = fox
    assert scene.format == "instant-ngp" and scene.split == "all"
    _assert_plausible(scene, 50, 240, 135)
    missing = [w for w in caught if "missing" in str(w.message)]
    assert len(missing) == 1 and "17" in str(missing[0].message)
    assert scene.skipped_missing == 17
    assert scene.intrinsics.has_distortion
    assert scene.metadata["aabb_scale"] == 4 and scene.metadata["original_size"] == [1080, 1920]
    assert scene.metadata["downscale"] == 8
    # NGP's box 0.5 +- aabb_scale/2 mapped back through x * 0.33 + 0.5.
    np.testing.assert_allclose(scene.aabb, [[-2 / 0.33] * 3, [2 / 0.33] * 3], rtol=1e-5)
    assert _inside(camera_focus(scene.c2w), scene.aabb)


@pytest.mark.slow
def test_face(face):
    assert face.format == "nerfstudio"
    _assert_plausible(face, 65, 512, 512)
    assert face.applied_transform.shape == (3, 4)
    assert face.metadata["aabb_source"] == "sparse_pc.ply"
    assert _inside(camera_focus(face.c2w), face.aabb)
    assert face.file_names == tuple(sorted(face.file_names))


@pytest.mark.slow
def test_face_point_cloud_is_already_in_the_transforms_world(face):
    """The ply lies in front of the cameras as the poses stand, not after another applied_transform."""
    points = read_ply_points(require_scene("face") / "sparse_pc.ply").astype(np.float64)

    def fraction_in_front(pts):
        cam = np.einsum("nji,npj->npi", face.c2w[:, :3, :3], pts[None] - face.c2w[:, None, :3, 3])
        return float((cam[..., 2] < 0).mean())

    applied = face.applied_transform.astype(np.float64)
    assert fraction_in_front(points) > 0.95
    assert fraction_in_front(points @ applied[:, :3].T + applied[:, 3]) < 0.5


@pytest.mark.slow
def test_garden(garden):
    assert garden.format == "nerfstudio"
    _assert_plausible(garden, 185, 512, 512)
    assert _inside(camera_focus(garden.c2w), garden.aabb)
    # 360 capture: the box of the sparse points holds the cameras' focus and most camera origins.
    assert _inside(garden.c2w[:, :3, 3], garden.aabb).mean() > 0.5


def test_fern_defaults_to_images_8(fern):
    assert fern.format == "llff"
    _assert_plausible(fern, 20, 378, 504)
    assert fern.metadata["image_folder"] == "images_8"
    assert fern.metadata["downscale"] == 8 and fern.metadata["original_size"] == [4032, 3024]
    assert fern.file_names[0] == "images_8/image000.png"
    bounds = np.load(require_scene("fern") / "poses_bounds.npy")[:, 15:]
    np.testing.assert_allclose(fern.near, 0.9 * bounds[:, 0].min(), rtol=1e-6)
    np.testing.assert_allclose(fern.far, bounds[:, 1].max(), rtol=1e-6)
    np.testing.assert_allclose(float(fern.intrinsics.fx), 3260.526 / 8, rtol=1e-4)
    # Forward-facing: the points on each optical axis between near and far lie in the box.
    dirs = -fern.c2w[:, :3, 2]
    for depth in (bounds[:, 0].min(), np.sqrt(bounds[:, 0].min() * bounds[:, 1].max()), bounds[:, 1].max()):
        assert _inside(fern.c2w[:, :3, 3] + depth * dirs, fern.aabb).all()


def test_fern_test_split_and_downscale():
    scene = load_scene(require_scene("fern"), downscale=16, split="test")
    assert scene.images.shape == (3, 189, 252, 3)  # images 0, 8, 16 of 20
    assert scene.metadata["image_folder"] == "images_8"
    np.testing.assert_allclose(float(scene.intrinsics.fx), 3260.526 / 16, rtol=1e-4)


def test_lego_splits(lego):
    assert lego.format == "blender" and lego.split == "train"
    _assert_plausible(lego, 90, 100, 100)
    assert (lego.near, lego.far) == (2.0, 6.0)
    np.testing.assert_array_equal(lego.aabb, [[-1.5] * 3, [1.5] * 3])
    assert lego.alphas.shape == (90, 100, 100)
    np.testing.assert_array_equal(lego.background, [1, 1, 1])
    assert _inside(camera_focus(lego.c2w), lego.aabb)
    test = load_scene(require_scene("lego_tiny"), split="test", background=(0.0, 0.0, 0.0))
    _assert_plausible(test, 10, 100, 100)
    assert test.file_names[0] == "test/r_9.png"


def test_lego_edges_are_straight_alpha():
    """On black, `rgb * a` can never exceed a; the stored rgb does at lego's edges (a third of them)."""
    scene = load_scene(require_scene("lego_tiny"), split="test", background=(0.0, 0.0, 0.0))
    assert np.all(scene.images.max(-1) <= scene.alphas + 1e-6)
    raw = iio.imread(require_scene("lego_tiny") / "test" / "r_9.png").astype(np.float32) / 255
    edge = (raw[..., 3] > 0.05) & (raw[..., 3] < 0.95)
    assert (raw[..., :3].max(-1) > raw[..., 3] + 0.02)[edge].mean() > 0.1


def test_detect_format_of_real_scenes():
    expected = {
        "fox": "instant-ngp",
        "face": "nerfstudio",
        "garden": "nerfstudio",
        "fern": "llff",
        "lego_tiny": "blender",
    }
    for name, fmt in expected.items():
        assert detect_format(require_scene(name)) == fmt


# ------------------------------------------------------------------------------------------------
# Synthetic scenes: behaviour.


def test_transforms_file_path_and_missing_frames(tmp_path):
    frames = [{"file_path": f"images/{i:03d}.png", "transform_matrix": _pose(tx=0.1 * i)} for i in range(12)]
    _transforms_scene(tmp_path, frames=frames)
    (tmp_path / "images" / "003.png").unlink()
    (tmp_path / "images" / "007.png").unlink()
    scene, caught = _load_recording(tmp_path / "transforms.json")
    assert scene.format == "instant-ngp" and scene.n_images == 10 and scene.skipped_missing == 2
    assert len(caught) == 1 and "skipped 2 of 12" in str(caught[0].message)
    assert "images/003.png" not in scene.file_names
    np.testing.assert_allclose(scene.c2w[3, 0, 3], 0.4)  # 003 skipped: fourth image is 004
    test, _ = _load_recording(tmp_path, split="test")
    train, _ = _load_recording(tmp_path, split="train")
    assert test.file_names == ("images/000.png", "images/010.png")  # sorted survivors 0 and 8
    assert len(train.file_names) == 8 and not set(train.file_names) & set(test.file_names)


def test_all_frames_missing(tmp_path):
    _transforms_scene(tmp_path)
    for f in (tmp_path / "images").iterdir():
        f.unlink()
    with pytest.raises(SceneFormatError, match=r"transforms\.json: none of the 3 image files"):
        load_scene(tmp_path)


def test_downscale_is_a_box_filter(tmp_path):
    _transforms_scene(tmp_path, n=2)
    full = load_scene(tmp_path)
    half = load_scene(tmp_path, downscale=2)
    assert half.images.shape == (2, 4, 4, 3)
    expected = full.images.reshape(2, 4, 2, 4, 2, 3).mean(axis=(2, 4))
    np.testing.assert_allclose(half.images, expected, atol=1 / 255 + 1e-6)
    assert (float(half.intrinsics.fx), float(half.intrinsics.cx)) == (4.0, 2.0)
    third = load_scene(tmp_path, downscale=3.0)  # not a divisor: resize(BOX) to round(8 / 3)
    assert third.images.shape == (2, 3, 3, 3)
    np.testing.assert_allclose(float(third.intrinsics.fx), 8 * 3 / 8)
    with pytest.raises(SceneArgumentError, match="downscale"):
        load_scene(tmp_path, downscale=0.5)


def test_grayscale_and_max_images(tmp_path):
    frames = [{"file_path": f"g{i}.png", "transform_matrix": _pose()} for i in range(5)]
    tmp_path.mkdir(exist_ok=True)
    for i in range(5):
        _write_image(tmp_path / f"g{i}.png", channels=1, value=51 * i)
    (tmp_path / "transforms.json").write_text(json.dumps({"camera_angle_x": 1.0, "frames": frames}))
    scene = load_scene(tmp_path, max_images=3)
    assert scene.images.shape == (3, 8, 8, 3)
    assert scene.file_names == ("g0.png", "g2.png", "g4.png")
    np.testing.assert_allclose(scene.images[:, 0, 0], [[0.0] * 3, [0.4] * 3, [0.8] * 3], atol=1e-6)
    np.testing.assert_allclose(float(scene.intrinsics.fx), 4.0 / np.tan(0.5))


def test_instant_ngp_aabb_from_scale_and_offset(tmp_path):
    _transforms_scene(tmp_path, extra={"aabb_scale": 2, "scale": 0.5, "offset": [0.5, 1.0, 0.0]})
    scene = load_scene(tmp_path)
    # NGP box [-0.5, 1.5]^3; world = (ngp - offset) / scale.
    np.testing.assert_allclose(scene.aabb, [[-2.0, -3.0, -1.0], [2.0, 1.0, 3.0]])
    near, far = camera_bounds(scene.c2w, scene.aabb)
    assert (scene.near, scene.far) == pytest.approx((near, far), rel=1e-6)


def test_camera_bounds_outside_box():
    c2w = np.eye(4)[None].copy()
    c2w[0, :3, 3] = (0.0, 0.0, 5.0)
    near, far = camera_bounds(c2w, np.array([[-1.0] * 3, [1.0] * 3]))
    np.testing.assert_allclose(near, 4.0)
    np.testing.assert_allclose(far, np.sqrt(1 + 1 + 36))


def test_nerfstudio_applied_transform_ply_and_intrinsics(tmp_path):
    applied = [[0.0, 1.0, 0.0, 0.0], [1.0, 0.0, 0.0, 0.0], [0.0, 0.0, -1.0, 0.0]]
    frames = [
        {"file_path": f"images/frame_{i:05d}.png", "transform_matrix": _pose(tx=0.1 * i), "fl_x": 9.0} for i in range(3)
    ]
    _transforms_scene(
        tmp_path, frames=frames, extra={"camera_model": "OPENCV", "applied_transform": applied, "k1": 0.1}
    )
    assert detect_format(tmp_path) == "nerfstudio"
    scene = load_scene(tmp_path)
    np.testing.assert_array_equal(scene.applied_transform, applied)
    assert float(scene.intrinsics.fx) == 9.0 and scene.intrinsics.has_distortion
    assert scene.metadata["aabb_source"] == "camera origins and focus"
    assert _inside(scene.c2w[:, :3, 3], scene.aabb).all()
    # A binary point cloud sets the box (1st-99th percentiles, padded by 10%).
    points = np.random.default_rng(0).uniform(-1, 1, (500, 3)).astype(np.float32)
    header = (
        b"ply\nformat binary_little_endian 1.0\nelement vertex 500\nproperty float x\n"
        b"property float y\nproperty float z\nproperty uchar red\nproperty uchar green\n"
        b"property uchar blue\nend_header\n"
    )
    rows = np.zeros(500, [("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("r", "u1"), ("g", "u1"), ("b", "u1")])
    rows["x"], rows["y"], rows["z"] = points.T
    (tmp_path / "sparse_pc.ply").write_bytes(header + rows.tobytes())
    np.testing.assert_array_equal(read_ply_points(tmp_path / "sparse_pc.ply"), points)
    boxed = load_scene(tmp_path)
    lo, hi = np.percentile(points, [1, 99], axis=0)
    np.testing.assert_allclose(boxed.aabb, [lo - 0.1 * (hi - lo), hi + 0.1 * (hi - lo)], rtol=1e-5)
    # Per-frame intrinsics that differ: several cameras are refused.
    frames[2]["fl_x"] = 10.0
    (tmp_path / "transforms.json").write_text(json.dumps({"camera_model": "OPENCV", "frames": frames}))
    with pytest.raises(SceneFormatError, match=r"transforms\.json: per-frame intrinsics differ .*frame 2"):
        load_scene(tmp_path)


def test_ascii_ply(tmp_path):
    text = (
        "ply\nformat ascii 1.0\ncomment hi\nelement vertex 2\nproperty float x\nproperty float y\n"
        "property float z\nproperty uchar red\nend_header\n1 2 3 9\n-4 5.5 6 9\n"
    )
    (tmp_path / "p.ply").write_text(text)
    np.testing.assert_array_equal(read_ply_points(tmp_path / "p.ply"), [[1, 2, 3], [-4, 5.5, 6]])
    (tmp_path / "bad.ply").write_text(text.replace("-4 5.5 6 9\n", ""))
    with pytest.raises(SceneFormatError, match=r"bad\.ply: malformed PLY"):
        read_ply_points(tmp_path / "bad.ply")


@pytest.mark.parametrize("count", [3, 2**63, 10**30], ids=["one-more", "2**63", "10**30"])
def test_a_ply_header_promising_more_vertices_than_the_file_holds_is_refused(tmp_path, count):
    """A binary PLY's vertex count is checked against the file's bytes before NumPy reads it (a count past
    2**63 once overflowed a C integer with a traceback)."""
    header = (
        f"ply\nformat binary_little_endian 1.0\nelement vertex {count}\nproperty float x\nproperty float y\n"
        "property float z\nend_header\n"
    )
    (tmp_path / "p.ply").write_bytes(header.encode() + np.zeros((2, 3), "<f4").tobytes())
    says = rf"p\.ply: malformed PLY vertex data \(the header's {count} vertices need"
    with pytest.raises(SceneFormatError, match=says):
        read_ply_points(tmp_path / "p.ply")


def test_a_ply_header_is_parsed_in_linear_time_and_bounded(tmp_path):
    """47,000 extra properties (a 1 MiB header) parse in well under a second (a quadratic duplicate check
    once took 22 s), and a header without its end in the first MiB is said to be one."""
    import time

    from waldo_jax.scenes.ply import parse_ply_header

    lines = "".join(f"property uchar e{i}\n" for i in range(47000))
    raw = ("ply\nformat binary_little_endian 1.0\nelement vertex 1\n" + lines + "end_header\n").encode()
    start = time.perf_counter()
    header = parse_ply_header(raw, "big.ply")
    assert time.perf_counter() - start < 1.0 and len(header.element("vertex").properties) == 47000
    with pytest.raises(SceneFormatError, match=r"long\.ply: PLY header without 'end_header' in its first 1,048,576"):
        parse_ply_header(b"ply\n" + b"comment x\n" * 200000, "long.ply")


def _blender_scene(folder, rgba, background_split="train"):
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "train").mkdir(exist_ok=True)
    iio.imwrite(folder / "train" / "r_0.png", rgba)
    meta = {"camera_angle_x": 2 * np.arctan(0.5), "frames": [{"file_path": "./train/r_0", "transform_matrix": _pose()}]}
    (folder / f"transforms_{background_split}.json").write_text(json.dumps(meta))


def test_blender_compositing_is_straight_alpha(tmp_path):
    rgba = np.zeros((8, 8, 4), np.uint8)
    rgba[..., :] = (0, 255, 0, 0)  # fully transparent pixels with a garbage colour
    rgba[0, 0] = (255, 0, 0, 255)  # opaque red
    rgba[4, 4] = (255, 255, 255, 102)  # white at alpha 0.4
    _blender_scene(tmp_path, rgba)
    scene = load_scene(tmp_path, background=(0.0, 0.0, 1.0))
    assert scene.format == "blender" and scene.file_names == ("train/r_0.png",)
    np.testing.assert_allclose(scene.images[0, 0, 0], [1, 0, 0], atol=1e-6)
    np.testing.assert_allclose(scene.images[0, 4, 4], [0.4, 0.4, 1.0], atol=1e-6)  # rgb*a + (1-a)*bg
    np.testing.assert_allclose(scene.images[0, 7, 7], [0, 0, 1], atol=1e-6)  # garbage colour hidden
    np.testing.assert_allclose(scene.alphas[0, 4, 4], 0.4, atol=1e-6)
    np.testing.assert_array_equal(scene.background, [0, 0, 1])
    np.testing.assert_allclose(float(scene.intrinsics.fx), 8.0, rtol=1e-6)
    # Downscaling filters premultiplied colour: the transparent green never leaks in.
    half = load_scene(tmp_path, downscale=2, background=(0.0, 0.0, 1.0))
    np.testing.assert_allclose(half.alphas[0, 0, 0], 0.25, atol=1e-6)
    np.testing.assert_allclose(half.images[0, 0, 0], [0.25, 0.0, 0.75], atol=1e-6)
    with pytest.raises(SceneFormatError, match=r"transforms_val\.json: no such file"):
        load_scene(tmp_path, split="val")


# ------------------------------------------------------------------------------------------------
# LLFF.


def _llff_scene(folder, poses_llff, hwf=(24.0, 32.0, 30.0), bounds=(2.0, 10.0), folder_name="images_4"):
    folder.mkdir(parents=True, exist_ok=True)
    n = len(poses_llff)
    table = np.zeros((n, 17))
    for i, pose in enumerate(poses_llff):
        block = np.concatenate([np.asarray(pose, np.float64), np.asarray(hwf)[:, None]], 1)  # [3, 5]
        table[i, :15] = block.reshape(-1)
        table[i, 15:] = bounds
    np.save(folder / "poses_bounds.npy", table)
    for i in range(n):
        _write_image(folder / folder_name / f"img{i:02d}.png", 6, 8)


def test_llff_axes_to_opengl(tmp_path):
    # LLFF columns [down, right, backward] = world x, y, z; OpenGL [right, up, backward] = y, -x, z.
    llff = [[1.0, 0.0, 0.0, 1.0], [0.0, 1.0, 0.0, 2.0], [0.0, 0.0, 1.0, 3.0]]
    # A general rotation built from a known OpenGL c2w.
    angle = 0.3
    gl_rot = np.array([[np.cos(angle), 0, np.sin(angle)], [0, 1, 0], [-np.sin(angle), 0, np.cos(angle)]])
    gl_rot = gl_rot @ np.array([[1, 0, 0], [0, np.cos(0.2), -np.sin(0.2)], [0, np.sin(0.2), np.cos(0.2)]])
    general = np.concatenate([np.stack([-gl_rot[:, 1], gl_rot[:, 0], gl_rot[:, 2]], 1), [[0.5], [-1], [2]]], 1)
    _llff_scene(tmp_path, [llff, general])
    assert detect_format(tmp_path / "poses_bounds.npy") == "llff"
    scene = load_scene(tmp_path)
    expected = np.array([[0, -1, 0, 1], [1, 0, 0, 2], [0, 0, 1, 3], [0, 0, 0, 1]], np.float32)
    np.testing.assert_allclose(scene.c2w[0], expected, atol=1e-7)
    np.testing.assert_allclose(scene.c2w[1, :3, :3], gl_rot, atol=1e-6)
    np.testing.assert_allclose(scene.c2w[1, :3, 3], [0.5, -1, 2], atol=1e-6)
    # Only images_4 (8x6 of a 32x24 capture): focal scaled by 1/4, default uses that folder.
    assert scene.metadata["image_folder"] == "images_4" and scene.metadata["downscale"] == 4
    np.testing.assert_allclose([float(scene.intrinsics.fx), float(scene.intrinsics.cx)], [7.5, 4.0])
    np.testing.assert_allclose([scene.near, scene.far], [1.8, 10.0])
    frustum_far = scene.c2w[:, :3, 3] - 10.0 * scene.c2w[:, :3, 2]
    assert _inside(frustum_far, scene.aabb).all()
    with pytest.raises(SceneFormatError, match=r"downscale 2 needs images/ or images_K .*images_4"):
        load_scene(tmp_path, downscale=2)
    assert load_scene(tmp_path, downscale=8).images.shape == (2, 3, 4, 3)


def test_llff_bad_shape_and_count(tmp_path):
    tmp_path.mkdir(exist_ok=True)
    np.save(tmp_path / "poses_bounds.npy", np.zeros((3, 15)))
    with pytest.raises(SceneFormatError, match=r"poses_bounds\.npy: expected shape \[N, 17\].*\[3, 15\]"):
        load_scene(tmp_path)
    (tmp_path / "poses_bounds.npy").write_bytes(b"not numpy")
    with pytest.raises(SceneFormatError, match=r"poses_bounds\.npy: not a \.npy array \(it starts b'not nu'"):
        load_scene(tmp_path)
    (tmp_path / "poses_bounds.npy").write_bytes(b"\x93NUMPY\x01\x00garbage")  # NumPy's magic, then no header
    with pytest.raises(SceneFormatError, match=r"poses_bounds\.npy: cannot read \.npy"):
        load_scene(tmp_path)
    _llff_scene(tmp_path / "b", [np.eye(3, 4)] * 2)
    (tmp_path / "b" / "images_4" / "img01.png").unlink()
    with pytest.raises(SceneFormatError, match=r"images_4: holds 1 images but poses_bounds\.npy has 2"):
        load_scene(tmp_path / "b")


# ------------------------------------------------------------------------------------------------
# Clear errors.


def test_missing_folder(tmp_path):
    with pytest.raises(SceneFormatError, match=r"nowhere: no such file or folder"):
        load_scene(tmp_path / "nowhere")


def test_unknown_format(tmp_path):
    (tmp_path / "notes.txt").write_text("hello")
    with pytest.raises(SceneFormatError, match=r"unknown scene format.*transforms\.json"):
        detect_format(tmp_path)
    with pytest.raises(SceneFormatError, match=r"notes\.txt: unknown scene format"):
        load_scene(tmp_path / "notes.txt")


def test_malformed_json(tmp_path):
    (tmp_path / "transforms.json").write_text('{\n  "frames": [\n    {"file_path": "a.png",,}\n')
    with pytest.raises(SceneFormatError, match=r"transforms\.json: malformed JSON at line 3, column \d+"):
        load_scene(tmp_path)


def test_no_frames(tmp_path):
    (tmp_path / "transforms.json").write_text(json.dumps({"fl_x": 8, "frames": []}))
    with pytest.raises(SceneFormatError, match=r"transforms\.json: no frames"):
        load_scene(tmp_path)


@pytest.mark.parametrize(
    "matrix, problem",
    [
        ([[2, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]], r"frame 1: pose is not rigid"),
        ([[-1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]], r"frame 1: pose is not rigid.*det = -1"),
        ([[float("nan"), 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]], r"frame 1: pose has non-finite"),
        ([[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0]], r"frame 1: transform_matrix has shape \[3, 4\]"),
        ([[1, 0], [0, 1, 0]], r"frame 1: transform_matrix is not a 4x4"),
        (None, r"frame 1 has no 'transform_matrix'"),
    ],
)
def test_bad_matrix(tmp_path, matrix, problem):
    frames = [{"file_path": "images/000.png", "transform_matrix": _pose()}, {"file_path": "images/001.png"}]
    if matrix is not None:
        frames[1]["transform_matrix"] = matrix
    _transforms_scene(tmp_path, frames=frames)  # json.dumps writes NaN, which json.loads accepts
    with pytest.raises(SceneFormatError, match=r"transforms\.json: " + problem):
        load_scene(tmp_path)


def test_inconsistent_image_sizes(tmp_path):
    _transforms_scene(tmp_path, sizes=[(8, 8), (8, 8), (6, 8)])
    with pytest.raises(SceneFormatError, match=r"002\.png: image is 8x6 but 000\.png is 8x8"):
        load_scene(tmp_path)


def test_corrupt_image(tmp_path):
    _transforms_scene(tmp_path)
    (tmp_path / "images" / "001.png").write_bytes(b"\x89PNG\r\n\x1a\n garbage")
    with pytest.raises(SceneFormatError, match=r"001\.png: cannot read image"):
        load_scene(tmp_path)


def test_an_image_of_several_frames_is_refused_and_a_turned_one_said(tmp_path):
    """A scene image of several frames (an animated PNG or GIF, a multi-page TIFF) is refused by name, as
    `waldo score` refuses one: its first frame had been read silently. An image that viewers show turned
    (EXIF orientation 6) is read as stored, and a warning line says so."""
    from PIL import Image

    _transforms_scene(tmp_path)
    first = tmp_path / "images" / "001.png"
    frames = [Image.fromarray(np.full((8, 8, 3), v, np.uint8)) for v in (0, 255)]
    frames[0].save(first, save_all=True, append_images=frames[1:])  # an APNG
    with pytest.raises(SceneFormatError, match=r"001\.png: an image of several frames"):
        load_scene(tmp_path)
    stored = _write_image(first)
    exif = Image.Exif()
    exif[0x0112] = 6
    Image.fromarray(stored).save(first, exif=exif)
    with pytest.warns(
        UserWarning, match=r"1 of the 3 images \(first: .*001\.png, EXIF orientation 6\) are shown turned"
    ):
        scene = load_scene(tmp_path)
    np.testing.assert_array_equal(np.round(scene.images[1] * 255).astype(np.uint8), stored)  # as stored


@pytest.mark.parametrize(
    "channels, value, says",
    [(4, 0, "are transparent (highest alpha 0, under 1/255)"), (3, 0, "are one colour (0, 0, 0)"), (3, None, None)],
    ids=["transparent", "black", "photos"],
)
def test_images_that_show_nothing_to_learn_warn(tmp_path, channels, value, says):
    """A scene whose images are all transparent, or all one colour, loads with a warning line: a field
    trained on them learns nothing (such a scene trained to 6.7 dB without a word)."""
    _transforms_scene(tmp_path)
    for i in range(3):
        _write_image(tmp_path / "images" / f"{i:03d}.png", channels=channels, value=value)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        load_scene(tmp_path)
    said = [str(w.message) for w in caught if "learns nothing" in str(w.message)]
    assert len(said) == (0 if says is None else 1), said
    assert says is None or said[0].startswith(f"{tmp_path / 'images'}: all 3 images {says}"), said


def test_bad_arguments(tmp_path):
    _transforms_scene(tmp_path)
    with pytest.raises(SceneArgumentError, match="unknown split 'dev'"):
        load_scene(tmp_path, split="dev")
    with pytest.raises(WaldoError, match="background"):
        load_scene(tmp_path, background=(1.0, 0.0))
    with pytest.raises(ValueError, match="max_images"):
        load_scene(tmp_path, max_images=0)


# ------------------------------------------------------------------------------------------------
# Bad input, by kind: every file a scene names or is, every field it reads.


def _nerfstudio_scene(folder, n=8, extra=None, frames=None):
    """A nerfstudio scene of n 8x8 images, cameras on a circle around the origin."""
    if frames is None:
        frames = []
        for i in range(n):
            angle = 2 * np.pi * i / n
            c2w = np.eye(4)
            c2w[:3, :3] = [[np.cos(angle), 0, np.sin(angle)], [0, 1, 0], [-np.sin(angle), 0, np.cos(angle)]]
            c2w[:3, 3] = 3.0 * c2w[:3, 2]
            frames.append({"file_path": f"images/{i:03d}.png", "transform_matrix": c2w.tolist()})
    return _transforms_scene(folder, frames=frames, extra={"camera_model": "OPENCV", **(extra or {})})


def _fifo(path):
    path.unlink(missing_ok=True)
    os.mkfifo(path)


def _loop(path):
    path.unlink(missing_ok=True)
    path.symlink_to(path.name)


def _to_dev_zero(path):
    path.unlink(missing_ok=True)
    path.symlink_to("/dev/zero")


@pytest.mark.parametrize(
    "build, target, says",
    [
        (lambda d: _transforms_scene(d), "transforms.json", "FIFO"),
        (lambda d: _transforms_scene(d), "./transforms.json", "FIFO"),  # the file itself, not its folder
        (lambda d: _transforms_scene(d), "zero:transforms.json", "FIFO, socket or device"),
        (lambda d: _llff_scene(d, [np.eye(3, 4)] * 2), "poses_bounds.npy", "FIFO"),
        (lambda d: _llff_scene(d, [np.eye(3, 4)] * 2), "images_4/img01.png", "FIFO"),
        (lambda d: _llff_scene(d, [np.eye(3, 4)] * 2), "loop:images_4/img01.png", "symbolic link loop"),
        (lambda d: _transforms_scene(d), "images/001.png", "FIFO"),
        (lambda d: _transforms_scene(d), "loop:images/001.png", "symbolic link loop"),
        (lambda d: _nerfstudio_scene(d), "sparse_pc.ply", "FIFO"),
        (lambda d: _blender_split_scene(d), "transforms_train.json", "FIFO"),
    ],
    ids=[
        "transforms-folder",
        "transforms-file",
        "transforms-dev-zero",
        "poses-bounds",
        "llff-image",
        "llff-image-loop",
        "frame-image",
        "frame-image-loop",
        "sparse-pc",
        "blender-split",
    ],
)
def test_a_scene_file_that_is_no_regular_file_is_refused_by_what_it_is(tmp_path, build, target, says):
    """A FIFO, a device or a link loop where a scene names a file is refused before it is opened (a FIFO
    blocked the reader, /dev/zero filled the memory) and said as such, not as missing."""
    build(tmp_path)
    kind, _, name = target.rpartition(":")
    path = tmp_path / name
    {"": _fifo, "loop": _loop, "zero": _to_dev_zero}[kind](path)
    scene_path = path if name.startswith("./") else tmp_path
    with within(), pytest.raises(SceneFormatError, match=re.escape(Path(name).name) + f".*{says}") as caught:
        load_scene(scene_path)
    assert "missing" not in str(caught.value) and "none of" not in str(caught.value)


def _blender_split_scene(folder):
    frames = [{"file_path": f"./train/r_{i}", "transform_matrix": _pose(tx=0.1 * i)} for i in range(2)]
    for i in range(2):
        _write_image(folder / "train" / f"r_{i}.png")
    (folder / "transforms_test.json").write_text(json.dumps({"camera_angle_x": 0.7, "frames": frames}))
    (folder / "transforms_train.json").write_text(json.dumps({"camera_angle_x": 0.7, "frames": frames}))


def test_colmap_and_ply_files_that_are_fifos_are_refused(tmp_path):
    from waldo_jax.scenes.colmap import ColmapCamera, ColmapImage, read_colmap_model, write_colmap_model

    write_colmap_model(tmp_path, [ColmapCamera(1, "PINHOLE", 8, 8, (8.0, 8.0, 4.0, 4.0))], [], binary=False)
    _fifo(tmp_path / "images.txt")
    with within(), pytest.raises(SceneFormatError, match=r"images\.txt: a FIFO"):
        read_colmap_model(tmp_path, ".txt")
    _fifo(tmp_path / "cloud.ply")
    with within(), pytest.raises(SceneFormatError, match=r"cloud\.ply: a FIFO"):
        read_ply_points(tmp_path / "cloud.ply")
    assert ColmapImage  # imported for the layout test below


_MATRIX = _pose()


@pytest.mark.parametrize(
    "extra, frame_edit, says",
    [
        ({"camera_model": ["OPENCV"]}, None, r"'camera_model' must be a string, got list"),
        ({"camera_model": {"name": "OPENCV"}}, None, r"'camera_model' must be a string, got dict"),
        ({"camera_model": None}, None, r"'camera_model' must be a string, got NoneType"),
        ({"fl_x": "8"}, None, r"'fl_x' must be a finite number, got str"),
        ({"fl_x": True}, None, r"'fl_x' must be a finite number, got bool"),
        ({"w": [8]}, None, r"'w' must be a finite number, got list"),
        ({"k1": "0.1"}, None, r"'k1' must be a finite number"),
        ({"aabb_scale": "1"}, None, r"'aabb_scale' must be a finite number"),
        ({"aabb": [["0", "0", "0"], [1, 1, 1]]}, None, r"'aabb' must be"),
        ({"applied_transform": [[True, False, False, 0]] * 3}, None, r"'applied_transform' must be a finite 3x4"),
        ({"from_mitsuba": "yes"}, None, r"'from_mitsuba' must be true or false"),
        ({"ply_file_path": 5, "camera_model": "OPENCV"}, None, r"'ply_file_path' must be a string, got int"),
        ({"frames": {"0": {}}}, None, r"'frames' must be a list, got dict"),
        ({}, {"file_path": 5}, r"frame 1: 'file_path' must be a string, got int"),
        ({}, {"fl_x": "8"}, r"frame 1: 'fl_x' must be a finite number, got str"),
        ({}, {"transform_matrix": [[str(v) for v in row] for row in _MATRIX]}, r"frame 1: transform_matrix is not"),
        ({}, {"transform_matrix": [[bool(v) for v in row] for row in _MATRIX]}, r"frame 1: transform_matrix is not"),
    ],
    ids=lambda v: None if not isinstance(v, str) else v[:24],
)
def test_every_transforms_field_of_the_wrong_type_is_refused_by_name(tmp_path, extra, frame_edit, says):
    """Each field the transforms reader reads is checked for its type (strings are strings, numbers are
    numbers and not booleans, matrices hold numbers: "1" and true are refused, not converted)."""
    _transforms_scene(tmp_path)
    meta = json.loads((tmp_path / "transforms.json").read_text())
    meta.update(extra)
    if frame_edit:
        meta["frames"][1].update(frame_edit)
    (tmp_path / "transforms.json").write_text(json.dumps(meta))
    with pytest.raises(SceneFormatError, match=r"transforms\.json: " + says):
        load_scene(tmp_path)


@pytest.mark.parametrize(
    "name, says",
    [
        ("/", "names a folder"),
        (".", "names a folder"),
        ("..", "names a folder"),
        ("images/", "names a folder"),
        ("", "is empty"),
        ("images/x.png\nwaldo: error: nothing is wrong", r"images/x\.png\\nwaldo: error: nothing is wrong"),
        ("images/\x1b[31mred.png", r"images/\\x1b\[31mred\.png"),
    ],
    ids=["slash", "dot", "dot-dot", "trailing-slash", "empty", "newline", "ansi-escape"],
)
def test_a_file_path_that_names_no_file_is_refused_on_one_line(tmp_path, name, says):
    """A frame's `file_path` must name a file: "/", "." or a name with control characters is refused by
    name (it raised a ValueError), and the name is shown escaped, so that the error stays one line."""
    _transforms_scene(tmp_path)
    meta = json.loads((tmp_path / "transforms.json").read_text())
    meta["frames"][1]["file_path"] = name
    (tmp_path / "transforms.json").write_text(json.dumps(meta))
    with pytest.raises(SceneFormatError, match=r"frame 1: 'file_path' .*" + says) as caught:
        load_scene(tmp_path)
    assert str(caught.value).isprintable()


def test_a_file_path_naming_a_folder_and_escaped_names_in_every_message(tmp_path):
    """A frame image that is a folder is refused by name; a scene folder whose own name holds a newline gives
    errors (and warnings) on one line."""
    _transforms_scene(tmp_path / "a")
    (tmp_path / "a" / "images" / "001.png").unlink()
    (tmp_path / "a" / "images" / "001.png").mkdir()
    with pytest.raises(SceneFormatError, match=r"001\.png: a directory"):
        load_scene(tmp_path / "a")
    odd = tmp_path / "b\nwaldo: error: forged"
    _transforms_scene(odd)
    (odd / "images" / "001.png").write_bytes(b"not a png")
    with pytest.raises(SceneFormatError, match=r"b\\nwaldo: error: forged") as caught:
        load_scene(odd)
    assert str(caught.value).isprintable()


def test_files_whose_content_is_another_format_are_refused_by_name(tmp_path):
    """np.load reads what a file holds: an .npz archive named poses_bounds.npy (an AttributeError) or a
    pickled object array is refused naming the file; so is a text file named .png or .ply."""
    _llff_scene(tmp_path / "npz", [np.eye(3, 4)] * 2)
    table = np.load(tmp_path / "npz" / "poses_bounds.npy")
    np.savez(tmp_path / "npz" / "archive.npz", table)
    os.replace(tmp_path / "npz" / "archive.npz", tmp_path / "npz" / "poses_bounds.npy")
    with pytest.raises(SceneFormatError, match=r"poses_bounds\.npy: not a \.npy array: the file holds a NpzFile"):
        load_scene(tmp_path / "npz")
    _llff_scene(tmp_path / "pickle", [np.eye(3, 4)] * 2)
    np.save(tmp_path / "pickle" / "poses_bounds.npy", np.array([{"a": 1}], dtype=object), allow_pickle=True)
    with pytest.raises(SceneFormatError, match=r"poses_bounds\.npy: cannot read \.npy"):
        load_scene(tmp_path / "pickle")
    (tmp_path / "pickle" / "poses_bounds.npy").write_text("hello world")  # NumPy: "contains pickled (object) data"
    with pytest.raises(SceneFormatError, match=r"poses_bounds\.npy: not a \.npy array \(it starts b'hello '"):
        load_scene(tmp_path / "pickle")
    _transforms_scene(tmp_path / "png")
    (tmp_path / "png" / "images" / "001.png").write_text("hello")
    with pytest.raises(SceneFormatError, match=r"001\.png: cannot read image"):
        load_scene(tmp_path / "png")
    (tmp_path / "cloud.ply").write_bytes(np.zeros(4).tobytes())
    with pytest.raises(SceneFormatError, match=r"cloud\.ply: not a PLY file"):
        read_ply_points(tmp_path / "cloud.ply")


@pytest.mark.parametrize(
    "distortion, says",
    [
        ({"k1": 1e30}, r"k1 = 1e\+30 gives non-finite rays"),
        ({"k1": -5.0}, r"k1 = -5 folds the image"),
        ({"k2": -3.0}, r"k2 = -3 folds the image"),
        ({"p1": 5.0}, r"p1 = 5 cannot be inverted"),
    ],
    ids=["k1-huge", "k1-fold", "k2-fold", "p1-fold"],
)
def test_distortion_that_folds_the_image_or_gives_non_finite_rays_is_refused(tmp_path, distortion, says):
    """Finite distortion coefficients whose map is not one to one over the image (the radius stops
    growing before the corner) or whose inverse overflows float32 (every ray NaN) are refused, naming the
    file and the coefficient; a mild lens loads."""
    _transforms_scene(tmp_path, extra=distortion)
    with pytest.raises(SceneFormatError, match=r"transforms\.json: camera: distortion " + says):
        load_scene(tmp_path)
    _transforms_scene(tmp_path, extra={"k1": 0.05, "k2": -0.02, "p1": 0.001})
    assert load_scene(tmp_path).intrinsics.has_distortion


def test_colmap_images_txt_without_points_lines_keeps_every_image(tmp_path):
    """images.txt with one line per image (its blank POINTS2D lines stripped) lost every second image; both
    layouts now read every image, 2D points lines are still skipped, and a repeated image id is refused."""
    from waldo_jax.scenes.colmap import ColmapCamera, ColmapImage, read_colmap_model, write_colmap_model

    camera = ColmapCamera(1, "PINHOLE", 8, 8, (8.0, 8.0, 4.0, 4.0))
    images = [ColmapImage(i + 1, (1.0, 0.0, 0.0, 0.0), (0.1 * i, 0.0, 4.0), 1, f"im {i}.png") for i in range(5)]
    write_colmap_model(tmp_path, [camera], images, binary=False)
    text = (tmp_path / "images.txt").read_text()
    assert [im.name for im in read_colmap_model(tmp_path, ".txt")[1]] == [im.name for im in images]
    (tmp_path / "images.txt").write_text("\n".join(line for line in text.splitlines() if line.strip()) + "\n")
    assert [im.name for im in read_colmap_model(tmp_path, ".txt")[1]] == [im.name for im in images]
    with_points = [line + ("\n1.5 2.5 -1 3.0 4.0 7" if line[:1].isdigit() else "") for line in text.splitlines()]
    (tmp_path / "images.txt").write_text("\n".join(line for line in with_points if line.strip()) + "\n")
    assert [im.image_id for im in read_colmap_model(tmp_path, ".txt")[1]] == [1, 2, 3, 4, 5]
    repeated = [im._replace(image_id=1) for im in images[:2]]
    write_colmap_model(tmp_path, [camera], repeated, binary=True)
    with pytest.raises(SceneFormatError, match=r"images\.bin: image id 1 appears twice"):
        read_colmap_model(tmp_path, ".bin")
    cameras_bin = (tmp_path / "cameras.bin").read_bytes()
    (tmp_path / "cameras.bin").write_bytes(cameras_bin[:32] + struct.pack("<d", 1e308) + cameras_bin[40:])
    with pytest.raises(SceneFormatError, match=r"cameras\.bin: camera 1: PINHOLE parameter 0 is 1e\+308"):
        read_colmap_model(tmp_path, ".bin")


def test_cameras_at_one_point_warn_and_get_a_box_with_volume(tmp_path):
    """A nerfstudio scene whose cameras all lie at one point (a panorama) spanned a 5e-10 box with
    near/far 1e-11: it warns and gets a cube around the cameras."""
    frames = []
    for i in range(8):
        angle = 2 * np.pi * i / 8
        c2w = np.eye(4)
        c2w[:3, :3] = [[np.cos(angle), 0, np.sin(angle)], [0, 1, 0], [-np.sin(angle), 0, np.cos(angle)]]
        frames.append({"file_path": f"images/{i:03d}.png", "transform_matrix": c2w.tolist()})
    _nerfstudio_scene(tmp_path, frames=frames)
    scene, caught = _load_recording(tmp_path)
    assert [str(w.message) for w in caught if "all 8 cameras lie at one point" in str(w.message)]
    assert np.all(scene.aabb[1] - scene.aabb[0] >= 1.0) and scene.near > 1e-3
    assert "they all lie at one point" in scene.metadata["aabb_source"]


@pytest.mark.parametrize("points", [[[0, 0, 0], [1, 0, 0], [2, 0, 0]], [[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]]])
def test_a_point_cloud_on_a_line_or_plane_warns_and_boxes_the_cameras_too(tmp_path, points):
    """A sparse_pc.ply whose points are collinear (or coplanar) gave a box 0.0004 thick: it warns, and the
    box joins the cameras' box, so that no side is thin."""
    _nerfstudio_scene(tmp_path)
    header = f"ply\nformat binary_little_endian 1.0\nelement vertex {len(points)}\n"
    header += "property float x\nproperty float y\nproperty float z\nend_header\n"
    (tmp_path / "sparse_pc.ply").write_bytes(header.encode() + np.asarray(points, "<f4").tobytes())
    scene, caught = _load_recording(tmp_path)
    assert [w for w in caught if "lie on a line or a plane" in str(w.message) and "sparse_pc.ply" in str(w.message)]
    sides = scene.aabb[1] - scene.aabb[0]
    assert sides.min() >= 0.099 * sides.max()


def test_a_ply_file_path_that_names_no_point_cloud_warns_or_is_refused(tmp_path):
    """`ply_file_path` naming a missing file was passed over silently: it warns (the cameras then bound the
    scene); a folder or a FIFO there is refused by name."""
    _nerfstudio_scene(tmp_path, extra={"ply_file_path": "points/missing.ply"})
    scene, caught = _load_recording(tmp_path)
    assert [w for w in caught if "'ply_file_path' names" in str(w.message) and "missing.ply" in str(w.message)]
    assert scene.metadata["aabb_source"] == "camera origins and focus"
    (tmp_path / "points" / "missing.ply").mkdir(parents=True)
    with pytest.raises(SceneFormatError, match=r"missing\.ply: a directory"):
        load_scene(tmp_path)
    _nerfstudio_scene(tmp_path, extra={"ply_file_path": "/"})
    with pytest.raises(SceneFormatError, match=r"'ply_file_path' '/' names a folder"):
        load_scene(tmp_path)


@pytest.mark.parametrize("fmt", ["instant-ngp", "nerfstudio", "llff"])
def test_split_val_of_a_format_without_one_is_refused(tmp_path, fmt):
    """--split val on a format that holds out only every 8th image as 'test' returned every image, the
    held-out ones included: it is refused, naming the split."""
    if fmt == "llff":
        _llff_scene(tmp_path, [np.eye(3, 4)] * 2)
    elif fmt == "nerfstudio":
        _nerfstudio_scene(tmp_path)
    else:
        _transforms_scene(tmp_path)
    assert detect_format(tmp_path) == fmt
    with pytest.raises(SceneArgumentError, match=rf"split 'val' does not exist in {fmt} scenes"):
        load_scene(tmp_path, split="val")


def test_the_memory_check_counts_the_full_size_decode(tmp_path, monkeypatch):
    """Images are decoded at full size (RGBA as float32 and its temporaries, 48 bytes a pixel) before they
    are downscaled: the check counts that, not only the downscaled images kept."""
    from waldo_jax import errors

    folder = tmp_path / "scene"
    _transforms_scene(folder, n=2)
    for i in range(2):
        iio.imwrite(folder / "images" / f"{i:03d}.png", np.full((128, 128, 4), 200, np.uint8))
    kept = 2 * 16 * 16 * 4 * 4  # what the check counted before: 8 KiB
    monkeypatch.setattr(errors, "host_memory_bytes", lambda: kept + 48 * 128 * 128 // 2)
    with pytest.raises(errors.MemoryBudgetError, match=r"images of 16x16 .* decoded from 128x128 RGBA"):
        load_scene(folder, downscale=8)
    monkeypatch.setattr(errors, "host_memory_bytes", lambda: kept + 48 * 128 * 128)  # one decode at a time fits
    assert load_scene(folder, downscale=8).images.shape == (2, 16, 16, 3)


@pytest.mark.parametrize("suffix", [".Png", ".PNG", ".jpG"])
def test_llff_image_extensions_in_any_case(tmp_path, suffix):
    """LLFF images named *.Png gave "holds 0 images"."""
    _llff_scene(tmp_path, [np.eye(3, 4)] * 2)
    for path in sorted((tmp_path / "images_4").iterdir()):
        if suffix.lower() == ".jpg":
            iio.imwrite(path.with_suffix(suffix), iio.imread(path), extension=".jpg")
            path.unlink()
        else:
            path.rename(path.with_suffix(suffix))
    assert load_scene(tmp_path).n_images == 2
