"""NIQE, the "completely blind" Natural Image Quality Evaluator (Mittal, Soundararajan and Bovik 2013).

A. Mittal, R. Soundararajan and A. C. Bovik, "Making a 'Completely Blind' Image Quality Analyzer",
IEEE Signal Processing Letters 20(3), 209-212, 2013; LIVE's "NIQE Software Release" (MATLAB,
`computequality.m`), whose pristine model the weights file holds. Lower is better: NIQE is the
distance between the statistics of the image's patches and those of pristine photographs.

Pipeline, for one image (the conventions of the official MATLAB code, which produced the model file):
  1. 8-bit grey (MATLAB rgb2gray of the quantised image), cropped (top-left) to whole 96x96 patches;
  2. two scales: the grey image and MATLAB's imresize(I, 0.5); at each the MSCN coefficients of the
     whole image (`nss.mscn`) are cut into the patch grid (96x96, then 48x48);
  3. 18 features per patch and scale, 36 per patch (scale 1 then scale 2): [alpha, (beta_l + beta_r) / 2]
     of the AGGD fit of the MSCN patch, then for each orientation H, V, D1, D2 of the pairwise products
     (circular within the patch): [alpha, eta, beta_l, beta_r];
  4. NIQE = sqrt((mu_p - mu_d)^T ((Sigma_p + Sigma_d) / 2)^-1 (mu_p - mu_d)), the image's Gaussian
     (mu_d, Sigma_d over its non-flat patches) against the pristine one (mu_p, Sigma_p), computed as
     NIQE^2 = 2 e^T (I + M)^-1 e with e = L^-1 (mu_p - mu_d), M = L^-1 Sigma_d L^-T and L the Cholesky
     factor of Sigma_p (inverted once in float64: Sigma_p is too ill-conditioned for float32).
Why no patch selection, the beta convention and the flat patches: docs/design.md, "Criteria".

Weights: `<weights>/niqe/niqe_image_params.mat` (MATLAB v5) holds `pop_mu` (1, 36) and `pop_cov`
(36, 36), the pristine model of the official LIVE release; the converter's tree is
`{"pop_mu": [36], "pop_cov": [36, 36]}` (float64). Scores are clipped to `VALUE_RANGE` = (0, 100);
100 is the finite worst score of failed views (NaN/inf pixels, no usable patch).
"""

from __future__ import annotations

import functools
from pathlib import Path
from typing import Any, Dict, NamedTuple, Optional, Tuple

import jax
import jax.numpy as jnp
import numpy as np

from waldo_jax.criteria import nss
from waldo_jax.criteria.base import Criterion, CriterionContext, CriterionError, CriterionSpec, register
from waldo_jax.types import Array
from waldo_jax.weights.store import Converter, WeightsError, check_shapes, load_model, register_converter

__all__ = [
    "MODEL",
    "PARAMS_FILE",
    "PATCH",
    "NUM_FEATURES",
    "VALUE_RANGE",
    "CHUNK",
    "NiqeFeatures",
    "rgb_to_grey",
    "imresize_half",
    "niqe_features",
    "niqe_distance",
    "niqe_score",
    "load_params",
    "params_from_model",
    "niqe",
]

MODEL = "niqe"
PARAMS_FILE = "niqe_image_params.mat"
PATCH = 96  # patch side at scale 1 (48 at scale 2)
NUM_FEATURES = 36
CHUNK = 4  # images vmapped at once, chunks scanned over (bounded memory; faster on CPU than all at once)
VALUE_RANGE = (0.0, 100.0)
# MATLAB rgb2gray: the first row of the inverse of the NTSC YIQ matrix.
_RGB2GRAY = np.array([0.298936021293775, 0.587043074451121, 0.114020904255103])
_PRECISION = jax.lax.Precision.HIGHEST  # no TF32/bf16 passes on accelerators


# ---------------------------------------------------------------------------------------------
# Weights.


def _read(model_dir: Path) -> Tuple[Dict[str, Any], Dict[str, Any]]:
    """Converter: `<model_dir>/niqe_image_params.mat` -> ({"pop_mu", "pop_cov"}, meta)."""
    import scipy.io  # a runtime dependency of the NIQE weights only

    path = model_dir / PARAMS_FILE
    try:
        data = scipy.io.loadmat(str(path))
    except Exception as exc:  # scipy raises several types for a corrupt file
        raise WeightsError(f"{path}: not a readable MATLAB .mat file ({type(exc).__name__}: {exc})") from None
    missing = [k for k in ("pop_mu", "pop_cov") if k not in data]
    if missing:
        raise WeightsError(f"{path}: no variable {missing[0]!r} (expected pop_mu (1, 36) and pop_cov (36, 36))")
    try:
        mu = np.asarray(data["pop_mu"], np.float64).reshape(-1)
        cov = np.asarray(data["pop_cov"], np.float64)
    except (TypeError, ValueError) as exc:
        raise WeightsError(f"{path}: pop_mu / pop_cov are not numeric arrays ({exc})") from None
    tree = {"pop_mu": mu, "pop_cov": cov}
    _check_model(tree, str(path))
    return tree, {"source": PARAMS_FILE, "release": "LIVE NIQE Software Release (official pristine model)"}


register_converter(Converter(MODEL, (PARAMS_FILE,), _read))


def _check_model(tree: Dict[str, Any], source: str) -> None:
    check_shapes({"pop_mu": (NUM_FEATURES,), "pop_cov": (NUM_FEATURES, NUM_FEATURES)}, tree, source)
    mu, cov = np.asarray(tree["pop_mu"], np.float64), np.asarray(tree["pop_cov"], np.float64)
    if not (np.all(np.isfinite(mu)) and np.all(np.isfinite(cov))):
        raise WeightsError(f"{source}: pop_mu / pop_cov hold NaN or inf")
    if not np.allclose(cov, cov.T, rtol=1e-6, atol=1e-12):
        raise WeightsError(f"{source}: pop_cov is not symmetric")
    try:
        np.linalg.cholesky(cov)
    except np.linalg.LinAlgError:
        raise WeightsError(f"{source}: pop_cov is not positive definite") from None


def params_from_model(tree: Dict[str, Any], source: str = "NIQE model") -> Dict[str, Array]:
    """The criterion's params from the converter tree: {"mu": [36], "whiten": L^-1 [36, 36]} float32.

    L is the Cholesky factor of pop_cov, inverted in float64 (see the module docstring).
    """
    _check_model(tree, source)
    cov = np.asarray(tree["pop_cov"], np.float64)
    whiten = np.linalg.inv(np.linalg.cholesky(cov))  # L^-1, lower triangular
    return {"mu": jnp.asarray(tree["pop_mu"], jnp.float32), "whiten": jnp.asarray(whiten, jnp.float32)}


def load_params(weights_dir: Optional[str] = None) -> Dict[str, Array]:
    """The NIQE params (`params_from_model`) from `<weights>/niqe/` (`niqe.npz` when converted).

    Raises:
      DataNotFoundError: no model file (the message names the expected path).
      WeightsError: a corrupt or foreign file, wrong shapes, a non-positive-definite covariance.
    """
    tree, _ = load_model(MODEL, weights_dir)
    return params_from_model(tree, f"{MODEL} weights")


# ---------------------------------------------------------------------------------------------
# Features (one image).


def rgb_to_grey(image: Array) -> Array:
    """MATLAB rgb2gray of the 8-bit quantised image: grey levels [H, W] float32 (integers 0..255).

    Args:
      image: RGB float [H, W, 3] in [0, 1].
    """
    levels = jnp.floor(jnp.clip(jnp.asarray(image, jnp.float32), 0.0, 1.0) * 255.0 + 0.5)  # [H, W, 3]
    # The weights split into a 12-bit head (exact products and sums in float32) and a small tail, so
    # the rounding below matches a float64 evaluation except within ~1e-8 of a half level.
    head = np.round(_RGB2GRAY * 4096.0) / 4096.0
    tail = _RGB2GRAY - head
    exact = jnp.tensordot(levels, jnp.asarray(head, jnp.float32), axes=1, precision=_PRECISION)
    small = jnp.tensordot(levels, jnp.asarray(tail, jnp.float32), axes=1, precision=_PRECISION)
    return jnp.floor(exact + small + 0.5)


def _cubic(x: np.ndarray) -> np.ndarray:
    """MATLAB imresize's bicubic kernel (a = -0.5)."""
    ax = np.abs(x)
    return (1.5 * ax**3 - 2.5 * ax**2 + 1.0) * (ax <= 1) + (-0.5 * ax**3 + 2.5 * ax**2 - 4.0 * ax + 2.0) * (
        (ax > 1) & (ax <= 2)
    )


@functools.lru_cache(maxsize=None)
def _half_matrix(length: int) -> np.ndarray:
    """[ceil(length / 2), length] float64: MATLAB imresize(., 0.5) along one axis (antialiased bicubic)."""
    scale = 0.5
    out_length = int(np.ceil(length * scale))
    width = 4.0 / scale  # the kernel widened by 1 / scale: antialiasing
    u = np.arange(1, out_length + 1) / scale + 0.5 * (1.0 - 1.0 / scale)  # 1-based input coordinates
    left = np.floor(u - width / 2.0)
    taps = int(np.ceil(width)) + 2
    index = left[:, None] + np.arange(taps)[None, :]  # 1-based [out, taps]
    weights = scale * _cubic(scale * (u[:, None] - index))
    weights /= weights.sum(axis=1, keepdims=True)
    mirror = np.concatenate([np.arange(length), np.arange(length - 1, -1, -1)])  # symmetric borders
    index = mirror[np.mod(index.astype(int) - 1, 2 * length)]
    matrix = np.zeros((out_length, length))
    np.add.at(matrix, (np.repeat(np.arange(out_length), taps), index.ravel()), weights.ravel())
    return matrix


def imresize_half(grey: Array) -> Array:
    """MATLAB imresize(grey, 0.5) of a float image [H, W] (bicubic, antialiased): [ceil(H/2), ceil(W/2)]."""
    height, width = grey.shape
    rows = jnp.asarray(_half_matrix(height), jnp.float32)
    cols = jnp.asarray(_half_matrix(width), jnp.float32)
    return jnp.matmul(jnp.matmul(rows, grey, precision=_PRECISION), cols.T, precision=_PRECISION)


def _patches(x: Array, side: int) -> Array:
    """The non-overlapping side x side patches of x [r * side, c * side], [r * c, side, side], row-major."""
    rows, cols = x.shape[0] // side, x.shape[1] // side
    return x.reshape(rows, side, cols, side).transpose(0, 2, 1, 3).reshape(rows * cols, side, side)


def _patch_features(patch: Array) -> Tuple[Array, Array]:
    """The 18 features [18] of one MSCN patch [s, s] and whether every fit was non-degenerate []."""
    samples = jnp.concatenate([patch[None], nss.pairwise_products(patch, "circular")])  # [5, s, s]
    fits = jax.vmap(nss.aggd_fit)(samples)  # fields [5]: the MSCN patch, then H, V, D1, D2
    features = [fits.alpha[0], 0.5 * (fits.beta_l[0] + fits.beta_r[0])]
    for k in range(1, 5):
        features += [fits.alpha[k], fits.eta[k], fits.beta_l[k], fits.beta_r[k]]
    return jnp.stack(features), jnp.all(fits.valid)


class NiqeFeatures(NamedTuple):
    """The patch features of one image: `features` float32 [N, 36] and `valid` bool [N] (non-flat patches)."""

    features: Array
    valid: Array


def niqe_features(image: Array) -> NiqeFeatures:
    """NIQE features of one image (see the module docstring), one row per 96x96 patch.

    Args:
      image: RGB float [H, W, 3] in [0, 1]; H, W >= 96 (static: they set the patch grid
        (H // 96) x (W // 96), row-major from the top left).

    Returns:
      `NiqeFeatures` with features [N, 36] (scale 1's 18, then scale 2's) and valid [N].

    Raises:
      CriterionError: an image smaller than 96x96 (at trace time; a `ValueError` and a `WaldoError`).
    """
    height, width = image.shape[0], image.shape[1]
    if height < PATCH or width < PATCH:
        raise CriterionError(
            f"NIQE needs images of at least {PATCH}x{PATCH} pixels (its patch size), got "
            f"{height}x{width}: render at --resolution {PATCH} or more"
        )
    grey = rgb_to_grey(image)[: PATCH * (height // PATCH), : PATCH * (width // PATCH)]
    per_scale = []
    for side, scaled in ((PATCH, grey), (PATCH // 2, imresize_half(grey))):
        coefficients, _ = nss.mscn(scaled)
        per_scale.append(jax.vmap(_patch_features)(_patches(coefficients, side)))
    (f1, v1), (f2, v2) = per_scale
    return NiqeFeatures(jnp.concatenate([f1, f2], axis=1), v1 & v2)


def niqe_distance(params: Dict[str, Array], features: Array, valid: Array) -> Array:
    """NIQE [] from patch features [N, 36] and their mask [N]; NaN when no patch is valid.

    Args:
      params: {"mu": [36], "whiten": [36, 36]} (`params_from_model`).
    """
    weight = valid.astype(jnp.float32)  # [N]
    count = jnp.sum(weight)
    mean = jnp.sum(features * weight[:, None], axis=0) / jnp.maximum(count, 1.0)  # [36]
    centred = (features - mean) * weight[:, None]  # [N, 36]
    whitened = jnp.matmul(centred, params["whiten"].T, precision=_PRECISION)  # [N, 36] rows L^-1 x
    m = jnp.matmul(whitened.T, whitened, precision=_PRECISION) / jnp.maximum(count - 1.0, 1.0)  # L^-1 S_d L^-T
    e = jnp.matmul(params["whiten"], params["mu"] - mean, precision=_PRECISION)  # [36]
    system = jnp.eye(NUM_FEATURES, dtype=jnp.float32) + m  # symmetric, eigenvalues >= 1
    z = jax.scipy.linalg.cho_solve(jax.scipy.linalg.cho_factor(system, lower=True), e)
    quality = jnp.sqrt(jnp.maximum(2.0 * jnp.dot(e, z, precision=_PRECISION), 0.0))
    return jnp.where(count > 0, quality, jnp.nan)


def niqe_score(params: Dict[str, Array], image: Array) -> Array:
    """NIQE [] of one image float32 [H, W, 3] in [0, 1] (lower is better; not clipped; NaN without a usable patch)."""
    found = niqe_features(image)
    return niqe_distance(params, found.features, found.valid)


# ---------------------------------------------------------------------------------------------
# The criterion.


def _apply(params, images: Array) -> Array:
    """Criterion scores [P] of images [P, H, W, 3]: `niqe_score`, clipped, the worst for failed views."""
    return nss.quality_scores(functools.partial(niqe_score, params), images, CHUNK, VALUE_RANGE)


def niqe(context: CriterionContext) -> Criterion:
    """The `niqe` criterion: NIQE against the LIVE pristine model (direction min, in `VALUE_RANGE`).

    Raises:
      DataNotFoundError / WeightsError: from `load_params(context.weights_dir)`.
    """
    return Criterion(
        params=load_params(context.weights_dir),
        name="niqe",
        direction="min",
        value_range=VALUE_RANGE,
        inputs="images",
        apply=_apply,
        description=_DESCRIPTION,
    )


_DESCRIPTION = (
    "NIQE (Mittal et al. 2013): distance of the image's patch statistics from pristine photographs' "
    "(LIVE model), no-reference, lower is better; images >= 96x96"
)
register(CriterionSpec("niqe", "min", "images", _DESCRIPTION, niqe, reads=("weights_dir",)))
