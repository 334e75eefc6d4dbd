"""Reading PyTorch checkpoints without PyTorch: legacy and zip-format torch pickles to NumPy.

`read_torch_file(path)` reads a file written by `torch.save` in either format (legacy, before torch
1.6; zip, from 1.6 on) and returns the unpickled object with tensors as `np.ndarray` (NumPy views of
their storages); `state_dict(obj)` finds the `{name: ndarray}` inside the usual wrappers
(`{"state_dict": ...}`, `{"model": ...}`) and strips a `module.` prefix left by `DataParallel`. The
unpickler maps the few torch classes it needs to small stand-ins and refuses any other global: no
torch import and no arbitrary code. Errors raise `TorchPickleError`.

The two file formats and how tensors and storages appear in them: see docs/design.md, section
"Weights > Torch pickles without torch".
"""

from __future__ import annotations

import collections
import io
import os
import pickle
import struct
import zipfile
import zlib
from pathlib import Path
from typing import Any, Callable, Dict, Tuple

import numpy as np

from waldo_jax.errors import DataNotFoundError, WaldoError, check_input_file, read_input_file

__all__ = ["PICKLE_ERRORS", "TorchPickleError", "pickle_problem", "read_torch_file", "state_dict"]

_LEGACY_MAGIC = 0x1950A86A20F9469CFC6C
_LEGACY_PROTOCOL = 1001
# The object pickle of a zip checkpoint (names and tensor headers, no data) and one tensor storage: far above any
# criterion's weights, far below this machine's memory.
MAX_PICKLE_BYTES = 64 * 2**20
MAX_STORAGE_BYTES = 4 * 2**30
MAX_FILE_BYTES = 4 * 2**30

# What unpickling a corrupt or hostile file raises (besides the readers' own errors): each is said in one line
# naming the file (`pickle_problem`). MemoryError: a length field claiming more bytes than memory holds (a
# 14-byte file that claims 2^60; Python asks for the memory before it reads the bytes, so nothing is used).
PICKLE_ERRORS = (
    pickle.UnpicklingError,
    EOFError,
    ValueError,
    TypeError,
    AttributeError,
    IndexError,
    KeyError,
    struct.error,
    zipfile.BadZipFile,
    zlib.error,
    NotImplementedError,  # a zip compression method the standard library lacks
    RecursionError,  # containers nested past Python's stack
    MemoryError,
)


def pickle_problem(exc: BaseException) -> str:
    """One of `PICKLE_ERRORS` in words, for a message that names the file."""
    if isinstance(exc, MemoryError):
        return "corrupt: an entry claims more bytes than this machine's memory (and the file) holds"
    return f"{type(exc).__name__}: {exc}"


_STORAGE_DTYPES = {
    "DoubleStorage": np.float64,
    "FloatStorage": np.float32,
    "HalfStorage": np.float16,
    "BFloat16Storage": None,  # no NumPy dtype: read as uint16 and widened below
    "LongStorage": np.int64,
    "IntStorage": np.int32,
    "ShortStorage": np.int16,
    "CharStorage": np.int8,
    "ByteStorage": np.uint8,
    "BoolStorage": np.bool_,
}


class TorchPickleError(WaldoError, ValueError):
    """A file that is not a readable torch checkpoint (truncated, corrupt, or using unsupported types)."""


class _StorageType:
    """Stand-in for `torch.FloatStorage` and friends: remembers the dtype."""

    def __init__(self, name: str):
        self.name = name
        self.bfloat16 = name == "BFloat16Storage"
        self.dtype = np.dtype(np.uint16 if self.bfloat16 else _STORAGE_DTYPES[name])


class _Storage:
    """A storage's element type and its flat data (filled in after the object pickle, for legacy files)."""

    def __init__(self, storage_type: _StorageType, key: str, numel: int):
        self.type = storage_type
        self.key = key
        self.numel = numel
        self.data: np.ndarray | None = None


class _LazyTensor:
    """A tensor whose storage bytes are not read yet (legacy files put them after the pickle)."""

    def __init__(self, storage: _Storage, offset: int, size: Tuple[int, ...], stride: Tuple[int, ...]):
        self.storage, self.offset, self.size, self.stride = storage, offset, tuple(size), tuple(stride)

    def materialise(self) -> np.ndarray:
        data = self.storage.data
        if data is None:
            raise TorchPickleError(f"storage {self.storage.key!r} has no data in the file")
        numbers = (self.offset, *self.size, *self.stride)
        if (
            len(self.size) != len(self.stride)
            or not all(isinstance(n, int) and not isinstance(n, bool) for n in numbers)
            or min(numbers, default=0) < 0
        ):
            # torch writes non-negative sizes, strides and offsets; anything else would read outside the storage.
            raise TorchPickleError(
                f"tensor of size {self.size}, stride {self.stride} at offset {self.offset}: "
                "sizes, strides and offset must be non-negative integers, one stride per dimension"
            )
        itemsize = data.dtype.itemsize
        needed = self.offset + sum((n - 1) * s for n, s in zip(self.size, self.stride)) + 1 if all(self.size) else 0
        if needed > data.size:
            raise TorchPickleError(
                f"tensor of size {self.size} at offset {self.offset} overruns its storage of {data.size} elements"
            )
        array = np.lib.stride_tricks.as_strided(
            data[self.offset :], shape=self.size, strides=tuple(s * itemsize for s in self.stride), writeable=False
        )
        array = np.array(array)  # own, contiguous copy
        if self.storage.type.bfloat16:
            array = (array.astype(np.uint32) << 16).view(np.float32)
        return array


def _rebuild_tensor(storage, storage_offset, size, stride, *unused):
    return _LazyTensor(storage, storage_offset, size, stride)


def _rebuild_parameter(data, requires_grad=None, backward_hooks=None, *unused):
    return data


_ALLOWED_GLOBALS: Dict[Tuple[str, str], Callable[..., Any]] = {
    ("torch._utils", "_rebuild_tensor_v2"): _rebuild_tensor,
    ("torch._utils", "_rebuild_tensor"): _rebuild_tensor,
    ("torch._utils", "_rebuild_parameter"): _rebuild_parameter,
    ("torch._utils", "_rebuild_parameter_with_state"): _rebuild_parameter,
    ("collections", "OrderedDict"): collections.OrderedDict,
    ("builtins", "set"): set,
    ("builtins", "frozenset"): frozenset,
    ("builtins", "slice"): slice,
}


class _Unpickler(pickle.Unpickler):
    def __init__(self, file, storages: Dict[str, _Storage], path: str):
        super().__init__(file, encoding="latin1")
        self._storages = storages
        self._path = path

    def find_class(self, module: str, name: str):
        if module == "torch" and name in _STORAGE_DTYPES:
            return _StorageType(name)
        if (module, name) in _ALLOWED_GLOBALS:
            return _ALLOWED_GLOBALS[(module, name)]
        if module == "torch" and name.endswith("Tensor") or module == "argparse" and name == "Namespace":
            return _Opaque(f"{module}.{name}")
        raise TorchPickleError(f"{self._path}: refusing to unpickle {module}.{name} (not a plain tensor checkpoint)")

    def persistent_load(self, pid):
        if not isinstance(pid, tuple) or not pid or pid[0] != "storage":
            raise TorchPickleError(f"{self._path}: unknown persistent id {pid!r}")
        storage_type, key, numel = pid[1], str(pid[2]), pid[4]
        if not isinstance(storage_type, _StorageType):
            raise TorchPickleError(f"{self._path}: unsupported storage type {storage_type!r}")
        if not isinstance(numel, int) or isinstance(numel, bool) or numel < 0:
            raise TorchPickleError(f"{self._path}: storage {key!r} of {numel!r} elements (not a count)")
        if key not in self._storages:
            self._storages[key] = _Storage(storage_type, key, numel)
        return self._storages[key]


class _PlainUnpickler(pickle.Unpickler):
    """For the legacy format's small pickles around the object (magic number, protocol, system info,
    storage keys): plain numbers, strings and containers only, so no global and no persistent id."""

    def __init__(self, file, path: str):
        super().__init__(file, encoding="latin1")
        self._path = path

    def find_class(self, module: str, name: str):
        raise TorchPickleError(f"{self._path}: refusing to unpickle {module}.{name} (not a plain tensor checkpoint)")

    def persistent_load(self, pid):
        raise TorchPickleError(f"{self._path}: unexpected persistent id {pid!r} outside the object pickle")


class _Opaque:
    """A harmless stand-in for objects that checkpoints carry beside the weights (e.g. argparse args)."""

    def __init__(self, name: str):
        self.name = name

    def __call__(self, *args, **kwargs):
        return self

    def __setstate__(self, state):
        self.state = state

    def __repr__(self):
        return f"<{self.name}>"


def _materialise(obj: Any) -> Any:
    if isinstance(obj, _LazyTensor):
        return obj.materialise()
    if isinstance(obj, collections.OrderedDict):
        return collections.OrderedDict((k, _materialise(v)) for k, v in obj.items())
    if isinstance(obj, dict):
        return {k: _materialise(v) for k, v in obj.items()}
    if isinstance(obj, list):
        return [_materialise(v) for v in obj]
    if isinstance(obj, tuple):
        return tuple(_materialise(v) for v in obj)
    return obj


def _read_legacy(raw: bytes, path: str) -> Any:
    f = io.BytesIO(raw)
    storages: Dict[str, _Storage] = {}
    magic = _PlainUnpickler(f, path).load()
    if magic != _LEGACY_MAGIC:
        raise TorchPickleError(f"{path}: not a torch checkpoint (bad magic number)")
    protocol = _PlainUnpickler(f, path).load()
    if protocol != _LEGACY_PROTOCOL:
        raise TorchPickleError(f"{path}: unsupported legacy torch protocol {protocol!r}")
    sys_info = _PlainUnpickler(f, path).load()
    if not isinstance(sys_info, dict):
        raise TorchPickleError(f"{path}: corrupt (its system information is a {type(sys_info).__name__}, not a dict)")
    if not sys_info.get("little_endian", True):
        raise TorchPickleError(f"{path}: big-endian torch checkpoints are not supported")
    obj = _Unpickler(f, storages, path).load()
    keys = _PlainUnpickler(f, path).load()
    if not isinstance(keys, (list, tuple)):
        raise TorchPickleError(f"{path}: corrupt (the storage keys are a {type(keys).__name__}, not a list)")
    for key in keys:
        storage = storages.get(str(key))
        if storage is None:
            raise TorchPickleError(f"{path}: storage {key!r} listed but never referenced")
        header = f.read(8)
        if len(header) != 8:
            raise TorchPickleError(f"{path}: truncated (storage {key!r} header missing)")
        (count,) = struct.unpack("<q", header)
        nbytes = count * storage.type.dtype.itemsize
        data = f.read(nbytes)
        if count != storage.numel or len(data) != nbytes:
            raise TorchPickleError(
                f"{path}: truncated or corrupt (storage {key!r}: expected {storage.numel} "
                f"elements, header says {count}, {len(data)} of {nbytes} bytes present)"
            )
        storage.data = np.frombuffer(data, dtype=storage.type.dtype.newbyteorder("<"))
    return obj


def _read_member(archive: zipfile.ZipFile, name: str, limit: int, path: str, exact: bool = True) -> bytes:
    """At most `limit` bytes of a zip member, decompressed no further (a member inflating to more is refused
    when `exact`, else cut there); KeyError where there is no such member."""
    with archive.open(name) as member:
        data = member.read(limit + 1 if exact else limit)
    if exact and len(data) > limit:
        raise TorchPickleError(f"{path}: {name} inflates past {limit / 2**20:.0f} MiB (not a weights pickle)")
    return data


def _read_zip(path: str) -> Any:
    storages: Dict[str, _Storage] = {}
    with zipfile.ZipFile(path) as archive:
        names = archive.namelist()
        pickles = [n for n in names if n.endswith("data.pkl")]
        if len(pickles) != 1:
            raise TorchPickleError(f"{path}: a zip torch checkpoint holds one */data.pkl, found {len(pickles)}")
        root = pickles[0][: -len("data.pkl")]
        obj = _Unpickler(io.BytesIO(_read_member(archive, pickles[0], MAX_PICKLE_BYTES, path)), storages, path).load()
        for key, storage in storages.items():
            member = f"{root}data/{key}"
            nbytes = storage.numel * storage.type.dtype.itemsize
            if nbytes > MAX_STORAGE_BYTES:
                raise TorchPickleError(
                    f"{path}: storage {member} of {nbytes / 2**30:.1f} GiB "
                    f"(at most {MAX_STORAGE_BYTES / 2**30:.0f} GiB)"
                )
            try:
                # Only the bytes the storage needs are decompressed: a member that inflates to more is not read whole.
                data = _read_member(archive, member, nbytes, path, exact=False)
            except KeyError:
                raise TorchPickleError(f"{path}: storage file {member} is missing") from None
            if len(data) < nbytes:
                raise TorchPickleError(f"{path}: storage {member} has {len(data)} bytes, expected {nbytes}")
            storage.data = np.frombuffer(data[:nbytes], dtype=storage.type.dtype.newbyteorder("<"))
    return obj


def read_torch_file(path: str | os.PathLike) -> Any:
    """Reads a file written by `torch.save` (legacy or zip format) without importing torch.

    Args:
      path: the checkpoint file.

    Returns:
      The saved object, with every tensor (and `nn.Parameter`) as a NumPy array of its dtype and shape.

    Raises:
      DataNotFoundError: the file does not exist.
      TorchPickleError: the file is not a torch checkpoint, is truncated or corrupt, or pickles
        objects other than tensors and plain containers.
    """
    path = os.fspath(path)
    if not os.path.lexists(path):
        raise DataNotFoundError(f"torch checkpoint not found: {path}")
    try:
        check_input_file(path, "torch checkpoint")  # a folder, a FIFO or a link loop, said as such
    except DataNotFoundError:  # a dangling link
        raise
    except WaldoError as exc:
        raise TorchPickleError(str(exc)) from None
    size = Path(path).stat().st_size
    if size > MAX_FILE_BYTES:
        raise TorchPickleError(
            f"{path}: {size / 2**30:.1f} GiB (a criterion's weights file is at most {MAX_FILE_BYTES / 2**30:.0f} GiB)"
        )
    try:
        if zipfile.is_zipfile(path):
            obj = _read_zip(path)
        else:
            raw = read_input_file(path, "torch checkpoint", lambda problem: TorchPickleError(f"{path}: {problem}"))
            obj = _read_legacy(raw, path)
        return _materialise(obj)
    except TorchPickleError as exc:
        if str(exc).startswith(path):
            raise
        raise TorchPickleError(f"{path}: {exc}") from None  # a tensor's own check names no file
    except PICKLE_ERRORS as exc:
        raise TorchPickleError(f"{path}: not a readable torch checkpoint ({pickle_problem(exc)})") from None


def state_dict(obj: Any, path: str = "checkpoint") -> Dict[str, np.ndarray]:
    """The `{name: ndarray}` of a loaded checkpoint.

    Accepts a bare state dict or one wrapped as `{"state_dict": ...}` / `{"model": ...}` /
    `{"net": ...}`; drops a leading `module.` (from `DataParallel`) and non-array entries.

    Raises:
      TorchPickleError: no dict of arrays is found (the message names `path`).
    """
    if isinstance(obj, dict):
        for wrapper in ("state_dict", "model", "net", "model_state_dict"):
            if wrapper in obj and isinstance(obj[wrapper], dict):
                obj = obj[wrapper]
                break
    if not isinstance(obj, dict):
        raise TorchPickleError(f"{path}: expected a state dict, found {type(obj).__name__}")
    tensors = {
        (k[len("module.") :] if k.startswith("module.") else k): v for k, v in obj.items() if isinstance(v, np.ndarray)
    }
    if not tensors:
        raise TorchPickleError(f"{path}: the state dict holds no tensors")
    return tensors
