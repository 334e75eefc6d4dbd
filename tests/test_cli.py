"""The `waldo` command line: help, scene info, procedural render, one-line errors."""

import json
import subprocess
import sys

import imageio.v3 as iio
import pytest

from conftest import require_scene
from waldo_jax.cli import main
from waldo_jax.pipeline.sources import parse_procedural
from waldo_jax.errors import WaldoError


def run_cli(*args):
    return subprocess.run([sys.executable, "-m", "waldo_jax", *args], capture_output=True, text=True, timeout=300)


@pytest.mark.slow
def test_help_lists_working_commands():
    result = run_cli("--help")
    assert result.returncode == 0
    assert "scene" in result.stdout and "render" in result.stdout


@pytest.mark.slow
def test_bad_path_is_one_line_error_without_traceback(tmp_path):
    result = run_cli("scene", "info", str(tmp_path / "nope"))
    assert result.returncode == 1
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("waldo: error:") and "nope" in lines[0]
    assert "Traceback" not in result.stderr


@pytest.mark.slow
def test_malformed_scene_is_one_line_error(tmp_path):
    (tmp_path / "transforms.json").write_text("{ not json")
    result = run_cli("scene", "info", str(tmp_path))
    assert result.returncode == 1 and "Traceback" not in result.stderr
    assert "transforms.json" in result.stderr


@pytest.mark.parametrize(
    "name,count,width,height,skipped,fmt",
    [
        ("fox", 50, 1080, 1920, 17, "instant-ngp"),
        ("fern", 20, 504, 378, 0, "llff"),
        ("lego_tiny", 90, 100, 100, 0, "blender"),
        ("face", 65, 512, 512, 0, "nerfstudio"),
        ("garden", 185, 512, 512, 0, "nerfstudio"),
    ],
)
@pytest.mark.slow
def test_scene_info_json(capsys, name, count, width, height, skipped, fmt):
    path = require_scene(name)
    args = ["scene", "info", str(path), "--json"]
    if name == "fox":  # keep the test light: downscaled images, full-size intrinsics are checked elsewhere
        args += ["--downscale", "8"]
        width, height = 135, 240
    assert main(args) == 0
    out = capsys.readouterr().out
    info = json.loads(out)  # exactly one JSON object on stdout
    assert info["format"] == fmt and info["n_images"] == count
    assert (info["width"], info["height"]) == (width, height)
    assert info["skipped_missing"] == skipped


def test_parse_procedural():
    assert parse_procedural("procedural") == 0
    assert parse_procedural("procedural:7") == 7
    assert parse_procedural("procedural", 3) == 3
    assert parse_procedural("runs/fox") is None
    with pytest.raises(WaldoError):
        parse_procedural("procedural:x")
    with pytest.raises(WaldoError):
        parse_procedural("procedural:1", 2)


def test_render_procedural_renders_large_views_in_strips_and_says_the_time_left(tmp_path, capsys, monkeypatch):
    """A view larger than a call's rays renders in strips of rows (its camera's principal point moved):
    the PNGs equal the whole views' bit for bit and the room's own `room_scene` render; after the first
    call that compiles nothing a line says how long the rest will take (`waldo render procedural
    --resolution 4096` said nothing for 1.7 hours on a 2-core CPU)."""
    import numpy as np

    from waldo_jax import io
    from waldo_jax.cli import render
    from waldo_jax.procedural import room_scene

    args = ["render", "procedural:2", "--views", "2", "--resolution", "24", "--samples", "16"]
    assert main(args + ["--out", str(tmp_path / "whole")]) == 0
    assert "left" not in capsys.readouterr().err  # one call: nothing to estimate
    monkeypatch.setattr(render, "RENDER_GROUP_PIXELS", 24 * 5)  # strips of 5 rows, the last one cropped
    monkeypatch.setattr(render, "ESTIMATE_EVERY_S", 0.0)
    assert render.render_calls(2, render.Intrinsics.create(24, 24, 20.0)) == (1, 5)
    assert main(args + ["--out", str(tmp_path / "strips")]) == 0
    err = capsys.readouterr().err
    assert "0.00 G samples" in err and "2 of 10 calls done (the first, compiling, took" in err and "left" in err
    scene, _ = room_scene(2, num_views=2, resolution=24, num_samples=16)
    for i in range(2):
        whole = iio.imread(tmp_path / "whole" / f"view_{i:03d}.png")
        assert np.array_equal(whole, iio.imread(tmp_path / "strips" / f"view_{i:03d}.png"))
        assert np.array_equal(whole, iio.imread(io.png_bytes(scene.images[i])))


@pytest.mark.slow
def test_render_procedural_writes_views_sheet_and_refuses_to_overwrite(tmp_path, capsys):
    out = tmp_path / "room"
    args = ["render", "procedural:2", "--views", "3", "--resolution", "16", "--samples", "32", "--out", str(out)]
    assert main(args) == 0
    names = sorted(p.name for p in out.iterdir())
    assert names == [
        "contact_sheet.png",
        "room.json",
        "transforms.json",
        "view_000.png",
        "view_001.png",
        "view_002.png",
    ]
    assert iio.imread(out / "view_000.png").shape == (16, 16, 3)
    room = json.loads((out / "room.json").read_text())
    assert room["seed"] == 2 and len(room["waldo_visibility"]) == 3
    assert max(room["waldo_visibility"]) <= 0.5
    # The written folder is itself a loadable scene.
    from waldo_jax.scenes import load_scene

    scene = load_scene(out)
    assert scene.n_images == 3 and scene.images.shape[1:] == (16, 16, 3)
    # A second run into the same folder is refused with a clear message, unless --force.
    capsys.readouterr()
    assert main(args) == 1
    err = capsys.readouterr().err
    assert "not empty" in err and "--force" in err
    assert main(args + ["--force"]) == 0
