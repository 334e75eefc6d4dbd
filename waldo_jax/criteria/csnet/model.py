"""CSNet's layers and network as Flax modules (NHWC feature maps, HWIO kernels), called functionally.

A block (`ILBlock`) is a gOctave conv-BN-PReLU followed by two per-branch depthwise 3x3
conv-BN-PReLU layers; the head (`CSFHead`) fuses the outputs of stages 2-4 through multi-scale
dilated convs into one logit map. BN runs in inference mode with the running statistics and
PyTorch's eps 1e-5; PReLU has one slope per channel; the reference's `Conv2dX100` layers multiply
their weights by 100 at run time. The architecture in words: docs/design.md, "Criteria".

Names: `xs` is a list of branches (branch i [N, H / 2**i, W / 2**i, c_i]); `splits` as in `config`.
"""

from __future__ import annotations

import functools
from typing import List, Sequence

import flax.linen as nn
import jax
import jax.numpy as jnp
from jax.custom_derivatives import SymbolicZero

from waldo_jax import autodiff
from waldo_jax.criteria.csnet.config import DILATIONS, CSNetConfig, Splits
from waldo_jax.types import Array

__all__ = [
    "conv",
    "avg_pool",
    "max_pool",
    "upsample",
    "depthwise3x3",
    "GOctaveCBR",
    "DepthwiseCBR",
    "MultiScaleBlock",
    "ILBlock",
    "CSFHead",
    "CSNet",
]

_BN_EPS = 1e-5  # PyTorch BatchNorm2d default
_PRELU_INIT = 0.25  # PyTorch PReLU default (only for `init`; loaded weights replace it)
_X100 = 100.0  # Conv2dX100's run-time weight multiplier


# --------------------------------------------------------------------------------------------------
# Layers (NHWC; kernels HWIO)
# --------------------------------------------------------------------------------------------------


def conv(x: Array, kernel: Array, *, stride: int = 1, padding: int = 0, dilation: int = 1) -> Array:
    """PyTorch-style conv2d without bias: x [N, H, W, C_in], kernel [kh, kw, C_in, C_out], zero padding."""
    return jax.lax.conv_general_dilated(
        x,
        kernel,
        (stride, stride),
        ((padding, padding), (padding, padding)),
        rhs_dilation=(dilation, dilation),
        dimension_numbers=("NHWC", "HWIO", "NHWC"),
    )


def avg_pool(x: Array, factor: int) -> Array:
    """Average over non-overlapping factor x factor windows (PyTorch `avg_pool2d(x, f, f)`), x [N, H, W, C]."""
    return nn.avg_pool(x, (factor, factor), strides=(factor, factor), padding="VALID")


def max_pool(x: Array, factor: int) -> Array:
    """Max over non-overlapping factor x factor windows (PyTorch `max_pool2d(x, f, f)`), x [N, H, W, C]."""
    return nn.max_pool(x, (factor, factor), strides=(factor, factor), padding="VALID")


def _upsample_axis_taps(x: Array, factor: int, axis: int) -> Array:
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
    return y.reshape(x.shape[:axis] + (n * factor,) + x.shape[axis + 1 :])


def _upsample_axis_adjoint(g: Array, factor: int, axis: int) -> Array:
    """The adjoint of `_upsample_axis_taps(., factor, axis)`, g [..., n * factor, ...] -> [..., n, ...], in
    the same gathering form: input i collects its own taps' weights of outputs f i + p, and the taps
    that outputs f (i + 1) + p (d_p < 0) and f (i - 1) + p (d_p > 0) read from it; the clamped edges
    keep the taps that fall outside."""
    n = g.shape[axis] // factor
    blocks = g.reshape(g.shape[:axis] + (n, factor) + g.shape[axis + 1 :])
    own, to_previous, to_following = 0.0, 0.0, 0.0
    for p in range(factor):
        d = (p + 0.5) / factor - 0.5
        phase = jax.lax.index_in_dim(blocks, p, axis=axis + 1, keepdims=False)  # [..., n, ...]
        if d < 0:
            own, to_previous = own + (1.0 + d) * phase, to_previous - d * phase
        else:
            own, to_following = own + (1.0 - d) * phase, to_following + d * phase
    if n == 1:
        return own + to_previous + to_following
    part = functools.partial(jax.lax.slice_in_dim, axis=axis)
    first = part(own, 0, 1) + part(to_previous, 0, 1) + part(to_previous, 1, 2)
    middle = part(own, 1, n - 1) + part(to_previous, 2, n) + part(to_following, 0, n - 2)
    last = part(own, n - 1, n) + part(to_following, n - 2, n - 1) + part(to_following, n - 1, n)
    return jnp.concatenate([first, middle, last], axis=axis)


@functools.partial(jax.custom_jvp, nondiff_argnums=(1, 2))
def _upsample_axis(x: Array, factor: int, axis: int) -> Array:
    """`_upsample_axis_taps`, differentiable in both modes with reverse mode as fast as the forward (the
    plain transpose of its slices and concatenations is padded copies, which made CSNet's gradient
    slow on CPU): its tangent is the transpose of the adjoint (`_upsample_axis_adjoint`), the same
    linear map, so that reverse mode, which transposes it, runs the adjoint itself."""
    return _upsample_axis_taps(x, factor, axis)


@_upsample_axis.defjvp
def _upsample_axis_jvp(factor: int, axis: int, primals, tangents):
    (x,), (dx,) = primals, tangents
    y = _upsample_axis_taps(x, factor, axis)
    adjoint = functools.partial(_upsample_axis_adjoint, factor=factor, axis=axis)
    return y, jax.linear_transpose(adjoint, y)(dx)[0]


def upsample(x: Array, factor: int) -> Array:
    """Bilinear upsampling of x [N, H, W, C] by an integer factor.

    This is PyTorch's `interpolate(scale_factor=factor, mode="bilinear", align_corners=False)`,
    whose source index (o + 0.5) / f - 0.5 is clamped to [0, n - 1]. Differentiates through its rule
    (`_upsample_axis`), or through the taps themselves inside `autodiff.tangents("forward")`.
    """
    axis_fn = _upsample_axis_taps if autodiff.forward_tangents() else _upsample_axis
    return axis_fn(axis_fn(x, factor, 1), factor, 2)


def _taps(x: Array, kernel: Array) -> Array:
    """The depthwise 3x3 conv with zero padding 1 as a sum of nine shifted products (see `depthwise3x3`)."""
    height, width = x.shape[1:3]
    padded = jnp.pad(x, ((0, 0), (1, 1), (1, 1), (0, 0)))
    out = 0.0
    for a in range(3):
        for b in range(3):
            out = out + padded[:, a : a + height, b : b + width, :] * kernel[a, b, 0]
    return out


def depthwise3x3(x: Array, kernel: Array) -> Array:
    """Depthwise 3x3 conv with zero padding 1: x [N, H, W, C], kernel [3, 3, 1, C] -> [N, H, W, C].

    A sum of nine shifted products, which XLA fuses into one loop; its grouped convolution is ~20x
    slower on CPU. Differentiable in both modes with a rule (`_depthwise3x3_jvp`) that keeps reverse
    mode as fast: the plain transpose of nine shifted products is nine padded copies of the cotangent,
    five times slower on CPU than the forward (CSNet's gradient with respect to its image took seven
    of its forwards); the rule's transpose is these nine shifted products with the kernel flipped.
    Inside `autodiff.tangents("forward")` autodiff pushes the tangents through the taps themselves.
    """
    return _taps(x, kernel) if autodiff.forward_tangents() else _depthwise3x3(x, kernel)


@jax.custom_jvp
def _depthwise3x3(x: Array, kernel: Array) -> Array:
    return _taps(x, kernel)


@functools.partial(_depthwise3x3.defjvp, symbolic_zeros=True)
def _depthwise3x3_jvp(primals, tangents):
    """The input's tangent goes through the transpose of the flipped-kernel taps (the same linear map,
    as the conv with the flipped kernel is this one's adjoint), so that reverse mode, which transposes
    it again, runs the taps themselves; the kernel's tangent through the taps."""
    x, kernel = primals
    dx, dkernel = tangents
    dy = jnp.zeros_like(x)
    if not isinstance(dx, SymbolicZero):
        flipped = kernel[::-1, ::-1]
        dy = dy + jax.linear_transpose(lambda g: _taps(g, flipped), dx)(dx)[0]
    if not isinstance(dkernel, SymbolicZero):
        dy = dy + _taps(x, dkernel)
    return _taps(x, kernel), dy


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
        kernels = [
            [
                self.param(f"kernel_{i}_{j}", nn.initializers.lecun_normal(), (k, k, c_in, c_out))
                for j, c_out in enumerate(self.out_splits)
            ]
            for i, c_in in enumerate(self.in_splits)
        ]
        if len(self.in_splits) == 1 and len(self.out_splits) == 1:
            # The reference builds a plain Conv2dX100 here: a strided conv, weights x 100 (applied to
            # the output, which is the same by linearity and fuses with what follows).
            outs = [_X100 * conv(xs[0], kernels[0][0], stride=self.stride, padding=pad)]
        else:
            outs = [None] * len(self.out_splits)
            for i, x in enumerate(xs):
                if self.stride == 2:
                    x = avg_pool(x, 2)
                for j in range(len(self.out_splits)):
                    if i > j:  # coarser input: conv at its resolution, then upsample
                        y = upsample(conv(x, kernels[i][j], padding=pad), 2 ** (i - j))
                    elif i < j:  # finer input: max-pool to the output's resolution, then conv
                        y = conv(max_pool(x, 2 ** (j - i)), kernels[i][j], padding=pad)
                    else:
                        y = conv(x, kernels[i][j], padding=pad)
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
            outs.append(_bn_prelu(depthwise3x3(x, _X100 * kernel), i))
        return outs


class MultiScaleBlock(nn.Module):
    """Parallel dilated 3x3 convs (weights x 100, dilations 1..16), concatenated, BN, PReLU (`MSBlock`).

    Attributes:
      dilation_channels: out channels of the conv with each dilation of `DILATIONS` (0: absent).
    """

    dilation_channels: Splits

    @nn.compact
    def __call__(self, x: Array) -> Array:
        """x [N, H, W, C_in] -> [N, H, W, sum(dilation_channels)]."""
        outs = []
        for index, (dilation, channels) in enumerate(zip(DILATIONS, self.dilation_channels)):
            if channels == 0:
                continue
            kernel = self.param(f"kernel_{index}", nn.initializers.lecun_normal(), (3, 3, x.shape[-1], channels))
            outs.append(_X100 * conv(x, kernel, padding=dilation, dilation=dilation))  # = conv with 100 w
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
        return upsample(logits, 2)
