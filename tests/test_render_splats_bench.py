"""`benchmarks/render_splats.py`: the synthetic part at --quick settings (the JSON, no overflow, positive
views/s, never overwriting), and the scenes part's helpers (pair parsing, train.json defaults, the poses
and camera on lego_tiny) without fitting or training anything."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "benchmarks"))

import render_splats  # noqa: E402
from conftest import require_scene  # noqa: E402


@pytest.mark.slow
def test_quick_synthetic_json(tmp_path):
    out = tmp_path / "splats.json"
    # One population (one compiled render) keeps it short; --quick's own grid is 1 and 4 poses.
    result = render_splats.main(["--quick", "--populations", "4", "--load-threshold", "1000", "--out", str(out)])
    written = json.loads(out.read_text())
    assert written["benchmark"] == "render_splats" and written["synthetic"] == json.loads(
        json.dumps(result["synthetic"])
    )
    for key in (
        "date",
        "commit",
        "device",
        "jax",
        "settings",
        "synthetic",
        "views_per_s",
        "stages",
        "scenes",
        "peak_memory",
        "targets",
        "definitions",
        "loaded",
        "loadavg_start",
    ):
        assert key in written, key
    cells = written["synthetic"]
    assert [(c["count"], c["size"], c["population"], c["status"]) for c in cells] == [(2000, 32, 4, "measured")]
    cell = cells[0]
    assert cell["pair_overflow"] == 0 and cell["lossy_pixels"] == 0 and written["pair_overflow_total"] == 0
    assert cell["views_per_s"] > 0 and cell["rays_per_s"] == pytest.approx(cell["views_per_s"] * 32 * 32)
    assert cell["max_pairs_of_a_view"] <= cell["max_pairs"] and cell["mean_pairs_per_view"] > 0
    assert cell["pose_chunk"] >= 1 and cell["peak_memory_bytes"] > 0 and 0 < cell["mean_acc"] <= 1
    stages = written["stages"]
    assert stages["status"] == "measured" and stages["cell"] == [2000, 32, 4]
    assert stages["render_s"] > 0 and set(stages["fraction"]) == {"project", "tile_lists", "composite"}
    assert sum(stages["fraction"].values()) == pytest.approx(1.0)
    assert written["scenes"] == [] and all(row["met"] is None for row in written["targets"])  # not a GPU, no scenes
    # Never over an earlier result: refused before any measurement.
    with pytest.raises(SystemExit, match="exists"):
        render_splats.main(["--quick", "--out", str(out)])


@pytest.mark.slow
def test_synthetic_scene_is_what_the_docstring_says():
    splats = render_splats.synthetic_splats(1000, sh_degree=1, seed=1)
    means, scales = np.asarray(splats.means), np.asarray(splats.scales())
    assert means.shape == (1000, 3) and np.all(np.abs(means) <= 0.5)
    assert np.exp(np.mean(np.log(scales))) == pytest.approx(0.5 * 1000 ** (-1 / 3), rel=0.05)
    assert np.all((np.asarray(splats.opacities()) >= 0.1 - 1e-6) & (np.asarray(splats.opacities()) <= 0.9 + 1e-6))
    assert splats.sh_degree == 1
    c2w = render_splats.synthetic_poses(16, 50.0)
    distance = np.linalg.norm(c2w[:, :3, 3], axis=1)
    assert c2w.shape == (16, 4, 4) and np.allclose(distance, np.sqrt(3) / 2 / np.sin(np.radians(25)), rtol=1e-5)
    forward = -c2w[:, :3, 2]  # OpenGL: the camera looks along -z, here at the box's centre
    assert np.allclose(forward, -c2w[:, :3, 3] / distance[:, None], atol=1e-5)


def test_pairs_from_the_command_line_and_train_json(tmp_path):
    pair = render_splats.parse_pair("lego=runs/s:runs/n:/data/lego_tiny:2")
    assert pair == render_splats.ScenePair("lego", "runs/s", "runs/n", "/data/lego_tiny", 2.0)
    assert render_splats.parse_pair("fox=a:b") == render_splats.ScenePair("fox", "a", "b")
    for bad in ("a:b", "x=a", "x=:b", "x=a:b:c:1:2"):
        with pytest.raises(ValueError):
            render_splats.parse_pair(bad)
    splat_run, nerf_run = tmp_path / "s", tmp_path / "n"
    splat_run.mkdir()
    nerf_run.mkdir()
    (splat_run / "train.json").write_text(json.dumps({"scene_path": "/data/fox", "downscale": 8}))
    resolved = render_splats.resolve_pair(render_splats.ScenePair("fox", str(splat_run), str(nerf_run)))
    assert (resolved.scene_path, resolved.downscale) == ("/data/fox", 8)
    given = render_splats.resolve_pair(render_splats.ScenePair("fox", str(splat_run), str(nerf_run), "/x", 4.0))
    assert (given.scene_path, given.downscale) == ("/x", 4.0)
    with pytest.raises(SystemExit, match="no scene path"):
        render_splats.resolve_pair(render_splats.ScenePair("n", str(nerf_run), str(nerf_run)))
    args = render_splats.argparse.Namespace(
        pair=["a=s:n"], splat_run=["x/s2"], nerf_run=["x/n2"], scene=["sc"], downscale=None
    )
    assert render_splats.pairs_from_args(args) == [
        render_splats.ScenePair("a", "s", "n"),
        render_splats.ScenePair("s2", "x/s2", "x/n2", "sc", None),
    ]


@pytest.mark.slow
def test_scene_poses_and_camera_on_lego_tiny():
    from render_trained import timing_poses

    from waldo_jax.scenes import load_scene

    path = require_scene("lego_tiny")
    train, test = load_scene(path, split="train"), load_scene(path, split="test")
    n_train, n_test = train.n_images, test.n_images
    poses = render_splats.scene_poses(train.c2w, test.c2w, 256)
    assert poses.shape == (256, 4, 4) and poses.dtype == np.float32 and n_train + n_test + n_train - 1 < 256
    assert np.array_equal(poses[:n_train], train.c2w) and np.array_equal(poses[n_train : n_train + n_test], test.c2w)
    # The first interpolated poses are render_trained.py's midpoints; then t = 1/4 between the first two.
    first = 2 * n_train + n_test - 1
    assert np.allclose(poses[:first], timing_poses(train.c2w, test.c2w, first), atol=1e-6)
    assert np.allclose(poses[first, :3, 3], 0.75 * train.c2w[0, :3, 3] + 0.25 * train.c2w[1, :3, 3], atol=1e-5)
    rotations = poses[:, :3, :3]
    assert np.allclose(rotations @ np.swapaxes(rotations, 1, 2), np.eye(3), atol=1e-5)
    assert len(np.unique(np.round(poses[:, :3, 3], 5), axis=0)) == 256
    camera = render_splats.scene_camera(train.intrinsics, 128)
    assert (camera.width, camera.height) == (128, 128)
    scale = 128 / max(train.intrinsics.width, train.intrinsics.height)
    assert float(camera.fx) == pytest.approx(float(train.intrinsics.fx) * scale)
    assert float(camera.fy) == pytest.approx(float(camera.fx)) and float(camera.cx) == pytest.approx(64.0)
