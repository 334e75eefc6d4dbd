"""Reading and writing 3D Gaussian Splatting scenes (waldo_jax.splats.io) in the reference layout."""

from __future__ import annotations

import json
import os
import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from conftest import _missing
from waldo_jax import paths
from waldo_jax.cameras import look_at
from waldo_jax.errors import SceneFormatError, WaldoError
from waldo_jax.scenes.ply import read_ply_points
from waldo_jax.splats.io import (
    SH_C0,
    SplatCameras,
    load_splat_model,
    read_cameras_json,
    read_splat_ply,
    splat_ply_properties,
    write_cameras_json,
    write_splat_model,
    write_splat_ply,
)
from waldo_jax.splats.model import make_splats, sh_coefficients
from waldo_jax.splats.cameras_json import render_intrinsics
from waldo_jax.splats.upright import extent_problem, robust_bounds
from waldo_jax.types import Intrinsics

DONUT_SPLATS = 45_624


def _require_data(relpath: str):
    """`$WALDO_DATA/<relpath>`, skipping (failing under WALDO_REQUIRE_DATA=1) when absent, as `require_scene`."""
    data = paths.data_dir()
    path = None if data is None else data / relpath
    if path is None or not path.exists():
        _missing(f"data file {relpath!r} ({path or 'WALDO_DATA unset and no ../shared'})")
    return path


MAX_ROWS = 32


def _random_splats(key, n: int, degree: int, valid=None):
    """n <= MAX_ROWS splats with every raw value drawn at random (quaternions far from zero); the
    draws have one shape whatever n and degree, so they compile once."""
    k = jax.random.split(key, 5)
    rows, coefficients = slice(0, n), slice(0, sh_coefficients(degree))
    quats = jax.random.normal(k[2], (MAX_ROWS, 4)) + jnp.array([3.0, 0.0, 0.0, 0.0])
    return make_splats(
        means=np.asarray(jax.random.normal(k[0], (MAX_ROWS, 3)))[rows],
        log_scales=np.asarray(jax.random.uniform(k[1], (MAX_ROWS, 3), minval=-6.0, maxval=0.0))[rows],
        quats=np.asarray(quats)[rows],
        logits=np.asarray(jax.random.normal(k[3], (MAX_ROWS,)) * 3)[rows],
        sh=np.asarray(jax.random.normal(k[4], (MAX_ROWS, 16, 3)))[rows, coefficients],
        valid=valid,
    )


def _header_of(path) -> list:
    raw = path.read_bytes()
    return raw[: raw.index(b"end_header\n") + len(b"end_header\n")].decode("ascii").splitlines()


def _structured_ply(path, table: np.ndarray, fmt: str = "binary_little_endian", count=None, extra_header=b""):
    """Writes a PLY of one vertex element from a structured array, in its field order and types."""
    types = {"f4": "float", "f8": "double", "u1": "uchar", "i4": "int"}
    lines = [
        b"ply",
        f"format {fmt} 1.0".encode(),
        b"comment hand-built",
        extra_header,
        f"element vertex {len(table) if count is None else count}".encode(),
    ]
    lines += [f"property {types[table.dtype[name].str[1:]]} {name}".encode() for name in table.dtype.names]
    header = b"\n".join(line for line in lines if line) + b"\nend_header\n"
    if fmt == "ascii":
        body = "".join(" ".join(repr(float(v)) for v in row) + "\n" for row in table.tolist()).encode()
    else:
        body = table.astype(table.dtype.newbyteorder(">" if fmt == "binary_big_endian" else "<")).tobytes()
    path.write_bytes(header + body)
    return path


def _splat_table(n: int = 5, m: int = 0, names=None) -> np.ndarray:
    """A structured table of reference splat properties (plus f_rest_0..m-1), each column distinct."""
    names = names or (
        ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2"]
        + [f"f_rest_{i}" for i in range(m)]
        + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    )
    table = np.zeros(n, [(name, "<f4") for name in names])
    for j, name in enumerate(names):
        table[name] = np.arange(n) + 100.0 * j
    table["rot_0"] = 1.0
    return table


# ---------------------------------------------------------------------------------------------
# The PLY.


@pytest.mark.slow
@pytest.mark.parametrize("normals", [True, False])
@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_round_trip_keeps_valid_rows_exactly(tmp_path, degree, normals):
    valid = np.array([True, False, True, True, False, True, True])
    splats = _random_splats(jax.random.key(degree), len(valid), degree, valid)
    path = write_splat_ply(tmp_path / "s.ply", splats, normals=normals)
    back = read_splat_ply(path)
    assert back.count == valid.sum() and back.sh_degree == degree and bool(np.all(back.valid))
    for field in ("means", "log_scales", "quats", "logits", "sh"):
        np.testing.assert_array_equal(getattr(back, field), np.asarray(getattr(splats, field))[valid], err_msg=field)
    assert ("property float nx" in _header_of(path)) == normals


@pytest.mark.slow
def test_written_header_is_the_reference_layout(tmp_path):
    splats = _random_splats(jax.random.key(0), 4, 3)
    path = write_splat_ply(tmp_path / "s.ply", splats)
    expected = (
        ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
        + [f"f_rest_{i}" for i in range(45)]
        + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    )
    assert _header_of(path) == (
        ["ply", "format binary_little_endian 1.0", "element vertex 4"]
        + [f"property float {name}" for name in expected]
        + ["end_header"]
    )
    assert splat_ply_properties(3) == expected
    assert path.stat().st_size == len("\n".join(_header_of(path))) + 1 + 4 * len(expected) * 4
    # The rows are the values in that order: channel-major f_rest, normals zero.
    raw = path.read_bytes()
    rows = np.frombuffer(raw[raw.index(b"end_header\n") + 11 :], "<f4").reshape(4, len(expected))
    sh = np.asarray(splats.sh)
    np.testing.assert_array_equal(rows[:, 3:6], 0.0)
    np.testing.assert_array_equal(rows[:, 9:24], sh[:, 1:, 0])  # f_rest_0..14: red
    np.testing.assert_array_equal(rows[:, 24:39], sh[:, 1:, 1])  # green
    np.testing.assert_array_equal(rows[:, -4:], np.asarray(splats.quats))


def test_hand_built_ply_in_shuffled_order_is_read_by_name_channel_major(tmp_path):
    n, k = 6, 9  # degree 2: 24 f_rest
    names = (
        ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2"]
        + [f"f_rest_{i}" for i in range(3 * (k - 1))]
        + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3", "nx", "ny", "nz", "extra"]
    )
    order = np.asarray(jax.random.permutation(jax.random.key(1), len(names)))
    shuffled = [names[i] for i in order]
    # Mixed float and double properties, in a shuffled order.
    table = np.zeros(n, [(name, "<f8" if i % 3 == 0 else "<f4") for i, name in enumerate(shuffled)])
    for name in shuffled:
        table[name] = np.arange(n) * 1000.0 + names.index(name)
    table["rot_0"] = 1.0 + np.arange(n)
    splats = read_splat_ply(_structured_ply(tmp_path / "shuffled.ply", table))
    assert splats.sh_degree == 2 and splats.count == n
    sh = np.asarray(splats.sh)
    for c in range(3):  # f_rest_{c (K-1) + j} is coefficient j + 1 of channel c
        expected = np.stack([table[f"f_rest_{c * (k - 1) + j}"] for j in range(k - 1)], -1)
        np.testing.assert_array_equal(sh[:, 1:, c], expected.astype(np.float32))
    np.testing.assert_array_equal(sh[:, 0, :], np.stack([table[f"f_dc_{c}"] for c in range(3)], -1))
    np.testing.assert_array_equal(splats.means, np.stack([table[c] for c in "xyz"], -1))
    np.testing.assert_array_equal(splats.quats, np.stack([table[f"rot_{i}"] for i in range(4)], -1))
    np.testing.assert_array_equal(splats.logits, table["opacity"].astype(np.float32))
    assert splats.means.dtype == jnp.float32


def test_nerfstudio_rgb_export_gives_dc_from_colours(tmp_path):
    names = (
        ["x", "y", "z", "nx", "ny", "nz", "red", "green", "blue", "opacity"]
        + [f"scale_{i}" for i in range(3)]
        + [f"rot_{i}" for i in range(4)]
    )
    table = np.zeros(3, [(name, "u1" if name in ("red", "green", "blue") else "<f4") for name in names])
    table["red"], table["green"], table["blue"], table["rot_0"] = [0, 128, 255], 255, 0, 1.0
    splats = read_splat_ply(_structured_ply(tmp_path / "rgb.ply", table))
    rgb = SH_C0 * np.asarray(splats.sh)[:, 0, :] + 0.5
    np.testing.assert_allclose(rgb, [[0, 1, 0], [128 / 255, 1, 0], [1, 1, 0]], atol=1e-6)


def test_real_donut():
    splats = read_splat_ply(_require_data("splats/donut/point_cloud.ply"))
    assert splats.count == DONUT_SPLATS and splats.sh_degree == 0
    for field in ("means", "log_scales", "quats", "logits", "sh"):
        assert np.all(np.isfinite(getattr(splats, field))), field
    norms = np.linalg.norm(np.asarray(splats.quats), axis=-1)
    assert 0.6 <= norms.min() < 0.7 and 2.6 < norms.max() <= 2.8  # raw, not normalised
    extent = np.ptp(np.asarray(splats.means), axis=0)
    assert 0.18 < extent[0] < 0.25 and 0.18 < extent[1] < 0.25 and extent[2] < extent[0]  # in the x-y plane


def _not_ply(tmp_path):
    path = tmp_path / "notes.ply"
    path.write_text("hello\n")
    return path


def _case(m=0, names=None, edit=None, **ply_arguments):
    """A builder of a broken PLY: `_splat_table(m, names)`, changed by `edit`, written by `_structured_ply`."""

    def build(tmp_path):
        table = _splat_table(m=m, names=names)
        if edit is not None:
            edit(table)
        return _structured_ply(tmp_path / "bad.ply", table, **ply_arguments)

    return build


def _uchar_opacity(tmp_path):
    table = _splat_table()
    typed = np.zeros(len(table), [(name, "u1" if name == "opacity" else "<f4") for name in table.dtype.names])
    for name in table.dtype.names:
        typed[name] = 1 if name == "opacity" else table[name]
    return _structured_ply(tmp_path / "bad.ply", typed)


def _truncated(tmp_path):
    path = _structured_ply(tmp_path / "bad.ply", _splat_table(n=5))
    path.write_bytes(path.read_bytes()[:-7])
    return path


def _point_cloud(tmp_path):
    table = np.zeros(4, [("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("red", "u1"), ("green", "u1"), ("blue", "u1")])
    return _structured_ply(tmp_path / "bad.ply", table)


def _list_property(tmp_path):
    path = tmp_path / "bad.ply"
    names = _splat_table().dtype.names
    header = (
        "ply\nformat binary_little_endian 1.0\nelement vertex 1\n"
        + "".join(f"property float {p}\n" for p in names)
        + "property list uchar int vertex_indices\nend_header\n"
    )
    path.write_bytes(header.encode() + _splat_table(n=1).tobytes() + bytes([0]))
    return path


def _non_finite(table):
    table["opacity"][3] = np.nan
    table["x"][[1, 2]] = np.inf


def _zero_quaternion(table):
    for i in range(4):
        table[f"rot_{i}"][4] = 0.0


_REST_NAMES = [
    "x",
    "y",
    "z",
    "f_dc_0",
    "f_dc_1",
    "f_dc_2",
    "f_rest_0",
    "f_rest_1",
    "f_rest_2",
    "f_rest_4",
    "opacity",
    "scale_0",
    "scale_1",
    "scale_2",
    "rot_0",
    "rot_1",
    "rot_2",
    "rot_3",
]

BAD_PLY = {
    "not a PLY": (_not_ply, r"not a PLY file"),
    "ascii": (_case(fmt="ascii"), r"ascii PLY is not supported: convert it to binary_little_endian"),
    "big-endian": (
        _case(fmt="binary_big_endian"),
        r"binary_big_endian PLY is not supported: convert it to "
        r"binary_little_endian",
    ),
    "point cloud": (_point_cloud, r"a point cloud, not a splat scene"),
    "missing": (
        _case(
            names=[
                "x",
                "y",
                "z",
                "f_dc_0",
                "f_dc_1",
                "f_dc_2",
                "opacity",
                "scale_0",
                "scale_1",
                "rot_0",
                "rot_1",
                "rot_2",
            ]
        ),
        r"missing splat properties scale_2, rot_3",
    ),
    "no degree": (_case(m=10), r"10 f_rest_\* properties are no SH degree 0\.\.3"),
    "degree 4": (_case(m=72), r"72 f_rest_\* properties are no SH degree 0\.\.3"),
    "f_rest gap": (_case(names=_REST_NAMES), r"f_rest_\* properties are not numbered 0\.\.3: missing f_rest_3"),
    "non-finite": (_case(edit=_non_finite), r"non-finite values .* in 3 of 5 splats: x \(2 rows\), opacity \(1 rows\)"),
    "zero quaternion": (_case(edit=_zero_quaternion), r"a zero quaternion .* in row 4"),
    "truncated": (_truncated, r"truncated: 5 splats of 56 bytes need 280 bytes of data, the file holds 273"),
    "no splats": (_case(count=0), r"no splats \(element vertex 0\)"),
    "list property": (_list_property, r"list properties \(vertex_indices\)"),
    "not float": (_uchar_opacity, r"splat properties must be float or double: opacity is uchar"),
    "compressed": (_case(extra_header=b"element chunk 0\nproperty float min_x"), r"a compressed splat PLY"),
    # f_rest_* indices read as numbers: one index twice, or numbers that are not 0..M-1, refused by name.
    "f_rest twice": (
        _case(names=_REST_NAMES[:6] + ["f_rest_0", "f_rest_00"] + _REST_NAMES[7:9] + _REST_NAMES[10:]),
        r"f_rest_0 and f_rest_00 are the same SH coefficient f_rest_0",
    ),
    "f_rest beyond": (
        _case(names=_REST_NAMES[:6] + ["f_rest_00", "f_rest_01", "f_rest_02", "f_rest_09"] + _REST_NAMES[10:]),
        r"not numbered 0\.\.3: missing f_rest_3 \(f_rest_09 given\)",
    ),
    # A header count smaller than the data: the rest is not silently left out.
    "count fewer": (_case(count=3), r"112 bytes follow its 3 splats of 56 bytes"),
}


@pytest.mark.parametrize("case", list(BAD_PLY))
def test_bad_ply_is_one_clear_line(tmp_path, case):
    build, message = BAD_PLY[case]
    path = build(tmp_path)
    with pytest.raises(SceneFormatError, match=message) as info:
        read_splat_ply(path)
    text = str(info.value)
    assert text.startswith(f"{path}: ") and "\n" not in text


def test_real_point_cloud_is_refused_and_its_colours_read():
    path = _require_data("scenes/face/sparse_pc.ply")
    with pytest.raises(SceneFormatError, match=r"sparse_pc\.ply: a point cloud, not a splat scene"):
        read_splat_ply(path)
    points, colours = read_ply_points(path, colors=True)
    assert points.shape == colours.shape == (9875, 3) and colours.dtype == np.float32
    assert 0.0 <= colours.min() and colours.max() <= 1.0 and np.ptp(colours) > 0.5


def test_point_colours(tmp_path):
    table = np.zeros(3, [("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("red", "u1"), ("green", "u1"), ("blue", "u1")])
    table["x"], table["red"], table["green"], table["blue"] = [1, 2, 3], [0, 51, 255], 255, [10, 20, 30]
    path = _structured_ply(tmp_path / "pc.ply", table)
    assert isinstance(read_ply_points(path), np.ndarray)  # the default is unchanged: positions only
    points, colours = read_ply_points(path, colors=True)
    np.testing.assert_array_equal(points[:, 0], [1, 2, 3])
    np.testing.assert_allclose(colours, [[0, 1, 10 / 255], [0.2, 1, 20 / 255], [1, 1, 30 / 255]], rtol=1e-6)
    ascii_path = _structured_ply(tmp_path / "pc_ascii.ply", table, fmt="ascii")
    np.testing.assert_allclose(read_ply_points(ascii_path, colors=True)[1], colours)
    plain = _structured_ply(tmp_path / "plain.ply", np.zeros(2, [("x", "<f4"), ("y", "<f4"), ("z", "<f4")]))
    assert read_ply_points(plain, colors=True)[1] is None


@pytest.mark.slow
def test_writer_refuses_what_the_reader_would(tmp_path):
    splats = _random_splats(jax.random.key(3), 4, 1)
    broken = splats.replace(logits=splats.logits.at[2].set(jnp.nan), quats=splats.quats.at[1].set(0.0))
    message = r"2 valid splats have non-finite values or a zero quaternion \(first: row 1\)"
    with pytest.raises(WaldoError, match=message):
        write_splat_ply(tmp_path / "s.ply", broken)
    assert not (tmp_path / "s.ply").exists()
    # Marked invalid, the broken rows are left out.
    kept = broken.replace(valid=jnp.array([True, False, False, True]))
    assert read_splat_ply(write_splat_ply(tmp_path / "s.ply", kept)).count == 2
    with pytest.raises(WaldoError, match=r"no valid splats"):
        write_splat_ply(tmp_path / "t.ply", splats.replace(valid=jnp.zeros(4, bool)))


# ---------------------------------------------------------------------------------------------
# cameras.json.


def _random_c2w(key, n: int) -> np.ndarray:
    """n <= 4 random OpenGL camera-to-world matrices [n, 4, 4] (one compiled shape whatever n)."""
    k = jax.random.split(key, 3)
    origins = jax.random.normal(k[0], (4, 3)) * 4
    targets = jax.random.normal(k[1], (4, 3))
    ups = jax.random.normal(k[2], (4, 3))
    return np.asarray(jax.vmap(look_at)(origins, targets, ups))[:n]


@pytest.mark.slow
def test_cameras_round_trip(tmp_path):
    c2w = _random_c2w(jax.random.key(5), 4)
    shared = Intrinsics.create(640, 480, 500.0, 510.0)
    path = write_cameras_json(tmp_path / "cameras.json", c2w, shared, ["a", "b", "c", "d"])
    cameras = read_cameras_json(path)
    np.testing.assert_allclose(cameras.c2w, c2w, atol=1e-6)
    assert cameras.c2w.dtype == np.float32 and cameras.names == ("a", "b", "c", "d") and len(cameras) == 4
    assert cameras.shared_intrinsics.to_dict() == {**shared.to_dict(), "cx": 320.0, "cy": 240.0}
    entries = json.loads(path.read_text())
    assert [e["id"] for e in entries] == [0, 1, 2, 3]
    assert list(entries[0]) == ["id", "img_name", "width", "height", "position", "rotation", "fy", "fx"]
    # Per-camera intrinsics, through a model folder.
    sizes = [Intrinsics.create(64 + 8 * i, 48, 50.0 + i) for i in range(4)]
    back = read_cameras_json(write_cameras_json(tmp_path / "c2.json", c2w, sizes, "abcd"))
    assert [(i.width, i.height, float(i.fx), float(i.fy), float(i.cx)) for i in back.intrinsics] == [
        (64 + 8 * i, 48, 50.0 + i, 50.0 + i, (64 + 8 * i) / 2) for i in range(4)
    ]
    assert back.shared_intrinsics is None


def test_cameras_json_is_opencv_camera_to_world(tmp_path):
    c2w = np.asarray(look_at(jnp.array([0.0, 0.0, 5.0]), jnp.zeros(3), jnp.array([0.0, 1.0, 0.0])))[None]
    path = write_cameras_json(tmp_path / "cameras.json", c2w, Intrinsics.create(32, 32, 30.0), ["front"])
    entry = json.loads(path.read_text())[0]
    rotation, position = np.array(entry["rotation"]), np.array(entry["position"])
    np.testing.assert_allclose(rotation, [[1, 0, 0], [0, -1, 0], [0, 0, -1]], atol=1e-7)
    np.testing.assert_allclose(position, [0, 0, 5], atol=1e-7)
    # The OpenCV z axis (third column) points from the camera to the origin; y points down.
    np.testing.assert_allclose(rotation[:, 2], -position / np.linalg.norm(position), atol=1e-7)
    assert rotation[1, 1] < 0
    np.testing.assert_allclose(read_cameras_json(path).c2w, c2w, atol=1e-7)


def _camera(**overrides):
    entry = {
        "id": 0,
        "img_name": "im",
        "width": 64,
        "height": 48,
        "position": [0, 0, 1],
        "rotation": [[1, 0, 0], [0, -1, 0], [0, 0, -1]],
        "fy": 50.0,
        "fx": 50.0,
    }
    entry.update(overrides)
    return {k: v for k, v in entry.items() if v is not None}


BAD_CAMERAS = {
    "not a list": ({"frames": []}, r"expected a non-empty JSON list of cameras"),
    "not rigid": (
        [_camera(), _camera(rotation=[[2, 0, 0], [0, 1, 0], [0, 0, 1]])],
        r"camera 1 \('im'\): pose is not rigid",
    ),
    "mirror": ([_camera(rotation=[[-1, 0, 0], [0, -1, 0], [0, 0, -1]])], r"camera 0 \('im'\): pose is not rigid"),
    "zero focal": ([_camera(), _camera(), _camera(fx=0.0)], r"camera 2 \('im'\): fx must be a finite focal length"),
    "tiny focal": ([_camera(fy=1e-50)], r"camera 0 \('im'\): fy must be a finite focal length of at least 0\.001"),
    "huge focal": ([_camera(fy=1e300)], r"camera 0 \('im'\): fy must be a finite focal length"),
    "focal past float64": ([_camera(fx=10**400)], r"camera 0 \('im'\): fx must be a finite focal length.*float inf"),
    "small image": (
        [_camera(width=4)],
        r"camera 0 \('im'\): width must be a whole number of pixels between 8 and "
        r"65536",
    ),
    "huge image": ([_camera(height=70000)], r"camera 0 \('im'\): height must be a whole number of pixels"),
    "fractional size": ([_camera(height=47.5)], r"camera 0 \('im'\): height must be a whole number"),
    "missing key": ([_camera(fx=None, position=None)], r"camera 0 \('im'\) lacks position, fx"),
    "bad position": ([_camera(position=[0, "1", 2])], r"camera 0 \('im'\): position must be 3 numbers"),
    "far origin": ([_camera(position=[0, 0, 1e9])], r"camera 0 \('im'\): camera origin has a coordinate of 1e\+09"),
}


@pytest.mark.parametrize("case", list(BAD_CAMERAS))
def test_bad_cameras_json_is_one_clear_line(tmp_path, case):
    content, message = BAD_CAMERAS[case]
    path = tmp_path / "cameras.json"
    path.write_text(json.dumps(content))
    with pytest.raises(SceneFormatError, match=message) as info:
        read_cameras_json(path)
    assert str(info.value).startswith(f"{path}: ") and "\n" not in str(info.value)


# ---------------------------------------------------------------------------------------------
# Model folders.


@pytest.mark.slow
def test_model_folder_takes_the_highest_iteration_numerically(tmp_path):
    cameras = SplatCameras(_random_c2w(jax.random.key(7), 2), (Intrinsics.create(32, 24, 20.0),) * 2, ("p", "q"))
    for iteration in (7000, 30000, 900):
        splats = _random_splats(jax.random.key(iteration), iteration // 1000 + 1, 1)
        write_splat_model(tmp_path / "model", splats, iteration, cameras=cameras if iteration == 7000 else None)
    assert sorted(p.name for p in (tmp_path / "model" / "point_cloud").iterdir()) == [
        "iteration_30000",
        "iteration_7000",
        "iteration_900",
    ]  # so a text sort would pick 900
    model = load_splat_model(tmp_path / "model")
    assert model.iteration == 30000 and model.splats.count == 31
    assert model.ply_path == tmp_path / "model" / "point_cloud" / "iteration_30000" / "point_cloud.ply"
    assert model.cameras.names == ("p", "q") and "iteration 30000" in model.source
    np.testing.assert_allclose(model.cameras.c2w, cameras.c2w, atol=1e-6)
    # The PLY alone finds the cameras two folders up; so does the point_cloud/ folder.
    by_file = load_splat_model(tmp_path / "model" / "point_cloud" / "iteration_900" / "point_cloud.ply")
    assert by_file.iteration == 900 and by_file.splats.count == 1 and by_file.cameras.names == ("p", "q")
    assert load_splat_model(tmp_path / "model" / "point_cloud").iteration == 30000


@pytest.mark.slow
def test_folder_with_point_cloud_ply_and_bare_ply(tmp_path):
    splats = _random_splats(jax.random.key(0), 5, 0)
    write_splat_ply(tmp_path / "flat" / "point_cloud.ply", splats, normals=False)
    model = load_splat_model(tmp_path / "flat")
    assert model.cameras is None and model.iteration is None and model.splats.count == 5
    write_cameras_json(
        tmp_path / "flat" / "cameras.json",
        _random_c2w(jax.random.key(1), 3),
        Intrinsics.create(16, 16, 10.0),
        ["a", "b", "c"],
    )
    assert len(load_splat_model(tmp_path / "flat" / "point_cloud.ply").cameras) == 3


def test_folder_without_a_scene_lists_what_was_looked_for(tmp_path):
    (tmp_path / "empty" / "point_cloud" / "iteration_10").mkdir(parents=True)
    message = (
        r"empty: no splat scene here: looked for point_cloud/iteration_<N>/point_cloud\.ply .* and "
        r"point_cloud\.ply; its point_cloud/ holds no"
    )
    with pytest.raises(SceneFormatError, match=message):
        load_splat_model(tmp_path / "empty")
    with pytest.raises(SceneFormatError, match=r"missing: no such file or folder"):
        load_splat_model(tmp_path / "missing")


# ---------------------------------------------------------------------------------------------
# Inputs found by a bad-input hunt, one test per kind.


@pytest.mark.parametrize("width", [1, 2])
def test_zero_padded_f_rest_indices_are_read_by_number(tmp_path, width):
    """f_rest_00 .. f_rest_08 (zero-padded, as some exporters write) are coefficients 0..8, read like
    f_rest_0 .. f_rest_8 (once a KeyError traceback)."""
    plain = _splat_table(m=9)
    padded = plain.copy()
    padded.dtype.names = [f"f_rest_{int(k[7:]):0{width}d}" if k.startswith("f_rest_") else k for k in plain.dtype.names]
    a = read_splat_ply(_structured_ply(tmp_path / "plain.ply", plain))
    b = read_splat_ply(_structured_ply(tmp_path / "padded.ply", padded))
    np.testing.assert_array_equal(np.asarray(a.sh), np.asarray(b.sh))


@pytest.mark.parametrize("value", [1e38, 1e-30])
def test_quaternions_beyond_float32_squares_keep_their_rotation(tmp_path, value):
    """rot_0..3 all 1e38 (their squares overflow float32) or 1e-30 (underflow) are the rotation of all 0.5;
    they once became the identity (1e38) or a refused 'zero quaternion' (1e-30)."""
    big, half = _splat_table(), _splat_table()
    for i in range(4):
        big[f"rot_{i}"], half[f"rot_{i}"] = value, 0.5
    a = read_splat_ply(_structured_ply(tmp_path / "big.ply", big))
    b = read_splat_ply(_structured_ply(tmp_path / "half.ply", half))
    np.testing.assert_allclose(np.asarray(a.rotations()), np.asarray(b.rotations()), rtol=1e-6)
    assert np.all(np.isfinite(np.asarray(a.quats)))


def test_a_fifo_where_cameras_json_lies_is_refused_not_waited_on(tmp_path):
    """A FIFO named cameras.json beside the PLY: one line naming it (a reader blocked on one forever)."""
    ply = write_splat_ply(tmp_path / "s.ply", _random_splats(jax.random.key(0), 8, 0))
    os.mkfifo(tmp_path / "cameras.json")
    with pytest.raises(WaldoError, match=r"cameras\.json: a FIFO, socket or device"):
        load_splat_model(ply)


def _cameras(path, c2w, width=64, height=48, focal=51.5):
    entries = [
        {
            "id": i,
            "img_name": f"im{i}",
            "width": width,
            "height": height,
            "position": m[:3, 3].tolist(),
            "rotation": m[:3, :3].tolist(),
            "fx": focal,
            "fy": focal,
        }
        for i, m in enumerate(np.asarray(c2w, np.float64))
    ]
    path.write_text(json.dumps(entries))
    return path


def _opencv_ring(count=4, distance=5.0):
    """c2w [count, 4, 4] in cameras.json's OpenCV axes, on a ring around the origin looking at it."""
    poses = []
    for i in range(count):
        angle = 2 * np.pi * i / count
        origin = np.array([distance * np.cos(angle), distance * np.sin(angle), 1.0])
        gl = np.asarray(look_at(jnp.asarray(origin), jnp.zeros(3), jnp.array([0.0, 0.0, 1.0])), np.float64)
        cv = np.eye(4)
        cv[:3, :4] = gl[:3, :4]
        cv[:3, 1:3] *= -1.0
        poses.append(cv)
    return np.stack(poses)


@pytest.mark.parametrize("size", [(8, 65536), (65536, 8), (16, 9000)])
def test_a_camera_no_render_size_can_show_is_refused_by_name(tmp_path, size):
    """A camera whose shorter side falls under MIN_RESOLUTION at every render size (8 x 65536: 1 pixel wide
    at 256) is refused naming cameras.json and the camera; one that fits some sizes is refused at the others
    by `render_intrinsics`, naming the --resolution that fits."""
    path = _cameras(tmp_path / "cameras.json", _opencv_ring(), width=size[0], height=size[1], focal=20000.0)
    with pytest.raises(
        SceneFormatError, match=r"cameras\.json: camera 0 \('im0'\): an image of .* renders, at most 4096"
    ):
        read_cameras_json(path)
    fits = Intrinsics.create(8, 200, 400.0, 400.0)
    assert render_intrinsics(fits, 200, path, "camera 0").width == 8
    with pytest.raises(SceneFormatError, match=r"camera 0: an image of 8x200 pixels renders at 3x64 .*at least 200"):
        render_intrinsics(fits, 64, path, "camera 0")


def test_cameras_that_all_face_away_from_the_splats_warn(tmp_path):
    """cameras.json written with OpenGL rotations (z backward) where OpenCV's are expected: no splat centre in
    front of any camera, a warning line; the same cameras in OpenCV axes load silently."""
    splats = _random_splats(jax.random.key(1), 32, 0)
    splats = splats.replace(means=splats.means * 0.1)
    ply = write_splat_ply(tmp_path / "s.ply", splats)
    good = _opencv_ring()
    _cameras(tmp_path / "cameras.json", good)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        load_splat_model(ply)
    flipped = good.copy()
    flipped[:, :3, 1:3] *= -1.0  # OpenGL rotations
    _cameras(tmp_path / "cameras.json", flipped)
    with pytest.warns(UserWarning, match=r"no splat centre is in front of any of the 4 cameras"):
        load_splat_model(ply)


@pytest.mark.parametrize("case", ["one splat", "one point"])
def test_a_scene_of_one_point_warns_and_is_flagged(tmp_path, case):
    """One splat, or every splat at one point: a ring of views cannot frame it (it once sat 2.6e-6 from the
    centre, inside the near plane: every render the background, exit 0): a warning and `degenerate`."""
    splats = _random_splats(jax.random.key(2), 1 if case == "one splat" else 16, 0)
    splats = splats.replace(means=jnp.full_like(splats.means, 0.5))
    ply = write_splat_ply(tmp_path / "s.ply", splats)
    with pytest.warns(UserWarning, match=r"a scene of one point, which no view frames"):
        model = load_splat_model(ply)
    assert "every render of a ring around it is the background alone" in model.degenerate


def test_robust_bounds_leave_far_strays_and_non_finite_means_out():
    """A quarter of the splats at 1e30 set the 98 % quantile (and the ring) 1e30 away; robust bounds leave
    them out, and the bounds of a scene without strays are the plain quantiles, bit for bit."""
    rng = np.random.default_rng(0)
    means = rng.normal(size=(2000, 3))
    low, high = robust_bounds(means)
    np.testing.assert_array_equal(low, np.quantile(means, 0.02, axis=0))
    np.testing.assert_array_equal(high, np.quantile(means, 0.98, axis=0))
    far = means.copy()
    far[:500, 0] = 1e30
    far[500, 1] = np.inf
    low, high = robust_bounds(far)
    assert np.all(np.abs(low) < 5) and np.all(np.abs(high) < 5), (low, high)
    assert extent_problem(far) is None and extent_problem(np.ones((5, 3))) is not None


@pytest.mark.parametrize(
    "line, says",
    [
        ("format binary_little_endian 2.0", "expected version 1.0"),  # was read as 1.0
        ("format binary_little_endian", "expected version 1.0"),
        ("format ascii 1.0 extra", "expected version 1.0"),
        ("format binary_middle_endian 1.0", "unsupported PLY format 'binary_middle_endian'"),
    ],
)
def test_a_ply_format_line_of_another_version_or_kind_is_refused(tmp_path, line, says):
    from waldo_jax.errors import SceneFormatError
    from waldo_jax.scenes.ply import parse_ply_header

    raw = f"ply\n{line}\nelement vertex 1\nproperty float x\nend_header\n".encode() + b"\0" * 4
    with pytest.raises(SceneFormatError, match=says):
        parse_ply_header(raw, tmp_path / "a.ply")


def test_a_ply_format_version_written_as_1_is_read():
    from waldo_jax.scenes.ply import parse_ply_header

    raw = b"ply\nformat binary_little_endian 1\nelement vertex 1\nproperty float x\nend_header\n" + b"\0" * 4
    assert parse_ply_header(raw, "a.ply").format == "binary_little_endian"
