"""Where criterion weights come from, and the native format they are converted to.

Weights live in a folder with one sub-folder per model (csnet, cnniqa, brisque, niqe), found by
`resolve_weights_dir`: `--weights DIR`, else `WALDO_WEIGHTS`, else `$WALDO_DATA/weights`.
`waldo weights convert SRC DST` (`convert_all`) writes each model once as `DST/<model>/<model>.npz`
(`save_native`), which loaders (`load_model`) read before falling back to the original files.
Each model registers a `Converter` (`register_converter`): the files it reads and a function from
the model folder to `(tree, meta)`.

The folder's files per model and the native format: see docs/design.md, section
"Weights > The weights folder and the native format".
"""

from __future__ import annotations

import dataclasses
import json
import os
import warnings
from pathlib import Path
from typing import Any, Callable, Dict, Mapping, Optional, Sequence, Tuple

import numpy as np

from waldo_jax import paths
from waldo_jax.errors import DataNotFoundError, WaldoError, check_input_file
from waldo_jax.io import atomic_file, parse_json

__all__ = [
    "NATIVE_FORMAT_VERSION",
    "WeightsError",
    "Converter",
    "CONVERTERS",
    "register_converter",
    "resolve_weights_dir",
    "weights_file",
    "check_shapes",
    "save_native",
    "load_native",
    "load_model",
    "convert_all",
]

NATIVE_FORMAT_VERSION = 1
_META_KEY = "__waldo_weights__"
# The most a native weights archive may inflate to (the criteria's weights take a few MiB; a 4 MB
# deflated archive of 1.8 GB was read whole before it was refused).
MAX_NATIVE_BYTES = 256 << 20


class WeightsError(WaldoError, ValueError):
    """Weights that exist but do not fit: a wrong shape, a missing key, a corrupt or foreign file."""


@dataclasses.dataclass(frozen=True)
class Converter:
    """How to turn a model folder's original files into its parameter tree.

    Attributes:
      model: the sub-folder name (e.g. "csnet"), also the native file's stem.
      files: the original file names the model needs, inside the sub-folder.
      read: `read(model_dir: Path) -> (tree, meta)`, the tree a nested dict of arrays and `meta` a
        JSON-able dict (e.g. channel splits); raises `WeightsError` naming the first mismatch.
    """

    model: str
    files: Tuple[str, ...]
    read: Callable[[Path], Tuple[Dict[str, Any], Dict[str, Any]]]


CONVERTERS: Dict[str, Converter] = {}


def register_converter(converter: Converter) -> Converter:
    """Adds a model's converter (by `converter.model`)."""
    CONVERTERS[converter.model] = converter
    return converter


def resolve_weights_dir(weights_dir: Optional[str | os.PathLike] = None) -> Path:
    """`weights_dir`, else `WALDO_WEIGHTS`, else `$WALDO_DATA/weights`; a clear error when none is set."""
    if weights_dir is not None:
        return Path(weights_dir).expanduser()
    found = paths.weights_dir()
    if found is None:
        raise DataNotFoundError(
            "no weights folder: pass --weights DIR or set WALDO_WEIGHTS (or WALDO_DATA, whose weights/ is used) "
            "to a folder in the ../shared/weights layout"
        )
    return found


def weights_file(weights_dir: Optional[str | os.PathLike], model: str, filename: str) -> Path:
    """The path `<weights>/<model>/<filename>`, checked to exist.

    Raises:
      DataNotFoundError: naming the expected file and how to point at another folder.
      WaldoError: something there that is no readable regular file (a folder, a FIFO, a link loop).
    """
    folder = resolve_weights_dir(weights_dir)
    if folder.exists() and not folder.is_dir():
        raise DataNotFoundError(f"weights folder {folder}: a file, not a folder (pass --weights DIR)")
    path = folder / model / filename
    if not path.exists():  # nothing there, or a dangling link: where to point instead
        raise DataNotFoundError(
            f"weights file not found: expected {path} (model {model!r}); pass --weights DIR or set WALDO_WEIGHTS "
            "to a folder in the ../shared/weights layout"
        )
    return check_input_file(path, f"{model} weights file")  # a folder or a FIFO there is said as such


def check_shapes(expected: Mapping[str, Sequence[int]], arrays: Mapping[str, np.ndarray], source: str) -> None:
    """Checks that `arrays` has exactly the keys of `expected`, with those shapes.

    Raises:
      WeightsError: naming `source` and the first missing, unexpected or mis-shaped key.
    """
    for name, shape in expected.items():
        if name not in arrays:
            raise WeightsError(f"{source}: missing weight {name!r} (expected shape {tuple(shape)})")
        if tuple(np.shape(arrays[name])) != tuple(shape):
            raise WeightsError(
                f"{source}: weight {name!r} has shape {tuple(np.shape(arrays[name]))}, expected {tuple(shape)}"
            )
    extra = sorted(set(arrays) - set(expected))
    if extra:
        raise WeightsError(f"{source}: unexpected weight {extra[0]!r} ({len(extra)} unexpected in all)")


def _flatten(tree: Mapping[str, Any], prefix: str = "") -> Dict[str, np.ndarray]:
    flat = {}
    for key, value in tree.items():
        if "/" in str(key):
            raise ValueError(f"tree key {key!r} contains '/'")
        path = f"{prefix}{key}"
        if isinstance(value, Mapping):
            flat.update(_flatten(value, path + "/"))
        else:
            flat[path] = np.asarray(value)
    return flat


def _unflatten(flat: Mapping[str, np.ndarray]) -> Dict[str, Any]:
    tree: Dict[str, Any] = {}
    for path, value in flat.items():
        node = tree
        *parents, leaf = path.split("/")
        for part in parents:
            node = node.setdefault(part, {})
        node[leaf] = value
    return tree


def save_native(path: str | os.PathLike, model: str, tree: Mapping[str, Any], meta: Mapping[str, Any]) -> Path:
    """Writes a parameter tree as `.npz` (atomically: a temp file renamed into place)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    record = json.dumps({"format_version": NATIVE_FORMAT_VERSION, "model": model, "meta": dict(meta)})
    arrays = _flatten(tree)
    arrays[_META_KEY] = np.frombuffer(record.encode(), np.uint8)
    with atomic_file(path) as f:
        np.savez(f, **arrays)
    return path


def load_native(path: str | os.PathLike, model: str) -> Tuple[Dict[str, Any], Dict[str, Any]]:
    """Reads a `.npz` written by `save_native`; returns `(tree, meta)`.

    Raises:
      WeightsError: the file is corrupt, of another model, or of another format version.
    """
    path = Path(path)
    try:
        check_input_file(path, "weights archive")
    except WaldoError as exc:
        raise WeightsError(str(exc)) from None
    try:
        with np.load(path, allow_pickle=False) as data:
            # Members inflate no further than their headers' sizes (zipfile stops there): bound those first.
            inflated = sum(info.file_size for info in data.zip.infolist()) if hasattr(data, "zip") else 0
            if inflated > MAX_NATIVE_BYTES:
                raise WeightsError(
                    f"{path}: its arrays would inflate to {inflated / 2**20:,.0f} MiB (at most "
                    f"{MAX_NATIVE_BYTES // 2**20} MiB: waldo's weights are a few MiB)"
                )
            flat = {k: np.array(data[k]) for k in data.files}
    except WeightsError:
        raise
    except Exception as exc:  # zip and npy errors come in many types
        raise WeightsError(f"{path}: not a readable weights archive ({type(exc).__name__}: {exc})") from None
    for key, array in flat.items():
        if key == _META_KEY:
            continue
        if array.dtype.kind not in "biuf":
            raise WeightsError(f"{path}: array {key!r} holds {array.dtype} values, not numbers")
        if array.dtype.kind == "f" and not np.all(np.isfinite(array)):
            raise WeightsError(f"{path}: array {key!r} holds NaN or infinity: convert the original files again")
    if _META_KEY not in flat:
        raise WeightsError(f"{path}: not a waldo weights archive (no {_META_KEY} record)")
    record = parse_json(
        flat.pop(_META_KEY).tobytes(), path, "weights record", lambda problem: WeightsError(f"{path}: {problem}")
    )
    if not isinstance(record, dict):
        raise WeightsError(f"{path}: its {_META_KEY} record is not a JSON object")
    if record.get("format_version") != NATIVE_FORMAT_VERSION:
        raise WeightsError(
            f"{path}: weights format version {record.get('format_version')!r}, this waldo_jax "
            f"reads version {NATIVE_FORMAT_VERSION}: convert the original files again"
        )
    if record.get("model") != model:
        raise WeightsError(f"{path}: holds weights of {record.get('model')!r}, expected {model!r}")
    return _unflatten(flat), record.get("meta", {})


def _warn_if_stale(native: Path, originals: Sequence[Path]) -> None:
    """Warns when an original file beside a converted archive was changed after it: the archive is what is
    loaded, so the change would go unseen."""
    try:
        made = native.stat().st_mtime
        newer = [p.name for p in originals if p.is_file() and p.stat().st_mtime > made]
    except OSError:
        return
    if newer:
        warnings.warn(
            f"{native} is older than {', '.join(newer)} beside it, and it is what is loaded: convert again "
            "(waldo weights convert --force) or remove it to use the originals",
            stacklevel=3,
        )


def load_model(model: str, weights_dir: Optional[str | os.PathLike] = None) -> Tuple[Dict[str, Any], Dict[str, Any]]:
    """A model's `(tree, meta)`: from `<weights>/<model>/<model>.npz` if present, else its original files.

    Raises:
      DataNotFoundError: neither the native file nor the original files are there (names the files).
      WeightsError: a file is there but does not fit, or no converter is registered for `model`
        (the criteria register theirs when `waldo_jax.criteria` is imported).
    """
    if model not in CONVERTERS:
        raise WeightsError(
            f"no converter registered for model {model!r} (registered: "
            f"{', '.join(sorted(CONVERTERS)) or 'none'}); import waldo_jax.criteria, which registers "
            "the criteria's models"
        )
    converter = CONVERTERS[model]
    root = resolve_weights_dir(weights_dir)
    native = root / model / f"{model}.npz"
    if native.exists():  # load_native says what is wrong with anything there that is no archive
        _warn_if_stale(native, [root / model / filename for filename in converter.files])
        return load_native(native, model)
    for filename in converter.files:
        weights_file(root, model, filename)
    return converter.read(root / model)


def convert_all(
    src: str | os.PathLike, dst: str | os.PathLike, models: Optional[Sequence[str]] = None
) -> Dict[str, Path]:
    """Converts every model of `src` (or the named `models`) to `dst/<model>/<model>.npz`.

    Models whose original files are all absent from `src` are skipped when `models` is None.

    Returns:
      `{model: written path}`.

    Raises:
      WaldoError: unknown model name; DataNotFoundError / WeightsError from the readers.
    """
    src, dst = Path(src), Path(dst)
    if src.exists() and not src.is_dir():
        raise DataNotFoundError(f"weights folder {src}: a file, not a folder")
    if not src.is_dir():
        raise DataNotFoundError(f"weights folder not found: {src}")
    if models is None:
        chosen = [m for m, c in CONVERTERS.items() if any((src / m / f).exists() for f in c.files)]
        if not chosen:
            raise DataNotFoundError(
                f"{src}: no model files found; expected sub-folders {', '.join(sorted(CONVERTERS))}"
            )
    else:
        unknown = [m for m in models if m not in CONVERTERS]
        if unknown:
            raise WaldoError(f"unknown model {unknown[0]!r}; choose from {', '.join(sorted(CONVERTERS))}")
        chosen = list(models)
    converted = {}
    for model in chosen:  # every model read before any is written: a bad one leaves DST as it was
        converter = CONVERTERS[model]
        for filename in converter.files:
            weights_file(src, model, filename)
        converted[model] = converter.read(src / model)
    return {model: save_native(dst / model / f"{model}.npz", model, *converted[model]) for model in chosen}
