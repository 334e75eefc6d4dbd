"""An independent NumPy/SciPy reference of NIQE and BRISQUE, for the tests only (float64 throughout).

Written from the reference implementations' descriptions (LIVE's NIQE MATLAB release, OpenCV contrib's
`qualitybrisque.cpp`), along a different code path from `waldo_jax.criteria.{nss,niqe,brisque}`:
  * local moments with `scipy.ndimage.correlate` of I and I^2 (in float64 the cancellation in
    E[I^2] - E[I]^2 is harmless), where the package accumulates window differences in float32;
  * MATLAB's half-size bicubic resize as the closed-form 8-tap kernel of a factor-2 reduction with
    numpy's symmetric padding (even sizes only), where the package builds a general resampling matrix;
    OpenCV's cubic resize as an explicit loop over output rows;
  * AGGD fits with boolean indexing and `scipy.special.gamma`; pairwise products with MATLAB's
    circshift convention (np.roll) or an explicitly zero-filled shifted copy;
  * the NIQE distance with `scipy.linalg.pinv` of (Sigma_p + Sigma_d) / 2, as the MATLAB code does;
  * the BRISQUE model read from the YAML text with regular expressions, not the package's parser.

The conventions the package documents as its own choices (8-bit quantisation of the input, zeroing
|I - mu| < 1e-4 grey levels, finite fits of degenerate samples, leaving flat NIQE patches out) are
mirrored here, so that the two agree to float32 rounding.
"""

from __future__ import annotations

import re
from typing import Dict, Tuple

import numpy as np
import scipy.io
import scipy.linalg
import scipy.ndimage
import scipy.special

GRID = np.linspace(0.2, 10.0, 9801)
R_GAM = scipy.special.gamma(2.0 / GRID) ** 2 / (scipy.special.gamma(1.0 / GRID) * scipy.special.gamma(3.0 / GRID))
FLAT_LEVEL = 1e-4


# ------------------------------------------------------------------------------------------------
# Common NSS.


def quantise(image: np.ndarray) -> np.ndarray:
    """0..255 integer levels (float64) of an RGB float image in [0, 1]."""
    return np.floor(np.clip(np.asarray(image, np.float64), 0.0, 1.0) * 255.0 + 0.5)


def grey_matlab(image: np.ndarray) -> np.ndarray:
    levels = quantise(image)
    y = 0.298936021293775 * levels[..., 0] + 0.587043074451121 * levels[..., 1] + 0.114020904255103 * levels[..., 2]
    return np.floor(y + 0.5)


def grey_opencv(image: np.ndarray) -> np.ndarray:
    levels = quantise(image).astype(np.int64)
    y = (levels[..., 0] * 4899 + levels[..., 1] * 9617 + levels[..., 2] * 1868 + 8192) // 16384
    return y.astype(np.float64)


def gauss2d() -> np.ndarray:
    w = np.zeros((7, 7))
    for i in range(7):
        for j in range(7):
            w[i, j] = np.exp(-((i - 3) ** 2 + (j - 3) ** 2) / (2.0 * (7.0 / 6.0) ** 2))
    return w / w.sum()


def mscn(grey: np.ndarray) -> np.ndarray:
    w = gauss2d()
    mu = scipy.ndimage.correlate(grey, w, mode="nearest")
    second = scipy.ndimage.correlate(grey * grey, w, mode="nearest")
    sigma = np.sqrt(np.abs(second - mu * mu))
    centred = grey - mu
    centred[np.abs(centred) < FLAT_LEVEL] = 0.0
    return centred / (sigma + 1.0)


def aggd(vec: np.ndarray) -> Dict[str, float]:
    vec = np.asarray(vec, np.float64).ravel()
    left, right = vec[vec < 0], vec[vec > 0]
    lstd = np.sqrt(np.mean(left**2)) if left.size else 0.0
    rstd = np.sqrt(np.mean(right**2)) if right.size else 0.0
    mean_sq = np.mean(vec**2)
    rhat = np.mean(np.abs(vec)) ** 2 / mean_sq if mean_sq > 0 else 0.0
    if rstd > 0:
        g = lstd / rstd
        rhatnorm = rhat * (g**3 + 1) * (g + 1) / (g**2 + 1) ** 2
    else:
        rhatnorm = rhat  # the limit g -> inf (or the symmetric 1 when both sides are empty)
    alpha = GRID[np.argmin((R_GAM - rhatnorm) ** 2)]
    ratio = np.sqrt(scipy.special.gamma(1 / alpha) / scipy.special.gamma(3 / alpha))
    betal, betar = lstd * ratio, rstd * ratio
    eta = (betar - betal) * scipy.special.gamma(2 / alpha) / scipy.special.gamma(1 / alpha)
    return {
        "alpha": alpha,
        "lstd": lstd,
        "rstd": rstd,
        "betal": betal,
        "betar": betar,
        "eta": eta,
        "valid": bool(left.size and right.size),
    }


def ggd(vec: np.ndarray) -> Tuple[float, float]:
    vec = np.asarray(vec, np.float64).ravel()
    rho = np.mean(vec**2) / np.mean(np.abs(vec)) ** 2
    g = GRID
    table = scipy.special.gamma(1 / g) * scipy.special.gamma(3 / g) / scipy.special.gamma(2 / g) ** 2
    return GRID[np.argmin(np.abs(rho - table))], np.mean(vec**2)


# ------------------------------------------------------------------------------------------------
# NIQE (LIVE MATLAB release conventions).


def _matlab_cubic(x: float) -> float:
    x = abs(x)
    if x <= 1:
        return 1.5 * x**3 - 2.5 * x**2 + 1
    if x <= 2:
        return -0.5 * x**3 + 2.5 * x**2 - 4 * x + 2
    return 0.0


HALF_TAPS = np.array([0.5 * _matlab_cubic(0.5 * d) for d in (3.5, 2.5, 1.5, 0.5, -0.5, -1.5, -2.5, -3.5)])


def imresize_half(grey: np.ndarray) -> np.ndarray:
    """MATLAB imresize(grey, 0.5) for even sizes: out[j] = sum_k taps[k] in[2j - 3 + k], symmetric borders."""
    assert grey.shape[0] % 2 == 0 and grey.shape[1] % 2 == 0
    out = grey
    for axis in (0, 1):
        pad = [(0, 0), (0, 0)]
        pad[axis] = (3, 4)
        padded = np.pad(out, pad, mode="symmetric")
        n = out.shape[axis] // 2
        acc = 0.0
        for k, tap in enumerate(HALF_TAPS):
            acc = acc + tap * np.take(padded, 2 * np.arange(n) + k, axis=axis)
        out = acc
    return out


def niqe_patch_features(patch: np.ndarray) -> Tuple[np.ndarray, bool]:
    fit = aggd(patch)
    feats = [fit["alpha"], (fit["betal"] + fit["betar"]) / 2]
    valid = fit["valid"]
    for shift in ((0, 1), (1, 0), (1, 1), (1, -1)):  # MATLAB circshift(structdis, shift)
        pair = aggd(patch * np.roll(patch, shift, axis=(0, 1)))
        feats += [pair["alpha"], pair["eta"], pair["betal"], pair["betar"]]
        valid = valid and pair["valid"]
    return np.array(feats), valid


def niqe_features(image: np.ndarray, patch: int = 96) -> Tuple[np.ndarray, np.ndarray]:
    grey = grey_matlab(image)
    rows, cols = grey.shape[0] // patch, grey.shape[1] // patch
    grey = grey[: rows * patch, : cols * patch]
    scales = []
    for level in range(2):
        coefficients = mscn(grey)
        side = patch // (2**level)
        feats, valid = [], []
        for r in range(rows):
            for c in range(cols):
                f, v = niqe_patch_features(coefficients[r * side : (r + 1) * side, c * side : (c + 1) * side])
                feats.append(f)
                valid.append(v)
        scales.append((np.array(feats), np.array(valid)))
        grey = imresize_half(grey)
    return np.concatenate([scales[0][0], scales[1][0]], axis=1), scales[0][1] & scales[1][1]


def load_niqe(path: str) -> Tuple[np.ndarray, np.ndarray]:
    data = scipy.io.loadmat(path)
    return np.ravel(data["pop_mu"]).astype(np.float64), np.asarray(data["pop_cov"], np.float64)


def niqe_score(model: Tuple[np.ndarray, np.ndarray], image: np.ndarray) -> float:
    mu_p, cov_p = model
    feats, valid = niqe_features(image)
    rows = feats[valid]
    if len(rows) == 0:
        return float("nan")
    mu_d = rows.mean(axis=0)
    cov_d = np.cov(rows, rowvar=False) if len(rows) > 1 else np.zeros((36, 36))
    d = mu_p - mu_d
    return float(np.sqrt(d @ scipy.linalg.pinv((cov_p + cov_d) / 2) @ d))


# ------------------------------------------------------------------------------------------------
# BRISQUE (OpenCV contrib conventions).


def opencv_resize_cubic(grey: np.ndarray, out_h: int, out_w: int) -> np.ndarray:
    """cv::resize INTER_CUBIC (a = -0.75, clamped borders), an explicit loop over output rows / columns."""

    def weights(t: float) -> np.ndarray:
        a = -0.75
        w0 = ((a * (t + 1) - 5 * a) * (t + 1) + 8 * a) * (t + 1) - 4 * a
        w1 = ((a + 2) * t - (a + 3)) * t * t + 1
        w2 = ((a + 2) * (1 - t) - (a + 3)) * (1 - t) * (1 - t) + 1
        return np.array([w0, w1, w2, 1 - w0 - w1 - w2])

    def along(x: np.ndarray, out_n: int) -> np.ndarray:  # resize axis 0
        n = x.shape[0]
        out = np.zeros((out_n,) + x.shape[1:])
        for d in range(out_n):
            f = (d + 0.5) * (n / out_n) - 0.5
            s = int(np.floor(f))
            w = weights(f - s)
            for k in range(4):
                out[d] += w[k] * x[min(max(s - 1 + k, 0), n - 1)]
        return out

    return along(along(grey, out_h).T, out_w).T


def brisque_features(image: np.ndarray) -> np.ndarray:
    grey = grey_opencv(image)
    feats = []
    for level in range(2):
        scaled = grey if level == 0 else opencv_resize_cubic(grey, grey.shape[0] // 2, grey.shape[1] // 2)
        coefficients = mscn(scaled)
        h, w = coefficients.shape
        fit = aggd(coefficients)
        feats += [fit["alpha"], (fit["lstd"] ** 2 + fit["rstd"] ** 2) / 2]
        for di, dj in ((0, 1), (1, 0), (1, 1), (-1, 1)):
            shifted = np.zeros_like(coefficients)
            for i in range(h):
                if 0 <= i + di < h:
                    lo, hi = max(0, -dj), min(w, w - dj)
                    shifted[i, lo:hi] = coefficients[i + di, lo + dj : hi + dj]
            pair = aggd(coefficients * shifted)
            feats += [pair["alpha"], pair["eta"], pair["lstd"] ** 2, pair["rstd"] ** 2]
    return np.array(feats)


_FLOAT = r"[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?"


def load_brisque(model_path: str, range_path: str) -> Dict[str, np.ndarray]:
    text = open(model_path).read()
    sv_text = text[text.index("support_vectors:") : text.index("decision_functions:")]
    sv = np.array([float(v) for v in re.findall(_FLOAT, sv_text.split(":", 1)[1])]).reshape(-1, 36)
    alpha_text = text[text.index("alpha:") + len("alpha:") :]
    alpha = np.array([float(v) for v in re.findall(_FLOAT, alpha_text)])
    rho = float(re.search(r"rho:\s*(" + _FLOAT + ")", text).group(1))
    gamma = float(re.search(r"gamma:\s*(" + _FLOAT + ")", text).group(1))
    rtext = open(range_path).read()
    data = np.array([float(v) for v in re.findall(_FLOAT, rtext[rtext.index("data:") + 5 :])]).reshape(2, 36)
    return {"sv": sv, "alpha": alpha, "rho": rho, "gamma": gamma, "min": data[0], "max": data[1]}


def brisque_scale(model: Dict[str, np.ndarray], feats: np.ndarray) -> np.ndarray:
    return 2.0 * (feats - model["min"]) / (model["max"] - model["min"]) - 1.0


def brisque_score(model: Dict[str, np.ndarray], image: np.ndarray) -> float:
    """The raw SVR output (before OpenCV's clamp to [0, 100])."""
    x = brisque_scale(model, brisque_features(image))
    total = -model["rho"]
    for sv, a in zip(model["sv"], model["alpha"]):
        total += a * np.exp(-model["gamma"] * np.sum((x - sv) ** 2))
    return float(total)
