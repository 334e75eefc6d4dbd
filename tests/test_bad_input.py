"""Bad input through the real CLI entry point: a one-line error naming the value, exit status 1, no
traceback, and nothing written or changed (issue [2/6]).

Each case runs `waldo_jax.cli.main(argv)` in-process with `{tmp}` in argv replaced by a fresh folder
that holds an earlier run (`{tmp}/run/keep.txt`) and the inputs of `_inputs` (a small scene, scenes
with broken cameras, a tiny trained run and one with NaN parameters, images), and checks that the
folder is byte-identical afterwards and that no other file appeared.
"""

import errno
import hashlib
import json
import os

import numpy as np
import pytest

from waldo_jax.cli import main
from waldo_jax.errors import MAX_RESOLUTION, MAX_SEED, WaldoError, check_seed

BIG = "100000000000000000000"  # 1e20 as an integer: overflows int64
LONG = "a" * 300  # a file name past every common file system's 255-byte limit

CASES = [
    # (id, argv, text the one-line message must contain)
    ("train-seed-overflow", ["train", "{tmp}/scene", "--out", "{tmp}/new", "--seed", BIG], BIG),
    ("train-seed-negative", ["train", "{tmp}/scene", "--out", "{tmp}/new", "--seed", "-1"], "--seed"),
    ("render-seed-overflow", ["render", "procedural", "--out", "{tmp}/new", "--seed", BIG], BIG),
    ("explore-seed-overflow", ["explore", "procedural", "--out", "{tmp}/new", "--seed", BIG], BIG),
    ("explore-seeds-past-the-limit", ["explore", "procedural", "--out", "{tmp}/new", "--seed", str(MAX_SEED),
                                      "--seeds", "2"], str(MAX_SEED)),
    ("demo-seed-overflow", ["demo", "--out", "{tmp}/new", "--seed", BIG], BIG),
    ("procedural-negative-seed", ["explore", "procedural:-1", "--out", "{tmp}/new"], "procedural:-1"),
    ("procedural-seed-overflow", ["render", f"procedural:{BIG}", "--out", "{tmp}/new"], BIG),
    ("demo-into-an-earlier-run", ["demo", "--out", "{tmp}/run"], "{tmp}/run"),
    # Scenes whose cameras cannot be used.
    ("scene-info-translation-overflow", ["scene", "info", "{tmp}/far", "--json"], "1e+308"),
    ("train-translation-overflow", ["train", "{tmp}/far", "--out", "{tmp}/new"], "far/transforms.json"),
    ("scene-negative-aabb-scale", ["scene", "info", "{tmp}/negative_aabb"], "'aabb_scale'"),
    ("train-downscale-to-1px", ["train", "{tmp}/scene", "--out", "{tmp}/new", "--downscale", "1000"],
     "--downscale 1000 leaves 1x1"),
    # Output folders that cannot be written, checked before any work.
    ("train-out-under-a-file", ["train", "{tmp}/scene", "--out", "{tmp}/run/keep.txt/new"], "keep.txt is not a directory"),
    ("train-out-name-too-long", ["train", "{tmp}/scene", "--out", "{tmp}/" + LONG], "300 bytes"),
    ("explore-out-name-too-long", ["explore", "procedural", "--out", "{tmp}/" + LONG], "300 bytes"),
    ("render-into-an-earlier-run", ["render", "{tmp}/tiny_run", "--poses", "train", "--out", "{tmp}/run"], "not empty"),
    # Sizes a user can ask for: each with its limit.
    ("render-resolution-huge", ["render", "procedural", "--out", "{tmp}/new", "--resolution", "100000"],
     f"between 8 and {MAX_RESOLUTION}"),
    ("render-run-resolution-huge", ["render", "{tmp}/tiny_run", "--poses", "train", "--out", "{tmp}/new",
                                    "--resolution", "100000"], f"between 8 and {MAX_RESOLUTION}"),
    ("render-poses-file-width-huge", ["render", "{tmp}/tiny_run", "--poses", "{tmp}/wide_poses.json",
                                      "--out", "{tmp}/new"], "wide_poses.json: camera of 100000x100"),
    ("explore-resolution-huge", ["explore", "procedural", "--out", "{tmp}/new", "--resolution", "100000"],
     f"between 8 and {MAX_RESOLUTION}"),
    ("explore-top-k-past-capacity", ["explore", "procedural", "--out", "{tmp}/new", "--top-k", "1000"],
     "--top-k) 1000 exceeds the 274 views"),
    ("explore-seeds-past-memory", ["explore", "procedural", "--criterion", "colorfulness", "--out", "{tmp}/new",
                                   "--seeds", "100000"], "at most --seeds"),
    ("explore-views-too-many", ["explore", "procedural", "--out", "{tmp}/new", "--views", "100000"],
     "--views must be an integer between 1 and 1000"),
    ("explore-target-too-large", ["explore", "procedural", "--criterion", "waldo", "--target", "{tmp}/huge.png",
                                  "--out", "{tmp}/new"], f"huge.png: the image is 4100x8; sides must lie between 2 and {MAX_RESOLUTION}"),
    ("score-1x1-image", ["score", "--criterion", "brisque", "{tmp}/dot.png"], "dot.png: the image is 1x1"),
    # Arguments that were accepted without a word.
    ("guard-fails-every-view", ["explore", "procedural", "--criterion", "colorfulness", "--guard", "opacity:2",
                                "--out", "{tmp}/new"], "fails every view"),
    ("guard-passes-every-view", ["explore", "procedural", "--criterion", "colorfulness", "--guard", "opacity:-1",
                                 "--out", "{tmp}/new"], "passes every view"),
    ("weighted-one-criterion-no-weight", ["explore", "procedural", "--criterion", "weighted:composition",
                                          "--out", "{tmp}/new"], "bad weight"),
    ("weighted-duplicate", ["explore", "procedural", "--criterion", "weighted:opacity=1,opacity=2",
                            "--out", "{tmp}/new"], "names 'opacity' twice"),
    ("explore-views-on-a-run", ["explore", "{tmp}/tiny_run", "--views", "5", "--criterion", "colorfulness",
                                "--out", "{tmp}/new"], "--views is for procedural sources"),
    ("render-views-on-a-run", ["render", "{tmp}/tiny_run", "--poses", "train", "--views", "5", "--out", "{tmp}/new"],
     "--views: for procedural sources only"),
    # Non-finite data: refused naming the file.
    ("render-nan-checkpoint", ["render", "{tmp}/nan_run", "--poses", "train", "--out", "{tmp}/new"],
     "nan_run/checkpoint.ckpt: the field's parameters hold NaN"),
    ("explore-nan-checkpoint", ["explore", "{tmp}/nan_run", "--criterion", "colorfulness", "--out", "{tmp}/new"],
     "nan_run/checkpoint.ckpt: the field's parameters hold NaN"),
    ("score-nan-pixel", ["score", "--criterion", "colorfulness", "{tmp}/nan.tiff"], "nan.tiff: the image has 1 NaN"),
    # Files that are not what they should be: said as they are, not "not found".
    ("score-a-directory", ["score", "--criterion", "colorfulness", "{tmp}/run"], "run: a directory"),
    ("score-a-fifo", ["score", "--criterion", "colorfulness", "{tmp}/fifo"], "fifo: a FIFO"),
    ("score-a-symlink-loop", ["score", "--criterion", "colorfulness", "{tmp}/loop"], "loop: a symbolic link loop"),
    ("score-not-an-image", ["score", "--criterion", "colorfulness", "{tmp}/junk.png"], "junk.png: not a readable image"),
    ("render-poses-a-directory", ["render", "{tmp}/tiny_run", "--poses", "{tmp}/run", "--out", "{tmp}/new"],
     "run: a directory"),
    ("scene-a-symlink-loop", ["scene", "info", "{tmp}/loop"], "loop: a symbolic link that leads nowhere"),
    ("train-scene-a-fifo", ["train", "{tmp}/fifo", "--out", "{tmp}/new"], "fifo: unknown scene format"),
    ("render-checkpoint-a-fifo", ["render", "{tmp}/fifo_run", "--poses", "train", "--out", "{tmp}/new"],
     "checkpoint.ckpt: a FIFO"),
]


def _write_scene(folder, translation=None, **meta):
    """A small instant-ngp scene: 8 cameras on a circle looking at the origin, 16x16 images."""
    import imageio.v3 as iio

    from waldo_jax.cameras import look_at

    (folder / "images").mkdir(parents=True)
    frames = []
    for i in range(8):
        angle = 2 * np.pi * i / 8
        c2w = np.asarray(look_at(np.array([3 * np.cos(angle), 0.5, 3 * np.sin(angle)], np.float32), np.zeros(3),
                                 np.array([0.0, 1.0, 0.0])), np.float64)
        c2w = np.concatenate([c2w[:3], [[0, 0, 0, 1]]])
        if translation is not None:
            c2w[0, 3] = translation
        iio.imwrite(folder / "images" / f"{i}.png", np.random.default_rng(i).integers(0, 256, (16, 16, 3), np.uint8))
        frames.append({"file_path": f"images/{i}.png", "transform_matrix": c2w.tolist()})
    (folder / "transforms.json").write_text(json.dumps({"camera_angle_x": 0.8, **meta, "frames": frames}))


def _write_run(folder, nan=False):
    """A run folder with an untrained tiny field (rendering it is cheap); NaN parameters if `nan`."""
    import jax

    from waldo_jax.nerf import HashGridConfig, NGPFieldConfig, init_field
    from waldo_jax.nerf.checkpoint import CHECKPOINT_NAME, save_checkpoint
    from waldo_jax.nerf.config import TrainConfig
    from waldo_jax.scenes import load_scene

    scene = load_scene(folder.parent / "scene")
    field = NGPFieldConfig(aabb=tuple(map(tuple, scene.aabb.tolist())),
                           hashgrid=HashGridConfig(L=2, T=2**8, F=2, N_min=4, N_max=8),
                           density_hidden=(8,), color_hidden=(8,))
    config = TrainConfig(field=field, steps=1, sampler="dense", num_samples=8, samples_per_batch=256, eval_samples=8)
    params = init_field(jax.random.key(0), field)
    if nan:
        params = jax.tree.map(lambda a: np.full_like(a, np.nan), params)
    folder.mkdir()
    save_checkpoint(folder / CHECKPOINT_NAME, params, config, scene)


def _inputs(tmp):
    """The files the cases read, written once per test into `tmp`."""
    import imageio.v3 as iio

    _write_scene(tmp / "scene")
    _write_scene(tmp / "far", translation=1e308)  # finite in JSON, infinite in float32
    _write_scene(tmp / "negative_aabb", aabb_scale=-4)
    _write_run(tmp / "tiny_run")
    _write_run(tmp / "nan_run", nan=True)
    (tmp / "fifo_run").mkdir()
    os.mkfifo(tmp / "fifo_run" / "checkpoint.ckpt")
    os.mkfifo(tmp / "fifo")
    os.symlink(tmp / "loop", tmp / "loop")
    (tmp / "junk.png").write_text("not an image")
    iio.imwrite(tmp / "huge.png", np.zeros((8, 4100, 3), np.uint8))
    iio.imwrite(tmp / "dot.png", np.zeros((1, 1, 3), np.uint8))
    nan = np.random.default_rng(0).random((16, 16, 3)).astype(np.float32)
    nan[3, 3, 0] = np.nan
    iio.imwrite(tmp / "nan.tiff", nan)
    c2w = json.loads((tmp / "scene" / "transforms.json").read_text())["frames"][0]["transform_matrix"]
    (tmp / "wide_poses.json").write_text(json.dumps({"fl_x": 100, "w": 100000, "h": 100,
                                                     "frames": [{"transform_matrix": c2w}]}))


def _snapshot(folder):
    """{relative path: sha256} of every regular file under folder (FIFOs and links by kind only)."""
    import stat

    out = {}
    for root, dirs, files in os.walk(folder):
        for name in files + dirs:
            path = os.path.join(root, name)
            mode = os.lstat(path).st_mode
            if stat.S_ISREG(mode):
                with open(path, "rb") as f:
                    out[os.path.relpath(path, folder)] = hashlib.sha256(f.read()).hexdigest()
            elif not stat.S_ISDIR(mode):
                out[os.path.relpath(path, folder)] = stat.S_IFMT(mode)
    return out


@pytest.fixture(scope="module")
def inputs(tmp_path_factory):
    """One folder of inputs for every case (each case checks it leaves the folder byte-identical)."""
    tmp = tmp_path_factory.mktemp("bad_input")
    (tmp / "run").mkdir()
    (tmp / "run" / "keep.txt").write_text("an earlier run")
    _inputs(tmp)
    return tmp


@pytest.mark.parametrize("argv, expected", [pytest.param(a, e, id=i) for i, a, e in CASES])
def test_bad_input_is_one_line_and_changes_nothing(inputs, capsys, argv, expected):
    tmp_path = inputs
    listing = sorted(os.listdir(tmp_path))
    before = _snapshot(tmp_path)
    status = main([a.replace("{tmp}", str(tmp_path)) for a in argv])
    err = capsys.readouterr().err.strip()
    assert status == 1, err
    lines = err.splitlines()
    assert len(lines) == 1 and lines[0].startswith("waldo: error: "), err
    assert "Traceback" not in err
    assert expected.replace("{tmp}", str(tmp_path)) in lines[0], lines[0]
    assert _snapshot(tmp_path) == before
    assert sorted(os.listdir(tmp_path)) == listing  # nothing created


def test_demo_refusal_does_not_suggest_a_flag_it_lacks(tmp_path, capsys):
    (tmp_path / "keep.txt").write_text("an earlier run")
    assert main(["demo", "--out", str(tmp_path)]) == 1
    err = capsys.readouterr().err
    assert "not empty" in err and "--force" not in err


def test_check_seed_bounds():
    assert check_seed(0) == 0 and check_seed(MAX_SEED) == MAX_SEED
    assert check_seed(MAX_SEED - 3, count=4) == MAX_SEED - 3
    for bad, count in ((-1, 1), (MAX_SEED + 1, 1), (MAX_SEED - 2, 4), (True, 1), (1.5, 1)):
        with pytest.raises(WaldoError, match="--seed"):
            check_seed(bad, count=count)


def _one_warning_line(capsys, argv):
    """Runs argv, expects success, returns the stderr lines that are waldo warnings."""
    status = main(argv)
    err = capsys.readouterr().err
    assert status == 0, err
    assert "Traceback" not in err
    return [line for line in err.splitlines() if line.startswith("waldo: warning: ")]


def test_legal_but_surely_wrong_cameras_load_with_a_one_line_warning(tmp_path, capsys):
    """Repeated camera poses and a principal point outside the image load (the files are valid) but
    each says what is wrong in one line."""
    _write_scene(tmp_path / "pp", cx=5000.0)
    warned = _one_warning_line(capsys, ["scene", "info", str(tmp_path / "pp")])
    assert len(warned) == 1 and "principal point (cx, cy) = (5000, 8) lies outside the 16x16 image" in warned[0]

    _write_scene(tmp_path / "same")
    meta = json.loads((tmp_path / "same" / "transforms.json").read_text())
    for frame in meta["frames"]:
        frame["transform_matrix"] = meta["frames"][0]["transform_matrix"]
    (tmp_path / "same" / "transforms.json").write_text(json.dumps(meta))
    warned = _one_warning_line(capsys, ["scene", "info", str(tmp_path / "same")])
    assert len(warned) == 1 and "7 of 8 cameras repeat another camera's pose (1 distinct)" in warned[0]


def test_an_output_folder_that_cannot_be_written_is_refused_before_training(tmp_path, capsys, monkeypatch):
    """A read-only --out is refused before the scene is loaded or anything trained (the suite may run
    as root, where permissions do not bind: the check's os.access answer is simulated)."""
    _write_scene(tmp_path / "scene")
    (tmp_path / "ro").mkdir()
    real_access = os.access
    monkeypatch.setattr(os, "access", lambda p, mode: False if str(p) == str(tmp_path / "ro") else real_access(p, mode))
    import waldo_jax.nerf.runs as runs

    monkeypatch.setattr(runs, "load_splits", lambda *a, **k: pytest.fail("loaded the scene for an unwritable folder"))
    monkeypatch.setattr(runs, "train", lambda *a, **k: pytest.fail("trained into an unwritable folder"))
    for out in (tmp_path / "ro", tmp_path / "ro" / "new"):
        assert main(["train", str(tmp_path / "scene"), "--out", str(out), "--quiet"]) == 1
        err = capsys.readouterr().err.strip()
        assert err == f"waldo: error: {out}: cannot write there: {tmp_path / 'ro'} is not writable (permission denied)"
    assert os.listdir(tmp_path / "ro") == []


@pytest.mark.parametrize("command", ["explore", "path"])
def test_a_bad_criterion_is_refused_before_the_source_loads(tmp_path, capsys, monkeypatch, command):
    """The criterion's text, its guards' ranges, the target image and a method that needs gradients are
    checked before the source (a room to render, a NeRF run to read) is loaded; the room's oracles,
    which need the source, are still built after it."""
    import waldo_jax.cli.explore as cli_explore
    import waldo_jax.cli.path as cli_path

    module = cli_explore if command == "explore" else cli_path
    real_load = module.load_source
    monkeypatch.setattr(module, "load_source", lambda *a, **k: pytest.fail("loaded the source before the criterion"))
    bad = [(["--criterion", "weighted:composition"], "bad weight"),
           (["--criterion", "weighted:opacity=1,opacity=2"], "names 'opacity' twice"),
           (["--criterion", "colourfulness"], "unknown criterion 'colourfulness'"),
           (["--criterion", "colorfulness", "--guard", "opacty:0.5"], "unknown criterion 'opacty'"),
           (["--criterion", "colorfulness", "--guard", "opacity:2"], "fails every view"),
           (["--criterion", "waldo", "--target", str(tmp_path / "missing.png")], "missing.png")]
    if command == "explore":
        bad.append((["--criterion", "niqe", "--method", "egps+refine"], "'niqe' is not differentiable"))
    for flags, message in bad:
        out = tmp_path / "new"
        assert main([command, "procedural", "--out", str(out), *flags]) == 1
        err = capsys.readouterr().err.strip()
        assert message in err and len(err.splitlines()) == 1, (flags, err)
        assert not out.exists()
    # An oracle needs the room: the source loads first and the oracle is built from it (here it is then
    # refused, as a poses criterion takes no guard).
    calls = []
    monkeypatch.setattr(module, "load_source", lambda *a, **k: calls.append(a) or real_load(*a, **k))
    assert main([command, "procedural:1", "--out", str(tmp_path / "oracle"), "--criterion", "waldo_oracle",
                 "--guard", "opacity:0.5"]) == 1
    assert calls and "scores poses" in capsys.readouterr().err


def test_a_full_disk_leaves_no_half_written_file_and_one_line(tmp_path, capsys, monkeypatch):
    """Every file goes through io.atomic_file: when the disk fills up mid-write, the file being written
    is absent (no 0-byte PNG), earlier files are whole, and the error is one line naming the file."""
    import waldo_jax.io as io_module

    real_open_temp = io_module._open_temp
    written = []

    class FullDisk:
        def __init__(self, f):
            self.f = f

        def write(self, data):
            raise OSError(errno.ENOSPC, "No space left on device", self.f.name)

        def __getattr__(self, name):
            return getattr(self.f, name)

        def __enter__(self):
            return self

        def __exit__(self, *exc):
            self.f.close()

    def open_temp(path):
        name, f = real_open_temp(path)
        written.append(path.name)
        return (name, FullDisk(f)) if len(written) == 2 else (name, f)  # the second file hits a full disk

    monkeypatch.setattr(io_module, "_open_temp", open_temp)
    out = tmp_path / "views"
    status = main(["render", "procedural", "--views", "3", "--resolution", "16", "--samples", "16", "--out", str(out)])
    err = capsys.readouterr().err.strip()
    assert status == 1 and len(err.splitlines()) == 1 and "No space left on device" in err, err
    assert "Traceback" not in err
    files = sorted(os.listdir(out))
    assert files == ["view_000.png"], files  # the first view whole; no temporary file, no empty PNG
    assert os.path.getsize(out / "view_000.png") > 0


def test_atomic_file_keeps_the_old_file_when_the_write_fails(tmp_path):
    from waldo_jax import io

    target = tmp_path / "results.json"
    io.write_json(target, {"a": 1})
    with pytest.raises(RuntimeError):
        with io.atomic_file(target) as f:
            f.write(b"half")
            raise RuntimeError("interrupted")
    assert json.loads(target.read_text()) == {"a": 1} and os.listdir(tmp_path) == ["results.json"]
    io.write_json(target, {"nan": float("nan"), "inf": np.float32(np.inf), "x": np.arange(2)})
    assert json.loads(target.read_text()) == {"nan": None, "inf": None, "x": [0, 1]}  # strict JSON


def test_render_force_replaces_an_earlier_render_without_stale_files(tmp_path, capsys):
    out = tmp_path / "views"
    assert main(["render", "procedural", "--views", "3", "--resolution", "8", "--samples", "8", "--out", str(out)]) == 0
    (out / "notes.txt").write_text("mine")
    assert main(["render", "procedural", "--views", "2", "--resolution", "8", "--samples", "8", "--out", str(out),
                 "--force"]) == 0
    capsys.readouterr()
    assert sorted(os.listdir(out)) == ["contact_sheet.png", "notes.txt", "room.json", "transforms.json",
                                       "view_000.png", "view_001.png"]
