"""CSNet-L-x1 (`saliency`): each layer type against an independent NumPy port of the reference
(ShangHua-Gao/SOD100K `CSNet/model/`, PyTorch layouts, loops where it loops), the converter and its
errors, salient objects on synthetic images and the fox in its training views, and the criterion
under jit."""

import waldo_jax  # noqa: F401  (XLA flags before JAX starts)

import copy
import json
import math
import os
import pickle

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from flax import traverse_util
from PIL import Image

from conftest import require_scene, require_weights
from waldo_jax import autodiff
from waldo_jax.criteria import csnet
from waldo_jax.criteria.csnet import convert as csnet_convert
from waldo_jax.criteria.csnet import model as csnet_model
from waldo_jax.criteria.base import CRITERIA, CriterionContext, make_criterion
from waldo_jax.errors import DataNotFoundError
from waldo_jax.weights import WeightsError, save_native

# ---------------------------------------------------------------------------------------------
# The independent reference: NumPy, float64, torch layouts (feature maps [C, H, W], kernels OIHW).

DILATIONS = (1, 2, 4, 8, 16)
BN_EPS = 1e-5


def np_conv(x, w, stride=1, padding=0, dilation=1, groups=1):
    """torch `conv2d`: x [C_in, H, W], w [C_out, C_in / groups, kh, kw] -> [C_out, H', W']."""
    c_in, h, wd = x.shape
    c_out, per_group, kh, kw = w.shape
    assert c_in == per_group * groups
    xp = np.pad(x, ((0, 0), (padding, padding), (padding, padding)))
    oh = (h + 2 * padding - dilation * (kh - 1) - 1) // stride + 1
    ow = (wd + 2 * padding - dilation * (kw - 1) - 1) // stride + 1
    xg = xp.reshape(groups, per_group, *xp.shape[1:])
    wg = w.reshape(groups, c_out // groups, per_group, kh, kw)
    out = np.zeros((groups, c_out // groups, oh, ow))
    for a in range(kh):
        for b in range(kw):
            window = xg[
                :,
                :,
                a * dilation : a * dilation + stride * (oh - 1) + 1 : stride,
                b * dilation : b * dilation + stride * (ow - 1) + 1 : stride,
            ]
            out += np.einsum("goc,gchw->gohw", wg[..., a, b], window)
    return out.reshape(c_out, oh, ow)


def np_pool(x, k, reduce):
    """torch `max_pool2d` / `avg_pool2d` with kernel = stride = k: x [C, H, W]."""
    c, h, w = x.shape
    return reduce(x[:, : h // k * k, : w // k * k].reshape(c, h // k, k, w // k, k), axis=(2, 4))


def np_upsample(x, factor):
    """torch `interpolate(scale_factor=factor, mode="bilinear", align_corners=False)`: x [C, H, W]."""

    def matrix(n_in):
        m = np.zeros((n_in * factor, n_in))
        for o in range(n_in * factor):
            src = max((o + 0.5) / factor - 0.5, 0.0)
            i0 = int(math.floor(src))
            i1 = min(i0 + 1, n_in - 1)
            lam = src - i0
            m[o, i0] += 1.0 - lam
            m[o, i1] += lam
        return m

    return matrix(x.shape[1]) @ x @ matrix(x.shape[2]).T  # [C, H f, W f]


def np_bn_prelu(sd, bn, prelu, x):
    """`BatchNorm2d` (eval) then `PReLU`, x [C, H, W]."""
    col = lambda name: sd[name].astype(np.float64)[:, None, None]  # noqa: E731
    y = (x - col(f"{bn}.running_mean")) / np.sqrt(col(f"{bn}.running_var") + BN_EPS) * col(f"{bn}.weight") + col(
        f"{bn}.bias"
    )
    return np.where(y >= 0, y, col(f"{prelu}.weight") * y)


def np_goctave_cbr(sd, prefix, xs, in_splits, out_splits, kernel_size, stride):
    """`gOctaveCBR.forward` (with `gOctaveConv`, or a plain `Conv2dX100` for one branch in and out)."""
    weight = sd[f"{prefix}.conv.weight"].astype(np.float64)
    pad = kernel_size // 2
    if len(in_splits) == 1 and len(out_splits) == 1:
        ys = [np_conv(xs[0], 100.0 * weight, stride=stride, padding=pad)]
    else:
        in_bounds, out_bounds = np.cumsum([0, *in_splits]), np.cumsum([0, *out_splits])
        ys = [0.0] * len(out_splits)
        for i, x in enumerate(xs):
            if stride == 2:
                x = np_pool(x, 2, np.mean)
            for j in range(len(out_splits)):
                part = weight[out_bounds[j] : out_bounds[j + 1], in_bounds[i] : in_bounds[i + 1]]
                if i > j:
                    y = np_upsample(np_conv(x, part, padding=pad), 2 ** (i - j))
                elif i < j:
                    y = np_conv(np_pool(x, 2 ** (j - i), np.max), part, padding=pad)
                else:
                    y = np_conv(x, part, padding=pad)
                ys[j] = ys[j] + y
    return [np_bn_prelu(sd, f"{prefix}.bns.{j}", f"{prefix}.prelus.{j}", y) for j, y in enumerate(ys)]


def np_depthwise_cbr(sd, prefix, xs):
    """`SimplifiedGOctConvBR.forward`: per branch a depthwise 3x3 `Conv2dX100`, BN, PReLU."""
    return [
        np_bn_prelu(
            sd,
            f"{prefix}.bns.{i}",
            f"{prefix}.prelus.{i}",
            np_conv(x, 100.0 * sd[f"{prefix}.convs.{i}.weight"].astype(np.float64), padding=1, groups=x.shape[0]),
        )
        for i, x in enumerate(xs)
    ]


def np_multiscale(sd, prefix, x, dilation_channels):
    """`MSBlock.forward`: dilated 3x3 `Conv2dX100`s (absent where the split is 0), concat, BN, PReLU."""
    outs = [
        np_conv(x, 100.0 * sd[f"{prefix}.msconv.{k}.weight"].astype(np.float64), padding=d, dilation=d)
        for k, (d, c) in enumerate(zip(DILATIONS, dilation_channels))
        if c
    ]
    return np_bn_prelu(sd, f"{prefix}.bn", f"{prefix}.prelu", np.concatenate(outs, axis=0))


def np_head(sd, layer_config, feats):
    """`CSFHead.forward` on the three stage outputs."""
    n = len(layer_config) - 4
    (fuse_in, fuse_mid), (_, fuse_ms, dils), (_, fuse_out) = layer_config[n], layer_config[n + 1], layer_config[n + 2]
    xs = np_goctave_cbr(sd, "oct_fuse.fuse", feats, fuse_in, fuse_mid, 1, 1)
    xs = [np_multiscale(sd, f"oct_fuse.ms.convs.{i}", x, d) for i, (x, d) in enumerate(zip(xs, dils))]
    return np_goctave_cbr(sd, "oct_fuse.fuse1x1", xs, fuse_ms, fuse_out, 1, 1)[0]


def np_blocks(layer_config):
    """(torch prefix, in splits, out splits, kernel, stride, ends a stage >= 2) as `CSNet.__init__` builds them."""
    stages = layer_config[-1]
    blocks = [("stage0.0", [3], layer_config[0][1], 3, 1, False)]
    index = 1
    for stage in range(1, 5):
        for k in range(stages[stage - 1]):
            stride = 2 if stage > 1 and k == 0 else 1
            blocks.append(
                (
                    f"stage{stage}.{k}",
                    *layer_config[index],
                    3 if stride == 2 else 1,
                    stride,
                    stage > 1 and k == stages[stage - 1] - 1,
                )
            )
            index += 1
    return blocks


def np_forward(sd, layer_config, x):
    """`CSNet.forward`: normalised image [3, H, W] -> logits [H, W] (test.py's sigmoid comes after)."""
    xs, feats = [x.astype(np.float64)], []
    for prefix, in_splits, out_splits, kernel, stride, stage_end in np_blocks(layer_config):
        xs = np_goctave_cbr(sd, f"{prefix}.conv1x1", xs, in_splits, out_splits, kernel, stride)
        xs = np_depthwise_cbr(sd, f"{prefix}.conv3x3_1", xs)
        xs = np_depthwise_cbr(sd, f"{prefix}.conv3x3_2", xs)
        if stage_end:
            feats.append(xs[0])
    fused = np_head(sd, layer_config, feats)
    logits = np_conv(fused, sd["cls_layer.weight"].astype(np.float64)) + sd["cls_layer.bias"][:, None, None]
    return np_upsample(logits, 2)[0]


# ---------------------------------------------------------------------------------------------
# A tiny random CSNet: every layer type, a strided single-branch (plain Conv2dX100) conv, 1 -> 2,
# 2 -> 1, 2 -> 2 and 3 -> 3 branch gOctave convs, absent dilations in the head.

TINY_LAYER_CONFIG = [
    [[3], [3, 2]],  # stage0.0: 1 -> 2 branches, 3x3
    [[3, 2], [2, 3]],  # stage1.0: 2 -> 2, 1x1
    [[2, 3], [4]],  # stage2.0: 2 -> 1, 3x3 stride 2
    [[4], [3, 3]],  # stage3.0: 1 -> 2, 3x3 stride 2
    [[3, 3], [5]],  # stage3.1: 2 -> 1, 1x1
    [[5], [6]],  # stage4.0: 1 -> 1, 3x3 stride 2: a plain strided Conv2dX100
    [[4, 5, 6], [3, 4, 4]],  # head gOctave 1x1, 3 -> 3
    [[3, 4, 4], [3, 4, 5], [[1, 0, 1, 0, 1], [1, 1, 1, 1, 0], [0, 2, 0, 1, 2]]],  # multi-scale blocks
    [[3, 4, 5], [4]],  # head gOctave 1x1, 3 -> 1
    [1, 1, 2, 1],
]
TINY_X100_SINGLE = "stage4.0.conv1x1.conv.weight"


def is_x100(name):
    return ("conv3x3" in name and ".convs." in name) or "msconv" in name or name == TINY_X100_SINGLE


def random_state_dict(config, seed=0):
    """A torch-style state dict for `config` with activations of order 1 (x100 weights scaled down)."""
    rng = np.random.default_rng(seed)
    sd = {}
    for name, shape in csnet.torch_shapes(config).items():
        if name.endswith("running_var"):
            value = rng.uniform(0.5, 1.5, shape)
        elif name.endswith(("running_mean", "bias")):
            value = 0.1 * rng.standard_normal(shape)
        elif "prelu" in name:
            value = rng.uniform(0.05, 0.5, shape)
        elif len(shape) == 1:  # BN weight
            value = 1.0 + 0.2 * rng.standard_normal(shape)
        else:
            value = rng.standard_normal(shape) / math.sqrt(np.prod(shape[1:])) / (100.0 if is_x100(name) else 1.0)
        sd[name] = value.astype(np.float32)
        if name.endswith("running_var"):
            sd[name.replace("running_var", "num_batches_tracked")] = np.array(7, np.int64)
    return sd


@pytest.fixture(scope="module")
def tiny():
    config = csnet.CSNetConfig.from_layer_config(TINY_LAYER_CONFIG, source="tiny")
    sd = random_state_dict(config)
    return config, sd, csnet.convert_state_dict(sd, config, source="tiny")


def variables_at(tree, *path):
    """The {"params", "batch_stats"} sub-tree of one submodule."""
    out = {}
    for collection in ("params", "batch_stats"):
        node = tree.get(collection, {})
        for key in path:
            node = node.get(key, {})
        if node:
            out[collection] = node
    return out


def random_branches(splits, seed, height=16, width=24):
    """Branch i [C_i, height / 2**i, width / 2**i], float64."""
    rng = np.random.default_rng(seed)
    return [rng.standard_normal((c, height >> i, width >> i)) for i, c in enumerate(splits)]


def to_jax(x):
    """[C, H, W] -> [1, H, W, C] float32."""
    return jnp.asarray(np.transpose(x, (1, 2, 0))[None], jnp.float32)


def to_np(y):
    """[1, H, W, C] -> [C, H, W]."""
    return np.transpose(np.asarray(y)[0], (2, 0, 1))


def assert_close(ours, ref):
    assert ours.shape == ref.shape
    assert np.max(np.abs(ref)) > 0.1  # a meaningful comparison, not two near-zero maps
    np.testing.assert_allclose(ours, ref, rtol=1e-4, atol=1e-4)


# ---------------------------------------------------------------------------------------------
# Layers against the reference.


def test_primitives_match_numpy():
    rng = np.random.default_rng(1)
    x = rng.standard_normal((5, 12, 20))
    w = rng.standard_normal((4, 5, 3, 3)) / 5
    for stride, padding, dilation in ((1, 1, 1), (2, 1, 1), (1, 2, 2), (1, 8, 8)):
        ours = csnet_model.conv(
            to_jax(x),
            jnp.asarray(w.transpose(2, 3, 1, 0), jnp.float32),
            stride=stride,
            padding=padding,
            dilation=dilation,
        )
        assert_close(to_np(ours), np_conv(x, w, stride, padding, dilation))
    depthwise = rng.standard_normal((5, 1, 3, 3))
    ours = csnet_model.depthwise3x3(to_jax(x), jnp.asarray(depthwise.transpose(2, 3, 1, 0), jnp.float32))
    assert_close(to_np(ours), np_conv(x, depthwise, padding=1, groups=5))
    for k in (2, 4):
        assert_close(to_np(csnet_model.max_pool(to_jax(x), k)), np_pool(x, k, np.max))
        assert_close(to_np(csnet_model.avg_pool(to_jax(x), k)), np_pool(x, k, np.mean))
    small = rng.standard_normal((3, 5, 7))
    for factor in (2, 4):
        assert_close(to_np(csnet_model.upsample(to_jax(small), factor)), np_upsample(small, factor))


def test_depthwise_gradient_matches_grouped_conv():
    """The depthwise conv (nine shifted products) differentiates like a grouped `lax` conv, in reverse mode
    (input and kernel) and in forward mode: refinement on procedural sources uses `jax.jvp` through CSNet,
    which a `jax.custom_vjp` here would break."""
    rng = np.random.default_rng(2)
    x = jnp.asarray(rng.standard_normal((2, 9, 7, 5)), jnp.float32)
    kernel = jnp.asarray(rng.standard_normal((3, 3, 1, 5)), jnp.float32)
    weights = jnp.asarray(rng.standard_normal((2, 9, 7, 5)), jnp.float32)

    def grouped(x, kernel):
        return jax.lax.conv_general_dilated(
            x, kernel, (1, 1), ((1, 1), (1, 1)), dimension_numbers=("NHWC", "HWIO", "NHWC"), feature_group_count=5
        )

    def loss(fn):
        return lambda x, kernel: jnp.sum(jnp.sin(fn(x, kernel)) * weights)

    ours = jax.grad(loss(csnet_model.depthwise3x3), argnums=(0, 1))(x, kernel)
    reference = jax.grad(loss(grouped), argnums=(0, 1))(x, kernel)
    for a, b in zip(ours, reference):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-5, atol=1e-5)
    tangents = (weights, jnp.ones_like(kernel))
    reference = jax.jvp(loss(grouped), (x, kernel), tangents)[1]
    ours = jax.jvp(loss(csnet_model.depthwise3x3), (x, kernel), tangents)[1]
    np.testing.assert_allclose(float(ours), float(reference), rtol=1e-4)
    with autodiff.tangents("forward"):  # refinement's forward mode: autodiff through the taps themselves
        ours = jax.jvp(loss(csnet_model.depthwise3x3), (x, kernel), tangents)[1]
    np.testing.assert_allclose(float(ours), float(reference), rtol=1e-4)
    with pytest.raises(ValueError, match="sideways"):
        with autodiff.tangents("sideways"):
            pass


def test_upsample_gradient_is_autodiffs_in_both_modes():
    """The upsampling's rule (its tangent the transpose of a hand-written adjoint, so that reverse mode
    runs that adjoint) gives autodiff's derivatives of the taps themselves, for factors 2 and 4, along
    both axes, down to one input row (the clamped edges), in reverse and forward mode."""
    rng = np.random.default_rng(3)
    for shape in ((2, 5, 7, 3), (1, 1, 2, 2)):
        x = jnp.asarray(rng.standard_normal(shape), jnp.float32)
        for factor in (2, 4):
            for axis in (1, 2):
                out_shape = list(shape)
                out_shape[axis] *= factor
                g = jnp.asarray(rng.standard_normal(out_shape), jnp.float32)
                ours = jax.vjp(lambda v: csnet_model._upsample_axis(v, factor, axis), x)[1](g)[0]
                plain = jax.vjp(lambda v: csnet_model._upsample_axis_taps(v, factor, axis), x)[1](g)[0]
                np.testing.assert_allclose(np.asarray(ours), np.asarray(plain), rtol=1e-6, atol=1e-6)
                ours = jax.jvp(lambda v: csnet_model._upsample_axis(v, factor, axis), (x,), (x[::-1],))
                plain = jax.jvp(lambda v: csnet_model._upsample_axis_taps(v, factor, axis), (x,), (x[::-1],))
                assert np.array_equal(np.asarray(ours[0]), np.asarray(plain[0]))
                np.testing.assert_allclose(np.asarray(ours[1]), np.asarray(plain[1]), rtol=1e-6, atol=1e-6)
    up = jnp.asarray(rng.standard_normal((1, 3, 4, 2)), jnp.float32)
    with autodiff.tangents("forward"):
        forward = jax.jvp(lambda v: csnet_model.upsample(v, 2), (up,), (up,))[1]
    np.testing.assert_allclose(
        np.asarray(forward),
        np.asarray(jax.jvp(lambda v: csnet_model.upsample(v, 2), (up,), (up,))[1]),
        rtol=1e-6,
        atol=1e-6,
    )


GOCTAVE_CASES = [  # torch prefix, Flax path, in splits, out splits, kernel, stride
    ("stage0.0.conv1x1", ("stage0_0", "conv1x1"), (3,), (3, 2), 3, 1),
    ("stage1.0.conv1x1", ("stage1_0", "conv1x1"), (3, 2), (2, 3), 1, 1),
    ("stage2.0.conv1x1", ("stage2_0", "conv1x1"), (2, 3), (4,), 3, 2),
    ("stage3.0.conv1x1", ("stage3_0", "conv1x1"), (4,), (3, 3), 3, 2),
    ("stage4.0.conv1x1", ("stage4_0", "conv1x1"), (5,), (6,), 3, 2),  # plain strided Conv2dX100
    ("oct_fuse.fuse", ("oct_fuse", "fuse"), (4, 5, 6), (3, 4, 4), 1, 1),
    ("oct_fuse.fuse1x1", ("oct_fuse", "fuse1x1"), (3, 4, 5), (4,), 1, 1),
]


@pytest.mark.parametrize(
    "prefix,path,in_splits,out_splits,kernel,stride", GOCTAVE_CASES, ids=[case[0] for case in GOCTAVE_CASES]
)
def test_goctave_cbr_matches_numpy(tiny, prefix, path, in_splits, out_splits, kernel, stride):
    _, sd, tree = tiny
    xs = random_branches(in_splits, seed=len(prefix))
    module = csnet.GOctaveCBR(in_splits, out_splits, kernel, stride)
    ours = jax.jit(module.apply)(variables_at(tree, *path), [to_jax(x) for x in xs])
    ref = np_goctave_cbr(sd, prefix, xs, in_splits, out_splits, kernel, stride)
    assert len(ours) == len(ref) == len(out_splits)
    for y, r in zip(ours, ref):
        assert_close(to_np(y), r)


@pytest.mark.parametrize(
    "prefix,path,splits",
    [
        ("stage1.0.conv3x3_1", ("stage1_0", "conv3x3_1"), (2, 3)),
        ("stage4.0.conv3x3_2", ("stage4_0", "conv3x3_2"), (6,)),
    ],
)
def test_depthwise_x100_cbr_matches_numpy(tiny, prefix, path, splits):
    _, sd, tree = tiny
    xs = random_branches(splits, seed=3)
    ours = jax.jit(csnet.DepthwiseCBR(splits).apply)(variables_at(tree, *path), [to_jax(x) for x in xs])
    for y, r in zip(ours, np_depthwise_cbr(sd, prefix, xs)):
        assert_close(to_np(y), r)


@pytest.mark.parametrize("branch", [0, 1, 2])
def test_dilated_x100_multiscale_block_matches_numpy(tiny, branch):
    config, sd, tree = tiny
    (x,) = random_branches((config.fuse_mid[branch],), seed=branch)
    dils = config.fuse_dilations[branch]
    ours = jax.jit(csnet.MultiScaleBlock(dils).apply)(variables_at(tree, "oct_fuse", f"ms_{branch}"), to_jax(x))
    assert_close(to_np(ours), np_multiscale(sd, f"oct_fuse.ms.convs.{branch}", x, dils))


def test_fusion_head_matches_numpy(tiny):
    config, sd, tree = tiny
    feats = [random_branches((c,), seed=10 + i, height=16 >> i, width=24 >> i)[0] for i, c in enumerate(config.fuse_in)]
    ours = jax.jit(csnet.CSFHead(config).apply)(variables_at(tree, "oct_fuse"), [to_jax(f) for f in feats])
    assert_close(to_np(ours), np_head(sd, TINY_LAYER_CONFIG, feats))


def test_tiny_network_matches_numpy_and_flax_builds_the_converted_shapes(tiny):
    config, sd, tree = tiny
    model = csnet.CSNet(config)
    built = jax.eval_shape(model.init, jax.random.key(0), jnp.zeros((1, 32, 32, 3)))
    built = {k: v.shape for k, v in traverse_util.flatten_dict(dict(built), sep="/").items()}
    converted = {k: v.shape for k, v in traverse_util.flatten_dict(tree, sep="/").items()}
    assert built == converted == csnet.flax_shapes(config)
    x = np.random.default_rng(5).standard_normal((3, 48, 64))
    ours = np.asarray(jax.jit(model.apply)(tree, to_jax(x)))[0, :, :, 0]  # logits [48, 64]
    ref = np_forward(sd, TINY_LAYER_CONFIG, x)
    assert ref.std() > 0.02  # a map with structure (std 0.034 here), not a constant
    np.testing.assert_allclose(ours, ref, rtol=1e-4, atol=1e-4)


def test_layer_config_round_trips_and_broken_ones_are_named(tiny):
    config = tiny[0]
    assert config.stages == (1, 1, 2, 1) and config.fuse_out == 4
    assert csnet.CSNetConfig.from_layer_config(json.loads(json.dumps(config.to_layer_config()))) == config
    broken_chain = copy.deepcopy(TINY_LAYER_CONFIG)
    broken_chain[2][0] = [2, 2]
    with pytest.raises(WeightsError, match=r"tiny\.bin: entry 2 takes \(2, 2\) but entry 1 gives \(2, 3\)"):
        csnet.CSNetConfig.from_layer_config(broken_chain, source="tiny.bin")
    with pytest.raises(WeightsError, match="need 10 entries, got 9"):
        csnet.CSNetConfig.from_layer_config(TINY_LAYER_CONFIG[:5] + TINY_LAYER_CONFIG[6:], source="x")
    bad = copy.deepcopy(TINY_LAYER_CONFIG)
    bad[7][2][2] = [0, 2, 0, 1, 1]
    with pytest.raises(WeightsError, match="must sum to"):
        csnet.CSNetConfig.from_layer_config(bad)
    bad = copy.deepcopy(TINY_LAYER_CONFIG)
    bad[1][1], bad[2][0] = [5, 0], [5, 0]
    with pytest.raises(WeightsError, match="zero-width branch"):
        csnet.CSNetConfig.from_layer_config(bad)


def test_converter_keeps_torch_values_and_checks_every_key(tiny):
    config, sd, tree = tiny
    kernel = tree["params"]["stage1_0"]["conv3x3_1"]["kernel_1"]
    np.testing.assert_array_equal(kernel, sd["stage1.0.conv3x3_1.convs.1.weight"].transpose(2, 3, 1, 0))  # no x100
    np.testing.assert_array_equal(
        tree["batch_stats"]["oct_fuse"]["ms_2"]["bn_0"]["var"], sd["oct_fuse.ms.convs.2.bn.running_var"]
    )
    missing = {k: v for k, v in sd.items() if k != "oct_fuse.ms.convs.0.msconv.2.weight"}
    with pytest.raises(WeightsError, match=r"src: missing weight 'oct_fuse\.ms\.convs\.0\.msconv\.2\.weight'"):
        csnet.convert_state_dict(missing, config, source="src")
    extra = dict(sd, **{"oct_fuse.ms.convs.0.msconv.1.weight": np.zeros((1, 3, 3, 3), np.float32)})
    with pytest.raises(WeightsError, match=r"unexpected weight 'oct_fuse\.ms\.convs\.0\.msconv\.1\.weight'"):
        csnet.convert_state_dict(extra, config, source="src")


# ---------------------------------------------------------------------------------------------
# The real weights: converter, errors, native round trip.


@pytest.fixture(scope="module")
def weights_dir():
    require_weights("csnet/csnet-L-x1.pth.tar")
    require_weights("csnet/csnet-L-x1.bin")
    from waldo_jax import paths

    return paths.weights_dir()


@pytest.fixture(scope="module")
def params(weights_dir):
    return csnet.load_params(weights_dir)


@pytest.fixture(scope="module")
def real_state_dict(weights_dir):
    from waldo_jax.weights import read_torch_file, state_dict

    return state_dict(read_torch_file(weights_dir / "csnet" / "csnet-L-x1.pth.tar"))


def test_converter_reads_the_real_files(weights_dir, params, real_state_dict):
    tree, meta = csnet.read(weights_dir / "csnet")
    config = params.config
    assert config.stages == (3, 4, 6, 4) and len(config.blocks) == 18
    assert config.fuse_in == (34, 38, 50) and config.fuse_dilations[1] == (1, 4, 4, 4, 5)
    assert csnet.CSNetConfig.from_layer_config(json.loads(json.dumps(meta))["layer_config"]) == config
    # Every tensor of the file is used and has the shape the splits give (check_shapes is exact).
    torch_names = {k for k in real_state_dict if not k.endswith("num_batches_tracked")}
    assert torch_names == set(csnet.torch_shapes(config)) and len(real_state_dict) == 739
    flat = traverse_util.flatten_dict(tree, sep="/")
    assert {k: v.shape for k, v in flat.items()} == csnet.flax_shapes(config)  # = what Flax builds (tiny test)
    assert sum(v.size for v in flat.values()) == 97_921  # the paper's count, running statistics included
    weight = real_state_dict["stage0.0.conv1x1.conv.weight"]  # [8 + 10, 3, 3, 3]: one kernel, two out branches
    np.testing.assert_array_equal(flat["params/stage0_0/conv1x1/kernel_0_0"], weight[:8].transpose(2, 3, 1, 0))
    np.testing.assert_array_equal(flat["params/stage0_0/conv1x1/kernel_0_1"], weight[8:].transpose(2, 3, 1, 0))


def copy_model(weights_dir, tmp_path, truncate=None):
    """tmp_path/csnet/ with the two files, one of them truncated to half."""
    folder = tmp_path / "csnet"
    folder.mkdir()
    for name in csnet.FILES:
        data = (weights_dir / "csnet" / name).read_bytes()
        (folder / name).write_bytes(data[: len(data) // 2] if name == truncate else data)
    return folder


def test_truncated_checkpoint_names_the_file(weights_dir, tmp_path):
    folder = copy_model(weights_dir, tmp_path, truncate="csnet-L-x1.pth.tar")
    with pytest.raises(WeightsError, match=r"csnet-L-x1\.pth\.tar.*truncated"):
        csnet.read(folder)
    with pytest.raises(WeightsError, match=r"csnet-L-x1\.pth\.tar"):
        csnet.load_params(tmp_path)


def test_truncated_or_foreign_splits_name_the_file(weights_dir, tmp_path):
    folder = copy_model(weights_dir, tmp_path, truncate="csnet-L-x1.bin")
    with pytest.raises(WeightsError, match=r"csnet-L-x1\.bin: not a readable CSNet layer config"):
        csnet.read(folder)
    (folder / "csnet-L-x1.bin").write_bytes(pickle.dumps([os.getcwd]))  # a global that is not an array
    with pytest.raises(WeightsError, match=r"csnet-L-x1\.bin: .*refusing to unpickle"):
        csnet.read(folder)


def test_wrong_tensor_shape_names_file_and_key(weights_dir, real_state_dict, monkeypatch):
    bad = dict(real_state_dict)
    bad["stage3.2.conv3x3_1.convs.1.weight"] = np.zeros((17, 1, 3, 3), np.float32)
    monkeypatch.setattr(csnet_convert, "state_dict", lambda obj: bad)
    with pytest.raises(
        WeightsError,
        match=r"csnet-L-x1\.pth\.tar: weight 'stage3\.2\.conv3x3_1\.convs\.1\.weight' "
        r"has shape \(17, 1, 3, 3\), expected \(18, 1, 3, 3\)",
    ):
        csnet.read(weights_dir / "csnet")


def test_missing_files_and_native_round_trip(params, weights_dir, tmp_path):
    with pytest.raises(DataNotFoundError, match=r"csnet-L-x1\.pth\.tar"):
        csnet.load_params(tmp_path)
    tree, meta = csnet.read(weights_dir / "csnet")
    save_native(tmp_path / "csnet" / "csnet.npz", "csnet", tree, meta)
    native = csnet.load_params(tmp_path)
    assert native.config == params.config
    same = jax.tree.map(lambda a, b: bool(np.array_equal(a, b)), native.variables, params.variables)
    assert all(jax.tree.leaves(same))
    flat = traverse_util.flatten_dict(tree)
    flat[("params", "cls_layer", "kernel")] = np.zeros((1, 1, 61, 1), np.float32)
    save_native(tmp_path / "csnet" / "csnet.npz", "csnet", traverse_util.unflatten_dict(flat), meta)
    with pytest.raises(WeightsError, match=r"'params/cls_layer/kernel' has shape \(1, 1, 61, 1\)"):
        csnet.load_params(tmp_path)


# ---------------------------------------------------------------------------------------------
# The real network: the NumPy reference, synthetic objects, the fox.

SIDE = csnet.INPUT_SIZE
SYNTHETIC = [  # shape, centre x, centre y, radius / half side (px), object RGB, background RGB, noise std
    ("disc", 112, 112, 45, (0.85, 0.15, 0.10), (0.50, 0.50, 0.50), 0.00),
    ("square", 80, 140, 40, (0.10, 0.20, 0.80), (0.90, 0.90, 0.85), 0.03),
    ("disc", 150, 80, 40, (0.95, 0.80, 0.10), (0.15, 0.20, 0.30), 0.03),
    ("square", 140, 100, 35, (0.10, 0.60, 0.20), (0.85, 0.85, 0.90), 0.00),
    ("disc", 70, 70, 30, (0.90, 0.10, 0.10), (0.60, 0.60, 0.60), 0.02),
    ("disc", 112, 150, 50, (0.05, 0.05, 0.05), (0.90, 0.90, 0.90), 0.02),
]
# Views of the fox (a mounted head on rose wallpaper) and boxes (x0, y0, x1, y1, fractions of width
# and height) around fox and mount, set by looking at the photographs.
FOX_BOXES = {
    "0001": (0.10, 0.08, 0.90, 0.72),
    "0008": (0.15, 0.05, 0.92, 0.72),
    "0021": (0.10, 0.08, 0.75, 0.72),
    "0026": (0.10, 0.15, 0.85, 0.80),
    "0030": (0.10, 0.17, 0.85, 0.82),
}


def synthetic_scene(shape, cx, cy, r, fg, bg, noise, seed):
    yy, xx = np.mgrid[:SIDE, :SIDE] + 0.5
    mask = (xx - cx) ** 2 + (yy - cy) ** 2 < r * r if shape == "disc" else (abs(xx - cx) < r) & (abs(yy - cy) < r)
    image = np.where(mask[..., None], np.asarray(fg), np.asarray(bg))
    image = image + noise * np.random.default_rng(seed).standard_normal(image.shape)
    return np.clip(image, 0.0, 1.0).astype(np.float32), mask


def fox_view(path):
    """A 1080x1920 fox view at the network's 224x224 (the network resizes every view so, anyway)."""
    import imageio.v3 as iio

    with Image.fromarray(iio.imread(path)) as im:
        return np.asarray(im.resize((SIDE, SIDE), Image.BILINEAR), np.float32) / 255.0


@pytest.fixture(scope="module")
def scenes():
    """Synthetic scenes and their masks, then the fox views (masks None) when the scene is there."""
    synthetic = [synthetic_scene(*case, seed=i) for i, case in enumerate(SYNTHETIC)]
    if paths_have_fox():
        fox = require_scene("fox") / "images"
        synthetic += [(fox_view(fox / f"{name}.jpg"), None) for name in FOX_BOXES]
    return synthetic


def paths_have_fox():
    from waldo_jax import paths

    data = paths.data_dir()
    return data is not None and (data / "scenes" / "fox" / "images").is_dir()


@pytest.fixture(scope="module")
def maps224(params, scenes):
    """Saliency maps [P, 224, 224] of all the scenes, in one compiled call."""
    return np.asarray(jax.jit(csnet.saliency_maps)(params, np.stack([image for image, _ in scenes])))


def test_real_network_matches_numpy(params, real_state_dict, scenes, maps224):
    image = scenes[1][0]  # 224x224: the input resize is the identity
    x = ((image - np.array([0.485, 0.456, 0.406])) / np.array([0.229, 0.224, 0.225])).transpose(2, 0, 1)
    ref = 1.0 / (1.0 + np.exp(-np_forward(real_state_dict, params.config.to_layer_config(), x)))
    np.testing.assert_allclose(maps224[1], ref, atol=1e-4)


@pytest.mark.parametrize("index", range(len(SYNTHETIC)))
def test_synthetic_object_is_segmented(scenes, maps224, index):
    mask = scenes[index][1]
    salient = maps224[index] > 0.5
    iou = (salient & mask).sum() / (salient | mask).sum()
    assert iou >= 0.7, f"IoU {iou:.3f} for {SYNTHETIC[index][:4]}"


@pytest.mark.parametrize("name", list(FOX_BOXES))
def test_fox_is_the_salient_object(scenes, maps224, name):
    require_scene("fox")
    saliency = maps224[len(SYNTHETIC) + list(FOX_BOXES).index(name)]
    x0, y0, x1, y1 = FOX_BOXES[name]
    ys, xs = (np.mgrid[:SIDE, :SIDE] + 0.5) / SIDE
    cx, cy = (saliency * xs).sum() / saliency.sum(), (saliency * ys).sum() / saliency.sum()
    assert x0 < cx < x1 and y0 < cy < y1, f"view {name}: salient centroid ({cx:.3f}, {cy:.3f}) outside the box"
    inside = (xs > x0) & (xs < x1) & (ys > y0) & (ys < y1)
    salient = saliency > 0.5
    assert salient.mean() > 0.05 and (salient & inside).sum() > 0.9 * salient.sum()  # 0.98-1.0 seen


# ---------------------------------------------------------------------------------------------
# The criterion.


def test_criterion_is_registered_and_scores_under_jit(weights_dir, params, scenes, maps224):
    assert CRITERIA["saliency"].direction == "max" and CRITERIA["saliency"].inputs == "images"
    crit = make_criterion("saliency", CriterionContext(weights_dir=str(weights_dir)))
    assert (crit.name, crit.direction, crit.value_range) == ("saliency", "max", (0.0, 1.0))
    traces = []

    def counted(p, images):
        traces.append(images.shape)
        return crit.apply(p, images)

    score = jax.jit(counted)
    nan_image = scenes[0][0].copy()
    nan_image[10, 20, 1] = np.nan
    batch = np.stack(
        [scenes[0][0], scenes[1][0], scenes[2][0], np.zeros_like(nan_image), np.ones_like(nan_image), nan_image]
    )
    # (Batches of 1, 8 and 64, one trace per batch shape and NaN/inf handling for every image criterion,
    # saliency included: test_criteria_all's contract. Here: the real scenes and their maps.)
    first_batch = np.asarray(score(crit.params, batch))
    again_batch = np.asarray(score(crit.params, batch))
    assert traces == [batch.shape]  # none on the repeat
    np.testing.assert_array_equal(first_batch, again_batch)
    assert first_batch.shape == (6,) and first_batch.dtype == np.float32
    assert np.all(np.isfinite(first_batch)) and np.all((first_batch >= 0) & (first_batch <= 1))
    assert first_batch[5] == 0.0  # the NaN image gets the worst score
    for k in range(3):  # the score is the salient fraction of the map; the object's area fraction
        np.testing.assert_allclose(first_batch[k], (maps224[k] > 0.5).mean(), atol=2e-3)
        np.testing.assert_allclose(first_batch[k], scenes[k][1].mean(), atol=0.02)
    # Maps come back at the images' own size, also under an outer vmap (traced only: no compile).
    stacked = jax.ShapeDtypeStruct((2, 3, 90, 50, 3), jnp.float32)
    shapes = jax.eval_shape(jax.vmap(csnet.saliency_maps, in_axes=(None, 0)), params, stacked)
    assert shapes.shape == (2, 3, 90, 50) and shapes.dtype == jnp.float32
