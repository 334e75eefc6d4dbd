"""The converter from the authors' torch CSNet weights to the Flax variables of `model.CSNet`.

`<weights>/csnet/` holds the checkpoint `csnet-L-x1.pth.tar` (a torch state dict, read without
torch) and `csnet-L-x1.bin` (the pickled channel splits, unpickled with an allow-list of NumPy
types). Each torch weight maps to one Flax variable (gOctave kernels to one variable per (in
branch, out branch) part); OIHW conv kernels become HWIO. `read` is registered as the `csnet`
converter of `waldo_jax.weights`.
"""

from __future__ import annotations

import functools
import io
import pickle
from pathlib import Path
from typing import Any, Dict, List, Mapping, NamedTuple, Optional, Tuple

import numpy as np
from flax import traverse_util

from waldo_jax.criteria.csnet.config import CSNetConfig, Splits
from waldo_jax.errors import DataNotFoundError
from waldo_jax.weights import (
    Converter,
    TorchPickleError,
    WeightsError,
    check_shapes,
    read_torch_file,
    register_converter,
    state_dict,
)
from waldo_jax.weights.torch_pickle import PICKLE_ERRORS, pickle_problem

__all__ = [
    "MODEL",
    "FILES",
    "torch_shapes",
    "flax_shapes",
    "convert_state_dict",
    "read_layer_config",
    "read",
]

MODEL = "csnet"
FILES = ("csnet-L-x1.pth.tar", "csnet-L-x1.bin")
# A `.bin` larger than this is refused before it is read (the authors' is 1.5 KiB).
MAX_LAYER_CONFIG_BYTES = 2**20


def _bounds(splits: Splits) -> Tuple[int, ...]:
    """Channel boundaries [0, c_0, c_0 + c_1, ...] of a split."""
    return tuple(int(b) for b in np.concatenate([[0], np.cumsum(splits)]))


class _Weight(NamedTuple):
    """One Flax variable and where it comes from in the torch state dict."""

    torch_name: str
    torch_shape: Tuple[int, ...]
    path: Tuple[str, ...]  # collection first, e.g. ("params", "stage0_0", "conv1x1", "kernel_0_1")
    conv: bool = False  # a conv kernel: OIHW in torch, HWIO in Flax
    part: Optional[Tuple[int, int, int, int]] = None  # (out_lo, out_hi, in_lo, in_hi) cut of a gOctave kernel

    def flax_shape(self) -> Tuple[int, ...]:
        if not self.conv:
            return self.torch_shape
        out_channels, in_channels, kh, kw = self.torch_shape
        if self.part is not None:
            out_channels, in_channels = self.part[1] - self.part[0], self.part[3] - self.part[2]
        return (kh, kw, in_channels, out_channels)


def _bn_prelu_weights(
    torch_bn: str, torch_prelu: str, path: Tuple[str, ...], index: int, channels: int
) -> List[_Weight]:
    bn, prelu = path + (f"bn_{index}",), path + (f"prelu_{index}",)
    return [
        _Weight(f"{torch_bn}.weight", (channels,), ("params",) + bn + ("scale",)),
        _Weight(f"{torch_bn}.bias", (channels,), ("params",) + bn + ("bias",)),
        _Weight(f"{torch_bn}.running_mean", (channels,), ("batch_stats",) + bn + ("mean",)),
        _Weight(f"{torch_bn}.running_var", (channels,), ("batch_stats",) + bn + ("var",)),
        _Weight(f"{torch_prelu}.weight", (channels,), ("params",) + prelu + ("alpha",)),
    ]


def _goctave_weights(
    prefix: str, path: Tuple[str, ...], in_splits: Splits, out_splits: Splits, kernel_size: int
) -> List[_Weight]:
    shape = (sum(out_splits), sum(in_splits), kernel_size, kernel_size)
    in_bounds, out_bounds = _bounds(in_splits), _bounds(out_splits)
    weights = [
        _Weight(
            f"{prefix}.conv.weight",
            shape,
            ("params",) + path + (f"kernel_{i}_{j}",),
            True,
            (out_bounds[j], out_bounds[j + 1], in_bounds[i], in_bounds[i + 1]),
        )
        for i in range(len(in_splits))
        for j in range(len(out_splits))
    ]
    for j, channels in enumerate(out_splits):
        weights += _bn_prelu_weights(f"{prefix}.bns.{j}", f"{prefix}.prelus.{j}", path, j, channels)
    return weights


@functools.lru_cache(maxsize=8)
def _layout(config: CSNetConfig) -> Tuple[_Weight, ...]:
    """Every variable of the network, in torch order of construction."""
    weights: List[_Weight] = []
    for spec in config.block_specs():
        weights += _goctave_weights(
            f"{spec.torch_prefix}.conv1x1", (spec.name, "conv1x1"), spec.in_splits, spec.out_splits, spec.kernel_size
        )
        for layer in ("conv3x3_1", "conv3x3_2"):
            prefix, path = f"{spec.torch_prefix}.{layer}", (spec.name, layer)
            for i, channels in enumerate(spec.out_splits):
                weights.append(
                    _Weight(
                        f"{prefix}.convs.{i}.weight", (channels, 1, 3, 3), ("params",) + path + (f"kernel_{i}",), True
                    )
                )
            for i, channels in enumerate(spec.out_splits):
                weights += _bn_prelu_weights(f"{prefix}.bns.{i}", f"{prefix}.prelus.{i}", path, i, channels)
    weights += _goctave_weights("oct_fuse.fuse", ("oct_fuse", "fuse"), config.fuse_in, config.fuse_mid, 1)
    for i, (in_channels, dils) in enumerate(zip(config.fuse_mid, config.fuse_dilations)):
        prefix, path = f"oct_fuse.ms.convs.{i}", ("oct_fuse", f"ms_{i}")
        for index, channels in enumerate(dils):
            if channels:
                weights.append(
                    _Weight(
                        f"{prefix}.msconv.{index}.weight",
                        (channels, in_channels, 3, 3),
                        ("params",) + path + (f"kernel_{index}",),
                        True,
                    )
                )
        weights += _bn_prelu_weights(f"{prefix}.bn", f"{prefix}.prelu", path, 0, sum(dils))
    weights += _goctave_weights("oct_fuse.fuse1x1", ("oct_fuse", "fuse1x1"), config.fuse_ms, (config.fuse_out,), 1)
    weights += [
        _Weight("cls_layer.weight", (1, config.fuse_out, 1, 1), ("params", "cls_layer", "kernel"), True),
        _Weight("cls_layer.bias", (1,), ("params", "cls_layer", "bias")),
    ]
    return tuple(weights)


def torch_shapes(config: CSNetConfig) -> Dict[str, Tuple[int, ...]]:
    """{torch name: shape} the reference model built from `config` has (without `num_batches_tracked`)."""
    return {w.torch_name: w.torch_shape for w in _layout(config)}


def flax_shapes(config: CSNetConfig) -> Dict[str, Tuple[int, ...]]:
    """{"params/stage0_0/conv1x1/kernel_0_1": shape, ...} of the Flax variables of `CSNet(config)`."""
    return {"/".join(w.path): w.flax_shape() for w in _layout(config)}


def convert_state_dict(
    state: Mapping[str, np.ndarray], config: CSNetConfig, source: str = "state dict"
) -> Dict[str, Any]:
    """The Flax variables `{"params": ..., "batch_stats": ...}` of a torch CSNet state dict.

    Args:
      state: {torch name: array}; `num_batches_tracked` counters are ignored.
      config: the architecture (from the `.bin` splits).
      source: what to name in errors (the file).

    Returns:
      nested dict of float32 arrays; conv kernels transposed OIHW -> HWIO (gOctave kernels cut into
      their (in branch, out branch) parts), values otherwise as stored (the x100 of Conv2dX100
      layers is applied at run time, as in the reference).

    Raises:
      WeightsError: naming `source` and the first missing, unexpected or mis-shaped weight.
    """
    weights = {k: v for k, v in state.items() if not k.endswith("num_batches_tracked")}
    check_shapes(torch_shapes(config), weights, source)
    flat = {}
    for w in _layout(config):
        value = np.asarray(weights[w.torch_name], np.float32)
        if w.part is not None:
            value = value[w.part[0] : w.part[1], w.part[2] : w.part[3]]
        flat[w.path] = np.ascontiguousarray(value.transpose(2, 3, 1, 0)) if w.conv else value
    return traverse_util.unflatten_dict(flat)


class _SplitsUnpickler(pickle.Unpickler):
    """Unpickles a `.bin` layer config: lists of NumPy arrays and nothing else (no arbitrary code)."""

    _ALLOWED = {"_reconstruct", "ndarray", "dtype", "scalar"}

    def find_class(self, module, name):
        if module in ("numpy", "numpy.core.multiarray", "numpy._core.multiarray") and name in self._ALLOWED:
            if name in ("ndarray", "dtype"):
                return getattr(np, name)
            multiarray = getattr(np, "_core", None) or np.core
            return getattr(multiarray.multiarray, name)
        raise pickle.UnpicklingError(f"refusing to unpickle {module}.{name} (not a CSNet layer config)")


def read_layer_config(path: str | Path) -> CSNetConfig:
    """The architecture of a CSNet `.bin` (a pickled list of per-layer channel splits).

    Raises:
      WeightsError: the file is unreadable or does not describe a CSNet (names the file).
    """
    path = Path(path)
    try:
        size = path.stat().st_size
        if size > MAX_LAYER_CONFIG_BYTES:  # checked before it is read: 1.5 KiB the authors'
            raise WeightsError(
                f"{path}: {size / 2**20:,.1f} MiB; a CSNet layer config is a short list of channel splits "
                f"(at most {MAX_LAYER_CONFIG_BYTES // 2**20} MiB)"
            )
        with open(path, "rb") as f:
            layer_config = _SplitsUnpickler(io.BytesIO(f.read())).load()
    except PICKLE_ERRORS as exc:
        raise WeightsError(f"{path}: not a readable CSNet layer config ({pickle_problem(exc)})") from None
    return CSNetConfig.from_layer_config(layer_config, source=str(path))


def read(model_dir: str | Path) -> Tuple[Dict[str, Any], Dict[str, Any]]:
    """Converter for `<weights>/csnet/`: the `.pth.tar` and `.bin` -> (Flax variables, meta).

    Returns:
      (tree, meta): tree `{"params": ..., "batch_stats": ...}`; meta `{"layer_config": ...}`, the
      `.bin` as JSON-able int lists (`CSNetConfig.from_layer_config` rebuilds the architecture).

    Raises:
      WeightsError: a file that is truncated, corrupt or does not fit the splits (names file and key).
    """
    model_dir = Path(model_dir)
    checkpoint, splits_file = model_dir / FILES[0], model_dir / FILES[1]
    for path in (checkpoint, splits_file):
        if not path.is_file():
            raise DataNotFoundError(f"weights file not found: expected {path} (model {MODEL!r})")
    config = read_layer_config(splits_file)
    try:
        state = state_dict(read_torch_file(checkpoint))
    except TorchPickleError as exc:
        message = str(exc)
        raise WeightsError(message if str(checkpoint) in message else f"{checkpoint}: {message}") from None
    tree = convert_state_dict(state, config, source=str(checkpoint))
    return tree, {"layer_config": config.to_layer_config()}


register_converter(Converter(MODEL, FILES, read))
