"""Shared helpers of the splat file formats' readers and writers (`waldo_jax.splats.formats`).

Every reader returns `Splats` in the reference layout's raw parameters (`waldo_jax.splats.model`):
means, log-scales, quaternions w first, opacity logits, sh [N, K, 3] with sh[:, 0] = f_dc and
colour = SH_C0 f_dc + 0.5. Stored bytes are u; quantised opacities end at 0 and 1, whose logits are
infinite: the end bytes decode to the middle of their rounding interval instead (`opacity_logits`).
Rounding follows the SPZ reference's toUint8 (C's std::round, halves away from zero).
"""

from __future__ import annotations

from pathlib import Path
from typing import Dict, Optional, Tuple

import numpy as np

from waldo_jax.errors import SceneFormatError, WaldoError, check_input_file, check_memory, read_input_file
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


def scale_quats(quats: np.ndarray) -> np.ndarray:
    """float32 quaternions [N, 4] whose rows are scaled by a power of two to a largest component in [1, 2)
    where their squared norm leaves float32's normal range (1e38 squared overflows to infinity, 1e-20
    squared to 0); other rows, and the direction of every row, are kept exactly. Zero rows stay zero."""
    quats = np.array(quats, np.float32)
    with np.errstate(over="ignore", under="ignore", invalid="ignore"):
        squared = np.sum(quats * quats, -1)
        largest = np.max(np.abs(quats), -1, initial=0.0)
    out = ~((squared >= np.finfo(np.float32).tiny) & (squared <= np.finfo(np.float32).max))
    out &= (largest > 0) & np.isfinite(largest)
    if out.any():
        _, exponent = np.frexp(largest[out])  # largest = m 2^e with m in [0.5, 1)
        quats[out] = np.ldexp(quats[out], (1 - exponent)[:, None]).astype(np.float32)
    return quats


def finish_splats(path: Path, what: str, means, log_scales, quats, logits, sh) -> Splats:
    """`Splats` from decoded arrays; a SceneFormatError when any value is not finite in float32 (the type the
    splats are held in: 1e39 is finite in float64, infinite there), naming the fields."""
    with np.errstate(over="ignore", invalid="ignore"):
        arrays = {
            "means": np.asarray(means, np.float32),
            "log_scales": np.asarray(log_scales, np.float32),
            "quats": np.asarray(quats, np.float32),
            "logits": np.asarray(logits, np.float32),
            "sh": np.asarray(sh, np.float32),
        }
    n = len(arrays["means"])
    bad = {k: int((~np.all(np.isfinite(v.reshape(n, -1)), axis=1)).sum()) for k, v in arrays.items()}
    bad = {k: v for k, v in bad.items() if v}
    if bad:
        listed = ", ".join(f"{k} ({v} rows)" for k, v in bad.items())
        raise SceneFormatError(
            path, f"{what} decodes to non-finite values (NaN, infinity, or beyond float32) in {n} splats: {listed}"
        )
    arrays["quats"] = scale_quats(arrays["quats"])
    return make_splats(**arrays)


# Each reader's peak memory while it reads (`read_splat_file`, the Splats it returns included), in bytes per
# splat: (a fixed part, a part per SH rest float, 3 (K - 1) of them a splat). Measured as the peak RSS
# increase of reading 300,000 random splats at SH degrees 0 and 3 (the same per splat at 3,000,000): PLY
# 273 and 1,364 bytes, SPZ 248 / 782 (version 3) and 270 / 820 (version 4), compressed PLY 508 / 1,854,
# .splat 212, SOG 384 / 1,165 with 5 / 6 images of about one texel a splat (their 12 bytes a texel,
# `SOG_IMAGE_BYTES_PER_TEXEL`, counted apart); the figures below are those times 1.25, rounded up.
PEAK_BYTES_PER_SPLAT: Dict[str, Tuple[float, float]] = {
    "ply": (345, 31),
    "compressed_ply": (640, 38),
    "splat": (270, 0),
    "spz": (340, 16),
    "sog": (405, 22),
}
# A SOG image decoded: Pillow's image, its RGBA conversion and the NumPy copy, 4 bytes a texel each.
SOG_IMAGE_BYTES_PER_TEXEL = 12
# The peak per float of a reader without a measured figure: 4 x its float32 result.
_DECODE_PEAK_FACTOR = 4


def peak_bytes(fmt: str, count: int, degree: int) -> float:
    """The peak memory, in bytes, of reading `count` splats of SH degree `degree` (0..4) in format `fmt`."""
    fixed, per_float = PEAK_BYTES_PER_SPLAT[fmt]
    return float(count) * (fixed + per_float * 3 * (sh_coefficients(min(max(int(degree), 0), 4)) - 1))


def check_splat_count(
    path: Path, count: int, degree: int, what: str, fmt: Optional[str] = None, extra_bytes: float = 0.0
) -> None:
    """A MemoryBudgetError, before anything is decoded, when reading `count` splats of SH degree `degree` (a
    count read from a header) in format `fmt` (its measured peak, `PEAK_BYTES_PER_SPLAT`), plus
    `extra_bytes` (a SOG's decoded images), would not fit this machine's free memory."""
    if fmt is None:
        need = float(count) * (3 + 3 + 4 + 1 + 3 * sh_coefficients(min(int(degree), MAX_SH_DEGREE))) * 4
        need *= _DECODE_PEAK_FACTOR
    else:
        need = peak_bytes(fmt, count, degree)
    check_memory(
        need + float(extra_bytes),
        f"{path}: reading its {count:,} splats ({what}, SH degree {degree})",
        "convert a part of the scene, or read it on a machine with more memory",
    )


def read_splat_bytes(path: Path, what: str) -> bytes:
    """The bytes of `path`; an error naming the file (and `what` it should be) when it is no regular file (a
    FIFO would block forever), larger than the memory free to read it, or unreadable."""
    path = check_input_file(path, what)
    return read_input_file(path, what, lambda problem: SceneFormatError(path, problem))


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
