"""CSNet-L-x1 saliency maps of images, and the `saliency` criterion built on them.

Input: RGB in [0, 1], resized to 224x224 (bilinear, antialiased when shrinking), normalised with
the ImageNet mean and std; the network's sigmoid map is upsampled back to the image's size. The
criterion scores an image by the fraction of its pixels whose saliency exceeds 0.5. Why antialias
where the reference does not: docs/design.md, "Criteria".

Names: `logits` is the network's output before the sigmoid; `saliency` is the sigmoid map in [0, 1].
"""

from __future__ import annotations

import functools
from pathlib import Path
from typing import Any, Optional

import flax.struct
import jax
import jax.numpy as jnp
from flax import traverse_util

from waldo_jax.criteria.base import (
    Criterion,
    CriterionContext,
    CriterionSpec,
    finite_or_worst,
    register,
    sanitize_images,
)
from waldo_jax.criteria.csnet.config import CSNetConfig
from waldo_jax.criteria.csnet.convert import MODEL, flax_shapes
from waldo_jax.criteria.csnet.model import CSNet
from waldo_jax.types import Array
from waldo_jax.weights import WeightsError, check_shapes, load_model, resolve_weights_dir

__all__ = [
    "INPUT_SIZE",
    "SALIENT_THRESHOLD",
    "CSNetParams",
    "load_params",
    "saliency_map",
    "saliency_maps",
    "salient_fraction",
    "soft_salient_fraction",
    "SOFTNESS",
    "saliency",
]

INPUT_SIZE = 224  # the network's input side (training and test size of the reference)
SALIENT_THRESHOLD = 0.5  # saliency above this counts as a salient pixel (BASNet's count in the paper)
SOFTNESS = 0.05  # width of the sigmoid that stands in for the threshold in the smooth score
_IMAGENET_MEAN = (0.485, 0.456, 0.406)
_IMAGENET_STD = (0.229, 0.224, 0.225)
_CHUNK = 16  # images per network call in `saliency_maps`


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


def soft_salient_fraction(saliency_image: Array, softness: float = SOFTNESS) -> Array:
    """`salient_fraction` with the step at `SALIENT_THRESHOLD` replaced by a sigmoid of width `softness`:
    the differentiable stand-in that gradient refinement follows."""
    return jnp.mean(jax.nn.sigmoid((saliency_image - SALIENT_THRESHOLD) / softness))


def _scores(params: CSNetParams, images: Array, fraction) -> Array:
    clean, bad = sanitize_images(images)
    maps = saliency_maps(params, clean)  # [P, H, W]
    scores = jax.vmap(fraction)(maps)
    bad = bad | ~jnp.all(jnp.isfinite(maps), axis=(1, 2))
    return finite_or_worst(scores, bad, 0.0)


def _apply(params: CSNetParams, images: Array) -> Array:
    """Scores [P] of images [P, H, W, 3]: the salient fraction, 0.0 for images with NaN/inf."""
    return _scores(params, images, salient_fraction)


def _smooth_apply(params: CSNetParams, images: Array) -> Array:
    """`_apply` with `soft_salient_fraction`."""
    return _scores(params, images, soft_salient_fraction)


_DESCRIPTION = "CSNet-L-x1 salient-object detection (Gao et al., ECCV 2020): the fraction of pixels with saliency > 0.5"


def saliency(context: CriterionContext) -> Criterion:
    """The `saliency` criterion (direction max, in [0, 1]).

    Score of an image = the fraction of its pixels whose CSNet-L-x1 saliency exceeds 0.5. The paper
    counts BASNet's salient pixels; dividing by H * W makes scores comparable across resolutions.
    Images containing NaN or inf get the worst score 0.0.

    Raises:
      DataNotFoundError / WeightsError: from `load_params(context.weights_dir)`.
    """
    return Criterion(
        params=load_params(context.weights_dir),
        name="saliency",
        direction="max",
        value_range=(0.0, 1.0),
        inputs="images",
        apply=_apply,
        description=_DESCRIPTION,
        smooth_apply=_smooth_apply,
    )


register(CriterionSpec("saliency", "max", "images", _DESCRIPTION, saliency, smooth=True, reads=("weights_dir",)))
