"""BRISQUE, the Blind/Referenceless Image Spatial Quality Evaluator (Mittal, Moorthy and Bovik 2012).

A. Mittal, A. K. Moorthy and A. C. Bovik, "No-Reference Image Quality Assessment in the Spatial
Domain", IEEE Trans. Image Processing 21(12), 4695-4708, 2012. An epsilon-SVR maps 36 natural-scene
statistics of the image to the LIVE database's DMOS: lower is better.

The model file is OpenCV contrib's (`modules/quality`), so the features follow its `qualitybrisque.cpp`:
  1. 8-bit grey (OpenCV's fixed-point BGR2GRAY of the quantised image), MSCN as `nss.mscn`;
  2. two scales: the grey image and its `cv::resize` INTER_CUBIC half (W // 2, H // 2);
  3. 18 features per scale over the whole image, 36 in all (scale 1 then scale 2):
       [alpha, (sigma_l^2 + sigma_r^2) / 2] of the AGGD fit of the MSCN image, then for each orientation
       (0, 1), (1, 0), (1, 1), (-1, 1) of the pairwise products (a neighbour outside the image counts
       as 0): [alpha, eta, sigma_l^2, sigma_r^2];
  4. each feature scaled to [-1, 1] by the range file: x' = -1 + 2 (x - min) / (max - min) (not clipped);
  5. the SVR: score = sum_i a_i exp(-gamma ||x' - s_i||^2) - rho, clamped to [0, 100] as OpenCV does.
Where OpenCV departs from MATLAB's BRISQUE, and why a constant image scores finite here where OpenCV
gives NaN: docs/design.md, "Criteria".

Weights (`<weights>/brisque/`, OpenCV FileStorage YAML, read by `waldo_jax.weights.opencv_yaml` without OpenCV):
`brisque_model_live.yml` (the SVR) and `brisque_range_live.yml` (per-feature min and max). The
converter's tree: {"support_vectors": [774, 36], "dual_coef": [774], "rho": [], "gamma": [],
"feature_min": [36], "feature_max": [36]}.
"""

from __future__ import annotations

import functools
from pathlib import Path
from typing import Any, Dict, List, Optional, Tuple

import jax
import jax.numpy as jnp
import numpy as np

from waldo_jax.criteria import nss
from waldo_jax.criteria.base import Criterion, CriterionContext, CriterionSpec, register
from waldo_jax.types import Array
from waldo_jax.weights.opencv_yaml import read_opencv_storage
from waldo_jax.weights.store import Converter, WeightsError, check_shapes, load_model, register_converter

__all__ = [
    "MODEL",
    "MODEL_FILE",
    "RANGE_FILE",
    "NUM_FEATURES",
    "VALUE_RANGE",
    "CHUNK",
    "rgb_to_grey",
    "resize_half_cubic",
    "brisque_features",
    "scale_features",
    "svr_predict",
    "brisque_score",
    "load_params",
    "brisque",
]

MODEL = "brisque"
MODEL_FILE = "brisque_model_live.yml"
RANGE_FILE = "brisque_range_live.yml"
NUM_FEATURES = 36
CHUNK = 4  # images vmapped at once, chunks scanned over (bounded memory; faster on CPU than all at once)
VALUE_RANGE = (0.0, 100.0)  # OpenCV clamps the SVR output to [0, 100]
_PRECISION = jax.lax.Precision.HIGHEST


# ---------------------------------------------------------------------------------------------
# Weights.


def _field(node: Dict[str, Any], key: str, source: Path) -> Any:
    if not isinstance(node, dict) or key not in node or node[key] is None:
        raise WeightsError(f"{source}: missing {key!r} in the SVM model")
    return node[key]


def _read(model_dir: Path) -> Tuple[Dict[str, Any], Dict[str, Any]]:
    """Converter: the OpenCV SVR model and feature range -> (tree, meta)."""
    model_path, range_path = model_dir / MODEL_FILE, model_dir / RANGE_FILE
    svm = _field(read_opencv_storage(model_path), "opencv_ml_svm", model_path)
    if _field(svm, "svmType", model_path) != "EPS_SVR":
        raise WeightsError(f"{model_path}: svmType {svm['svmType']!r}, expected EPS_SVR")
    kernel = _field(svm, "kernel", model_path)
    if _field(kernel, "type", model_path) != "RBF":
        raise WeightsError(f"{model_path}: kernel type {kernel['type']!r}, expected RBF")
    var_count, sv_total = _field(svm, "var_count", model_path), _field(svm, "sv_total", model_path)
    if var_count != NUM_FEATURES:
        raise WeightsError(f"{model_path}: var_count {var_count}, expected {NUM_FEATURES}")
    functions = _field(svm, "decision_functions", model_path)
    if not isinstance(functions, list) or len(functions) != 1:
        raise WeightsError(
            f"{model_path}: an SVR has one decision function, found "
            f"{len(functions) if isinstance(functions, list) else 'none'}"
        )
    try:
        tree = {
            "support_vectors": np.asarray(_field(svm, "support_vectors", model_path), np.float32),
            "dual_coef": np.asarray(_field(functions[0], "alpha", model_path), np.float64),
            "rho": np.asarray(_field(functions[0], "rho", model_path), np.float64),
            "gamma": np.asarray(_field(kernel, "gamma", model_path), np.float64),
        }
    except (TypeError, ValueError) as exc:
        raise WeightsError(f"{model_path}: support vectors or coefficients are not numeric arrays ({exc})") from None
    ranges = _field(read_opencv_storage(range_path), "range", range_path)
    if not isinstance(ranges, np.ndarray) or ranges.shape != (2, NUM_FEATURES):
        raise WeightsError(
            f"{range_path}: 'range' must be an opencv-matrix 2 x {NUM_FEATURES}, got "
            f"{getattr(ranges, 'shape', type(ranges).__name__)}"
        )
    tree["feature_min"] = np.asarray(ranges[0], np.float64)
    tree["feature_max"] = np.asarray(ranges[1], np.float64)
    _check_model(tree, f"{model_path} / {range_path.name}", sv_total)
    return tree, {"source": [MODEL_FILE, RANGE_FILE], "svm": "EPS_SVR", "kernel": "RBF", "trained_on": "LIVE R2"}


register_converter(Converter(MODEL, (MODEL_FILE, RANGE_FILE), _read))


def _check_model(tree: Dict[str, Any], source: str, sv_total: Optional[int] = None) -> None:
    total = int(np.shape(tree.get("support_vectors", np.zeros((0, 0))))[0]) if sv_total is None else int(sv_total)
    check_shapes(
        {
            "support_vectors": (total, NUM_FEATURES),
            "dual_coef": (total,),
            "rho": (),
            "gamma": (),
            "feature_min": (NUM_FEATURES,),
            "feature_max": (NUM_FEATURES,),
        },
        tree,
        source,
    )
    if not all(np.all(np.isfinite(np.asarray(v, np.float64))) for v in tree.values()):
        raise WeightsError(f"{source}: NaN or inf in the model")
    if not np.all(np.asarray(tree["feature_max"]) > np.asarray(tree["feature_min"])):
        raise WeightsError(f"{source}: a feature range has max <= min")
    if not float(tree["gamma"]) > 0:
        raise WeightsError(f"{source}: RBF gamma must be positive, got {float(tree['gamma'])}")


def load_params(weights_dir: Optional[str] = None) -> Dict[str, Array]:
    """The BRISQUE SVR and feature range (the converter's tree) as float32 jnp arrays.

    Reads `<weights>/brisque/brisque.npz` when converted, else the two OpenCV YAML files.

    Raises:
      DataNotFoundError: a model file is missing (the message names the expected path).
      WeightsError: a malformed file or model (names the file).
    """
    tree, _ = load_model(MODEL, weights_dir)
    _check_model(tree, f"{MODEL} weights")
    return {key: jnp.asarray(value, jnp.float32) for key, value in tree.items()}


# ---------------------------------------------------------------------------------------------
# Features (one image).


def rgb_to_grey(image: Array) -> Array:
    """OpenCV's BGR2GRAY of the 8-bit quantised image: grey levels [H, W] float32 (integers 0..255).

    Args:
      image: RGB float [H, W, 3] in [0, 1].
    """
    levels = jnp.floor(jnp.clip(jnp.asarray(image, jnp.float32), 0.0, 1.0) * 255.0 + 0.5).astype(jnp.int32)
    grey = (4899 * levels[..., 0] + 9617 * levels[..., 1] + 1868 * levels[..., 2] + (1 << 13)) >> 14
    return grey.astype(jnp.float32)


@functools.lru_cache(maxsize=None)
def _cubic_matrix(length: int, out_length: int) -> np.ndarray:
    """[out_length, length] float64: cv::resize INTER_CUBIC along one axis (a = -0.75, clamped borders)."""
    a = -0.75
    scale = length / out_length
    f = (np.arange(out_length) + 0.5) * scale - 0.5
    s = np.floor(f)
    t = f - s
    weights = np.stack(
        [
            ((a * (t + 1) - 5 * a) * (t + 1) + 8 * a) * (t + 1) - 4 * a,
            ((a + 2) * t - (a + 3)) * t * t + 1,
            ((a + 2) * (1 - t) - (a + 3)) * (1 - t) * (1 - t) + 1,
        ],
        axis=1,
    )
    weights = np.concatenate([weights, 1.0 - weights.sum(axis=1, keepdims=True)], axis=1)  # [out, 4]
    index = np.clip(s[:, None].astype(int) - 1 + np.arange(4)[None, :], 0, length - 1)
    matrix = np.zeros((out_length, length))
    np.add.at(matrix, (np.repeat(np.arange(out_length), 4), index.ravel()), weights.ravel())
    return matrix


def resize_half_cubic(grey: Array) -> Array:
    """cv::resize(grey, (W // 2, H // 2), INTER_CUBIC) of a float image [H, W]: [H // 2, W // 2]."""
    height, width = grey.shape
    rows = jnp.asarray(_cubic_matrix(height, height // 2), jnp.float32)
    cols = jnp.asarray(_cubic_matrix(width, width // 2), jnp.float32)
    return jnp.matmul(jnp.matmul(rows, grey, precision=_PRECISION), cols.T, precision=_PRECISION)


def _scale_features(coefficients: Array) -> List[Array]:
    """The 18 features of one scale's MSCN image [h, w] (see the module docstring)."""
    samples = jnp.concatenate([coefficients[None], nss.pairwise_products(coefficients, "zero")])  # [5, h, w]
    fits = jax.vmap(nss.aggd_fit)(samples)  # fields [5]: the MSCN image, then H, V, D1, D2
    features = [fits.alpha[0], 0.5 * (fits.sigma_l[0] ** 2 + fits.sigma_r[0] ** 2)]
    for k in range(1, 5):
        features += [fits.alpha[k], fits.eta[k], fits.sigma_l[k] ** 2, fits.sigma_r[k] ** 2]
    return features


def brisque_features(image: Array) -> Array:
    """The 36 BRISQUE features [36] float32 of one image (unscaled; see the module docstring).

    Args:
      image: RGB float [H, W, 3] in [0, 1], H, W >= 2.

    Raises:
      ValueError: an image smaller than 2x2 (at trace time).
    """
    height, width = image.shape[0], image.shape[1]
    if height < 2 or width < 2:
        raise ValueError(f"BRISQUE needs images of at least 2x2 pixels, got {height}x{width}")
    grey = rgb_to_grey(image)
    features = []
    for scaled in (grey, resize_half_cubic(grey)):
        coefficients, _ = nss.mscn(scaled)
        features += _scale_features(coefficients)
    return jnp.stack(features)


def scale_features(params: Dict[str, Array], features: Array) -> Array:
    """Features [..., 36] mapped linearly to [-1, 1] by the range file (min -> -1, max -> 1; not clipped)."""
    low, high = params["feature_min"], params["feature_max"]
    return -1.0 + 2.0 * (features - low) / (high - low)


def svr_predict(params: Dict[str, Array], scaled: Array) -> Array:
    """The RBF epsilon-SVR at scaled features [36]: sum_i a_i exp(-gamma ||x - s_i||^2) - rho, []."""
    distance = jnp.sum((scaled[None, :] - params["support_vectors"]) ** 2, axis=1)  # [S]
    kernel = jnp.exp(-params["gamma"] * distance)  # [S]
    return jnp.dot(params["dual_coef"], kernel, precision=_PRECISION) - params["rho"]


def brisque_score(params: Dict[str, Array], image: Array) -> Array:
    """BRISQUE [] of one image float32 [H, W, 3] in [0, 1] (LIVE DMOS scale, lower is better; not clamped)."""
    return svr_predict(params, scale_features(params, brisque_features(image)))


# ---------------------------------------------------------------------------------------------
# The criterion.


def _apply(params, images: Array) -> Array:
    """Criterion scores [P] of images [P, H, W, 3]: `brisque_score`, clipped, the worst for failed views."""
    return nss.quality_scores(functools.partial(brisque_score, params), images, CHUNK, VALUE_RANGE)


def brisque(context: CriterionContext) -> Criterion:
    """The `brisque` criterion: OpenCV's LIVE BRISQUE score, clamped to [0, 100] (direction min).

    Raises:
      DataNotFoundError / WeightsError: from `load_params(context.weights_dir)`.
    """
    return Criterion(
        params=load_params(context.weights_dir),
        name="brisque",
        direction="min",
        value_range=VALUE_RANGE,
        inputs="images",
        apply=_apply,
        description=_DESCRIPTION,
    )


_DESCRIPTION = (
    "BRISQUE (Mittal et al. 2012): SVR from natural-scene statistics to LIVE DMOS (OpenCV model), "
    "no-reference, lower is better, in [0, 100]"
)
register(CriterionSpec("brisque", "min", "images", _DESCRIPTION, brisque, reads=("weights_dir",)))
