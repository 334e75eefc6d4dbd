"""Checkpoints of trained fields: one self-checking file with params, occupancy grid, config and scene.

`save_checkpoint` writes it atomically; `load_checkpoint` checks magic, header, version, size,
SHA-256 digest and every array's dtype and shape against the stored config, then the contents as a
whole (finite field parameters, a usable camera, box and near < far, finite rigid training poses, a
background in [0, 1]; the occupancy grid's densities may hold NaN: its update sanitises them), raising
`CheckpointError` naming the file. A round trip is bit-exact. The file layout: docs/design.md, "Checkpoints".
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import os
import struct
from pathlib import Path
from typing import Any, Dict, List, Optional, Tuple

import jax
import jax.numpy as jnp
import numpy as np

from waldo_jax.errors import (
    MAX_RESOLUTION,
    DataNotFoundError,
    SceneFormatError,
    WaldoError,
    check_input_file,
    host_memory_bytes,
    is_finite_number,
)
from waldo_jax.io import atomic_file, parse_json
from waldo_jax.nerf.config import TrainConfig, TrainConfigError
from waldo_jax.nerf.field import init_field
from waldo_jax.nerf.samplers import make_sampler
from waldo_jax.scenes.common import check_rigid, extent_problem, intrinsics_problem
from waldo_jax.types import Intrinsics, Scene

__all__ = [
    "CHECKPOINT_NAME",
    "FORMAT_VERSION",
    "Checkpoint",
    "CheckpointError",
    "SceneRecord",
    "load_checkpoint",
    "save_checkpoint",
]

FORMAT_VERSION = 1
MAGIC = b"\x89WALDO-CKPT\r\n\x1a\n\x00\x00\x00"
CHECKPOINT_NAME = "checkpoint.ckpt"  # the file name inside a run directory
_LENGTH = struct.Struct("<Q")
_DIGEST_BYTES = 32
_MAX_HEADER_BYTES = 1 << 30


class CheckpointError(WaldoError):
    """A checkpoint file is missing, corrupt, truncated or incompatible: the message names the file."""

    def __init__(self, path: str | os.PathLike, problem: str):
        self.path = os.fspath(path)
        self.problem = problem
        super().__init__(f"{self.path}: {problem}")


@dataclasses.dataclass(frozen=True, eq=False)
class SceneRecord:
    """What a checkpoint remembers of its training scene (enough to render its poses again).

    Attributes:
      intrinsics: the training camera.
      c2w: float32 [N, 4, 4] training poses.
      aabb: float32 [2, 3] scene box.
      near, far: ray bounds.
      file_names: the N training image files, relative to the scene folder.
      path, format, name, split: where the scene came from and how it was read.
      background: float32 [3] colour RGBA images were composited on, or None.
      metadata: the scene's free-form metadata (JSON-normalised).
    """

    intrinsics: Intrinsics
    c2w: np.ndarray
    aabb: np.ndarray
    near: float
    far: float
    file_names: Tuple[str, ...]
    path: str = ""
    format: str = ""
    name: str = ""
    split: str = ""
    background: Optional[np.ndarray] = None
    metadata: Dict[str, Any] = dataclasses.field(default_factory=dict)

    @classmethod
    def from_scene(cls, scene: Scene) -> "SceneRecord":
        return cls(
            intrinsics=scene.intrinsics,
            c2w=np.asarray(scene.c2w, np.float32),
            aabb=np.asarray(scene.aabb, np.float32).reshape(2, 3),
            near=float(scene.near),
            far=float(scene.far),
            file_names=tuple(str(f) for f in scene.file_names),
            path=os.path.abspath(scene.path) if scene.path else "",  # a run is read from any folder
            format=str(scene.format),
            name=str(scene.name),
            split=str(scene.split),
            background=None if scene.background is None else np.asarray(scene.background, np.float32),
            metadata=_json_normalise(scene.metadata),
        )

    def header(self) -> Dict[str, Any]:
        """The JSON part (c2w is stored as an array)."""
        return {
            "intrinsics": self.intrinsics.to_dict(),
            "aabb": np.asarray(self.aabb, np.float64).tolist(),
            "near": float(self.near),
            "far": float(self.far),
            "file_names": list(self.file_names),
            "path": self.path,
            "format": self.format,
            "name": self.name,
            "split": self.split,
            "background": None if self.background is None else np.asarray(self.background, np.float64).tolist(),
            "metadata": _json_normalise(self.metadata),
            "n_images": int(np.asarray(self.c2w).shape[0]),
        }


@dataclasses.dataclass(frozen=True, eq=False)
class Checkpoint:
    """A loaded checkpoint.

    Attributes:
      params: the field's parameters (NumPy arrays in the structure of `init_field`).
      occupancy: the occupancy grid (the sampler's state), or None.
      config: the training config.
      scene: the training scene's record.
      info: free-form statistics saved with it (e.g. the contents of train.json).
      path: the file it was read from.
      format_version: the file's format version.
    """

    params: Any
    occupancy: Any
    config: TrainConfig
    scene: SceneRecord
    info: Dict[str, Any]
    path: str
    format_version: int = FORMAT_VERSION


def _json_normalise(value: Any) -> Any:
    """A JSON-ready copy (NumPy scalars and arrays to Python, tuples to lists, other keys to str)."""
    if isinstance(value, dict):
        return {str(k): _json_normalise(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_json_normalise(v) for v in value]
    if isinstance(value, np.ndarray):
        return _json_normalise(value.tolist())
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, (str, int, float, bool)) or value is None:
        return value
    return str(value)


def _named_leaves(prefix: str, tree: Any) -> List[Tuple[str, Any]]:
    """(name, leaf) pairs of a pytree, names "prefix/<key path>" in the tree's flattening order."""
    leaves = jax.tree_util.tree_flatten_with_path(tree)[0]
    return [(f"{prefix}/{jax.tree_util.keystr(path, simple=True, separator='/')}", leaf) for path, leaf in leaves]


def _host_array(name: str, leaf: Any) -> np.ndarray:
    if isinstance(leaf, jax.Array) and jnp.issubdtype(leaf.dtype, jax.dtypes.prng_key):
        raise TypeError(f"checkpoint array {name}: typed PRNG keys cannot be stored (store key_data)")
    return np.ascontiguousarray(np.asarray(jax.device_get(leaf)))


# ----------------------------------------------------------------------------------------------
# Writing.


def save_checkpoint(
    path: str | os.PathLike,
    params: Any,
    config: TrainConfig,
    scene: Scene | SceneRecord,
    occupancy: Any = None,
    info: Optional[Dict[str, Any]] = None,
) -> Path:
    """Writes a checkpoint atomically (temporary file in the same folder, then `os.replace`).

    Args:
      path: the file to write (its folder must exist).
      params: the field's parameters (device or host arrays).
      config: the training config.
      scene: the training scene (or its record).
      occupancy: the occupancy grid (sampler state) or None.
      info: JSON-able statistics to keep with it.

    Returns:
      The path written.
    """
    path = Path(path)
    record = scene if isinstance(scene, SceneRecord) else SceneRecord.from_scene(scene)
    arrays = _named_leaves("params", params)
    if occupancy is not None:
        arrays += _named_leaves("occupancy", occupancy)
    arrays.append(("scene/c2w", np.asarray(record.c2w, np.float32)))

    table, chunks, offset = [], [], 0
    for name, leaf in arrays:
        data = _host_array(name, leaf)
        raw = data.tobytes()
        table.append(
            {"name": name, "dtype": data.dtype.name, "shape": list(data.shape), "offset": offset, "nbytes": len(raw)}
        )
        chunks.append(raw)
        offset += len(raw)
    header = {
        "format_version": FORMAT_VERSION,
        "kind": "waldo_jax.nerf checkpoint",
        "config": config.to_dict(),
        "scene": record.header(),
        "has_occupancy": occupancy is not None,
        "info": _json_normalise(info or {}),
        "arrays": table,
        "payload_bytes": offset,
    }
    header_bytes = json.dumps(header, allow_nan=True).encode("utf-8")

    folder = path.parent if str(path.parent) else Path(".")
    digest = hashlib.sha256()
    with atomic_file(path) as f:
        for part in (MAGIC, _LENGTH.pack(len(header_bytes)), header_bytes, *chunks):
            digest.update(part)
            f.write(part)
        f.write(digest.digest())
    _fsync_dir(folder)
    return path


def _fsync_dir(folder: Path) -> None:
    """Makes the rename durable where the platform allows it."""
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


# ----------------------------------------------------------------------------------------------
# Reading.


def _read_header(path: Path, raw: bytes) -> Tuple[Dict[str, Any], int]:
    """The parsed header and the payload's start offset."""
    if len(raw) < len(MAGIC) or raw[: len(MAGIC)] != MAGIC:
        if len(raw) < len(MAGIC) and MAGIC.startswith(raw):
            raise CheckpointError(path, f"truncated checkpoint ({len(raw)} bytes, not even a header)")
        raise CheckpointError(path, "not a waldo_jax checkpoint (bad magic bytes)")
    start = len(MAGIC) + _LENGTH.size
    if len(raw) < start:
        raise CheckpointError(path, f"truncated checkpoint ({len(raw)} bytes, not even a header)")
    (header_length,) = _LENGTH.unpack_from(raw, len(MAGIC))
    if header_length > _MAX_HEADER_BYTES:
        raise CheckpointError(path, f"corrupt checkpoint (implausible header length {header_length})")
    if len(raw) < start + header_length:
        raise CheckpointError(
            path, f"truncated checkpoint ({len(raw)} bytes, the header alone needs {start + header_length})"
        )
    header = parse_json(
        raw[start : start + header_length],
        path,
        "checkpoint header",
        lambda problem: CheckpointError(path, f"corrupt checkpoint (unreadable header: {problem})"),
    )
    if not isinstance(header, dict):
        raise CheckpointError(path, "corrupt checkpoint (header is not a JSON object)")
    return header, start + header_length


def _check_version(path: Path, header: Dict[str, Any]) -> None:
    version = header.get("format_version")
    if version != FORMAT_VERSION:
        raise CheckpointError(
            path,
            f"incompatible checkpoint format_version {version!r}: this waldo_jax reads version "
            f"{FORMAT_VERSION} (re-train, or use the waldo_jax version that wrote it)",
        )


def _info(path: Path, info: Any) -> Dict[str, Any]:
    """The header's free-form `info` object (None counts as empty); a CheckpointError for anything else."""
    if info is None:
        return {}
    if not isinstance(info, dict):
        raise CheckpointError(path, f"corrupt checkpoint (its 'info' is a {type(info).__name__}, not an object)")
    return dict(info)


def _array_table(path: Path, header: Dict[str, Any], payload_start: int, file_size: int) -> Dict[str, Dict]:
    """The validated array table, by name; checks the file size against it."""
    try:
        table = header["arrays"]
        payload_bytes = int(header["payload_bytes"])
        entries = {}
        for entry in table:
            entries[str(entry["name"])] = {
                "dtype": jnp.dtype(entry["dtype"]),
                "shape": tuple(int(s) for s in entry["shape"]),
                "offset": int(entry["offset"]),
                "nbytes": int(entry["nbytes"]),
            }
    except (KeyError, TypeError, ValueError, OverflowError) as e:
        raise CheckpointError(path, f"corrupt checkpoint (bad array table: {e!r})") from None
    expected = payload_start + payload_bytes + _DIGEST_BYTES
    if file_size < expected:
        raise CheckpointError(path, f"truncated checkpoint ({file_size} bytes, expected {expected})")
    if file_size > expected:
        raise CheckpointError(path, f"corrupt checkpoint ({file_size} bytes, expected {expected}: trailing data)")
    for name, e in entries.items():
        if e["dtype"].kind not in "biuf" or e["dtype"].itemsize == 0:  # numbers only: no objects, text or complex
            raise CheckpointError(path, f"corrupt checkpoint (array {name}: dtype {e['dtype']} is not a number type)")
        if min(e["shape"], default=0) < 0:
            raise CheckpointError(path, f"corrupt checkpoint (array {name}: negative shape {list(e['shape'])})")
        count = math.prod(e["shape"])  # Python integers: a huge shape cannot wrap around
        if e["nbytes"] != count * e["dtype"].itemsize or e["offset"] < 0 or e["offset"] + e["nbytes"] > payload_bytes:
            raise CheckpointError(path, f"corrupt checkpoint (array {name}: inconsistent size or offset)")
    return entries


def _restore(path: Path, prefix: str, template: Any, entries: Dict[str, Dict], payload: memoryview) -> Any:
    """The tree of `template` filled from the stored arrays, checking names, dtypes and shapes."""
    named = _named_leaves(prefix, template)
    expected = {name for name, _ in named}
    stored = {name for name in entries if name.startswith(prefix + "/")}
    missing = sorted(expected - stored)
    if missing:
        raise CheckpointError(
            path, f"incompatible checkpoint: array {missing[0]} is missing ({len(missing)} missing in all)"
        )
    unexpected = sorted(stored - expected)
    if unexpected:
        raise CheckpointError(
            path, f"incompatible checkpoint: unexpected array {unexpected[0]} (does not match the stored config)"
        )
    leaves = []
    for name, spec in named:
        e = entries[name]
        if e["shape"] != tuple(spec.shape) or e["dtype"] != jnp.dtype(spec.dtype):
            raise CheckpointError(
                path,
                f"incompatible checkpoint: array {name} is {e['dtype'].name}{list(e['shape'])}, the "
                f"config implies {jnp.dtype(spec.dtype).name}{list(spec.shape)}",
            )
        data = (
            np.frombuffer(payload, dtype=e["dtype"], count=int(np.prod(e["shape"], dtype=np.int64)), offset=e["offset"])
            .reshape(e["shape"])
            .copy()
        )
        leaves.append(data)
    return jax.tree_util.tree_unflatten(jax.tree_util.tree_structure(template), leaves)


def _templates(path: Path, config: TrainConfig, has_occupancy: bool) -> Tuple[Any, Any]:
    """Shapes and dtypes of params (and occupancy grid) implied by a config, without computing them."""
    key = jax.random.key(0)
    params = jax.eval_shape(lambda k: init_field(k, config.field), key)
    if not has_occupancy:
        return params, None
    try:
        sampler = make_sampler(config)
    except TrainConfigError as e:
        raise CheckpointError(path, f"checkpoint has an occupancy grid but it cannot be restored: {e}") from None
    occupancy = jax.eval_shape(lambda p: sampler.init(key, p), params)
    if occupancy is None:
        raise CheckpointError(path, f"checkpoint has an occupancy grid but its sampler {config.sampler!r} has none")
    return params, occupancy


def _file_names(names: Any, count: int) -> Tuple[str, ...]:
    """The record's training image names: one string per training pose."""
    if not isinstance(names, list) or not all(isinstance(name, str) for name in names):
        raise ValueError("file_names is not a list of names")
    if len(names) != count:
        raise ValueError(f"file_names lists {len(names)} names for {count} training poses")
    return tuple(names)


def _scene_record(path: Path, scene: Dict[str, Any], c2w: np.ndarray) -> SceneRecord:
    try:
        background = scene.get("background")
        return SceneRecord(
            intrinsics=Intrinsics.from_dict(scene["intrinsics"]),
            c2w=c2w,
            aabb=np.asarray(scene["aabb"], np.float32).reshape(2, 3),
            near=float(scene["near"]),
            far=float(scene["far"]),
            file_names=_file_names(scene["file_names"], len(c2w)),
            path=str(scene.get("path", "")),
            format=str(scene.get("format", "")),
            name=str(scene.get("name", "")),
            split=str(scene.get("split", "")),
            background=None if background is None else np.asarray(background, np.float32).reshape(3),
            metadata=dict(scene.get("metadata", {})),
        )
    except (KeyError, TypeError, ValueError, OverflowError) as e:
        raise CheckpointError(path, f"corrupt checkpoint (bad scene record: {e!r})") from None


def _is_number(value: Any, positive: bool = False) -> bool:
    return is_finite_number(value) and (value > 0 if positive else True)


def _is_matrix(value: Any) -> bool:
    """A 3x4 or 4x4 nested list of finite numbers."""
    return (
        isinstance(value, list)
        and len(value) in (3, 4)
        and all(isinstance(row, list) and len(row) == 4 and all(_is_number(v) for v in row) for row in value)
    )


def _is_inner_name(value: Any) -> bool:
    """A relative path that stays inside its folder."""
    return isinstance(value, str) and value != "" and not Path(value).is_absolute() and ".." not in Path(value).parts


# What the readers of a run take from its scene record's metadata (`pipeline.sources.export_info`,
# `run_source`, `procedural.room_from_metadata`, the occupancy grid): each key's test, and what it expects.
_METADATA_KEYS = {
    "aabb_scale": (lambda v: _is_number(v, positive=True), "a positive number"),
    "scale": (lambda v: _is_number(v, positive=True), "a positive number"),
    "offset": (lambda v: isinstance(v, list) and len(v) == 3 and all(map(_is_number, v)), "3 numbers"),
    "from_mitsuba": (lambda v: isinstance(v, bool), "true or false"),
    "scene_file": (  # Blender scenes list their split files
        lambda v: all(map(_is_inner_name, v if isinstance(v, list) and v else [v])),
        "a file name inside the scene's folder (or a list of them)",
    ),
    "downscale": (lambda v: v is None or _is_number(v, positive=True), "a positive number"),
    "seed": (lambda v: isinstance(v, int) and not isinstance(v, bool), "an integer"),
    "waldo_scale": (lambda v: _is_number(v) and 0.25 <= v <= 2.0, "a number in [0.25, 2]"),
    "stripe_width": (lambda v: v is None or _is_number(v, positive=True), "a positive number"),
    "nerfstudio_applied": (
        lambda v: (
            isinstance(v, dict)
            and (v.get("transform") is None or _is_matrix(v.get("transform")))
            and _is_number(v.get("scale", 1.0), positive=True)
            and isinstance(v.get("source", ""), str)
        ),
        "an object of a 3x4 or 4x4 'transform' (or null), a positive 'scale' and a 'source' name",
    ),
}


def _check_metadata(path: Path, scene: SceneRecord) -> None:
    """Refuses a scene record whose metadata holds a value of the wrong type or range under a key that
    the run's readers use (an older or hand-edited file), naming the key, before any reader trips on it."""
    for key, (valid, expected) in _METADATA_KEYS.items():
        if key in scene.metadata and not valid(scene.metadata[key]):
            shown = json.dumps(scene.metadata[key])
            shown = shown if len(shown) <= 80 else shown[:77] + "..."
            raise CheckpointError(path, f"the scene record's metadata {key!r} is {shown}, not {expected}")


def _check_scene_record(path: Path, scene: SceneRecord) -> None:
    """Refuses a scene record that renders nothing or nonsense: a camera with a side beyond
    MAX_RESOLUTION or a degenerate focal length (`intrinsics_problem`), a flipped box or near >= far
    (`extent_problem`), a training pose that is not finite and rigid, a background colour that is
    not 3 numbers in [0, 1]."""
    problem = intrinsics_problem(scene.intrinsics, sides=(1, MAX_RESOLUTION))  # renders of it allocate that much
    if problem:
        raise CheckpointError(path, f"the training camera: {problem}")
    problem = extent_problem(scene.aabb, scene.near, scene.far)
    if problem:
        raise CheckpointError(path, problem)
    if len(scene.c2w) == 0:
        raise CheckpointError(path, "the checkpoint holds no training poses")
    for i, matrix in enumerate(np.asarray(scene.c2w, np.float64)):
        try:
            check_rigid(matrix, path, f"training pose {i}")
        except SceneFormatError as e:
            raise CheckpointError(path, e.problem) from None
    _check_metadata(path, scene)
    if scene.background is not None:
        background = np.asarray(scene.background, np.float64)
        if not (np.all(np.isfinite(background)) and np.all((background >= 0) & (background <= 1))):
            raise CheckpointError(path, f"the background colour {background.tolist()} is not 3 numbers in [0, 1]")


def load_checkpoint(path: str | os.PathLike) -> Checkpoint:
    """Reads and validates a checkpoint written by `save_checkpoint`.

    Args:
      path: the checkpoint file, or a run directory holding `CHECKPOINT_NAME`.

    Returns:
      A `Checkpoint` whose arrays are bit-identical to those saved (as NumPy arrays).

    Raises:
      CheckpointError: the file is missing, not a checkpoint, truncated, corrupt (any flipped byte),
        of another format version, or its arrays do not match its config. The message names the file.
    """
    path = Path(path)
    if path.is_dir():
        path = path / CHECKPOINT_NAME
    try:
        check_input_file(path, "checkpoint file")  # a FIFO would block read_bytes, a folder fail late
    except DataNotFoundError:
        raise CheckpointError(path, "no such checkpoint file") from None
    try:  # the header first: a file larger (or smaller) than its header says is refused before it is read
        with open(path, "rb") as f:
            head = f.read(len(MAGIC) + _LENGTH.size)
            if len(head) == len(MAGIC) + _LENGTH.size and head[: len(MAGIC)] == MAGIC:
                (header_length,) = _LENGTH.unpack_from(head, len(MAGIC))
                head += f.read(min(header_length, _MAX_HEADER_BYTES))
            header, payload_start = _read_header(path, head)
            _check_version(path, header)
            size = os.fstat(f.fileno()).st_size
            entries = _array_table(path, header, payload_start, size)
            available = host_memory_bytes()
            if available and size > available:
                raise CheckpointError(
                    path, f"{size / 2**30:,.1f} GiB, more than the {available / 2**30:.1f} GiB this machine has free"
                )
            raw = head + f.read()
    except FileNotFoundError:
        raise CheckpointError(path, "no such checkpoint file") from None
    except OSError as e:
        raise CheckpointError(path, f"cannot read checkpoint ({e.strerror or e})") from None
    body = memoryview(raw)[: len(raw) - _DIGEST_BYTES]
    if hashlib.sha256(body).digest() != raw[len(raw) - _DIGEST_BYTES :]:
        raise CheckpointError(path, "corrupt checkpoint (SHA-256 digest mismatch: the file was altered or damaged)")
    try:
        config = TrainConfig.from_dict(header["config"])
    except (KeyError, TrainConfigError) as e:
        raise CheckpointError(path, f"incompatible checkpoint config: {e}") from None
    payload = body[payload_start:]
    params_template, occupancy_template = _templates(path, config, bool(header.get("has_occupancy")))
    params = _restore(path, "params", params_template, entries, payload)
    occupancy = None
    if occupancy_template is not None:
        occupancy = _restore(path, "occupancy", occupancy_template, entries, payload)
    bad = [
        name
        for name, leaf in jax.tree_util.tree_leaves_with_path(params)
        if np.issubdtype(np.asarray(leaf).dtype, np.floating) and not np.all(np.isfinite(leaf))
    ]
    if bad:
        raise CheckpointError(
            path,
            f"the field's parameters hold NaN or infinity ({len(bad)} arrays, e.g. "
            f"{jax.tree_util.keystr(bad[0])}): the training diverged; train again",
        )
    if "scene/c2w" not in entries:
        raise CheckpointError(path, "incompatible checkpoint: array scene/c2w is missing")
    e = entries["scene/c2w"]
    if len(e["shape"]) != 3 or e["shape"][1:] != (4, 4):
        raise CheckpointError(
            path, f"incompatible checkpoint: scene/c2w has shape {list(e['shape'])}, expected [N, 4, 4]"
        )
    c2w = np.frombuffer(payload, dtype=e["dtype"], count=int(np.prod(e["shape"])), offset=e["offset"])
    c2w = c2w.reshape(e["shape"]).astype(np.float32)
    scene = _scene_record(path, header.get("scene", {}), c2w)
    _check_scene_record(path, scene)
    return Checkpoint(
        params=params,
        occupancy=occupancy,
        config=config,
        scene=scene,
        info=_info(path, header.get("info", {})),
        path=str(path),
        format_version=FORMAT_VERSION,
    )
