"""Weights: the torch pickle reader (legacy and zip, written here without torch), the native store,
`waldo weights convert`."""

from __future__ import annotations

import collections
import io
import json
import os
import pickle
import struct
import warnings
import zipfile

import numpy as np
import pytest

import waldo_jax  # noqa: F401  (before jax: XLA flags)
from waldo_jax.cli import main
from waldo_jax.errors import DataNotFoundError, WaldoError
from waldo_jax.weights import (
    TorchPickleError,
    WeightsError,
    check_shapes,
    load_native,
    read_torch_file,
    save_native,
    state_dict,
)
from waldo_jax.weights.store import convert_all

from conftest import require_weights


# --- writing torch checkpoints without torch ------------------------------------------------------
# A tensor pickles as REDUCE(torch._utils._rebuild_tensor_v2, (storage, offset, size, stride,
# requires_grad, hooks)), its storage as a persistent id ("storage", torch.FloatStorage, key,
# location, numel). The pure-Python pickler lets us emit those globals by name.


class _Global:
    def __init__(self, module, name):
        self.module, self.name = module, name

    def __call__(self):  # pickle wants a callable in REDUCE; never called here
        raise NotImplementedError


_REBUILD = _Global("torch._utils", "_rebuild_tensor_v2")
_STORAGE_NAMES = {
    np.dtype(np.float32): "FloatStorage",
    np.dtype(np.int64): "LongStorage",
    np.dtype(np.float64): "DoubleStorage",
    np.dtype(np.float16): "HalfStorage",
}


class _FakeStorage:
    def __init__(self, key, array):
        self.key, self.array = key, np.ascontiguousarray(array).ravel()


class _FakeTensor:
    def __init__(self, storage, offset, shape, stride):
        self.storage, self.offset, self.shape, self.stride = storage, offset, shape, stride


class _TorchPickler(pickle._Pickler):
    def reducer_override(self, obj):
        if isinstance(obj, _FakeTensor):
            return _REBUILD, (obj.storage, obj.offset, obj.shape, obj.stride, False, collections.OrderedDict())
        return NotImplemented

    def save(self, obj, save_persistent_id=True):
        if isinstance(obj, _Global):
            self.write(pickle.GLOBAL + f"{obj.module}\n{obj.name}\n".encode())
            return
        super().save(obj, save_persistent_id)

    def persistent_id(self, obj):
        if isinstance(obj, _FakeStorage):
            storage_type = _Global("torch", _STORAGE_NAMES[obj.array.dtype])
            return ("storage", storage_type, obj.key, "cpu", obj.array.size)
        return None


def _tensors(arrays):
    """One storage and one contiguous fake tensor per array."""
    storages, obj = [], collections.OrderedDict()
    for i, (name, array) in enumerate(arrays.items()):
        storage = _FakeStorage(str(i), array)
        storages.append(storage)
        strides = tuple(s // array.itemsize for s in np.require(array, requirements="C").strides)
        obj[name] = _FakeTensor(storage, 0, array.shape, strides)
    return storages, obj


def _dumps(obj):
    buffer = io.BytesIO()
    _TorchPickler(buffer, protocol=2).dump(obj)
    return buffer.getvalue()


def write_legacy(path, arrays, wrap=True):
    storages, tensors = _tensors(arrays)
    obj = {"epoch": 3, "state_dict": tensors} if wrap else tensors
    parts = [
        pickle.dumps(0x1950A86A20F9469CFC6C, protocol=2),
        pickle.dumps(1001, protocol=2),
        pickle.dumps({"protocol_version": 1001, "little_endian": True}, protocol=2),
        _dumps(obj),
        pickle.dumps([s.key for s in storages], protocol=2),
    ]
    for s in storages:
        parts.append(struct.pack("<q", s.array.size) + s.array.astype(s.array.dtype.newbyteorder("<")).tobytes())
    path.write_bytes(b"".join(parts))


def write_zip(path, arrays):
    storages, tensors = _tensors(arrays)
    with zipfile.ZipFile(path, "w") as archive:
        archive.writestr("archive/data.pkl", _dumps(tensors))
        archive.writestr("archive/version", "3\n")
        for s in storages:
            archive.writestr(f"archive/data/{s.key}", s.array.tobytes())


ARRAYS = {
    "conv.weight": np.arange(2 * 3 * 3 * 3, dtype=np.float32).reshape(2, 3, 3, 3) / 7,
    "conv.bias": np.array([0.5, -1.25], np.float32),
    "bn.num_batches_tracked": np.array(12, np.int64),
    "fc.weight": np.random.default_rng(0).normal(size=(4, 5)).astype(np.float64),
}


@pytest.mark.parametrize("writer", [write_legacy, write_zip], ids=["legacy", "zip"])
def test_reader_round_trips_tensors_bit_exactly(tmp_path, writer):
    path = tmp_path / "model.pth"
    writer(path, ARRAYS)
    got = state_dict(read_torch_file(path))
    assert list(got) == list(ARRAYS)
    for name, array in ARRAYS.items():
        assert got[name].dtype == array.dtype and got[name].shape == array.shape
        np.testing.assert_array_equal(got[name], array)


def test_reader_honours_offsets_and_strides(tmp_path):
    """A transposed view at an offset into a shared storage (as torch saves `w.t()` or a slice)."""
    base = np.arange(30, dtype=np.float32)
    storage = _FakeStorage("0", base)
    obj = collections.OrderedDict(
        t=_FakeTensor(storage, 2, (4, 3), (1, 4)),  # columns of a 3x4 block starting at element 2
        tail=_FakeTensor(storage, 20, (10,), (1,)),
    )
    path = tmp_path / "views.pth"
    parts = [
        pickle.dumps(0x1950A86A20F9469CFC6C, protocol=2),
        pickle.dumps(1001, protocol=2),
        pickle.dumps({"little_endian": True}, protocol=2),
        _dumps(obj),
        pickle.dumps(["0"], protocol=2),
        struct.pack("<q", base.size) + base.tobytes(),
    ]
    path.write_bytes(b"".join(parts))
    got = read_torch_file(path)
    np.testing.assert_array_equal(got["t"], base[2:14].reshape(3, 4).T)
    np.testing.assert_array_equal(got["tail"], base[20:30])


def test_reader_refuses_code_and_reports_corruption(tmp_path):
    evil = tmp_path / "evil.pth"
    parts = [
        pickle.dumps(0x1950A86A20F9469CFC6C, protocol=2),
        pickle.dumps(1001, protocol=2),
        pickle.dumps({"little_endian": True}, protocol=2),
        b"cos\nsystem\n(S'true'\ntR.",
    ]
    evil.write_bytes(b"".join(parts))
    with pytest.raises(TorchPickleError, match="refusing to unpickle os.system"):
        read_torch_file(evil)

    good = tmp_path / "good.pth"
    write_legacy(good, ARRAYS)
    raw = good.read_bytes()
    truncated = tmp_path / "truncated.pth"
    truncated.write_bytes(raw[:-10])
    with pytest.raises(TorchPickleError, match="truncated.pth.*truncated or corrupt"):
        read_torch_file(truncated)
    garbage = tmp_path / "garbage.pth"
    garbage.write_bytes(b"\x00" * 100)
    with pytest.raises(TorchPickleError, match="garbage.pth"):
        read_torch_file(garbage)
    with pytest.raises(DataNotFoundError, match="nope.pth"):
        read_torch_file(tmp_path / "nope.pth")


_EVIL = b"cos\nsystem\n(S'touch {marker}'\ntR."


@pytest.mark.parametrize("position", range(5))
def test_no_pickle_of_a_legacy_file_runs_code(tmp_path, position):
    """Code in any of the legacy format's five pickles (magic number, protocol, system info, object,
    storage keys) is refused before it runs: the marker file is never made."""
    marker = tmp_path / "ran"
    parts = [
        pickle.dumps(0x1950A86A20F9469CFC6C, protocol=2),
        pickle.dumps(1001, protocol=2),
        pickle.dumps({"little_endian": True}, protocol=2),
        pickle.dumps({}, protocol=2),
        pickle.dumps([], protocol=2),
    ]
    parts[position] = _EVIL.replace(b"{marker}", str(marker).encode())
    evil = tmp_path / "evil.pth"
    evil.write_bytes(b"".join(parts))
    with pytest.raises(TorchPickleError, match="evil.pth: refusing to unpickle os.system"):
        read_torch_file(evil)
    assert not marker.exists()


@pytest.mark.parametrize(
    "offset, size, stride",
    [(0, (1000,), (-1000000,)), (0, (-5,), (1,)), (-3, (2,), (1,)), (0, (2, 2), (1,)), (0, (2.5,), (1,))],
    ids=["negative-stride", "negative-size", "negative-offset", "stride-per-dimension", "float-size"],
)
def test_a_tensor_header_outside_its_storage_is_refused(tmp_path, offset, size, stride):
    """A tensor's offset, sizes and strides must address its storage: a negative stride once read
    memory outside it (a crash), a negative size raised from NumPy."""
    storage = _FakeStorage("0", np.arange(10, dtype=np.float32))
    path = tmp_path / "bad.pth"
    path.write_bytes(
        b"".join(
            [
                pickle.dumps(0x1950A86A20F9469CFC6C, protocol=2),
                pickle.dumps(1001, protocol=2),
                pickle.dumps({"little_endian": True}, protocol=2),
                _dumps(collections.OrderedDict(w=_FakeTensor(storage, offset, size, stride))),
                pickle.dumps(["0"], protocol=2),
                struct.pack("<q", 10) + storage.array.tobytes(),
            ]
        )
    )
    with pytest.raises(TorchPickleError, match="bad.pth.*(non-negative|overruns)"):
        read_torch_file(path)


def test_a_zip_member_that_inflates_past_its_storage_is_not_read_whole(tmp_path, monkeypatch):
    """A storage member longer than its tensor loads (its tensor's bytes are used), and an object pickle
    inflating past `MAX_PICKLE_BYTES` is refused by name. (That the long member is inflated only as far as
    the tensor needs is `_read_member`'s bounded read; the peak memory is not measured here.)"""
    from waldo_jax.weights import torch_pickle

    path = tmp_path / "bomb.pth"
    write_zip(path, {"w": np.arange(4, dtype=np.float32)})
    # Rewrite the storage member as its 16 bytes followed by 64 MiB of zeros (a 64 KiB deflated member).
    rebuilt = tmp_path / "rebuilt.pth"
    with zipfile.ZipFile(path) as src, zipfile.ZipFile(rebuilt, "w", compression=zipfile.ZIP_DEFLATED) as dst:
        for name in src.namelist():
            data = src.read(name)
            dst.writestr(name, data + bytes(64 * 2**20) if name == "archive/data/0" else data)
    assert rebuilt.stat().st_size < 2**20
    np.testing.assert_array_equal(state_dict(read_torch_file(rebuilt))["w"], np.arange(4, dtype=np.float32))
    monkeypatch.setattr(torch_pickle, "MAX_PICKLE_BYTES", 16)
    with pytest.raises(TorchPickleError, match="rebuilt.pth: archive/data.pkl inflates past"):
        read_torch_file(rebuilt)


def test_reader_reads_the_real_checkpoints():
    csnet = state_dict(read_torch_file(require_weights("csnet/csnet-L-x1.pth.tar")))
    assert len(csnet) == 739
    counted = sum(v.size for k, v in csnet.items() if not k.endswith("num_batches_tracked"))
    assert counted == 97_921  # the count ../shared/README.md gives (weights + BN statistics)
    cnniqa = state_dict(read_torch_file(require_weights("cnniqa/CNNIQA-LIVE")))
    assert {k: v.shape for k, v in cnniqa.items()} == {
        "conv1.weight": (50, 1, 7, 7),
        "conv1.bias": (50,),
        "fc1.weight": (800, 100),
        "fc1.bias": (800,),
        "fc2.weight": (800, 800),
        "fc2.bias": (800,),
        "fc3.weight": (1, 800),
        "fc3.bias": (1,),
    }
    assert all(np.all(np.isfinite(v)) for v in cnniqa.values())


def test_check_shapes_names_the_first_mismatch():
    arrays = {"a": np.zeros((2, 3)), "b": np.zeros(4)}
    check_shapes({"a": (2, 3), "b": (4,)}, arrays, "x.pth")
    with pytest.raises(WeightsError, match=r"x.pth: weight 'a' has shape \(2, 3\), expected \(3, 2\)"):
        check_shapes({"a": (3, 2), "b": (4,)}, arrays, "x.pth")
    with pytest.raises(WeightsError, match="missing weight 'c'"):
        check_shapes({"a": (2, 3), "b": (4,), "c": (1,)}, arrays, "x.pth")
    with pytest.raises(WeightsError, match="unexpected weight 'b'"):
        check_shapes({"a": (2, 3)}, arrays, "x.pth")


def test_native_store_round_trip_and_errors(tmp_path):
    tree = {
        "layer": {"w": np.arange(6, dtype=np.float32).reshape(2, 3), "b": np.ones(3, np.float32)},
        "gamma": np.float32(0.05),
    }
    path = save_native(tmp_path / "m" / "m.npz", "m", tree, {"splits": [[1, 2], [3]]})
    got, meta = load_native(path, "m")
    assert meta == {"splits": [[1, 2], [3]]}
    np.testing.assert_array_equal(got["layer"]["w"], tree["layer"]["w"])
    assert got["gamma"].dtype == np.float32 and got["gamma"] == np.float32(0.05)
    with pytest.raises(WeightsError, match="holds weights of 'm', expected 'other'"):
        load_native(path, "other")
    bad = tmp_path / "bad.npz"
    bad.write_bytes(path.read_bytes()[:50])
    with pytest.raises(WeightsError, match="bad.npz: not a readable weights archive"):
        load_native(bad, "m")
    np.savez(tmp_path / "foreign.npz", a=np.zeros(2))
    with pytest.raises(WeightsError, match="not a waldo weights archive"):
        load_native(tmp_path / "foreign.npz", "m")
    # Arrays of text or of NaN (a hand-edited archive: NaN weights scored every image -100 silently), and an
    # archive whose members would inflate past any weights' size, refused before they are read.
    for name, value, says in (
        ("text", np.array(["x"]), "holds <U1 values, not numbers"),
        ("nan", np.full(2, np.nan, np.float32), "holds NaN"),
    ):
        edited = save_native(tmp_path / name / "m.npz", "m", {**tree, "gamma": value}, {})
        with pytest.raises(WeightsError, match=f"array 'gamma' {says}"):
            load_native(edited, "m")
    with zipfile.ZipFile(tmp_path / "bomb.npz", "w", zipfile.ZIP_DEFLATED) as archive:
        archive.writestr("a.npy", bytes(300 << 20))
    with pytest.raises(WeightsError, match="would inflate to 300 MiB"):
        load_native(tmp_path / "bomb.npz", "m")


def test_an_opencv_yaml_file_nested_too_deep_or_out_of_range_is_one_error(tmp_path):
    """Flow lists 20,000 deep recursed past Python's limit; a uint8 matrix holding 300 overflowed in NumPy."""
    from waldo_jax.weights.opencv_yaml import read_opencv_storage

    deep = tmp_path / "deep.yml"
    deep.write_text("%YAML:1.0\n---\nrange: " + "[" * 20000 + "1" + "]" * 20000 + "\n")
    with pytest.raises(WeightsError, match="deep.yml: malformed OpenCV YAML \\(nested too deep to read\\)"):
        read_opencv_storage(deep)
    wide = tmp_path / "wide.yml"
    wide.write_text("%YAML:1.0\n---\nm: !!opencv-matrix\n   rows: 1\n   cols: 1\n   dt: u\n   data: [ 300 ]\n")
    with pytest.raises(WeightsError, match="wide.yml: malformed OpenCV YAML \\(.*300"):
        read_opencv_storage(wide)


@pytest.mark.slow
def test_weights_convert_cli_writes_loadable_files(tmp_path, capsys):
    import waldo_jax.criteria  # noqa: F401  (registers converters)
    from waldo_jax.weights import CONVERTERS, load_model

    src = require_weights("cnniqa/CNNIQA-LIVE").parent.parent
    dst = tmp_path / "converted"
    models = sorted(CONVERTERS)
    assert main(["weights", "convert", str(src), str(dst)]) == 0
    out = capsys.readouterr().out
    assert f"converted {len(models)} model(s)" in out
    for model in models:
        native, native_meta = load_model(model, dst)
        original, original_meta = CONVERTERS[model].read(src / model)
        assert json.dumps(native_meta, sort_keys=True) == json.dumps(original_meta, sort_keys=True)
        flat_native = dict(_flat(native))
        flat_original = dict(_flat(original))
        assert flat_native.keys() == flat_original.keys()
        for key in flat_native:
            np.testing.assert_array_equal(flat_native[key], flat_original[key])
    # never overwrite silently
    assert main(["weights", "convert", str(src), str(dst)]) == 1
    assert "exists; pass --force" in capsys.readouterr().err
    assert main(["weights", "convert", str(src), str(dst), "--force", "--model", models[0]]) == 0
    with pytest.raises(DataNotFoundError, match=f"expected {tmp_path}/{models[0]}/"):
        convert_all(tmp_path, tmp_path / "out", [models[0]])


def test_missing_weights_name_the_expected_file(tmp_path):
    from waldo_jax.criteria import CriterionContext, make_criterion

    import waldo_jax.criteria  # noqa: F401
    from waldo_jax.weights import CONVERTERS

    for model in CONVERTERS:
        name = {"csnet": "saliency", "cnniqa": "iqa_cnn"}.get(model, model)
        with pytest.raises(DataNotFoundError, match=f"expected {tmp_path}/{model}/"):
            make_criterion(name, CriterionContext(weights_dir=str(tmp_path)))


def _flat(tree, prefix=""):
    if isinstance(tree, dict):
        for key, value in tree.items():
            yield from _flat(value, f"{prefix}{key}/")
    else:
        yield prefix, np.asarray(tree)


@pytest.mark.parametrize("kind", ["folder", "fifo"])
def test_a_weights_file_that_is_no_regular_file_is_said_as_such(tmp_path, kind):
    """A folder or a FIFO where a model's weights file (native or original) belongs was said to be missing
    ("weights file not found"), or, for a native archive, passed over for the originals; it is named as
    what it is, for every model, as everywhere else a file is read."""
    from waldo_jax.criteria import CriterionContext, make_criterion

    from waldo_jax.weights import CONVERTERS

    for model, converter in CONVERTERS.items():
        name = {"csnet": "saliency", "cnniqa": "iqa_cnn"}.get(model, model)
        for filename in (converter.files[0], f"{model}.npz"):
            root = tmp_path / f"{model}_{filename}"
            (root / model).mkdir(parents=True)
            path = root / model / filename
            path.mkdir() if kind == "folder" else os.mkfifo(path)
            says = "a directory" if kind == "folder" else "a FIFO, socket or device"
            with pytest.raises(WaldoError, match=f"{path}: {says}, where a"):
                make_criterion(name, CriterionContext(weights_dir=str(root)))


def test_a_model_that_fails_to_convert_leaves_the_destination_as_it_was(tmp_path, capsys):
    """Every model is read before any is written: a broken later one (cnniqa's file cut in half) used to leave
    the models converted before it behind in DST."""
    import shutil

    src = tmp_path / "src"
    shutil.copytree(require_weights("cnniqa/CNNIQA-LIVE").parent.parent, src)
    cut = src / "cnniqa" / "CNNIQA-LIVE"
    cut.chmod(0o644)
    cut.write_bytes(cut.read_bytes()[: cut.stat().st_size // 2])
    dst = tmp_path / "dst"
    assert main(["weights", "convert", str(src), str(dst)]) == 1
    assert "CNNIQA-LIVE" in capsys.readouterr().err
    assert not dst.exists() or not any(dst.rglob("*.npz")), sorted(dst.rglob("*"))


def test_an_original_changed_after_its_conversion_is_warned_of(tmp_path):
    """The converted archive beside the originals is what loads: an original edited after it would go unseen,
    so loading says so."""
    import shutil

    import waldo_jax.criteria  # noqa: F401  (registers converters)
    from waldo_jax.weights import load_model

    folder = tmp_path / "w"
    shutil.copytree(require_weights("cnniqa/CNNIQA-LIVE").parent, folder / "cnniqa")
    assert main(["weights", "convert", str(folder), str(folder), "--model", "cnniqa", "--quiet"]) == 0
    native = folder / "cnniqa" / "cnniqa.npz"
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        load_model("cnniqa", folder)
    os.utime(folder / "cnniqa" / "CNNIQA-LIVE", (native.stat().st_mtime + 10,) * 2)
    with pytest.warns(UserWarning, match=f"{native} is older than CNNIQA-LIVE beside it, and it is what is loaded"):
        load_model("cnniqa", folder)
