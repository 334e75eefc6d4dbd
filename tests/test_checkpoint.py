"""Tests of checkpoints (waldo_jax.nerf.checkpoint) and the `waldo train` / `waldo render` handlers.

A synthetic 3-view scene and a tiny field keep these independent of the data folder and fast.
"""

from __future__ import annotations

import dataclasses
import json
import os
import re

import waldo_jax  # noqa: F401  (XLA flags before the first computation)

import imageio.v3 as iio
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from waldo_jax.cameras import look_at
from waldo_jax.errors import WaldoError
from waldo_jax.nerf import HashGridConfig, NGPFieldConfig, init_field
from waldo_jax.nerf import checkpoint as ckpt
from waldo_jax.cli import build_parser
from waldo_jax.nerf.config import TrainConfig
from waldo_jax.nerf.samplers import make_sampler
from waldo_jax.types import Intrinsics, Scene

BOX = ((-1.5, -1.5, -1.5), (1.5, 1.5, 1.5))
FIELD = NGPFieldConfig(
    aabb=BOX, hashgrid=HashGridConfig(L=4, T=2**10, F=2, N_min=4, N_max=32), density_hidden=(16,), color_hidden=(16,)
)


def _config(sampler: str = "dense") -> TrainConfig:
    return TrainConfig(
        field=FIELD,
        steps=10,
        sampler=sampler,
        occupancy_resolution=8,
        num_samples=16,
        samples_per_batch=256,
        eval_samples=16,
    )


def _scene() -> Scene:
    origins = np.array([[0.0, 0.5, 4.0], [4.0, 0.3, 0.0], [-2.0, 3.0, 2.5]], np.float32)
    c2w = np.stack([np.asarray(look_at(o, np.zeros(3), np.array([0.0, 1.0, 0.0]))) for o in origins])
    return Scene(
        images=np.random.default_rng(0).uniform(size=(3, 6, 8, 3)).astype(np.float32),
        c2w=c2w.astype(np.float32),
        intrinsics=Intrinsics.create(8, 6, 9.5, 9.25, 4.1, 2.9, [0.01, -0.002, 0.0005, 0.0]),
        aabb=np.asarray(BOX, np.float32),
        near=2.0,
        far=6.0,
        file_names=("train/r_0.png", "train/r_1.png", "train/r_2.png"),
        format="blender",
        name="synthetic",
        split="train",
        path="/data/synthetic",
        alphas=np.ones((3, 6, 8), np.float32),
        background=np.ones(3, np.float32),
        metadata={"scene_file": ["transforms_train.json"], "downscale": np.float64(1.0)},
    )


def _params(seed: int = 0):
    params = init_field(jax.random.key(seed), FIELD)
    # Values whose bits a lossy round trip would change: -0.0, a subnormal, the largest float32 (NaN
    # and inf go into the occupancy density: a checkpoint refuses non-finite field parameters).
    special = jnp.array([[3.4028235e38, -0.0], [-3.4028235e38, 1e-45]], jnp.float32)
    params["hash"] = params["hash"].at[:2].set(special)
    return params


def _occupancy(config: TrainConfig):
    params = init_field(jax.random.key(0), FIELD)
    grid = make_sampler(config).init(jax.random.key(1), params)
    density = jax.random.uniform(jax.random.key(2), grid.density.shape)
    # A NaN payload and inf: stored bit for bit.
    nan_payload = jnp.asarray(np.array([0x7FC00123], np.uint32).view(np.float32))
    density = (
        density.reshape(-1).at[:2].set(jnp.concatenate([nan_payload, jnp.array([jnp.inf])])).reshape(density.shape)
    )
    return grid.replace(density=density, bitfield=density > 0.5)


def _bytes(tree):
    return [(np.asarray(x).dtype.str, np.asarray(x).shape, np.asarray(x).tobytes()) for x in jax.tree.leaves(tree)]


@pytest.fixture()
def saved(tmp_path):
    path = tmp_path / "run" / ckpt.CHECKPOINT_NAME
    path.parent.mkdir()
    ckpt.save_checkpoint(path, _params(), _config(), _scene(), info={"psnr_test": 31.5})
    return path


# ----------------------------------------------------------------------------------------------
# Round trip.


@pytest.mark.slow
@pytest.mark.parametrize("sampler", ["dense", "occupancy"])
def test_round_trip_is_bit_exact(tmp_path, sampler):
    config = _config(sampler)
    params = _params()
    occupancy = _occupancy(config) if sampler == "occupancy" else None
    scene = _scene()
    path = ckpt.save_checkpoint(
        tmp_path / "model.ckpt", params, config, scene, occupancy, info={"steps": 10, "psnr_test": float("nan")}
    )
    loaded = ckpt.load_checkpoint(path)
    assert _bytes(loaded.params) == _bytes(params)
    assert jax.tree.structure(loaded.params) == jax.tree.structure(params)
    if occupancy is None:
        assert loaded.occupancy is None
    else:
        assert _bytes(loaded.occupancy) == _bytes(occupancy)
        assert type(loaded.occupancy) is type(occupancy)
        assert loaded.occupancy.resolution == occupancy.resolution
    assert loaded.config == config
    assert loaded.format_version == ckpt.FORMAT_VERSION
    record = loaded.scene
    assert record.intrinsics.to_dict() == scene.intrinsics.to_dict()
    assert record.c2w.tobytes() == scene.c2w.tobytes()
    assert record.aabb.tobytes() == scene.aabb.tobytes()
    assert (record.near, record.far) == (scene.near, scene.far)
    assert record.file_names == scene.file_names
    assert (record.path, record.format, record.name, record.split) == (scene.path, "blender", "synthetic", "train")
    np.testing.assert_array_equal(record.background, scene.background)
    assert record.metadata == {"scene_file": ["transforms_train.json"], "downscale": 1.0}
    assert loaded.info["steps"] == 10 and np.isnan(loaded.info["psnr_test"])
    # A run directory works as well as the file.
    assert _bytes(ckpt.load_checkpoint(_dir_with(tmp_path, path)).params) == _bytes(params)


@pytest.mark.slow
def test_trained_field_of_a_checkpoint_is_one_pytree_with_its_scene_settings(saved):
    """`TrainedField.from_checkpoint`: params and occupancy are the leaves, the config is static, and near,
    far, box and background come from the training scene (black for an opaque one); it renders as the
    same field built by hand."""
    from waldo_jax.nerf.trained import TrainedField, render_trained

    loaded = ckpt.load_checkpoint(saved)
    field = TrainedField.from_checkpoint(loaded)
    assert (float(field.near), float(field.far)) == (2.0, 6.0)
    np.testing.assert_array_equal(field.aabb, np.asarray(BOX, np.float32))
    np.testing.assert_array_equal(field.background, np.ones(3, np.float32))
    leaves, treedef = jax.tree.flatten(field)
    assert len(leaves) == len(jax.tree.leaves(loaded.params)) + 4  # + near, far, background, aabb (dense: no grid)
    assert jax.tree.unflatten(treedef, leaves).config == loaded.config
    opaque = dataclasses.replace(loaded, scene=dataclasses.replace(loaded.scene, background=None))
    np.testing.assert_array_equal(TrainedField.from_checkpoint(opaque).background, np.zeros(3, np.float32))
    c2w, intrinsics = loaded.scene.c2w[:1], loaded.scene.intrinsics.scaled(8, 6)
    by_hand = TrainedField.create(loaded.params, None, loaded.config, 2.0, 6.0, np.ones(3), BOX)
    np.testing.assert_array_equal(
        np.asarray(render_trained(field, c2w, intrinsics).rgb), np.asarray(render_trained(by_hand, c2w, intrinsics).rgb)
    )


def test_a_relative_scene_path_is_recorded_whole(tmp_path, monkeypatch):
    """A run trained from `cd a; waldo train scene` is read from any folder: its scene is recorded by its
    whole path (a relative one was read from the reader's folder, where another scene of the same file
    names was scored as the training images without a word)."""
    monkeypatch.chdir(tmp_path)
    scene = dataclasses.replace(_scene(), path="scenes/synthetic")
    path = ckpt.save_checkpoint(tmp_path / "a.ckpt", _params(), _config(), scene)
    monkeypatch.chdir("/")
    assert ckpt.load_checkpoint(path).scene.path == str(tmp_path / "scenes" / "synthetic")


def _dir_with(tmp_path, path):
    run = tmp_path / "rundir"
    run.mkdir(exist_ok=True)
    (run / ckpt.CHECKPOINT_NAME).write_bytes(path.read_bytes())
    return run


# ----------------------------------------------------------------------------------------------
# Damaged and incompatible files.


@pytest.mark.slow
@pytest.mark.parametrize("where", [0.0, 0.01, 0.3, 0.6, 0.999])
def test_flipped_byte_is_reported_naming_the_file(saved, where):
    raw = bytearray(saved.read_bytes())
    index = min(len(raw) - 1, int(where * len(raw)))
    raw[index] ^= 0x5A
    saved.write_bytes(bytes(raw))
    with pytest.raises(ckpt.CheckpointError, match="corrupt|not a waldo_jax checkpoint|truncated") as info:
        ckpt.load_checkpoint(saved)
    assert str(saved) in str(info.value)


@pytest.mark.slow
@pytest.mark.parametrize("keep", [0, 5, 30, 0.5, -1])
def test_truncated_file_is_reported_naming_the_file(saved, keep):
    raw = saved.read_bytes()
    length = keep if isinstance(keep, int) and keep >= 0 else (len(raw) - 1 if keep == -1 else int(keep * len(raw)))
    saved.write_bytes(raw[:length])
    with pytest.raises(ckpt.CheckpointError, match="truncated") as info:
        ckpt.load_checkpoint(saved)
    assert str(saved) in str(info.value)


def _resigned(path, edit):
    """The checkpoint at `path` with its header edited by `edit(header)`, length and digest written again
    (a file that passes the digest check: what a tool or a hand that rewrites checkpoints could leave)."""
    import hashlib
    import struct

    raw = path.read_bytes()
    start = len(ckpt.MAGIC) + 8
    (length,) = struct.unpack_from("<Q", raw, len(ckpt.MAGIC))
    header = json.loads(raw[start : start + length])
    edit(header)
    text = json.dumps(header).encode()
    body = ckpt.MAGIC + struct.pack("<Q", len(text)) + text + raw[start + length : -32]
    path.write_bytes(body + hashlib.sha256(body).digest())


def _c2w_entry(header):
    return next(e for e in header["arrays"] if e["name"] == "scene/c2w")


@pytest.mark.parametrize(
    "edit, says",
    [
        (lambda h: _c2w_entry(h).update(dtype="object"), "array scene/c2w: dtype object is not a number type"),
        (lambda h: _c2w_entry(h).update(dtype="U", nbytes=0), "array scene/c2w: dtype <U0 is not a number type"),
        (lambda h: _c2w_entry(h).update(dtype="complex64"), "dtype complex64 is not a number type"),
        (lambda h: _c2w_entry(h).update(shape=[-8, 4, 4], nbytes=-512), "array scene/c2w: negative shape [-8, 4, 4]"),
        (lambda h: _c2w_entry(h).update(shape=[2**62, 2**62, 4]), "array scene/c2w: inconsistent size or offset"),
        (lambda h: h.update(info=5), "its 'info' is a int, not an object"),
        (lambda h: h["scene"].update(near=10**400), "near"),
        # The metadata that a run's readers use, by key (each once a traceback in `waldo render`/`explore`).
        (lambda h: h["scene"]["metadata"].update(nerfstudio_applied=5), "metadata 'nerfstudio_applied' is 5"),
        (
            lambda h: h["scene"]["metadata"].update(nerfstudio_applied={"transform": None, "scale": "x"}),
            "metadata 'nerfstudio_applied'",
        ),
        (lambda h: h["scene"]["metadata"].update(scale="x"), "metadata 'scale' is \"x\", not a positive number"),
        (lambda h: h["scene"]["metadata"].update(offset=[0, 0]), "metadata 'offset' is [0, 0], not 3 numbers"),
        (lambda h: h["scene"]["metadata"].update(seed="abc"), "metadata 'seed' is \"abc\", not an integer"),
        (lambda h: h["scene"]["metadata"].update(scale=10**400), "metadata 'scale' is Infinity, not a positive"),
        (lambda h: h["scene"]["metadata"].update(waldo_scale=9), "metadata 'waldo_scale' is 9"),
        (lambda h: h["scene"]["metadata"].update(scene_file="/etc/passwd"), "metadata 'scene_file'"),
        (lambda h: h["scene"].update(file_names=h["scene"]["file_names"][:1]), "lists 1 names for 3 training poses"),
        (lambda h: h["scene"].update(file_names=[1, 2]), "file_names is not a list of names"),
    ],
    ids=[
        "object",
        "text",
        "complex",
        "negative-shape",
        "shape-wraps-int64",
        "info",
        "huge-int",
        "applied-int",
        "applied-scale-text",
        "scale-text",
        "offset-short",
        "seed-text",
        "scale-past-float64",
        "waldo-scale-range",
        "scene-file-absolute",
        "names-short",
        "names-numbers",
    ],
)
def test_a_checkpoint_header_that_passes_its_digest_is_still_checked(saved, edit, says):
    """The array table and header fields are checked by kind even where the digest matches (each case once
    ended in a traceback from NumPy, or loaded an inconsistent table)."""
    _resigned(saved, edit)
    with pytest.raises(ckpt.CheckpointError, match=re.escape(says)) as info:
        ckpt.load_checkpoint(saved)
    assert str(saved) in str(info.value)


@pytest.mark.slow
def test_wrong_format_version_is_a_clear_error(tmp_path, monkeypatch):
    monkeypatch.setattr(ckpt, "FORMAT_VERSION", 99)
    path = ckpt.save_checkpoint(tmp_path / "future.ckpt", _params(), _config(), _scene())
    monkeypatch.undo()
    with pytest.raises(ckpt.CheckpointError, match=r"format_version 99.*reads version 1") as info:
        ckpt.load_checkpoint(path)
    assert str(path) in str(info.value)


@pytest.mark.slow
def test_shape_mismatch_with_the_stored_config_names_the_array(tmp_path):
    bigger = NGPFieldConfig(
        aabb=BOX,
        hashgrid=HashGridConfig(L=4, T=2**11, F=2, N_min=4, N_max=64),
        density_hidden=(16,),
        color_hidden=(16,),
    )
    params = init_field(jax.random.key(0), bigger)
    path = ckpt.save_checkpoint(tmp_path / "mismatch.ckpt", params, _config(), _scene())
    with pytest.raises(ckpt.CheckpointError, match=r"incompatible.*params/hash") as info:
        ckpt.load_checkpoint(path)
    assert str(path) in str(info.value)


def test_missing_file_and_other_files_are_reported(tmp_path):
    with pytest.raises(ckpt.CheckpointError, match="no such checkpoint"):
        ckpt.load_checkpoint(tmp_path / "absent.ckpt")
    other = tmp_path / "notes.txt"
    other.write_text("hello, this is not a checkpoint at all")
    with pytest.raises(ckpt.CheckpointError, match="not a waldo_jax checkpoint"):
        ckpt.load_checkpoint(other)


# ----------------------------------------------------------------------------------------------
# Atomic writes.


def test_write_leaves_no_temporary_file(tmp_path):
    ckpt.save_checkpoint(tmp_path / "a.ckpt", _params(), _config(), _scene())
    ckpt.save_checkpoint(tmp_path / "a.ckpt", _params(1), _config(), _scene())  # overwrite
    assert sorted(os.listdir(tmp_path)) == ["a.ckpt"]
    assert _bytes(ckpt.load_checkpoint(tmp_path / "a.ckpt").params) == _bytes(_params(1))


def test_failed_write_keeps_the_old_file_and_cleans_up(saved, monkeypatch):
    before = saved.read_bytes()

    def failing_replace(src, dst):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(ckpt.os, "replace", failing_replace)
    with pytest.raises(OSError, match="No space left"):
        ckpt.save_checkpoint(saved, _params(1), _config(), _scene())
    monkeypatch.undo()
    assert saved.read_bytes() == before
    assert sorted(os.listdir(saved.parent)) == [saved.name]


# ----------------------------------------------------------------------------------------------
# Command handlers.


def _parse(argv):
    return build_parser().parse_args(argv)


def test_train_refuses_a_non_empty_run_dir_without_force(tmp_path):
    run = tmp_path / "run"
    run.mkdir()
    (run / "keep.txt").write_text("earlier results")
    args = _parse(["train", str(tmp_path / "no-scene-needed"), "--out", str(run), "--steps", "3"])
    with pytest.raises(WaldoError, match=r"not empty.*--force") as info:
        args.handler(args)
    assert str(run) in str(info.value)
    assert sorted(os.listdir(run)) == ["keep.txt"]
    # With --force the run dir is accepted and the next problem (the missing scene) is reported.
    forced = _parse(["train", str(tmp_path / "no-scene-needed"), "--out", str(run), "--force"])
    with pytest.raises(WaldoError, match="no-scene-needed"):
        forced.handler(forced)


@pytest.mark.parametrize(
    "argv, message",
    [
        (["--preset", "best"], "unknown --preset 'best'"),  # refused by the parser (choices), one line too
        (["--steps", "0"], "--steps must be a positive integer"),
        (["--downscale", "-2"], "--downscale must be a positive number"),
        (["--render-step-scale", "0"], "--render-step-scale must be a positive number"),
        (["--eval-max-pixels", "-1"], "--eval-max-pixels must be 0"),
        (["--eval-max-pixels", "1"], "at least 64 pixels"),  # held-out views of 1x1 were compared
        (["--model", "splat", "--eval-max-pixels", "100"], "--eval-max-pixels: for NeRF training only"),
        (["--pixel-sampling", "worst"], "unknown --pixel-sampling 'worst'"),
        (["--model", "splat", "--pixel-sampling", "error"], "--pixel-sampling: for NeRF training only"),
    ],
)
def test_train_rejects_bad_arguments(tmp_path, argv, message):
    with pytest.raises(WaldoError, match=message):
        args = _parse(["train", str(tmp_path), "--out", str(tmp_path / "run")] + argv)
        args.handler(args)


@pytest.mark.slow
def test_train_draws_pixels_by_their_error_when_asked(tmp_path):
    """`waldo train --pixel-sampling error` trains with `TrainConfig.pixel_sampling="error"` (recorded in the
    checkpoint and train.json); the default stays uniform."""
    from test_bad_input import _write_scene

    _write_scene(tmp_path / "scene")
    for mode in ("error", None):
        out = tmp_path / f"run-{mode}"
        argv = ["train", str(tmp_path / "scene"), "--out", str(out), "--steps", "2", "--quiet"]
        args = _parse(argv + ([] if mode is None else ["--pixel-sampling", mode]))
        assert args.handler(args) == 0
        expected = mode or "uniform"
        assert ckpt.load_checkpoint(out / ckpt.CHECKPOINT_NAME).config.pixel_sampling == expected
        assert json.loads((out / "train.json").read_text())["config"]["pixel_sampling"] == expected


@pytest.mark.slow
def test_render_writes_pngs_of_train_poses_and_a_poses_file(tmp_path, capsys):
    run = tmp_path / "run"
    run.mkdir()
    scene = _scene()
    ckpt.save_checkpoint(run / ckpt.CHECKPOINT_NAME, init_field(jax.random.key(0), FIELD), _config(), scene)

    args = _parse(["render", str(run), "--poses", "train", "--out", str(tmp_path / "train_views")])
    assert args.handler(args) == 0
    files = sorted(os.listdir(tmp_path / "train_views"))
    assert files == ["0000.png", "0001.png", "0002.png"]
    assert iio.imread(tmp_path / "train_views" / "0000.png").shape == (6, 8, 3)

    poses = {
        "w": 20,
        "h": 10,
        "fl_x": 18.0,
        "frames": [
            {"file_path": "a.png", "transform_matrix": np.asarray(scene.c2w[1], np.float64).tolist()},
            {"file_path": "b.png", "transform_matrix": np.asarray(scene.c2w[2], np.float64).tolist()},
        ],
    }
    (tmp_path / "poses.json").write_text(json.dumps(poses))
    args = _parse(
        [
            "render",
            str(run),
            "--poses",
            str(tmp_path / "poses.json"),
            "--out",
            str(tmp_path / "novel"),
            "--resolution",
            "12",
        ]
    )
    assert args.handler(args) == 0
    assert sorted(os.listdir(tmp_path / "novel")) == ["0000.png", "0001.png"]
    assert iio.imread(tmp_path / "novel" / "0001.png").shape == (6, 12, 3)  # longer side 12, aspect 2:1

    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"frames": [{"transform_matrix": [[1, 0], [0, 1]]}]}))
    args = _parse(["render", str(run), "--poses", str(bad), "--out", str(tmp_path / "x")])
    with pytest.raises(WaldoError, match=r"bad.json.*frame 0.*shape \[2, 2\]"):
        args.handler(args)
    args = _parse(["render", str(tmp_path / "nothing"), "--poses", "train", "--out", str(tmp_path / "y")])
    with pytest.raises(WaldoError, match="does not exist"):
        args.handler(args)
    # Earlier renders are never overwritten silently; a run needs --poses.
    args = _parse(["render", str(run), "--poses", "train", "--out", str(tmp_path / "train_views")])
    with pytest.raises(WaldoError, match="not empty"):
        args.handler(args)
    args = _parse(["render", str(run), "--out", str(tmp_path / "z")])
    with pytest.raises(WaldoError, match="--poses"):
        args.handler(args)


def test_non_finite_field_parameters_are_refused_naming_the_file(tmp_path):
    """A diverged training (NaN parameters, valid digest) would render all-white views: refused."""
    params = init_field(jax.random.key(0), FIELD)
    params["hash"] = params["hash"].at[3, 1].set(jnp.nan)
    path = ckpt.save_checkpoint(tmp_path / "diverged.ckpt", params, _config(), _scene())
    with pytest.raises(
        ckpt.CheckpointError,
        match=r"diverged\.ckpt: the field's parameters hold NaN or infinity "
        r"\(1 arrays, e.g. \['hash'\]\)",
    ):
        ckpt.load_checkpoint(path)


@pytest.mark.slow
def test_a_run_of_the_demo_room_rebuilds_that_room_not_the_default(tmp_path):
    """`waldo demo` trains on a room with a larger Waldo and wider stripes than `make_room(seed)`: its
    checkpoint records them, and `run_source` (`waldo explore RUN`) rebuilds that room for its oracle."""
    from waldo_jax.pipeline.sources import run_source
    from waldo_jax.procedural import make_room, room_scene

    room = make_room(1, waldo_scale=1.5, stripe_width=0.15)
    scene, _ = room_scene(1, num_views=2, resolution=8, num_samples=16, room=room)
    run = tmp_path / "run"
    run.mkdir()
    ckpt.save_checkpoint(run / ckpt.CHECKPOINT_NAME, init_field(jax.random.key(0), FIELD), _config(), scene)
    source = run_source(str(run))
    assert source.info["procedural_seed"] == 1
    for name in ("center", "size", "waldo_points", "waldo_scale", "stripe_width"):
        np.testing.assert_array_equal(getattr(source.room, name), getattr(room, name), err_msg=name)
    assert not np.array_equal(make_room(1).waldo_points, room.waldo_points)  # the default room differs


def test_a_file_larger_than_its_header_says_is_refused_before_it_is_read(saved, monkeypatch):
    """A checkpoint grown (sparse) to 32 GiB past what its header describes, more than this machine's memory
    (a 4 GiB one took 4.4 GB to be refused): refused from its header and size alone; reading it whole would
    have failed. One too large for the free memory is refused by its size before it is read."""
    with open(saved, "r+b") as f:
        f.truncate(32 << 30)
    with pytest.raises(ckpt.CheckpointError, match="trailing data"):
        ckpt.load_checkpoint(saved)
    saved.unlink()
    ckpt.save_checkpoint(saved, _params(), _config(), _scene())
    monkeypatch.setattr(ckpt, "host_memory_bytes", lambda: 1000)
    with pytest.raises(ckpt.CheckpointError, match="GiB, more than the 0.0 GiB this machine has free"):
        ckpt.load_checkpoint(saved)
