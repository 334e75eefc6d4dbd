"""CNNIQA, a no-reference image quality network (Kang, Ye, Li and Doermann, "Convolutional neural
networks for no-reference image quality assessment", CVPR 2014), with the LIVE-trained weights of
the public PyTorch port (lidq92/CNNIQA, `CNNIQAnet` in `main.py`, patches in `IQADataset.py`).

The pipeline, as in the reference:
  1. grey level `g = 0.299 R + 0.587 G + 0.114 B` in [0, 1] (PIL's `convert('L')` then
     `to_tensor`; PIL rounds to 8 bits, we keep the float value: at most 0.5/255 apart);
  2. non-overlapping 32x32 patches at rows and columns `range(0, side - 32, 32)` (the reference's
     loop: its bound `side - 32` drops the last patch when the side is a multiple of 32, e.g. a
     256x256 image gives 7x7 = 49 patches, not 64);
  3. each patch locally normalised at the [0, 1] intensity scale,
     `x_hat = (x - mu) / (sigma + 1)`, where mu and E[x^2] are 3x3 box means over the patch with
     symmetric (edge-repeating) borders (`scipy.signal.convolve2d(..., boundary='symm',
     mode='same')`) and `sigma = sqrt(max(E[x^2] - mu^2, 0))`;
  4. conv 7x7, 50 kernels, valid -> per-kernel global max and global min over the 26x26 map,
     concatenated as [max (50), min (50)] -> fc 800 + ReLU -> fc 800 + ReLU -> fc 1;
  5. the image's prediction is the mean over its patches: LIVE (realigned) DMOS, lower is better.

The reference calls `F.dropout(h)` between fc1 and fc2 in its functional form, whose default
`training=True` keeps dropout on even in `model.eval()`, so its test-time scores are random. We
apply no dropout, dropout's usual inference form (PyTorch rescales the kept units during training),
which makes the score deterministic.

Small images: where the reference's grid would be empty (a side of 32 px or less) we take the one
patch at the origin, after resizing any side below 32 px up to 32 px (bilinear). The patch grid is
a function of the static image shape, so it compiles once per image size.

The criterion `iqa_cnn` (direction max) reports `score = 100 - DMOS`: LIVE's realigned DMOS runs
roughly from 0 (pristine) to 100 (worst), so the score is roughly 100 for a pristine image and 0 for
a very distorted one, and higher is better like the other "max" criteria. Measured predictions:
sharp 256 px photos of fox and fern 12 to 32, the same Gaussian-blurred (sigma 4 px) about 72 or with
noise (std 0.1) about 55; constant images 88; uniform noise 77; but out-of-distribution patterns go
far beyond LIVE's range (binary noise 145, a one-pixel checkerboard 573). The score is clipped to
`VALUE_RANGE = (-100, 150)` (DMOS from -50 to 200), which keeps every plausible rendering unclipped
and bounds the pathological ones; an image with NaN/inf pixels gets the worst score, -100 (as does a
pathological pattern whose DMOS exceeds 200).
"""

from __future__ import annotations

import functools
from pathlib import Path
from typing import Any, Dict, Optional, Tuple

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np

from waldo_jax.criteria.base import (Criterion, CriterionContext, CriterionSpec, finite_or_worst, register,
                                     sanitize_images, worst_score)
from waldo_jax.types import Array
from waldo_jax.weights.store import Converter, check_shapes, load_model, register_converter
from waldo_jax.weights.torch_pickle import read_torch_file, state_dict

__all__ = [
    "PATCH",
    "VALUE_RANGE",
    "CNNIQANet",
    "TORCH_SHAPES",
    "convert_state_dict",
    "load_params",
    "grey",
    "local_normalise",
    "patch_grid",
    "image_patches",
    "cnniqa_dmos",
    "cnniqa_dmos_batch",
    "iqa_cnn",
]

PATCH = 32  # patch side, pixels
KERNEL = 7  # conv kernel side
NUM_KERNELS = 50
HIDDEN = 800
NORM_C = 1.0  # the constant added to sigma in the local normalisation
LUMA = (0.299, 0.587, 0.114)  # ITU-R 601-2, as PIL's convert('L')
VALUE_RANGE = (-100.0, 150.0)  # score = 100 - DMOS, clipped; the low end is the failed-image score
# Images per step of `cnniqa_dmos_batch`: the conv activations of a 256x256 image (49 patches x
# 26x26x50 floats) are 6.6 MB, so chunks keep them in cache (1.4x faster than one vmap on CPU) and
# bound the memory of large batches.
CHUNK = 4

MODEL = "cnniqa"
WEIGHTS_FILE = "CNNIQA-LIVE"
# The reference's state dict: names and shapes (PyTorch layouts: conv OIHW, linear [out, in]).
TORCH_SHAPES: Dict[str, Tuple[int, ...]] = {
    "conv1.weight": (NUM_KERNELS, 1, KERNEL, KERNEL),
    "conv1.bias": (NUM_KERNELS,),
    "fc1.weight": (HIDDEN, 2 * NUM_KERNELS),
    "fc1.bias": (HIDDEN,),
    "fc2.weight": (HIDDEN, HIDDEN),
    "fc2.bias": (HIDDEN,),
    "fc3.weight": (1, HIDDEN),
    "fc3.bias": (1,),
}
# The same in the Flax tree (conv HWIO, dense [in, out]), as flattened by `weights.store`.
FLAX_SHAPES: Dict[str, Tuple[int, ...]] = {
    "params/conv1/kernel": (KERNEL, KERNEL, 1, NUM_KERNELS),
    "params/conv1/bias": (NUM_KERNELS,),
    "params/fc1/kernel": (2 * NUM_KERNELS, HIDDEN),
    "params/fc1/bias": (HIDDEN,),
    "params/fc2/kernel": (HIDDEN, HIDDEN),
    "params/fc2/bias": (HIDDEN,),
    "params/fc3/kernel": (HIDDEN, 1),
    "params/fc3/bias": (1,),
}


class CNNIQANet(nn.Module):
    """The CNNIQA network on locally normalised patches.

    Call with patches float32 [N, 32, 32, 1] (already normalised); returns the DMOS of each patch [N].
    """

    num_kernels: int = NUM_KERNELS
    hidden: int = HIDDEN

    @nn.compact
    def __call__(self, patches: Array) -> Array:
        h = nn.Conv(self.num_kernels, (KERNEL, KERNEL), padding="VALID", name="conv1")(patches)  # [N, 26, 26, 50]
        h = jnp.concatenate([jnp.max(h, axis=(1, 2)), jnp.min(h, axis=(1, 2))], axis=-1)  # [N, 100]: max, then min
        h = nn.relu(nn.Dense(self.hidden, name="fc1")(h))  # [N, 800]
        h = nn.relu(nn.Dense(self.hidden, name="fc2")(h))  # [N, 800]
        return nn.Dense(1, name="fc3")(h)[:, 0]  # [N]


_NET = CNNIQANet()


# ---------------------------------------------------------------------------------------------
# Weights.


def convert_state_dict(tensors: Dict[str, np.ndarray], source: str = "CNNIQA state dict") -> Dict[str, Any]:
    """The Flax variables `{"params": ...}` of the reference's PyTorch state dict.

    Args:
      tensors: `{name: ndarray}` with exactly the keys and shapes of `TORCH_SHAPES`.
      source: what to name in error messages (the file).

    Raises:
      WeightsError: naming `source` and the first missing, unexpected or mis-shaped key.
    """
    check_shapes(TORCH_SHAPES, tensors, source)
    t = {k: np.asarray(v, np.float32) for k, v in tensors.items()}
    return {"params": {
        "conv1": {"kernel": t["conv1.weight"].transpose(2, 3, 1, 0), "bias": t["conv1.bias"]},  # OIHW -> HWIO
        "fc1": {"kernel": t["fc1.weight"].T, "bias": t["fc1.bias"]},
        "fc2": {"kernel": t["fc2.weight"].T, "bias": t["fc2.bias"]},
        "fc3": {"kernel": t["fc3.weight"].T, "bias": t["fc3.bias"]},
    }}


def _read(model_dir: Path) -> Tuple[Dict[str, Any], Dict[str, Any]]:
    """Converter: `<model_dir>/CNNIQA-LIVE` (legacy torch state dict) -> (variables, meta)."""
    path = model_dir / WEIGHTS_FILE
    tree = convert_state_dict(state_dict(read_torch_file(path), str(path)), str(path))
    return tree, {"source": WEIGHTS_FILE, "trained_on": "LIVE", "output": "DMOS (lower is better)"}


register_converter(Converter(MODEL, (WEIGHTS_FILE,), _read))


def _flat(tree: Any, prefix: str = "") -> Dict[str, np.ndarray]:
    if isinstance(tree, dict):
        out = {}
        for key, value in tree.items():
            out.update(_flat(value, f"{prefix}{key}/"))
        return out
    return {prefix[:-1]: np.asarray(tree)}


def load_params(weights_dir: Optional[str] = None) -> Dict[str, Any]:
    """The CNNIQA-LIVE variables `{"params": ...}` as float32 jnp arrays.

    Reads `<weights>/cnniqa/cnniqa.npz` when converted, else `<weights>/cnniqa/CNNIQA-LIVE`.

    Args:
      weights_dir: folder in the `../shared/weights` layout (default: `WALDO_WEIGHTS`).

    Raises:
      DataNotFoundError: no weights file (the message names the expected path).
      TorchPickleError: the original file is truncated or corrupt (names the file).
      WeightsError: a tensor of the wrong shape, a missing or unexpected one (names the key).
    """
    tree, _ = load_model(MODEL, weights_dir)
    check_shapes(FLAX_SHAPES, _flat(tree), f"{MODEL} weights")  # a converted .npz is checked too
    return jax.tree.map(lambda a: jnp.asarray(a, jnp.float32), tree)


# ---------------------------------------------------------------------------------------------
# Pre-processing (one image).


def grey(image: Array) -> Array:
    """Grey level [H, W] of an RGB image float [H, W, 3] in [0, 1] (PIL's 'L' weights, not rounded)."""
    return jnp.tensordot(jnp.asarray(image, jnp.float32), jnp.asarray(LUMA, jnp.float32), axes=1)


def _box3_symmetric(x: Array) -> Array:
    """3x3 box mean of x [h, w] with symmetric borders (the edge row/column repeated), same size."""
    p = jnp.pad(x, 1, mode="symmetric")
    h, w = x.shape
    return sum(p[i:i + h, j:j + w] for i in range(3) for j in range(3)) / 9.0


def local_normalise(patch: Array) -> Array:
    """(x - mu) / (sigma + 1) of one patch [h, w] at its own intensity scale (3x3 box, symmetric borders)."""
    mu = _box3_symmetric(patch)
    second = _box3_symmetric(patch * patch)
    sigma = jnp.sqrt(jnp.maximum(second - mu * mu, 0.0))
    return (patch - mu) / (sigma + NORM_C)


def patch_grid(side: int) -> int:
    """Patches along a side of `side` pixels: `len(range(0, side - 32, 32))`, at least 1 (static)."""
    return max(1, len(range(0, side - PATCH, PATCH)))


def image_patches(image: Array) -> Array:
    """The locally normalised patches [N, 32, 32, 1] of one RGB image float [H, W, 3] in [0, 1].

    The grid is static (from the shape): `patch_grid(H) x patch_grid(W)` patches, row-major from
    the top left; sides below 32 px are resized up to 32 px first.
    """
    g = grey(image)  # [H, W]
    height, width = g.shape
    if height < PATCH or width < PATCH:
        g = jax.image.resize(g, (max(height, PATCH), max(width, PATCH)), "linear")
        height, width = g.shape
    rows, cols = patch_grid(height), patch_grid(width)
    g = g[:rows * PATCH, :cols * PATCH]
    patches = g.reshape(rows, PATCH, cols, PATCH).transpose(0, 2, 1, 3).reshape(rows * cols, PATCH, PATCH)
    return jax.vmap(local_normalise)(patches)[..., None]


# ---------------------------------------------------------------------------------------------
# Scores.


def cnniqa_dmos(params: Dict[str, Any], image: Array) -> Array:
    """Predicted LIVE DMOS [] of one image float32 [H, W, 3] in [0, 1] (lower is better).

    Args:
      params: the variables of `load_params`.
      image: RGB in [0, 1]; H and W are static (they set the patch grid).

    Returns:
      The mean over the image's patches of the network's output.
    """
    return jnp.mean(_NET.apply(params, image_patches(image)))


def cnniqa_dmos_batch(params: Dict[str, Any], images: Array) -> Array:
    """`cnniqa_dmos` of images [P, H, W, 3], vmapped over chunks of `CHUNK` images; returns [P]."""
    return jax.lax.map(functools.partial(cnniqa_dmos, params), images, batch_size=CHUNK)


def _apply(params, images: Array) -> Array:
    clean, bad = sanitize_images(images)
    score = jnp.clip(100.0 - cnniqa_dmos_batch(params, clean), *VALUE_RANGE)
    return finite_or_worst(score, bad, worst_score("max", VALUE_RANGE))


def iqa_cnn(context: CriterionContext) -> Criterion:
    """The `iqa_cnn` criterion: 100 - CNNIQA-LIVE DMOS (direction max, in `VALUE_RANGE`).

    Raises:
      DataNotFoundError / WeightsError / TorchPickleError: from `load_params(context.weights_dir)`.
    """
    return Criterion(params=load_params(context.weights_dir), name="iqa_cnn", direction="max",
                     value_range=VALUE_RANGE, inputs="images", apply=_apply, description=_DESCRIPTION)


_DESCRIPTION = "100 - predicted LIVE DMOS of CNNIQA (Kang et al. 2014), no-reference quality, higher is better"
register(CriterionSpec("iqa_cnn", "max", "images", _DESCRIPTION, iqa_cnn))
