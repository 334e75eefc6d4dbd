"""CNNIQA, a no-reference image quality network (Kang, Ye, Li and Doermann, CVPR 2014), with the
LIVE-trained weights of the public PyTorch port (lidq92/CNNIQA).

As in the reference: grey level, non-overlapping 32x32 patches (`image_patches`), local normalisation
(`local_normalise`), `CNNIQANet` (conv 7x7 x 50, global max and min, fc 800 + ReLU twice, fc 1), and
the mean over patches: predicted LIVE DMOS, lower is better (`cnniqa_dmos`, `cnniqa_dmos_batch`).
Unlike it, no dropout at test time, so the score is deterministic. The criterion `iqa_cnn`
(direction max) reports 100 - DMOS, clipped to `VALUE_RANGE = (-100, 150)`; NaN/inf images score
-100. `load_params` reads the weights (`convert_state_dict` maps the torch state dict).

Each step as in the reference, the dropout and small-image choices and the measured predictions: see
docs/design.md, section "Criteria > CNNIQA".
"""

from __future__ import annotations

import functools
from pathlib import Path
from typing import Any, Dict, Optional, Tuple

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np

from waldo_jax.criteria.base import (
    Criterion,
    CriterionContext,
    CriterionSpec,
    finite_or_worst,
    register,
    sanitize_images,
    worst_score,
)
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
    return {
        "params": {
            "conv1": {"kernel": t["conv1.weight"].transpose(2, 3, 1, 0), "bias": t["conv1.bias"]},  # OIHW -> HWIO
            "fc1": {"kernel": t["fc1.weight"].T, "bias": t["fc1.bias"]},
            "fc2": {"kernel": t["fc2.weight"].T, "bias": t["fc2.bias"]},
            "fc3": {"kernel": t["fc3.weight"].T, "bias": t["fc3.bias"]},
        }
    }


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
    return sum(p[i : i + h, j : j + w] for i in range(3) for j in range(3)) / 9.0


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
    g = g[: rows * PATCH, : cols * PATCH]
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
    return Criterion(
        params=load_params(context.weights_dir),
        name="iqa_cnn",
        direction="max",
        value_range=VALUE_RANGE,
        inputs="images",
        apply=_apply,
        description=_DESCRIPTION,
        smooth_apply=_apply,
    )


_DESCRIPTION = "100 - predicted LIVE DMOS of CNNIQA (Kang et al. 2014), no-reference quality, higher is better"
register(CriterionSpec("iqa_cnn", "max", "images", _DESCRIPTION, iqa_cnn, smooth=True, reads=("weights_dir",)))
