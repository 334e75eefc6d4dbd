"""Bad input by kind (issue [5/5]): structured files bounded in depth, work and memory set by input
estimated before it runs, degenerate fields flagged. One case per kind and entry point; the environment
variables have their own file (tests/test_environment.py).

Each CLI case runs `waldo_jax.cli.main` in-process and checks the one-line error, exit status 1 and that
nothing was created.
"""

from __future__ import annotations

import json
import os
import random
import re
import warnings

import numpy as np
import pytest
from test_bad_input import _snapshot, _write_run, _write_scene

import waldo_jax.errors as errors
import waldo_jax.pipeline.experiment as experiment
from waldo_jax.cli import main
from waldo_jax.errors import WaldoError
from waldo_jax.io import MAX_JSON_DEPTH, json_depth, parse_json
from waldo_jax.splats.io import write_splat_ply
from waldo_jax.splats.model import make_splats

DEEP = 100_000  # the issue's transforms.json nesting


def _deep(depth: int) -> str:
    return "[" * depth + "]" * depth


def _cli_refuses(argv, expected, capsys, folder):
    before = _snapshot(folder)
    listing = sorted(os.listdir(folder))
    status = main(argv)
    err = capsys.readouterr().err.strip()
    assert status == 1, err
    lines = [line for line in err.splitlines() if not line.startswith("waldo: warning:")]
    assert len(lines) == 1 and lines[0].startswith("waldo: error: "), err
    assert expected in lines[0], lines[0]
    assert "Traceback" not in err
    assert _snapshot(folder) == before and sorted(os.listdir(folder)) == listing


def _tiny_splats(opacity_logit: float = 2.0, n: int = 64):
    rng = np.random.default_rng(0)
    return make_splats(
        means=rng.normal(size=(n, 3)).astype(np.float32),
        log_scales=np.full((n, 3), -3.0, np.float32),
        quats=np.tile(np.array([1, 0, 0, 0], np.float32), (n, 1)),
        logits=np.full((n,), opacity_logit, np.float32),
        sh=rng.normal(size=(n, 1, 3)).astype(np.float32),
    )


# --------------------------------------------------------------------------------------------------
# Structured files: depth and size bounded.


def _brute_depth(value) -> int:
    if isinstance(value, list):
        return 1 + max((_brute_depth(v) for v in value), default=0)
    if isinstance(value, dict):
        return 1 + max((_brute_depth(v) for v in value.values()), default=0)
    return 0


def _random_json(rng: random.Random, depth: int):
    kind = rng.random()
    if depth == 0 or kind < 0.3:
        return rng.choice(['a "quoted" [bracket', "}{", "\\", "plain", 3, None, True, "\u00e9[\n]"])
    if kind < 0.65:
        return [_random_json(rng, depth - 1) for _ in range(rng.randint(0, 3))]
    return {f"k{i}[": _random_json(rng, depth - 1) for i in range(rng.randint(0, 3))}


def test_json_depth_agrees_with_a_brute_force_count():
    rng = random.Random(0)
    for _ in range(300):
        value = _random_json(rng, rng.randint(0, 8))
        text = json.dumps(value, ensure_ascii=rng.random() < 0.5)
        assert json_depth(text.encode()) == _brute_depth(value), text


def test_parse_json_refuses_deep_and_large_text_by_name(monkeypatch):
    with pytest.raises(errors.WaldoError, match=f"f.json: JSON file nests {DEEP} levels deep"):
        parse_json(_deep(DEEP), "f.json")
    assert parse_json(_deep(MAX_JSON_DEPTH), "f.json") is not None
    monkeypatch.setattr("waldo_jax.io.MAX_JSON_BYTES", 10)
    with pytest.raises(errors.WaldoError, match="at most 0 MiB"):
        parse_json("[" + " " * 20 + "]", "f.json")


@pytest.mark.parametrize(
    "argv", [["scene", "info", "{tmp}/scene"], ["train", "{tmp}/scene", "--steps", "1", "--out", "{tmp}/new"]]
)
def test_a_deep_transforms_json_is_one_line(tmp_path, capsys, argv):
    (tmp_path / "scene").mkdir()
    (tmp_path / "scene" / "transforms.json").write_text('{"frames": ' + _deep(DEEP) + "}")
    argv = [a.replace("{tmp}", str(tmp_path)) for a in argv]
    _cli_refuses(argv, f"levels deep (at most {MAX_JSON_DEPTH})", capsys, tmp_path)


@pytest.mark.slow
def test_a_deep_poses_file_is_one_line(tmp_path, capsys):
    (tmp_path / "poses.json").write_text('{"w": 16, "h": 16, "frames": ' + _deep(DEEP) + "}")
    argv = ["render", "procedural", "--poses", str(tmp_path / "poses.json"), "--out", str(tmp_path / "new")]
    _cli_refuses(argv, "poses.json: poses file nests", capsys, tmp_path)


def test_a_deep_cameras_json_beside_splats_is_one_line(tmp_path, capsys):
    write_splat_ply(tmp_path / "point_cloud.ply", _tiny_splats())
    (tmp_path / "cameras.json").write_text(_deep(DEEP))
    argv = ["scene", "info", str(tmp_path / "point_cloud.ply")]
    _cli_refuses(argv, "cameras.json: cameras file nests", capsys, tmp_path)


def test_a_deep_sog_meta_is_not_taken_for_a_sog_scene(tmp_path, capsys):
    (tmp_path / "meta.json").write_text('{"means": ' + _deep(DEEP) + "}")
    _cli_refuses(["scene", "info", str(tmp_path / "meta.json")], "meta.json", capsys, tmp_path)


# --------------------------------------------------------------------------------------------------
# Work and memory set by input: estimated before anything runs.


def test_images_that_cannot_fit_are_refused_before_they_load(tmp_path, capsys, monkeypatch):
    _write_scene(tmp_path / "scene")  # 8 images of 16x16: 24 KiB as float32
    monkeypatch.setattr(errors, "host_memory_bytes", lambda: 10_000)
    _cli_refuses(
        ["train", str(tmp_path / "scene"), "--out", str(tmp_path / "new"), "--steps", "1"],
        "images of 16x16",
        capsys,
        tmp_path,
    )


def test_a_run_of_large_images_renders_at_most_256_pixels_a_side_unless_told(tmp_path):
    """A NeRF run trained on 1080x1920 images (the fox) is searched and rendered at 144x256 by default
    (at its own size, one view is 2M rays and a search's epoch did not fit in 24 GiB); `--resolution`
    sets another size, and a run of small images keeps its own."""
    from waldo_jax.pipeline.sources import RUN_RESOLUTION, run_source
    from waldo_jax.scenes import load_scene

    _write_scene(tmp_path / "scene")  # 16x16
    large = load_scene(tmp_path / "scene").intrinsics.scaled(1080, 1920)
    _write_run(tmp_path / "large_run", intrinsics=large)
    _write_run(tmp_path / "small_run")
    size = lambda source: (source.intrinsics.width, source.intrinsics.height)  # noqa: E731
    assert RUN_RESOLUTION == 256 and size(run_source(str(tmp_path / "large_run"), images=False)) == (144, 256)
    assert size(run_source(str(tmp_path / "large_run"), 512, images=False)) == (288, 512)
    assert size(run_source(str(tmp_path / "small_run"), images=False)) == (16, 16)


def test_one_seed_that_cannot_fit_is_told_the_resolution_that_would(monkeypatch):
    """When even one seed's epoch exceeds the memory, the advice is a --resolution that fits (it was
    "at most --seeds 0"), and that resolution passes the same check."""
    from types import SimpleNamespace

    from waldo_jax.types import Intrinsics

    config = SimpleNamespace(children_per_epoch=46)
    source = lambda side: SimpleNamespace(intrinsics=Intrinsics.from_fov(side * 9 // 16, side, 0.8))  # noqa: E731
    monkeypatch.setattr(experiment, "memory_bytes", lambda: 11 << 30)
    with pytest.raises(errors.WaldoError, match=r"--resolution 1920: .*; pass --resolution (\d+) or less") as info:
        experiment.check_epoch_memory(source(1920), config, 1)
    fits = int(info.value.args[0].rsplit("--resolution ", 1)[1].split()[0])
    assert 256 < fits < 1920
    experiment.check_epoch_memory(source(fits), config, 1)  # passes
    experiment.check_epoch_memory(source(fits), config, 100)  # seeds render one after another: not counted
    # Children no resolution can hold: the advice names --children-per-epoch (it said "--resolution 0").
    many = SimpleNamespace(children_per_epoch=10**9)
    with pytest.raises(
        errors.WaldoError, match=r"^--children-per-epoch 1000000000: .*at most --children-per-epoch (\d+)"
    ):
        experiment.check_epoch_memory(source(64), many, 1)


@pytest.mark.parametrize("kind", ["procedural", "splats", "path"])
def test_a_size_the_epoch_cannot_hold_is_refused_before_the_source_renders(kind, tmp_path, capsys, monkeypatch):
    """--resolution 4096: the room rendered its 24 training views (the splats their calibration views) at
    that size for minutes before the epoch's memory check refused it; the check now comes first."""
    import waldo_jax.pipeline.sources as sources
    import waldo_jax.pipeline.splat_sources as splat_sources

    def never(*args, **kwargs):
        raise AssertionError("rendered before the epoch's memory check")

    monkeypatch.setattr(sources, "room_scene", never)
    monkeypatch.setattr(splat_sources, "calibrate_max_pairs", never)
    monkeypatch.setattr(experiment, "memory_bytes", lambda: 4 << 30)
    import waldo_jax.pipeline.path_run as path_run

    monkeypatch.setattr(path_run, "memory_bytes", lambda: 4 << 30)
    spec = "procedural"
    if kind == "splats":
        spec = str(tmp_path / "tiny.ply")
        write_splat_ply(spec, _tiny_splats())
    command, expected = ("path", "one path's 24 frames of 4096x4096") if kind == "path" else ("explore", "one epoch")
    argv = [command, spec, "--resolution", "4096", "--out", str(tmp_path / "new"), "--quiet"]
    _cli_refuses(argv, f"--resolution 4096: {expected}", capsys, tmp_path)


@pytest.mark.slow
def test_a_search_that_cannot_fit_is_refused_before_it_runs(tmp_path, capsys, monkeypatch):
    """XLA's analysis of the compiled search against the memory at hand (here made small)."""
    monkeypatch.setattr(experiment, "memory_bytes", lambda: 50_000)
    monkeypatch.setattr(experiment, "host_memory_bytes", lambda: 50_000)
    monkeypatch.setattr(experiment, "check_epoch_pixels", lambda *a: None)  # the per-epoch rule of thumb: aside
    argv = ["explore", "procedural", "--resolution", "16", "--out", str(tmp_path / "new"), "--quiet"]
    _cli_refuses(argv, "the compiled search needs", capsys, tmp_path)


@pytest.mark.slow
def test_the_issues_hundred_million_epochs_are_one_line(tmp_path, capsys):
    argv = [
        "explore",
        "procedural",
        "--epochs",
        "100000000",
        "--children-per-epoch",
        "1",
        "--budget",
        "high",
        "--resolution",
        "16",
        "--out",
        str(tmp_path / "new"),
        "--quiet",
    ]
    _cli_refuses(argv, "--epochs 100000000", capsys, tmp_path)


# --------------------------------------------------------------------------------------------------
# Degenerate fields: a warning line and a flag in the results.


def _huge_splats(**kw):
    splats = _tiny_splats(**kw)
    return splats.replace(log_scales=np.full_like(np.asarray(splats.log_scales), 100.0))


@pytest.mark.slow
@pytest.mark.parametrize(
    "make, says",
    [
        (lambda: _tiny_splats(opacity_logit=-20.0), "are transparent"),
        (lambda: _tiny_splats(opacity_logit=-200.0), "are transparent"),  # opacity exactly 0 in float32
        (lambda: _tiny_splats(n=2), None),  # too few to find an up: the file family's axis, not an error
        (_huge_splats, "64 opaque ones have a scale past exp(40)"),
    ],
    ids=["transparent", "opacity-zero", "two-splats", "scales-overflow"],
)
def test_splats_that_cannot_show_warn_and_are_flagged(tmp_path, make, says):
    """Every kind of splat scene the renderer would draw as the background alone (transparent, or scales
    whose covariance overflows float32) loads with a warning and `degenerate` in its info; a scene of
    two splats loads with the file family's up (too few to find one) instead of a traceback."""
    from waldo_jax.pipeline.splat_sources import splat_source, splat_upright
    from waldo_jax.splats.io import load_splat_model

    write_splat_ply(tmp_path / "point_cloud.ply", make())
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        source = splat_source(str(tmp_path / "point_cloud.ply"), resolution=16)
    if says is None:
        assert "degenerate" not in source.info
        upright = splat_upright(load_splat_model(tmp_path / "point_cloud.ply"))
        assert upright.rule == "format axis" and "too few" in upright.reason
        return
    assert says in source.info["degenerate"]
    assert any("every render is the background alone" in str(w.message) for w in caught)


@pytest.mark.parametrize("offset, warned", [(0.0, False), (100.0, False), (1e4, True), (1e7, True)])
def test_splats_far_from_the_origin_for_their_size_warn_and_are_flagged(offset, warned):
    """Splats read in float32 far from the origin for their extent are placed coarsely (a model saved at
    +10^6 in float64 rendered as a slab, at +10^7 as a streak, silently): a warning names the distance and
    the step, and `coarse_positions` flags it in the source's info. A model of 6 units at 100 has 10^6
    steps across it, and says nothing."""
    from waldo_jax.pipeline.splat_sources import _flag_coarse_positions

    splats = _tiny_splats()
    splats = splats.replace(means=np.asarray(splats.means) * np.float32(0.05) + np.float32(offset))  # 0.3 across
    info = {}
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        _flag_coarse_positions("far.ply", splats, info)
    assert ("coarse_positions" in info) == warned
    said = [str(w.message) for w in caught]
    assert said == ([f"far.ply: {info['coarse_positions']}"] if warned else [])
    if warned:
        assert f"lie {offset:.3g} from the origin" in said[0] and "placed coarsely" in said[0]


@pytest.mark.slow
def test_a_splat_source_far_from_the_origin_is_flagged_in_its_info(tmp_path):
    """The check above, as a splat scene loads: a PLY 10^4 out flags `coarse_positions` in the source's
    info (results.json's source_info) with its warning line; the same PLY at the origin does not."""
    from waldo_jax.pipeline.splat_sources import splat_source

    splats = _tiny_splats()
    for offset, flagged in ((0.0, False), (1e4, True)):
        moved = splats.replace(means=np.asarray(splats.means) * np.float32(0.05) + np.float32(offset))
        path = write_splat_ply(tmp_path / f"at_{offset:g}.ply", moved)
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            source = splat_source(str(path), resolution=16)
        assert ("coarse_positions" in source.info) == flagged
        assert any("placed coarsely" in str(w.message) for w in caught) == flagged


@pytest.mark.parametrize(
    "record, says",
    [
        ([1, 2], "a splat run record must be a JSON object, not list"),
        ({"background": "abc"}, "'background' must be 3 numbers in [0, 1], got 'abc'"),
        ({"background": [5, 5, 5]}, "'background' must be 3 numbers in [0, 1]"),
        ({"background": [1, 0]}, "'background' must be 3 numbers"),
        ({"scene_path": 5}, "'scene_path' must be a path, got 5"),
        ({"downscale": 0}, "'downscale' must be a number >= 1"),
        ({"steps": 1e400}, "'steps' must be a whole number >= 0, got inf"),
    ],
    ids=["list", "background-text", "background-range", "background-short", "scene-path", "downscale", "steps"],
)
def test_a_splat_runs_record_is_checked_key_by_key(tmp_path, record, says):
    """A splat run's train.json, read back for its background, scene and figures, is refused by name and key
    when it holds the wrong kind of value (each once ended in a traceback, or a background of 5 rendered)."""
    from waldo_jax.pipeline.splat_sources import splat_source

    run = tmp_path / "run"
    (run / "point_cloud" / "iteration_1").mkdir(parents=True)
    write_splat_ply(run / "point_cloud" / "iteration_1" / "point_cloud.ply", _tiny_splats())
    (run / "train.json").write_text(json.dumps(record).replace("Infinity", "1e400"))
    with pytest.raises(WaldoError, match=re.escape(f"{run / 'train.json'}: {says}")):
        splat_source(str(run), resolution=16)


@pytest.mark.slow
def test_visible_splats_are_not_flagged(tmp_path):
    from waldo_jax.pipeline.splat_sources import splat_source

    write_splat_ply(tmp_path / "point_cloud.ply", _tiny_splats())
    with warnings.catch_warnings():
        warnings.simplefilter("error", UserWarning)
        source = splat_source(str(tmp_path / "point_cloud.ply"), resolution=16)
    assert "degenerate" not in source.info


@pytest.mark.slow
def test_a_run_with_an_empty_occupancy_grid_warns_and_is_flagged(tmp_path):
    import dataclasses

    import jax
    import jax.numpy as jnp

    from waldo_jax.nerf.checkpoint import CHECKPOINT_NAME, load_checkpoint, save_checkpoint
    from waldo_jax.nerf.samplers import make_sampler
    from waldo_jax.pipeline.sources import run_source

    _write_scene(tmp_path / "scene")
    _write_run(tmp_path / "run")
    checkpoint = load_checkpoint(tmp_path / "run")
    config = dataclasses.replace(checkpoint.config, sampler="occupancy")
    grid = make_sampler(config).init(jax.random.key(0), checkpoint.params)
    empty = grid.replace(bitfield=jnp.zeros_like(grid.bitfield), density=jnp.zeros_like(grid.density))
    save_checkpoint(tmp_path / "run" / CHECKPOINT_NAME, checkpoint.params, config, checkpoint.scene, empty)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        source = run_source(str(tmp_path / "run"), resolution=16)
    assert "occupancy grid is empty" in source.info["degenerate"]
    assert any("marks no cell occupied" in str(w.message) for w in caught)


# --------------------------------------------------------------------------------------------------
# Images in another colour space: converted where Pillow can, refused where it cannot.


@pytest.mark.parametrize("suffix", [".tiff", ".jpg"])
def test_a_cmyk_image_reads_as_its_colours_not_its_ink(tmp_path, suffix):
    """imageio hands a CMYK file's four ink channels over as they are: read as RGBA they were the image's
    negative (a score then judged the negative). Read as Pillow converts it, it matches the RGB original."""
    from PIL import Image

    from waldo_jax.io import read_image

    rgb = np.random.default_rng(0).integers(0, 256, (32, 40, 3), dtype=np.uint8)
    Image.fromarray(rgb).convert("CMYK").save(tmp_path / f"cmyk{suffix}")
    got = read_image(tmp_path / f"cmyk{suffix}")
    assert got.shape == (32, 40, 3)
    tolerance = 1.5 / 255 if suffix == ".tiff" else 0.2  # JPEG is lossy; the negative is off by ~0.5 on average
    assert float(np.abs(got - rgb / 255.0).mean()) < tolerance


def test_a_grey_and_alpha_image_reads_as_grey_rgb_with_its_alpha(tmp_path):
    """A PNG of grey and alpha (Pillow's LA mode) is read as its grey in R, G and B, with its alpha where
    asked for: `waldo score` had refused it ("an array of shape (H, W, 2)") though a scene read it."""
    from PIL import Image

    from waldo_jax.io import read_image

    la = np.stack([np.arange(256, dtype=np.uint8).reshape(16, 16), np.full((16, 16), 128, np.uint8)], axis=-1)
    Image.fromarray(la, "LA").save(tmp_path / "la.png")
    grey = la[..., 0] / 255.0
    np.testing.assert_allclose(read_image(tmp_path / "la.png"), np.repeat(grey[..., None], 3, -1), atol=1e-7)
    with_alpha = read_image(tmp_path / "la.png", keep_alpha=True)
    assert with_alpha.shape == (16, 16, 4) and np.allclose(with_alpha[..., 3], 128 / 255)


def test_a_lab_image_is_refused_by_name(tmp_path):
    from PIL import Image

    from waldo_jax.io import read_image

    Image.fromarray(np.zeros((16, 16, 3), np.uint8)).convert("LAB").save(tmp_path / "lab.tiff")
    with pytest.raises(WaldoError, match=r"lab\.tiff: a LAB image \(another colour space"):
        read_image(tmp_path / "lab.tiff")


@pytest.mark.parametrize("suffix", [".gif", ".webp", ".png", ".tiff"])
def test_an_image_of_several_frames_is_refused_before_decoding_them(tmp_path, suffix):
    """An animated GIF, WebP or PNG or a multi-page TIFF: imageio decoded every frame before the shape was
    refused (a 29 KB GIF reached 2.25 GB), and an animated WebP was scored by its first frame. A still GIF,
    which imageio hands over as a stack of one frame, is read."""
    from PIL import Image

    from waldo_jax.io import read_image

    frames = [Image.fromarray(np.full((16, 16, 3), 40 * i, np.uint8)) for i in range(3)]
    frames[0].save(tmp_path / f"many{suffix}", save_all=True, append_images=frames[1:])
    with pytest.raises(WaldoError, match=rf"many\{suffix}: an image of several frames"):
        read_image(tmp_path / f"many{suffix}")
    frames[1].save(tmp_path / f"one{suffix}")
    np.testing.assert_allclose(
        read_image(tmp_path / f"one{suffix}"), 40 / 255, atol=1 / 255 if suffix != ".webp" else 0.05
    )


def test_frames_that_share_an_image_file_warn(tmp_path):
    """Frames naming one image file (a copy-paste slip: one photo for eight poses) load with one warning that
    names the file and how many frames share it; distinct files load without it."""
    from waldo_jax.scenes import load_scene

    _write_scene(tmp_path / "scene")
    path = tmp_path / "scene" / "transforms.json"
    with warnings.catch_warnings():
        warnings.simplefilter("error", UserWarning)
        load_scene(tmp_path / "scene")
    meta = json.loads(path.read_text())
    for frame in meta["frames"]:
        frame["file_path"] = "images/0.png"
    path.write_text(json.dumps(meta))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        load_scene(tmp_path / "scene")
    shared = [str(w.message) for w in caught if "share" in str(w.message)]
    assert len(shared) == 1 and "8 of 8 frames share 1 image files" in shared[0] and "0.png" in shared[0]


def test_an_ngp_camera_path_with_a_scale_or_rotation_that_cannot_be_inverted_is_refused():
    """waldo's own Instant-NGP export read back (`waldo render --poses`): an ngp_scale past float64 (a huge
    integer) once rendered views at the origin without a word, a zero quaternion warned of a division."""
    from waldo_jax.cameras import look_at
    from waldo_jax.scenes.camera_paths import instant_ngp_camera_path, read_camera_path
    from waldo_jax.scenes.tool_frames import NgpFrame
    from waldo_jax.types import Intrinsics

    c2w = np.stack(
        [np.asarray(look_at(np.array([3.0, 0.5, float(i)]), np.zeros(3), np.array([0, 1.0, 0]))) for i in (0, 1)]
    )
    c2w = np.concatenate([c2w[:, :3], np.tile([[[0, 0, 0, 1.0]]], (2, 1, 1))], 1)
    intrinsics = Intrinsics.from_fov(32, 32, 0.8)
    text = json.dumps(instant_ngp_camera_path(c2w, intrinsics, 24, frame=NgpFrame.create()))
    np.testing.assert_allclose(read_camera_path(json.loads(text), intrinsics)[0], c2w, atol=2e-5)
    big = json.loads(text)
    big["waldo"]["ngp_scale"] = 1
    big = parse_json(json.dumps(big).replace('"ngp_scale": 1', '"ngp_scale": 1' + "0" * 400), "path.json")
    with pytest.raises(ValueError, match=r"'ngp_scale' must be a finite number .*, got inf"):
        read_camera_path(big, intrinsics)
    zero = json.loads(text)
    zero["path"][0]["R"] = [0, 0, 0, 0]
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        with pytest.raises(ValueError, match=r"quaternion \[0.0, 0.0, 0.0, 0.0\] is zero or not finite"):
            read_camera_path(zero, intrinsics)


@pytest.mark.parametrize(
    "points, says",
    [
        (np.zeros((1, 3)), r"sparse_pc\.ply: its 1 points lie at one spot"),
        (np.full((5, 3), 1e300), r"sparse_pc\.ply: PLY vertices have coordinates beyond float32's range"),
    ],
    ids=["one-spot", "past-float32"],
)
def test_a_point_cloud_that_gives_no_scene_box_is_blamed_by_name(tmp_path, points, says):
    """The scene box of a transforms.json without one comes from its sparse_pc.ply: points at one spot or past
    float32 are that file's fault, and the message names it (it once blamed transforms.json's near/far)."""
    from waldo_jax.scenes import load_scene

    _write_scene(tmp_path / "scene", camera_model="OPENCV")  # a nerfstudio file: its box comes from the PLY
    header = "ply\nformat binary_little_endian 1.0\nelement vertex {}\nproperty double x\nproperty double y\n"
    header += "property double z\nend_header\n"
    (tmp_path / "scene" / "sparse_pc.ply").write_bytes(
        header.format(len(points)).encode() + np.asarray(points, "<f8").tobytes()
    )
    with pytest.raises(WaldoError, match=says):
        load_scene(tmp_path / "scene")


@pytest.mark.parametrize(
    "flags, says",
    [
        (["--epochs", "1073741823", "--children-per-epoch", "2"], "past the 2,147,483,647 that int32 counts"),
        (
            ["--epochs", "1", "--children-per-epoch", "4", "--method", "egps+refine", "--refine-steps", "2147483647"],
            "for its gradient steps (--refine-poses x --refine-steps x --gradient-cost)",
        ),
        (
            ["--epochs", "1", "--children-per-epoch", "4", "--method", "egps+refine", "--gradient-cost", "2147483647"],
            "past the 2,147,483,647 that int32 counts",
        ),
    ],
    ids=["epochs-x-children", "refine-steps", "gradient-cost"],
)
def test_counts_whose_product_passes_int32_are_refused_by_their_flags(tmp_path, capsys, flags, says):
    """Each flag alone fits int32; their product, the run's views and renders, did not (an OverflowError from
    JAX's indexing, or a search that ran on for ever)."""
    argv = ["explore", "procedural:1", "--views", "4", "--resolution", "16", "--top-k", "2", "--criterion"]
    argv += ["colorfulness", *flags, "--out", str(tmp_path / "new"), "--quiet"]
    _cli_refuses(argv, says, capsys, tmp_path)


# --------------------------------------------------------------------------------------------------
# The second hunt's kinds: counts whose product passes int32, files read whole, lengths inside files.


def test_training_views_that_cannot_fit_are_refused_by_their_flags(tmp_path, capsys, monkeypatch):
    """--views 1000 at --resolution 4096 (16.8 G pixels): the room's training views had ended in JAX's
    OverflowError (their flat pixel index past int32); now their memory is checked before they render."""
    import waldo_jax.pipeline.sources as sources

    def never(*args, **kwargs):
        raise AssertionError("rendered before the training views' memory check")

    monkeypatch.setattr(sources, "room_scene", never)
    monkeypatch.setattr(experiment, "memory_bytes", lambda: 1 << 50)  # the epoch's check passes
    monkeypatch.setattr(errors, "host_memory_bytes", lambda: 24 << 30)
    argv = ["explore", "procedural", "--views", "1000", "--resolution", "4096", "--epochs", "1"]
    _cli_refuses(
        [*argv, "--out", str(tmp_path / "new"), "--quiet"],
        "--views 1000 at --resolution 4096 (the room's training views) would take 500.0 GiB",
        capsys,
        tmp_path,
    )


def test_a_render_of_more_rays_than_int32_indexes_is_refused_before_it_runs():
    """A render call's rays are one flat int32 index: 200 views of 4096x4096 (3.4 G rays) would wrap round.
    Refused while tracing, before anything is computed."""
    import jax.numpy as jnp

    from waldo_jax.render.volume import MAX_RAYS_PER_CALL, RenderConfig, render_views
    from waldo_jax.types import Intrinsics

    def field(params, x, d):
        return jnp.ones(()), jnp.ones(3)

    c2w = jnp.tile(jnp.eye(4), (200, 1, 1))
    with pytest.raises(
        ValueError, match=f"200 views of 4096x4096 are 3,355,443,200 rays, more than the {MAX_RAYS_PER_CALL:,}"
    ):
        render_views(field, {}, c2w, Intrinsics.create(4096, 4096, 4096.0), RenderConfig(near=0.1, far=1.0))


@pytest.mark.parametrize("opcode", [b"\x8e", b"\x8d"])  # BINBYTES8 (MemoryError before), BINUNICODE8
def test_a_pickle_that_claims_more_bytes_than_memory_is_refused_by_name(tmp_path, opcode):
    """14 bytes that claim a 2^60-byte string: Python asks for the memory before it reads, and its
    MemoryError had ended `waldo score` in a traceback. The torch reader and CSNet's layer config say so."""
    import struct

    from waldo_jax.criteria.csnet.convert import read_layer_config
    from waldo_jax.weights import TorchPickleError, WeightsError, read_torch_file

    path = tmp_path / "claims.pth"
    path.write_bytes(b"\x80\x04" + opcode + struct.pack("<Q", 1 << 60) + b"abc.")
    with pytest.raises(TorchPickleError, match=re.escape(f"{path}: not a readable torch checkpoint")):
        read_torch_file(path)
    with pytest.raises(WeightsError, match=re.escape(f"{path}: not a readable CSNet layer config")):
        read_layer_config(path)
    (tmp_path / "large.bin").write_bytes(b"\0" * (2 << 20))
    with pytest.raises(WeightsError, match="large.bin: 2.0 MiB; a CSNet layer config is a short list"):
        read_layer_config(tmp_path / "large.bin")


def test_files_read_whole_are_refused_when_larger_than_the_free_memory(tmp_path, capsys, monkeypatch):
    """An SPZ, a .splat, a PLY point cloud and COLMAP text are read whole: past the free memory Linux kills
    the process mid-read (or Python raises MemoryError). Each is refused by its size first, by name."""
    from waldo_jax.errors import SceneFormatError
    from waldo_jax.scenes.colmap import _lines
    from waldo_jax.scenes.ply import read_ply_points
    from waldo_jax.splats.formats.common import read_splat_bytes

    import gzip
    import struct

    (tmp_path / "data").mkdir()
    big = tmp_path / "data" / "big.spz"  # outside the folder `_cli_refuses` hashes: 3 GiB of zeros take 15 s
    with open(big, "wb") as f:  # an SPZ header (version 2, 10 splats), then a sparse tail: nothing is written
        f.write(gzip.compress(b"NGSP" + struct.pack("<IIBBBB", 2, 10, 0, 12, 0, 0)))
        f.truncate(3 << 30)
    monkeypatch.setattr(errors, "host_memory_bytes", lambda: 2 << 30)
    said = "3.0 GiB, more than the 2.0 GiB this machine has free to read it"
    with pytest.raises(SceneFormatError, match=re.escape(f"{big}: SPZ file of {said}")):
        read_splat_bytes(big, "SPZ file")
    with pytest.raises(SceneFormatError, match=re.escape(f"{big}: PLY file of {said}")):
        read_ply_points(big)
    with pytest.raises(SceneFormatError, match=re.escape(f"{big}: COLMAP text file of {said}")):
        _lines(big)
    (tmp_path / "work").mkdir()
    _cli_refuses(["scene", "info", str(big)], said, capsys, tmp_path / "work")


def test_an_allocation_no_check_foresaw_is_one_line_and_removes_the_new_folder(tmp_path, capsys, monkeypatch):
    """A MemoryError from anywhere (NumPy says how much it asked for) is one line, exit status 1, and the
    output folder the command had made is removed, as for any error."""
    import waldo_jax.cli.render as render_cli

    def allocate(*args, **kwargs):
        raise MemoryError("Unable to allocate 33.5 GiB for an array with shape (300000, 100, 100, 3)")

    monkeypatch.setattr(render_cli, "_write_groups", allocate)
    argv = ["render", "procedural", "--views", "2", "--resolution", "8", "--samples", "4", "--out", str(tmp_path / "o")]
    assert main(argv) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1].startswith("waldo: error: out of memory: Unable to allocate 33.5 GiB for an array"), err
    assert not (tmp_path / "o").exists()


def test_an_xla_allocation_no_check_foresaw_is_one_line_and_removes_the_new_folder(tmp_path, capsys, monkeypatch):
    """XLA's own out-of-memory (JAX's RESOURCE_EXHAUSTED, here a real 256 TiB allocation of the CPU
    backend) is one line naming the size, exit status 1, and the new output folder is removed (`waldo train
    --sampler dense` had ended in a 50-line traceback and left its empty folder)."""
    import jax
    import jax.numpy as jnp

    import waldo_jax.cli.render as render_cli

    def allocate(*args, **kwargs):
        jax.jit(lambda: jnp.ones((2**48,), jnp.uint8))().block_until_ready()

    monkeypatch.setattr(render_cli, "_write_groups", allocate)
    argv = ["render", "procedural", "--views", "2", "--resolution", "8", "--samples", "4", "--out", str(tmp_path / "o")]
    assert main(argv) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1].startswith("waldo: error: out of memory: XLA could not allocate 256.0 TiB"), err
    assert "removed the unfinished output folder" in err[-1], err
    assert not (tmp_path / "o").exists()

    def fails(*args, **kwargs):  # any other XLA failure is not dressed up as one
        raise jax.errors.JaxRuntimeError("INTERNAL: something else")

    monkeypatch.setattr(render_cli, "_write_groups", fails)
    with pytest.raises(jax.errors.JaxRuntimeError):
        main(argv[:-1] + [str(tmp_path / "p")])


def test_the_memory_at_hand_counts_an_address_space_limit(monkeypatch):
    """Under `ulimit -v` (RLIMIT_AS) a process can take no more than its limit less what it has mapped, however
    much the machine has free: the memory checks' estimate counts it (it had read MemAvailable alone, so a
    check passed that the limit then failed, in a traceback)."""
    import resource

    unlimited = errors.host_memory_bytes()
    with open("/proc/self/status", encoding="ascii") as f:
        mapped = next(int(line.split()[1]) * 1024 for line in f if line.startswith("VmSize:"))
    limit = mapped + (1 << 30)
    monkeypatch.setattr(resource, "getrlimit", lambda kind: (limit, resource.RLIM_INFINITY))
    limited = errors.host_memory_bytes()
    assert 0 < limited <= 1 << 30 and limited <= unlimited
    monkeypatch.setattr(resource, "getrlimit", lambda kind: (mapped - (1 << 30), resource.RLIM_INFINITY))  # past it
    assert errors.host_memory_bytes() == 1  # the least there is, not 0 ("unknown": no check)


def test_a_file_that_cannot_be_made_is_named_as_asked_not_by_its_temporary_name(tmp_path):
    """Files are written through a temporary file beside them: where it cannot be made (/proc, a missing
    folder), the error names the file asked for (`view --export /proc/x.html` said '/proc/.x.html.3240.tmp')."""
    from waldo_jax import io

    for target in (tmp_path / "missing" / "x.html", tmp_path / "x.html" / "y"):
        with pytest.raises(FileNotFoundError) as caught:
            io.write_text(target, "page")
        assert caught.value.filename == str(target) and ".tmp" not in str(caught.value)
