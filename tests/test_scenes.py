"""Tests of waldo_jax.scenes: the real scenes in $WALDO_DATA and tiny synthetic fixtures."""

from __future__ import annotations

import json
import warnings
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pytest

from conftest import require_scene
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


def test_bad_arguments(tmp_path):
    _transforms_scene(tmp_path)
    with pytest.raises(SceneArgumentError, match="unknown split 'dev'"):
        load_scene(tmp_path, split="dev")
    with pytest.raises(WaldoError, match="background"):
        load_scene(tmp_path, background=(1.0, 0.0))
    with pytest.raises(ValueError, match="max_images"):
        load_scene(tmp_path, max_images=0)
