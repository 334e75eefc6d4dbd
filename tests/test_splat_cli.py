"""Splat scenes through the CLI: `waldo train --model splat`, then `explore`, `path`, `render` and `score`
on a fitted run, on the real donut and on a reference-layout folder; what results.json says; errors."""

import json
import shutil

import imageio.v3 as iio
import numpy as np
import pytest

from conftest import built_once, require_scene
from waldo_jax import paths
from waldo_jax.cli import main
from waldo_jax.pipeline import load_source
from waldo_jax.pipeline.splat_sources import SPLAT_GRADIENT_COST
from waldo_jax.scenes import load_scene
from waldo_jax.splats.io import load_splat_model, read_cameras_json, write_cameras_json
from waldo_jax.types import Intrinsics

TINY = ["--resolution", "24", "--epochs", "2", "--children-per-epoch", "6", "--top-k", "4", "--quiet"]


def require_donut():
    data = paths.data_dir()
    path = None if data is None else data / "splats" / "donut" / "point_cloud.ply"
    if path is None or not path.exists():
        if paths.require_data():
            pytest.fail(f"the donut splats are missing ({path}) and WALDO_REQUIRE_DATA=1", pytrace=False)
        pytest.skip("the donut splats not found (set WALDO_DATA to the folder holding splats/)")
    return path


@pytest.fixture(scope="module")
def fitted(tmp_path_factory):
    """lego_tiny fitted with splats once per session: a short fit, enough for real surfaces."""
    lego = require_scene("lego_tiny")

    def build(folder):
        assert (
            main(
                [
                    "train",
                    str(lego),
                    "--model",
                    "splat",
                    "--steps",
                    "60",
                    "--capacity",
                    "2048",
                    "--out",
                    str(folder),
                    "--quiet",
                ]
            )
            == 0
        )

    return built_once(tmp_path_factory, "splat_lego_fit", build)


@pytest.mark.slow
def test_a_fit_writes_the_reference_layout_that_reads_back(fitted):
    record = json.loads((fitted / "train.json").read_text())
    assert (fitted / "point_cloud" / "iteration_60" / "point_cloud.ply").is_file()
    assert record["model"] == "splat" and record["steps"] == 60
    assert record["psnr_test"] is not None and record["psnr_test"] > 10.0  # far above an empty render (~6 dB)
    assert record["n_test"] == 10 and record["init"].endswith("random points in the scene box")
    model = load_splat_model(fitted)
    assert model.iteration == 60 and model.splats.count == record["splats"] <= 2048
    scene = load_scene(require_scene("lego_tiny"), split="train")
    cameras = read_cameras_json(fitted / "cameras.json")
    np.testing.assert_allclose(cameras.c2w, scene.c2w, atol=1e-5)
    assert cameras.names == tuple(scene.file_names)


@pytest.mark.slow
def test_explore_a_fitted_run_scores_its_real_images_and_reports_the_renderer(fitted, tmp_path):
    out = tmp_path / "explore"
    assert (
        main(["explore", str(fitted), "--criterion", "colorfulness", "--method", "grs", "--out", str(out), *TINY]) == 0
    )
    r = json.loads((out / "results.json").read_text())
    assert r["initial_scores"] == "images" and "train_images" not in r["source_info"]
    assert r["source_info"]["psnr_test"] == json.loads((fitted / "train.json").read_text())["psnr_test"]
    report = r["renderer"]
    assert report["renderer"] == "splats" and report["views"] == r["n_train"] + r["n_generated"]
    assert report["views_over_max_pairs"] >= 0 and report["max_pairs"] == r["source_info"]["renderer"]["max_pairs"]


@pytest.fixture(scope="module")
def donut_explore(tmp_path_factory):
    donut = require_donut()
    out = tmp_path_factory.mktemp("donut") / "egps"
    assert (
        main(
            [
                "explore",
                str(donut),
                "--criterion",
                "colorfulness",
                "--method",
                "egps+refine",
                "--refine-poses",
                "2",
                "--refine-steps",
                "2",
                "--out",
                str(out),
                *TINY,
            ]
        )
        == 0
    )
    return out, json.loads((out / "results.json").read_text())


@pytest.mark.slow
def test_explore_the_donut_from_a_ring_with_reverse_mode_refinement(donut_explore):
    out, r = donut_explore
    assert r["source_info"]["poses"] == "ring" and r["n_train"] == 24
    assert r["source_info"]["splats"] == 45624 and r["source_info"]["sh_degree"] == 0
    assert r["initial_scores"] == "images"  # the ring's renders stand for the missing photos
    assert r["refine"]["gradient"] == "reverse" and r["refine"]["gradient_cost"] == SPLAT_GRADIENT_COST
    assert r["renderer"]["views_over_max_pairs"] == 0
    assert np.isfinite(r["cvir"]) and r["topk"][0]["score"] >= max(r["scores_train"])
    image = iio.imread(out / "topk" / "00.png")
    assert image.shape == (24, 24, 3) and image.max() > 100  # the donut, not an empty view


@pytest.mark.slow
def test_render_and_score_agree_with_the_search(donut_explore, tmp_path, capsys):
    out, r = donut_explore
    donut = require_donut()
    # The search's top views, rendered again from its poses file.
    views = tmp_path / "views"
    assert main(["render", str(donut), "--poses", str(out / "poses.json"), "--out", str(views)]) == 0
    for i in range(len(r["topk"])):
        again = iio.imread(views / f"{i:04d}.png").astype(int)
        found = iio.imread(out / "topk" / f"{i:02d}.png").astype(int)
        assert np.abs(again - found).max() <= 2  # PNG rounding of float32 renders
    # The training views scored through --source equal the search's initial scores.
    capsys.readouterr()
    assert main(["score", "--criterion", "colorfulness", "--source", str(donut), "--resolution", "24", "--json"]) == 0
    scores = json.loads(capsys.readouterr().out)["scores"]
    np.testing.assert_allclose(scores, r["scores_train"], rtol=1e-4)


@pytest.mark.slow
def test_render_train_poses_of_the_donut(tmp_path):
    donut = require_donut()
    out = tmp_path / "ring"
    assert main(["render", str(donut), "--poses", "train", "--resolution", "16", "--out", str(out)]) == 0
    names = sorted(p.name for p in out.glob("*.png"))
    assert names == [f"{i:04d}.png" for i in range(24)]


@pytest.mark.slow
def test_path_on_the_donut(tmp_path):
    donut = require_donut()
    out = tmp_path / "path"
    assert (
        main(
            [
                "path",
                str(donut),
                "--criterion",
                "colorfulness",
                "--out",
                str(out),
                "--resolution",
                "16",
                "--epochs",
                "2",
                "--initial-paths",
                "4",
                "--paths-per-epoch",
                "4",
                "--keyframes",
                "3",
                "--frames",
                "6",
            ]
        )
        == 0
    )
    r = json.loads((out / "results.json").read_text())
    assert r["source_info"]["poses"] == "ring" and len(r["found"]["frame_scores"]) == 6
    assert np.isfinite(r["found"]["score"]) and (out / "path.mp4").stat().st_size > 0


@pytest.mark.slow
def test_a_reference_layout_folder_takes_its_cameras_json(tmp_path):
    donut = require_donut()
    model = tmp_path / "model"
    (model / "point_cloud" / "iteration_900").mkdir(parents=True)
    (model / "point_cloud" / "iteration_30000").mkdir(parents=True)
    shutil.copy(donut, model / "point_cloud" / "iteration_30000" / "point_cloud.ply")
    ring = load_source(str(donut), 24)
    write_cameras_json(
        model / "cameras.json", ring.train_c2w[:6], ring.intrinsics.with_max_side(48), [f"cam{i}" for i in range(6)]
    )
    source = load_source(str(model))
    assert source.info["poses"] == "cameras.json" and source.info["iteration"] == 30000
    assert source.n_train == 6 and source.train_names == tuple(f"cam{i}" for i in range(6))
    np.testing.assert_allclose(source.train_c2w, ring.train_c2w[:6], atol=1e-6)
    assert (source.intrinsics.width, source.intrinsics.height) == (48, 48)


def test_splat_errors_are_one_line(tmp_path, capsys):
    cloud = tmp_path / "cloud.ply"
    cloud.write_bytes(
        b"ply\nformat binary_little_endian 1.0\nelement vertex 1\nproperty float x\n"
        b"property float y\nproperty float z\nend_header\n" + np.zeros(3, "<f4").tobytes()
    )
    cases = [
        (
            ["explore", str(cloud), "--criterion", "colorfulness", "--out", str(tmp_path / "a")],
            "a point cloud, not a splat scene",
        ),
        (
            ["explore", "procedural", "--cameras", str(cloud), "--out", str(tmp_path / "b")],
            "--cameras gives a splat scene its poses",
        ),
        (["render", str(cloud), "--out", str(tmp_path / "c")], "needs --poses"),
        (
            ["explore", "procedural", "--up", "0,0,1", "--out", str(tmp_path / "e")],
            "--up/--orbit place the ring of views of a splat scene without cameras",
        ),
        (
            ["train", "procedural", "--model", "splat", "--preset", "quality", "--out", str(tmp_path / "d")],
            "for NeRF training only",
        ),
    ]
    for argv, message in cases:
        capsys.readouterr()
        assert main(argv) == 1, argv
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and message in err[0], (argv, err)
        assert not (tmp_path / argv[-1]).exists()


@pytest.mark.parametrize("up", ["0,0,0", "1,2", "x,y,z"])
def test_a_bad_up_is_refused_before_anything_loads(tmp_path, capsys, up):
    assert main(["explore", "procedural", "--up", up, "--out", str(tmp_path / "a")]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--up" in err[0] and not (tmp_path / "a").exists(), err


def test_up_and_orbit_are_refused_where_cameras_fix_the_views(tmp_path, capsys):
    """A reference-layout folder with cameras.json: its cameras are the training views, a ring is not made."""
    donut = require_donut()
    folder = tmp_path / "model"
    (folder / "point_cloud" / "iteration_7").mkdir(parents=True)
    shutil.copy(donut, folder / "point_cloud" / "iteration_7" / "point_cloud.ply")
    c2w = np.eye(4, dtype=np.float32)[None].copy()
    c2w[0, 2, 3] = 0.5
    write_cameras_json(folder / "cameras.json", c2w, Intrinsics.from_fov(32, 32, 1.0), ["a"])
    capsys.readouterr()
    argv = ["explore", str(folder), "--orbit", "surround", "--criterion", "colorfulness", "--out", str(tmp_path / "o")]
    assert main(argv) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "fix its training views" in err[0], err
    assert not (tmp_path / "o").exists()


def test_scene_info_of_the_donut_prints_its_up_and_layout(capsys):
    assert main(["scene", "info", str(require_donut()), "--json", "--quiet"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["splats"] == 45624 and summary["cameras"] is None
    up = np.asarray(summary["upright"]["up"])
    assert up[2] >= np.cos(np.radians(10.0)), summary["upright"]  # the iced side, +z
    assert summary["upright"]["layout"] == "object"


def test_the_splats_robust_bounds_are_computed_once_per_load(monkeypatch, capsys):
    """A pass over every splat (10 s at 30M splats): `load_splat_model` keeps its bounds, which the degenerate
    check, `scene info` and the ring of views read, each the same as computed afresh."""
    from waldo_jax.splats import io as splat_io
    from waldo_jax.splats import upright

    calls = []
    counted = upright.robust_bounds

    def counting(*args, **kwargs):
        calls.append(1)
        return counted(*args, **kwargs)

    monkeypatch.setattr(splat_io, "robust_bounds", counting)
    monkeypatch.setattr(upright, "robust_bounds", counting)
    monkeypatch.setattr("waldo_jax.pipeline.splat_sources.upright_robust_bounds", counting)
    assert main(["scene", "info", str(require_donut()), "--json", "--quiet"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert len(calls) == 1, len(calls)
    model = load_splat_model(require_donut())
    fresh = counted(np.asarray(model.splats.means), np.asarray(model.splats.valid))
    assert np.array_equal(model.bounds, fresh)
    assert summary["bounds_2_98"] == [fresh[0].round(6).tolist(), fresh[1].round(6).tolist()]
    calls.clear()
    from waldo_jax.pipeline.splat_sources import RING_FOV_DEG, SPLAT_RESOLUTION, ring_cameras, splat_upright

    intrinsics = Intrinsics.from_fov(SPLAT_RESOLUTION, SPLAT_RESOLUTION, np.radians(RING_FOV_DEG))
    means, valid = np.asarray(model.splats.means), np.asarray(model.splats.valid)
    given = ring_cameras(means, valid, intrinsics, upright=splat_upright(model), bounds=model.bounds)
    assert not calls
    afresh = ring_cameras(means, valid, intrinsics, upright=splat_upright(model))
    assert len(calls) == 1 and np.array_equal(given[0], afresh[0]) and given[1] == afresh[1]
