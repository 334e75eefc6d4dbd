"""`scenes.read_poses_file`: the cameras of a transforms.json-like file, with clear errors."""

import json
import math
import os

import numpy as np
import pytest

import waldo_jax  # noqa: F401
from waldo_jax.errors import SceneFormatError
from waldo_jax.scenes import read_poses_file
from waldo_jax.types import Intrinsics

DEFAULT = Intrinsics.create(40, 30, 35.0, 35.0)


def _rotation_y(angle):
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def _c2w(angle, origin):
    m = np.eye(4)
    m[:3, :3] = _rotation_y(angle)
    m[:3, 3] = origin
    return m


def _write(tmp_path, meta, name="poses.json"):
    path = tmp_path / name
    path.write_text(json.dumps(meta))
    return path


def test_valid_file_gives_poses_intrinsics_and_names(tmp_path):
    a, b = _c2w(0.3, [1.0, 2.0, 3.0]), _c2w(-1.2, [0.0, -1.0, 4.0])
    path = _write(
        tmp_path,
        {
            "w": 20,
            "h": 10,
            "fl_x": 18.0,
            "cx": 9.0,
            "k1": 0.01,
            "frames": [
                {"file_path": "images/a.png", "transform_matrix": a.tolist()},
                {"transform_matrix": b[:3].tolist()},  # 3x4: the bottom row is added
            ],
        },
    )
    c2w, intrinsics, names = read_poses_file(path, DEFAULT)
    assert c2w.dtype == np.float32 and c2w.shape == (2, 4, 4)
    np.testing.assert_allclose(c2w[0], a, atol=1e-6)
    np.testing.assert_allclose(c2w[1], b, atol=1e-6)
    assert names == ["images/a.png", None]
    assert (intrinsics.width, intrinsics.height) == (20, 10)
    assert float(intrinsics.fx) == pytest.approx(18.0) and float(intrinsics.fy) == pytest.approx(18.0)
    assert float(intrinsics.cx) == pytest.approx(9.0)
    assert float(np.asarray(intrinsics.distortion)[0]) == pytest.approx(0.01)


def test_the_world_a_file_records_comes_with_its_poses_from_one_parse(tmp_path, monkeypatch):
    """`load_poses_file` reads a poses.json of `waldo explore` / `waldo path` and waldo's camera paths once:
    the poses, and the `source_world` their block records (None where none is recorded)."""
    from waldo_jax.scenes import load_poses_file, poses_file
    from waldo_jax.scenes.camera_paths import nerfstudio_camera_path

    frames = [{"transform_matrix": _c2w(0.1 * i, [i, 0.0, 1.0]).tolist()} for i in range(3)]
    files = {
        "explore": {"frames": frames, "waldo_explore": {"source_world": "procedural:4"}},
        "path": {"frames": frames, "waldo_path": {"source_world": str(tmp_path)}},
        "camera_path": nerfstudio_camera_path(
            np.stack([_c2w(0.2 * i, [0.0, i, 2.0]) for i in range(3)]),
            DEFAULT,
            24.0,
            extra={"source_world": "procedural:7"},
        ),
        "other tool": {"frames": frames},
    }
    parses = []
    reader = poses_file.read_json_file
    monkeypatch.setattr(poses_file, "read_json_file", lambda *a, **k: parses.append(a[0]) or reader(*a, **k))
    for (name, meta), world in zip(files.items(), ["procedural:4", str(tmp_path), "procedural:7", None]):
        parses.clear()
        loaded = load_poses_file(_write(tmp_path, meta, f"{name.replace(' ', '_')}.json"), DEFAULT)
        assert loaded.world == world and loaded.c2w.shape == (3, 4, 4), name
        assert len(parses) == 1, name
        c2w, intrinsics, names = read_poses_file(tmp_path / f"{name.replace(' ', '_')}.json", DEFAULT)
        np.testing.assert_array_equal(c2w, loaded.c2w)
        assert names == loaded.file_names and intrinsics.width == loaded.intrinsics.width


def test_an_off_image_principal_point_is_warned_at_the_readers_caller(tmp_path):
    """The warning names the line that called `read_poses_file` or `load_poses_file` (this file), not the
    reader's own code."""
    from waldo_jax.scenes import load_poses_file

    path = _write(
        tmp_path, {"w": 16, "h": 16, "fl_x": 20.0, "cx": 500.0, "frames": [{"transform_matrix": np.eye(4).tolist()}]}
    )
    for reader in (read_poses_file, load_poses_file):
        with pytest.warns(UserWarning, match="principal point") as caught:
            reader(path, DEFAULT)
        assert [w.filename for w in caught] == [__file__], reader.__name__


def test_file_without_focal_length_uses_the_default_camera(tmp_path):
    path = _write(tmp_path, {"frames": [{"transform_matrix": np.eye(4).reshape(-1).tolist()}]})  # 16 numbers
    c2w, intrinsics, _ = read_poses_file(path, DEFAULT)
    np.testing.assert_array_equal(c2w[0], np.eye(4))
    assert intrinsics is DEFAULT


def test_camera_angle_and_missing_size_follow_the_default_camera(tmp_path):
    path = _write(tmp_path, {"camera_angle_x": 1.0, "frames": [{"transform_matrix": np.eye(4).tolist()}]})
    _, intrinsics, _ = read_poses_file(path, DEFAULT)
    assert (intrinsics.width, intrinsics.height) == (DEFAULT.width, DEFAULT.height)
    assert float(intrinsics.fx) == pytest.approx(0.5 * DEFAULT.width / math.tan(0.5))


def test_missing_transform_matrix_names_the_file_and_frame(tmp_path):
    path = _write(tmp_path, {"frames": [{"transform_matrix": np.eye(4).tolist()}, {"file_path": "b.png"}]})
    with pytest.raises(SceneFormatError, match=r"poses\.json: frame 1 has no 'transform_matrix'") as info:
        read_poses_file(path, DEFAULT)
    assert info.value.path == str(path)


@pytest.mark.parametrize(
    "matrix, problem",
    [
        ([[1, 0], [0, 1]], r"frame 0 transform_matrix has shape \[2, 2\], expected 4x4"),
        ([[1, 0, 0, 0]] * 3, "pose is not rigid"),
        ([[1, 0, 0, float("nan")], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]], "non-finite"),
        ([["a", 0, 0, 0]] * 4, "not a matrix of numbers"),
    ],
)
def test_bad_matrix_is_refused_naming_the_problem(tmp_path, matrix, problem):
    path = tmp_path / "bad.json"
    path.write_text(json.dumps({"frames": [{"transform_matrix": matrix}]}))
    with pytest.raises(SceneFormatError, match=r"bad\.json: .*" + problem):
        read_poses_file(path, DEFAULT)


def test_mirrored_rotation_is_refused(tmp_path):
    m = np.diag([1.0, 1.0, -1.0, 1.0])  # orthonormal but det -1
    path = _write(tmp_path, {"frames": [{"transform_matrix": m.tolist()}]})
    with pytest.raises(SceneFormatError, match="pose is not rigid"):
        read_poses_file(path, DEFAULT)


def test_nerfstudio_camera_path_is_refused(tmp_path):
    path = _write(
        tmp_path,
        {
            "camera_type": "perspective",
            "render_height": 10,
            "render_width": 20,
            "camera_path": [{"camera_to_world": np.eye(4).reshape(-1).tolist(), "fov": 50}],
        },
        name="render-path.json",
    )
    with pytest.raises(SceneFormatError, match=r"render-path\.json: a nerfstudio camera path"):
        read_poses_file(path, DEFAULT)


@pytest.mark.parametrize(
    "content, problem",
    [
        (None, "no such poses file"),
        ("{not json", "malformed JSON at line 1"),
        ("[1, 2]", "expected a JSON object"),
        ('{"frames": []}', "'frames' is empty"),
        ('{"cameras": []}', "no 'frames' list"),
        (
            '{"fl_x": -3, "frames": [{"transform_matrix": [[1,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]]}]}',
            "'fl_x' must be a positive number",
        ),
        (
            '{"fl_x": true, "frames": [{"transform_matrix": [[1,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]]}]}',
            "'fl_x' must be a finite number",
        ),
    ],
)
def test_unusable_files_are_refused_naming_the_file(tmp_path, content, problem):
    path = tmp_path / "poses.json"
    if content is not None:
        path.write_text(content)
    with pytest.raises(SceneFormatError, match=problem) as info:
        read_poses_file(path, DEFAULT)
    assert str(path) in str(info.value)


_EYE = np.eye(4).tolist()


@pytest.mark.parametrize(
    "meta, problem",
    [
        ({"fl_x": 20, "w": 16, "h": 16, "k1": 1e30}, r"camera: distortion k1 = 1e\+30 gives non-finite rays"),
        ({"fl_x": 20, "w": 16, "h": 16, "k1": -5}, r"camera: distortion k1 = -5 folds the image"),
        ({"frames": [{"transform_matrix": [[str(v) for v in row] for row in _EYE]}]}, r"frame 0 .*not a matrix"),
        ({"frames": [{"transform_matrix": [[bool(v) for v in row] for row in _EYE]}]}, r"frame 0 .*not a matrix"),
        ({"frames": [{"transform_matrix": _EYE, "file_path": ["a.png"]}]}, r"'file_path' must be a string"),
        # A camera the file gives in part, or per frame, was dropped for the default camera without a word.
        ({"w": 64, "h": 32, "cx": 5, "k1": 0.3}, r"camera keys w, h, cx, k1 without a focal length"),
        (
            {"fl_x": 20, "w": 16, "h": 16, "frames": [{"transform_matrix": _EYE, "fl_x": 40}]},
            r"frame 0 has its own camera",
        ),
    ],
    ids=["k1-huge", "k1-fold", "matrix-of-strings", "matrix-of-booleans", "file-path-list", "no-focal", "per-frame"],
)
def test_unusable_lenses_and_fields_of_the_wrong_type_are_refused(tmp_path, meta, problem):
    """A lens whose rays are not finite (k1 = 1e30 rendered blank PNGs, exit 0) or that folds the image is
    refused naming the file and the coefficient; a matrix of strings or booleans is refused, not converted."""
    meta = {"frames": [{"transform_matrix": _EYE}], **meta}
    path = _write(tmp_path, meta)
    with pytest.raises(SceneFormatError, match=problem) as info:
        read_poses_file(path, DEFAULT)
    assert str(path) in str(info.value)


def test_a_poses_file_that_is_a_fifo_is_refused_without_blocking(tmp_path):
    os.mkfifo(tmp_path / "poses.json")
    with pytest.raises(SceneFormatError, match=r"poses\.json: a FIFO"):
        read_poses_file(tmp_path / "poses.json", DEFAULT)


def test_a_fractional_image_side_is_refused(tmp_path):
    """A camera of 16.5 x 16 pixels had rendered at 16 x 16 in silence."""
    meta = {"w": 16.5, "h": 16, "fl_x": 20.0, "frames": [{"transform_matrix": np.eye(4).tolist()}]}
    with pytest.raises(SceneFormatError, match=r"'w' must be a whole number of pixels, got 16.5"):
        read_poses_file(_write(tmp_path, meta), DEFAULT)
    meta.update(w=16.0)  # a whole number written as a float is one
    assert read_poses_file(_write(tmp_path, meta), DEFAULT)[1].width == 16
