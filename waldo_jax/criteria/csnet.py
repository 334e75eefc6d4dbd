"""CSNet-L-x1 salient-object detection, and the `saliency` criterion built on it.

The network is CSNet (Gao, Tan, Cheng, Lu, Chen and Yan, "Highly Efficient Salient Object Detection
with 100K Parameters", ECCV 2020), in its published CSNet-L-x1 variant (97,921 parameters counting
the batch-norm running statistics). This is a port of the architecture and a converter for the
authors' weights; the code is written from the paper and the facts of the reference implementation
(github.com/ShangHua-Gao/SOD100K, `CSNet/model/`), none of it copied.

Licence: the weights are the authors' release under CC BY-NC-SA 4.0 (non-commercial). They are read
from the weights folder (`--weights`, `WALDO_WEIGHTS`) and never committed to this repository.

Architecture, in words. Feature maps are lists of *branches*: branch `j` holds `c_j` channels at
1 / 2**j of the block's resolution (a generalised octave, gOctConv). The channel counts `c_j` of every
layer were found by the paper's pruning and are stored in `csnet-L-x1.bin` (22 entries: 18 blocks,
3 head layers, the stage lengths `(3, 4, 6, 4)`).

  * A block (ILBlock) is a gOctave conv-BN-PReLU (1x1; 3x3 for the first block and for the first,
    stride-2 block of stages 2-4) followed by two depthwise 3x3 conv-BN-PReLU layers, one per branch.
  * The gOctave conv's kernel [C_out, C_in, k, k] is cut into (in branch i, out branch j) parts (the
    reference slices at run time; this port stores the parts): for i == j a plain conv; for i > j a
    conv at branch i's resolution, then bilinear upsampling by 2**(i - j); for i < j max pooling by
    2**(j - i), then the conv; the parts reaching an out branch are summed. Stride 2 is 2x2 average
    pooling of every input branch first. A conv with one input and one output branch is a plain
    (strided) conv instead (none in CSNet-L-x1, whose every gOctave conv has two or three branches
    on one side).
  * Every conv of type `Conv2dX100` (the depthwise convs, the head's dilated convs, and the plain
    single-branch gOctave conv) multiplies its weights by 100 at run time ("for faster convergence"
    in the reference); the gOctave conv proper and the classifier do not.
  * Stage resolutions: stage 0 and stage 1 at the input's 224, stages 2, 3, 4 at 112, 56, 28; each of
    stages 2-4 ends in a single branch.
  * The head (CSF) takes those three stage outputs as the three branches of a gOctave 1x1 conv-BN-PReLU,
    then per branch a multi-scale block (3x3 convs with dilations 1, 2, 4, 8, 16, zero padding equal to
    the dilation, with the per-dilation channel counts of the `.bin`, concatenated, BN, PReLU), then
    a gOctave 1x1 conv-BN-PReLU to a single full-resolution (112) branch, then a 1x1 conv with bias to
    one logit channel, bilinear upsampling to 224 (half-pixel centres, `align_corners=False`) and a
    sigmoid. The result is upsampled to the image's own size.

BN runs in inference mode with the running statistics and PyTorch's eps 1e-5; PReLU has one slope per
channel. Input: RGB in [0, 1], resized to 224x224 (bilinear; antialiased when shrinking, because the
views scored here are often much larger than 224 and plain bilinear sampling would alias), then
normalised with the ImageNet mean and std. The reference resizes without antialiasing (skimage,
`anti_aliasing=False`); for images near 224 the two agree.

Names: `splits` are per-branch channel counts (a tuple of ints per layer); `logits` is the network's
output before the sigmoid; `saliency` is the sigmoid map in [0, 1].
"""

from __future__ import annotations

import dataclasses
import functools
import io
import pickle
from pathlib import Path
from typing import Any, Dict, List, Mapping, NamedTuple, Optional, Sequence, Tuple

import flax.linen as nn
import flax.struct
import jax
import jax.numpy as jnp
import numpy as np
from flax import traverse_util

from waldo_jax.criteria.base import (Criterion, CriterionContext, CriterionSpec, finite_or_worst, register,
                                     sanitize_images)
from waldo_jax.errors import DataNotFoundError
from waldo_jax.types import Array
from waldo_jax.weights import (Converter, TorchPickleError, WeightsError, check_shapes, load_model, read_torch_file,
                               register_converter, resolve_weights_dir, state_dict)

__all__ = [
    "MODEL",
    "FILES",
    "INPUT_SIZE",
    "SALIENT_THRESHOLD",
    "BlockSpec",
    "CSNetConfig",
    "GOctaveCBR",
    "DepthwiseCBR",
    "MultiScaleBlock",
    "ILBlock",
    "CSFHead",
    "CSNet",
    "CSNetParams",
    "torch_shapes",
    "flax_shapes",
    "convert_state_dict",
    "read_layer_config",
    "read",
    "load_params",
    "saliency_map",
    "saliency_maps",
    "salient_fraction",
    "saliency",
]

MODEL = "csnet"
FILES = ("csnet-L-x1.pth.tar", "csnet-L-x1.bin")
INPUT_SIZE = 224  # the network's input side (training and test size of the reference)
SALIENT_THRESHOLD = 0.5  # saliency above this counts as a salient pixel (BASNet's count in the paper)
_IMAGENET_MEAN = (0.485, 0.456, 0.406)
_IMAGENET_STD = (0.229, 0.224, 0.225)
_BN_EPS = 1e-5  # PyTorch BatchNorm2d default
_PRELU_INIT = 0.25  # PyTorch PReLU default (only for `init`; loaded weights replace it)
_DILATIONS = (1, 2, 4, 8, 16)  # the head's multi-scale block
_X100 = 100.0  # Conv2dX100's run-time weight multiplier
_NUM_STAGES = 4  # stages 1..4 after stage 0
_CHUNK = 16  # images per network call in `saliency_maps`

Splits = Tuple[int, ...]


# --------------------------------------------------------------------------------------------------
# Architecture, as set by the channel splits
# --------------------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class BlockSpec:
    """One ILBlock: its torch prefix (e.g. "stage2.0"), Flax name, splits, first conv's kernel and stride."""

    torch_prefix: str
    name: str
    in_splits: Splits
    out_splits: Splits
    kernel_size: int
    stride: int


@dataclasses.dataclass(frozen=True)
class CSNetConfig:
    """The static architecture of a (pruned) CSNet, from its `.bin` layer config. Hashable.

    Attributes:
      blocks: (in_splits, out_splits) of each ILBlock, stage 0 then stages 1-4 in order.
      stages: blocks in stages 1-4, e.g. (3, 4, 6, 4).
      fuse_in: channels of the three stage outputs the head takes (stages 2, 3, 4).
      fuse_mid: out splits of the head's first gOctave 1x1 conv (= the multi-scale blocks' inputs).
      fuse_ms: out channels of the multi-scale block of each head branch.
      fuse_dilations: per head branch, out channels of the convs with dilations 1, 2, 4, 8, 16
        (0: that conv is absent).
      fuse_out: channels of the head's output (its final gOctave 1x1 conv, one branch).
    """

    blocks: Tuple[Tuple[Splits, Splits], ...]
    stages: Tuple[int, ...]
    fuse_in: Splits
    fuse_mid: Splits
    fuse_ms: Splits
    fuse_dilations: Tuple[Splits, ...]
    fuse_out: int

    def block_specs(self) -> Tuple[BlockSpec, ...]:
        """The ILBlocks in order, with the stride and first-conv kernel the reference gives each."""
        specs = [BlockSpec("stage0.0", "stage0_0", *self.blocks[0], kernel_size=3, stride=1)]
        index = 1
        for stage, length in enumerate(self.stages, start=1):
            for k in range(length):
                stride = 2 if (stage >= 2 and k == 0) else 1
                kernel = 3 if stride == 2 else 1
                specs.append(BlockSpec(f"stage{stage}.{k}", f"stage{stage}_{k}", *self.blocks[index],
                                       kernel_size=kernel, stride=stride))
                index += 1
        return tuple(specs)

    def stage_ends(self) -> Tuple[int, int, int]:
        """Indices (into `block_specs()`) of the last blocks of stages 2, 3, 4 (the head's inputs)."""
        ends = np.cumsum((1,) + self.stages) - 1  # last block index of stage 0, 1, 2, 3, 4
        return int(ends[2]), int(ends[3]), int(ends[4])

    def to_layer_config(self) -> List[Any]:
        """The `.bin` layer config as JSON-able nested int lists (the converter's `meta`)."""
        layers: List[Any] = [[list(i), list(o)] for i, o in self.blocks]
        layers.append([list(self.fuse_in), list(self.fuse_mid)])
        layers.append([list(self.fuse_mid), list(self.fuse_ms), [list(d) for d in self.fuse_dilations]])
        layers.append([list(self.fuse_ms), [self.fuse_out]])
        layers.append(list(self.stages))
        return layers

    @classmethod
    def from_layer_config(cls, layer_config: Sequence[Any], source: str = "layer config") -> "CSNetConfig":
        """Parses and checks a `.bin` layer config (NumPy arrays or nested lists, as in `to_layer_config`).

        Raises:
          WeightsError: naming `source` and the first entry that does not describe a CSNet.
        """

        def splits(value, where: str) -> Splits:
            array = np.atleast_1d(np.asarray(value, dtype=np.float64))
            if array.ndim != 1 or array.size == 0 or not np.all(np.isfinite(array)):
                raise WeightsError(f"{source}: {where} must be a non-empty list of channel counts, got {value!r}")
            if np.any(np.abs(array - np.round(array)) > 1e-6) or np.any(array < 0):
                raise WeightsError(f"{source}: {where} has non-integer or negative channel counts {value!r}")
            return tuple(int(round(v)) for v in array)

        try:
            layers = list(layer_config)
        except TypeError:
            raise WeightsError(f"{source}: not a CSNet layer config (a list), got {type(layer_config).__name__}") \
                from None
        if len(layers) < 6:
            raise WeightsError(f"{source}: a CSNet layer config has at least 6 entries, got {len(layers)}")
        stages = splits(layers[-1], "the last entry (blocks per stage)")
        if len(stages) != _NUM_STAGES or min(stages) < 1:
            raise WeightsError(f"{source}: the last entry must give {_NUM_STAGES} stage lengths >= 1, got {stages}")
        num_blocks = 1 + sum(stages)
        if len(layers) != num_blocks + 4:
            raise WeightsError(f"{source}: stages {stages} need {num_blocks + 4} entries, got {len(layers)}")

        def entry(index: int, size: int):
            try:
                items = list(layers[index])
            except TypeError:
                items = []
            if len(items) != size:
                raise WeightsError(f"{source}: entry {index} must have {size} parts, got {layers[index]!r}")
            return items

        blocks = []
        for index in range(num_blocks):
            raw_in, raw_out = entry(index, 2)
            in_splits = (3,) if index == 0 else splits(raw_in, f"entry {index} (in)")
            out_splits = splits(raw_out, f"entry {index} (out)")
            if index == 0 and splits(raw_in, "entry 0 (in)") != (3,):
                raise WeightsError(f"{source}: entry 0 must take the 3 RGB channels, got {raw_in!r}")
            if index > 0 and in_splits != blocks[-1][1]:
                raise WeightsError(f"{source}: entry {index} takes {in_splits} but entry {index - 1} gives "
                                   f"{blocks[-1][1]}")
            if 0 in in_splits or 0 in out_splits:
                raise WeightsError(f"{source}: entry {index} has a zero-width branch ({in_splits} -> {out_splits}); "
                                   "this port supports only CSNets without empty branches")
            blocks.append((in_splits, out_splits))
        raw_fuse_in, raw_fuse_mid = entry(num_blocks, 2)
        raw_ms_in, raw_ms_out, raw_dils = entry(num_blocks + 1, 3)
        raw_out_in, raw_out = entry(num_blocks + 2, 2)
        fuse_in = splits(raw_fuse_in, f"entry {num_blocks} (head in)")
        fuse_mid = splits(raw_fuse_mid, f"entry {num_blocks} (head out)")
        fuse_ms = splits(raw_ms_out, f"entry {num_blocks + 1} (multi-scale out)")
        fuse_out = splits(raw_out, f"entry {num_blocks + 2} (head out)")
        try:
            dils = np.asarray(raw_dils, dtype=np.float64)
        except (TypeError, ValueError):
            dils = np.zeros((0,))
        if dils.shape != (len(fuse_ms), len(_DILATIONS)):
            raise WeightsError(f"{source}: entry {num_blocks + 1} needs dilation channels of shape "
                               f"({len(fuse_ms)}, {len(_DILATIONS)}), got {dils.shape}")
        fuse_dilations = tuple(splits(row, f"entry {num_blocks + 1} (dilations)") for row in dils)
        config = cls(blocks=tuple(blocks), stages=stages, fuse_in=fuse_in, fuse_mid=fuse_mid, fuse_ms=fuse_ms,
                     fuse_dilations=fuse_dilations, fuse_out=0)
        stage_outs = tuple(blocks[i][1] for i in config.stage_ends())
        if any(len(out) != 1 for out in stage_outs) or fuse_in != tuple(out[0] for out in stage_outs):
            raise WeightsError(f"{source}: the head takes {fuse_in} but stages 2-4 end in branches {stage_outs} "
                               "(each must be one branch of that width)")
        if len(fuse_mid) != len(fuse_in) or splits(raw_ms_in, f"entry {num_blocks + 1} (in)") != fuse_mid:
            raise WeightsError(f"{source}: the head's splits {fuse_in} -> {fuse_mid} -> {raw_ms_in!r} do not chain")
        if tuple(sum(d) for d in fuse_dilations) != fuse_ms or 0 in fuse_mid or 0 in fuse_ms:
            raise WeightsError(f"{source}: dilation channels {fuse_dilations} must sum to the non-empty "
                               f"multi-scale widths {fuse_ms}")
        if splits(raw_out_in, f"entry {num_blocks + 2} (in)") != fuse_ms or len(fuse_out) != 1:
            raise WeightsError(f"{source}: entry {num_blocks + 2} must map {fuse_ms} to one branch, "
                               f"got {layers[num_blocks + 2]!r}")
        return dataclasses.replace(config, fuse_out=fuse_out[0])


def _bounds(splits: Splits) -> Tuple[int, ...]:
    """Channel boundaries [0, c_0, c_0 + c_1, ...] of a split."""
    return tuple(int(b) for b in np.concatenate([[0], np.cumsum(splits)]))


# --------------------------------------------------------------------------------------------------
# Layers (NHWC; kernels HWIO)
# --------------------------------------------------------------------------------------------------


def _conv(x: Array, kernel: Array, *, stride: int = 1, padding: int = 0, dilation: int = 1) -> Array:
    """PyTorch-style conv2d without bias: x [N, H, W, C_in], kernel [kh, kw, C_in, C_out], zero padding."""
    return jax.lax.conv_general_dilated(x, kernel, (stride, stride), ((padding, padding), (padding, padding)),
                                        rhs_dilation=(dilation, dilation), dimension_numbers=("NHWC", "HWIO", "NHWC"))


def _avg_pool(x: Array, factor: int) -> Array:
    """Average over non-overlapping factor x factor windows (PyTorch `avg_pool2d(x, f, f)`), x [N, H, W, C]."""
    return nn.avg_pool(x, (factor, factor), strides=(factor, factor), padding="VALID")


def _max_pool(x: Array, factor: int) -> Array:
    """Max over non-overlapping factor x factor windows (PyTorch `max_pool2d(x, f, f)`), x [N, H, W, C]."""
    return nn.max_pool(x, (factor, factor), strides=(factor, factor), padding="VALID")


def _upsample_axis(x: Array, factor: int, axis: int) -> Array:
    """Bilinear upsampling along one axis by an integer factor, half-pixel centres, edges clamped.

    Output sample f * i + p reads the input at i + d_p, d_p = (p + 0.5) / f - 0.5 in (-1/2, 1/2): two
    taps with fixed weights per phase p. Written out (instead of `jax.image.resize`, which contracts
    a dense [f n, n] matrix) because it is many times faster on CPU.
    """
    n = x.shape[axis]
    first = jax.lax.slice_in_dim(x, 0, 1, axis=axis)
    last = jax.lax.slice_in_dim(x, n - 1, n, axis=axis)
    previous = jnp.concatenate([first, jax.lax.slice_in_dim(x, 0, n - 1, axis=axis)], axis=axis)  # x[i - 1]
    following = jnp.concatenate([jax.lax.slice_in_dim(x, 1, n, axis=axis), last], axis=axis)  # x[i + 1]
    phases = []
    for p in range(factor):
        d = (p + 0.5) / factor - 0.5
        phases.append(-d * previous + (1.0 + d) * x if d < 0 else (1.0 - d) * x + d * following)
    y = jnp.stack(phases, axis=axis + 1)  # [..., n, factor, ...]
    return y.reshape(x.shape[:axis] + (n * factor,) + x.shape[axis + 1:])


def _upsample(x: Array, factor: int) -> Array:
    """Bilinear upsampling of x [N, H, W, C] by an integer factor.

    This is PyTorch's `interpolate(scale_factor=factor, mode="bilinear", align_corners=False)`,
    whose source index (o + 0.5) / f - 0.5 is clamped to [0, n - 1].
    """
    return _upsample_axis(_upsample_axis(x, factor, 1), factor, 2)


def _depthwise3x3(x: Array, kernel: Array) -> Array:
    """Depthwise 3x3 conv with zero padding 1: x [N, H, W, C], kernel [3, 3, 1, C] -> [N, H, W, C].

    A sum of nine shifted products, which XLA fuses into one loop; its grouped convolution is ~20x
    slower on CPU.
    """
    height, width = x.shape[1:3]
    padded = jnp.pad(x, ((0, 0), (1, 1), (1, 1), (0, 0)))
    out = 0.0
    for a in range(3):
        for b in range(3):
            out = out + padded[:, a:a + height, b:b + width, :] * kernel[a, b, 0]
    return out


class _PReLU(nn.Module):
    """PyTorch PReLU with one slope per channel (last axis)."""

    @nn.compact
    def __call__(self, x: Array) -> Array:
        alpha = self.param("alpha", nn.initializers.constant(_PRELU_INIT), (x.shape[-1],))
        return jnp.where(x >= 0, x, alpha * x)


def _bn_prelu(x: Array, index: int) -> Array:
    """BN (running statistics) then PReLU, as submodules `bn_<index>`, `prelu_<index>` of the calling module."""
    x = nn.BatchNorm(use_running_average=True, epsilon=_BN_EPS, name=f"bn_{index}")(x)
    return _PReLU(name=f"prelu_{index}")(x)


class GOctaveCBR(nn.Module):
    """Generalised octave conv + BN + PReLU (the reference's `gOctaveCBR`).

    The reference keeps one kernel [C_out, C_in, k, k] and slices it per (in branch i, out branch j)
    at run time; here the parts are separate parameters `kernel_<i>_<j>` [k, k, c_i, c_j] (the
    converter cuts them), which spares XLA a copy of every slice.

    Attributes:
      in_splits: channels of each input branch (branch i at 1 / 2**i resolution).
      out_splits: channels of each output branch.
      kernel_size: 1 or 3 (zero padding kernel_size // 2).
      stride: 1 or 2.
    """

    in_splits: Splits
    out_splits: Splits
    kernel_size: int = 1
    stride: int = 1

    @nn.compact
    def __call__(self, xs: Sequence[Array]) -> List[Array]:
        """xs: branches [N, H / 2**i, W / 2**i, in_splits[i]] -> branches [N, H' / 2**j, W' / 2**j, out_splits[j]]."""
        k, pad = self.kernel_size, self.kernel_size // 2
        kernels = [[self.param(f"kernel_{i}_{j}", nn.initializers.lecun_normal(), (k, k, c_in, c_out))
                    for j, c_out in enumerate(self.out_splits)] for i, c_in in enumerate(self.in_splits)]
        if len(self.in_splits) == 1 and len(self.out_splits) == 1:
            # The reference builds a plain Conv2dX100 here: a strided conv, weights x 100 (applied to
            # the output, which is the same by linearity and fuses with what follows).
            outs = [_X100 * _conv(xs[0], kernels[0][0], stride=self.stride, padding=pad)]
        else:
            outs = [None] * len(self.out_splits)
            for i, x in enumerate(xs):
                if self.stride == 2:
                    x = _avg_pool(x, 2)
                for j in range(len(self.out_splits)):
                    if i > j:  # coarser input: conv at its resolution, then upsample
                        y = _upsample(_conv(x, kernels[i][j], padding=pad), 2 ** (i - j))
                    elif i < j:  # finer input: max-pool to the output's resolution, then conv
                        y = _conv(_max_pool(x, 2 ** (j - i)), kernels[i][j], padding=pad)
                    else:
                        y = _conv(x, kernels[i][j], padding=pad)
                    outs[j] = y if outs[j] is None else outs[j] + y
        return [_bn_prelu(y, j) for j, y in enumerate(outs)]


class DepthwiseCBR(nn.Module):
    """Per-branch depthwise 3x3 conv (weights x 100) + BN + PReLU (the reference's `SimplifiedGOctConvBR`).

    Attributes:
      splits: channels of each branch (unchanged by the layer).
    """

    splits: Splits

    @nn.compact
    def __call__(self, xs: Sequence[Array]) -> List[Array]:
        """xs: branches [N, h_i, w_i, splits[i]] -> the same shapes."""
        outs = []
        for i, (x, channels) in enumerate(zip(xs, self.splits)):
            kernel = self.param(f"kernel_{i}", nn.initializers.lecun_normal(), (3, 3, 1, channels))
            outs.append(_bn_prelu(_depthwise3x3(x, _X100 * kernel), i))
        return outs


class MultiScaleBlock(nn.Module):
    """Parallel dilated 3x3 convs (weights x 100, dilations 1..16), concatenated, BN, PReLU (`MSBlock`).

    Attributes:
      dilation_channels: out channels of the conv with each dilation of `_DILATIONS` (0: absent).
    """

    dilation_channels: Splits

    @nn.compact
    def __call__(self, x: Array) -> Array:
        """x [N, H, W, C_in] -> [N, H, W, sum(dilation_channels)]."""
        outs = []
        for index, (dilation, channels) in enumerate(zip(_DILATIONS, self.dilation_channels)):
            if channels == 0:
                continue
            kernel = self.param(f"kernel_{index}", nn.initializers.lecun_normal(), (3, 3, x.shape[-1], channels))
            outs.append(_X100 * _conv(x, kernel, padding=dilation, dilation=dilation))  # = conv with 100 w
        return _bn_prelu(jnp.concatenate(outs, axis=-1), 0)


class ILBlock(nn.Module):
    """A CSNet block: gOctave conv-BN-PReLU, then two per-branch depthwise conv-BN-PReLU layers."""

    in_splits: Splits
    out_splits: Splits
    kernel_size: int
    stride: int

    @nn.compact
    def __call__(self, xs: Sequence[Array]) -> List[Array]:
        xs = GOctaveCBR(self.in_splits, self.out_splits, self.kernel_size, self.stride, name="conv1x1")(xs)
        xs = DepthwiseCBR(self.out_splits, name="conv3x3_1")(xs)
        return DepthwiseCBR(self.out_splits, name="conv3x3_2")(xs)


class CSFHead(nn.Module):
    """The cross-stage fusion head: gOctave 1x1 over stages 2-4, multi-scale blocks, gOctave 1x1 to one branch."""

    config: CSNetConfig

    @nn.compact
    def __call__(self, xs: Sequence[Array]) -> Array:
        """xs: stage outputs [N, H, W, C2], [N, H/2, W/2, C3], [N, H/4, W/4, C4] -> [N, H, W, fuse_out]."""
        c = self.config
        xs = GOctaveCBR(c.fuse_in, c.fuse_mid, name="fuse")(xs)
        xs = [MultiScaleBlock(d, name=f"ms_{i}")(x) for i, (x, d) in enumerate(zip(xs, c.fuse_dilations))]
        return GOctaveCBR(c.fuse_ms, (c.fuse_out,), name="fuse1x1")(xs)[0]


class CSNet(nn.Module):
    """CSNet: normalised images [N, H, W, 3] (H, W multiples of 16; 224 in training) -> logits [N, H, W, 1]."""

    config: CSNetConfig

    @nn.compact
    def __call__(self, x: Array) -> Array:
        if x.ndim != 4 or x.shape[1] % 16 or x.shape[2] % 16:
            raise ValueError(f"CSNet takes images [N, H, W, 3] with H and W multiples of 16, got {x.shape}")
        xs = [x]
        outputs = []
        for spec in self.config.block_specs():
            xs = ILBlock(spec.in_splits, spec.out_splits, spec.kernel_size, spec.stride, name=spec.name)(xs)
            outputs.append(xs)
        fused = CSFHead(self.config, name="oct_fuse")([outputs[i][0] for i in self.config.stage_ends()])
        logits = nn.Conv(1, (1, 1), name="cls_layer")(fused)  # [N, H / 2, W / 2, 1]
        return _upsample(logits, 2)


# --------------------------------------------------------------------------------------------------
# Converter: torch state dict + splits -> Flax variables
# --------------------------------------------------------------------------------------------------

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


def _bn_prelu_weights(torch_bn: str, torch_prelu: str, path: Tuple[str, ...], index: int,
                      channels: int) -> List[_Weight]:
    bn, prelu = path + (f"bn_{index}",), path + (f"prelu_{index}",)
    return [_Weight(f"{torch_bn}.weight", (channels,), ("params",) + bn + ("scale",)),
            _Weight(f"{torch_bn}.bias", (channels,), ("params",) + bn + ("bias",)),
            _Weight(f"{torch_bn}.running_mean", (channels,), ("batch_stats",) + bn + ("mean",)),
            _Weight(f"{torch_bn}.running_var", (channels,), ("batch_stats",) + bn + ("var",)),
            _Weight(f"{torch_prelu}.weight", (channels,), ("params",) + prelu + ("alpha",))]


def _goctave_weights(prefix: str, path: Tuple[str, ...], in_splits: Splits, out_splits: Splits,
                     kernel_size: int) -> List[_Weight]:
    shape = (sum(out_splits), sum(in_splits), kernel_size, kernel_size)
    in_bounds, out_bounds = _bounds(in_splits), _bounds(out_splits)
    weights = [_Weight(f"{prefix}.conv.weight", shape, ("params",) + path + (f"kernel_{i}_{j}",), True,
                       (out_bounds[j], out_bounds[j + 1], in_bounds[i], in_bounds[i + 1]))
               for i in range(len(in_splits)) for j in range(len(out_splits))]
    for j, channels in enumerate(out_splits):
        weights += _bn_prelu_weights(f"{prefix}.bns.{j}", f"{prefix}.prelus.{j}", path, j, channels)
    return weights


@functools.lru_cache(maxsize=8)
def _layout(config: CSNetConfig) -> Tuple[_Weight, ...]:
    """Every variable of the network, in torch order of construction."""
    weights: List[_Weight] = []
    for spec in config.block_specs():
        weights += _goctave_weights(f"{spec.torch_prefix}.conv1x1", (spec.name, "conv1x1"), spec.in_splits,
                                    spec.out_splits, spec.kernel_size)
        for layer in ("conv3x3_1", "conv3x3_2"):
            prefix, path = f"{spec.torch_prefix}.{layer}", (spec.name, layer)
            for i, channels in enumerate(spec.out_splits):
                weights.append(_Weight(f"{prefix}.convs.{i}.weight", (channels, 1, 3, 3),
                                       ("params",) + path + (f"kernel_{i}",), True))
            for i, channels in enumerate(spec.out_splits):
                weights += _bn_prelu_weights(f"{prefix}.bns.{i}", f"{prefix}.prelus.{i}", path, i, channels)
    weights += _goctave_weights("oct_fuse.fuse", ("oct_fuse", "fuse"), config.fuse_in, config.fuse_mid, 1)
    for i, (in_channels, dils) in enumerate(zip(config.fuse_mid, config.fuse_dilations)):
        prefix, path = f"oct_fuse.ms.convs.{i}", ("oct_fuse", f"ms_{i}")
        for index, channels in enumerate(dils):
            if channels:
                weights.append(_Weight(f"{prefix}.msconv.{index}.weight", (channels, in_channels, 3, 3),
                                       ("params",) + path + (f"kernel_{index}",), True))
        weights += _bn_prelu_weights(f"{prefix}.bn", f"{prefix}.prelu", path, 0, sum(dils))
    weights += _goctave_weights("oct_fuse.fuse1x1", ("oct_fuse", "fuse1x1"), config.fuse_ms, (config.fuse_out,), 1)
    weights += [_Weight("cls_layer.weight", (1, config.fuse_out, 1, 1), ("params", "cls_layer", "kernel"), True),
                _Weight("cls_layer.bias", (1,), ("params", "cls_layer", "bias"))]
    return tuple(weights)


def torch_shapes(config: CSNetConfig) -> Dict[str, Tuple[int, ...]]:
    """{torch name: shape} the reference model built from `config` has (without `num_batches_tracked`)."""
    return {w.torch_name: w.torch_shape for w in _layout(config)}


def flax_shapes(config: CSNetConfig) -> Dict[str, Tuple[int, ...]]:
    """{"params/stage0_0/conv1x1/kernel_0_1": shape, ...} of the Flax variables of `CSNet(config)`."""
    return {"/".join(w.path): w.flax_shape() for w in _layout(config)}


def convert_state_dict(state: Mapping[str, np.ndarray], config: CSNetConfig,
                       source: str = "state dict") -> Dict[str, Any]:
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
            value = value[w.part[0]:w.part[1], w.part[2]:w.part[3]]
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
        with open(path, "rb") as f:
            layer_config = _SplitsUnpickler(io.BytesIO(f.read())).load()
    except (pickle.UnpicklingError, EOFError, ValueError, TypeError, AttributeError, IndexError) as exc:
        raise WeightsError(f"{path}: not a readable CSNet layer config ({type(exc).__name__}: {exc})") from None
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


# --------------------------------------------------------------------------------------------------
# Public functions: parameters, saliency maps, the criterion
# --------------------------------------------------------------------------------------------------


@flax.struct.dataclass
class CSNetParams:
    """What the `saliency` criterion carries: the network's variables (traced) and its architecture (static).

    Attributes:
      variables: `{"params": ..., "batch_stats": ...}` of `CSNet(config)`, float32 arrays.
      config: the architecture from the splits (hashable, part of the pytree structure).
    """

    variables: Any
    config: CSNetConfig = flax.struct.field(pytree_node=False)


def load_params(weights_dir: Optional[str | Path] = None) -> CSNetParams:
    """CSNet-L-x1 parameters from `<weights>/csnet/` (the native `csnet.npz`, else the original files).

    Args:
      weights_dir: folder in the `../shared/weights` layout (default `WALDO_WEIGHTS`, `$WALDO_DATA/weights`).

    Raises:
      DataNotFoundError: no weights there (names the expected files).
      WeightsError: weights that do not fit the architecture (names the file and the first bad key).
    """
    tree, meta = load_model(MODEL, weights_dir)
    source = str(resolve_weights_dir(weights_dir) / MODEL)
    if "layer_config" not in meta:
        raise WeightsError(f"{source}: the converted weights carry no 'layer_config' (convert them again)")
    config = CSNetConfig.from_layer_config(meta["layer_config"], source=source)
    flat = traverse_util.flatten_dict(tree, sep="/")
    check_shapes(flax_shapes(config), flat, source)
    return CSNetParams(variables=jax.tree.map(lambda a: jnp.asarray(a, jnp.float32), tree), config=config)


def saliency_map(params: CSNetParams, image: Array) -> Array:
    """The saliency map of one image.

    Args:
      params: from `load_params`.
      image: float32 [H, W, 3], RGB in [0, 1], any size.

    Returns:
      float32 [H, W] in [0, 1]: the network's sigmoid output at 224x224, upsampled (bilinear) to the
      image's size.
    """
    image = jnp.asarray(image, jnp.float32)
    height, width = image.shape[:2]
    x = image
    if (height, width) != (INPUT_SIZE, INPUT_SIZE):
        x = jax.image.resize(image, (INPUT_SIZE, INPUT_SIZE, 3), method="linear", antialias=True)
    x = (x - jnp.asarray(_IMAGENET_MEAN)) / jnp.asarray(_IMAGENET_STD)  # [224, 224, 3]
    logits = CSNet(params.config).apply(params.variables, x[None])[0, :, :, 0]  # [224, 224]
    saliency = jax.nn.sigmoid(logits)
    if (height, width) != (INPUT_SIZE, INPUT_SIZE):
        saliency = jax.image.resize(saliency, (height, width), method="linear", antialias=True)
    return jnp.clip(saliency, 0.0, 1.0)


def saliency_maps(params: CSNetParams, images: Array) -> Array:
    """Saliency maps of a batch of images (`saliency_map` of each).

    The batch runs in chunks of at most `_CHUNK` images (the largest divisor of P up to it, so that
    the network is compiled once per call): the full-resolution activations of a whole population
    would take gigabytes, and chunks that stay in cache are no slower.

    Args:
      params: from `load_params`.
      images: float32 [P, H, W, 3], RGB in [0, 1].

    Returns:
      float32 [P, H, W] in [0, 1].
    """
    images = jnp.asarray(images, jnp.float32)
    count, height, width = images.shape[:3]
    chunk = max(d for d in range(1, max(1, min(_CHUNK, count)) + 1) if count % d == 0)
    chunks = images.reshape(count // chunk, chunk, height, width, 3)
    maps = jax.lax.map(jax.vmap(functools.partial(saliency_map, params)), chunks)  # [P / chunk, chunk, H, W]
    return maps.reshape(count, height, width)


def salient_fraction(saliency_image: Array) -> Array:
    """Fraction [] of the pixels of a saliency map [H, W] whose saliency exceeds `SALIENT_THRESHOLD`."""
    return jnp.mean((saliency_image > SALIENT_THRESHOLD).astype(jnp.float32))


def _apply(params: CSNetParams, images: Array) -> Array:
    """Scores [P] of images [P, H, W, 3]: the salient fraction, 0.0 for images with NaN/inf."""
    clean, bad = sanitize_images(images)
    maps = saliency_maps(params, clean)  # [P, H, W]
    scores = jax.vmap(salient_fraction)(maps)
    bad = bad | ~jnp.all(jnp.isfinite(maps), axis=(1, 2))
    return finite_or_worst(scores, bad, 0.0)


_DESCRIPTION = ("CSNet-L-x1 salient-object detection (Gao et al., ECCV 2020): the fraction of pixels with "
                "saliency > 0.5")


def saliency(context: CriterionContext) -> Criterion:
    """The `saliency` criterion (direction max, in [0, 1]).

    Score of an image = the fraction of its pixels whose CSNet-L-x1 saliency exceeds 0.5. The paper
    counts BASNet's salient pixels; dividing by H * W makes scores comparable across resolutions.
    Images containing NaN or inf get the worst score 0.0.

    Raises:
      DataNotFoundError / WeightsError: from `load_params(context.weights_dir)`.
    """
    return Criterion(params=load_params(context.weights_dir), name="saliency", direction="max",
                     value_range=(0.0, 1.0), inputs="images", apply=_apply, description=_DESCRIPTION)


register(CriterionSpec("saliency", "max", "images", _DESCRIPTION, saliency))
