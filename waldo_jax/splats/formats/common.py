"""Shared helpers of the splat file formats' readers and writers (`waldo_jax.splats.formats`).

Every reader returns `Splats` in the reference layout's raw parameters (`waldo_jax.splats.model`):
means, log-scales, quaternions w first, opacity logits, sh [N, K, 3] with sh[:, 0] = f_dc and
colour = SH_C0 f_dc + 0.5. Stored bytes are u; quantised opacities end at 0 and 1, whose logits are
infinite: the end bytes decode to the middle of their rounding interval instead (`opacity_logits`).
Rounding follows the SPZ reference's toUint8 (C's std::round, halves away from zero).
"""

from __future__ import annotations

from pathlib import Path
from typing import Dict

import numpy as np

from waldo_jax.errors import SceneFormatError, WaldoError, check_memory
from waldo_jax.splats.model import MAX_SH_DEGREE, Splats, make_splats, sh_coefficients

SH_C0 = 0.28209479177387814


def round_half_away(x: np.ndarray) -> np.ndarray:
    """C's std::round: halves away from zero (NumPy's round takes them to even)."""
    return np.sign(x) * np.floor(np.abs(x) + 0.5)


def to_uint8(x: np.ndarray) -> np.ndarray:
    """The SPZ reference's toUint8: round half away from zero, clamp to 0..255."""
    return np.clip(round_half_away(np.asarray(x, np.float32)), 0, 255).astype(np.uint8)


def sigmoid(x: np.ndarray) -> np.ndarray:
    """The logistic function in float32 (no overflow warning for large negative inputs)."""
    with np.errstate(over="ignore"):
        return (1.0 / (1.0 + np.exp(-np.asarray(x, np.float32)))).astype(np.float32)


def opacity_logits(fraction: np.ndarray) -> np.ndarray:
    """Logits of quantised opacities in [0, 1]; 0 and 1 (infinite logits) are moved a quarter byte inwards,
    the middle of the interval a round-to-nearest byte of 0 or 255 stands for."""
    p = np.clip(np.asarray(fraction, np.float64), 0.25 / 255, 1.0 - 0.25 / 255)
    return np.log(p / (1.0 - p)).astype(np.float32)


def valid_rows(path: Path, splats: Splats) -> Dict[str, np.ndarray]:
    """The valid rows of `splats` as float32 NumPy arrays; a WaldoError for none or non-finite ones."""
    rows = np.flatnonzero(np.asarray(splats.valid, bool))
    if len(rows) == 0:
        raise WaldoError(f"{path}: no valid splats to write")
    arrays = {
        k: np.asarray(getattr(splats, k), np.float32)[rows] for k in ("means", "log_scales", "quats", "logits", "sh")
    }
    bad = np.zeros(len(rows), bool)
    for v in arrays.values():
        bad |= ~np.all(np.isfinite(v.reshape(len(rows), -1)), axis=1)
    bad |= np.sum(arrays["quats"] ** 2, -1) < np.finfo(np.float32).tiny
    if bad.any():
        raise WaldoError(
            f"{path}: {int(bad.sum())} valid splats have non-finite values or a zero quaternion (first: "
            f"row {int(rows[np.argmax(bad)])}); mark them invalid before writing"
        )
    return arrays


def finish_splats(path: Path, what: str, means, log_scales, quats, logits, sh) -> Splats:
    """`Splats` from decoded arrays; a SceneFormatError when any value is not finite."""
    arrays = {"means": means, "log_scales": log_scales, "quats": quats, "logits": logits, "sh": sh}
    n = len(means)
    bad = {k: int((~np.all(np.isfinite(np.asarray(v).reshape(n, -1)), axis=1)).sum()) for k, v in arrays.items()}
    bad = {k: v for k, v in bad.items() if v}
    if bad:
        listed = ", ".join(f"{k} ({v} rows)" for k, v in bad.items())
        raise SceneFormatError(path, f"{what} decodes to non-finite values in {n} splats: {listed}")
    return make_splats(**arrays)


# A decoder's peak memory per float of the splats it returns: the file's bytes, float64 intermediates and the
# float32 result (measured below 3 on the formats' readers; 4 leaves room).
_DECODE_PEAK_FACTOR = 4


def check_splat_count(path: Path, count: int, degree: int, what: str) -> None:
    """A MemoryBudgetError, before anything is decoded, when `count` splats of SH degree `degree` (a count
    read from a header) would not fit this machine's free memory."""
    floats = 3 + 3 + 4 + 1 + 3 * sh_coefficients(min(int(degree), MAX_SH_DEGREE))
    check_memory(
        float(count) * floats * 4 * _DECODE_PEAK_FACTOR,
        f"{path}: reading its {count:,} splats ({what}, SH degree {degree})",
        "convert a part of the scene, or read it on a machine with more memory",
    )


def read_splat_bytes(path: Path, what: str) -> bytes:
    """The bytes of `path`; a SceneFormatError naming the file (and `what` it should be) when unreadable."""
    try:
        return Path(path).read_bytes()
    except OSError as e:
        raise SceneFormatError(path, f"cannot read this {what} ({e.strerror or e})") from None


def rest_from_channel_major(rest: np.ndarray, n: int) -> np.ndarray:
    """[N, 3 (K - 1)] f_rest columns, channel-major as in a PLY, to [N, K - 1, 3]."""
    k1 = rest.shape[1] // 3
    return rest.reshape(n, 3, k1).transpose(0, 2, 1)


def sh_degree_of_rest(path: Path, count: int, what: str) -> int:
    """The SH degree whose higher-order coefficients number `count` floats; a SceneFormatError otherwise."""
    for degree in range(MAX_SH_DEGREE + 1):
        if 3 * (sh_coefficients(degree) - 1) == count:
            return degree
    raise SceneFormatError(path, f"{count} {what} are no SH degree 0..{MAX_SH_DEGREE} (expected 0, 9, 24 or 45)")
