"""antimatter15 .splat: rows of 3 float32 position, 3 float32 linear scales, 4 uint8 RGBA (colour
SH_C0 f_dc + 0.5 and opacity, times 255, truncated), 4 uint8 quaternion w x y z (q / |q| * 128 + 128,
truncated). Reference: antimatter15/splat convert.py (writer) and main.js (reader).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from waldo_jax.errors import SceneFormatError, check_input_file
from waldo_jax.io import write_bytes
from waldo_jax.splats.formats.common import (
    SH_C0,
    check_splat_count,
    finish_splats,
    opacity_logits,
    read_splat_bytes,
    sigmoid,
    valid_rows,
)
from waldo_jax.splats.model import Splats


def importance_order(splats: Splats) -> np.ndarray:
    """The valid rows of `splats` by decreasing volume times opacity, as antimatter15's convert.py sorts
    them (viewers then stream the big opaque splats first)."""
    rows = np.flatnonzero(np.asarray(splats.valid, bool))
    log_scales = np.asarray(splats.log_scales, np.float32)[rows]
    logits = np.asarray(splats.logits, np.float32)[rows]
    with np.errstate(over="ignore"):
        key = -np.exp(log_scales.sum(-1)) / (1.0 + np.exp(-logits))
    return rows[np.argsort(key, kind="stable")]


def decode_dot_splat(path: Path):
    """(Splats, details line, extras) of an antimatter15 `.splat` file: 32-byte rows, SH degree 0."""
    raw = read_splat_bytes(path, ".splat file")
    if not raw or len(raw) % 32:
        raise SceneFormatError(path, f"not a .splat file: {len(raw)} bytes is no whole number of 32-byte splats")
    n = len(raw) // 32
    check_splat_count(path, n, 0, "a .splat file", fmt="splat")
    floats = np.frombuffer(raw, "<f4").reshape(n, 8)
    u8 = np.frombuffer(raw, np.uint8).reshape(n, 32)
    with np.errstate(invalid="ignore", divide="ignore"):
        bad = ~np.all(np.isfinite(floats[:, :6]), axis=1) | ~np.all(floats[:, 3:6] > 0, axis=1)
    if bad.any():
        raise SceneFormatError(
            path,
            f"not a .splat file: {int(bad.sum())} of {n} rows have a non-finite position or a scale that is "
            f"not positive (first: row {int(np.argmax(bad))})",
        )
    quats = (u8[:, 28:32].astype(np.float32) - 128.0) / 128.0
    zero = np.sum(quats * quats, -1) == 0
    quats[zero] = (1.0, 0.0, 0.0, 0.0)
    splats = finish_splats(
        path,
        "the .splat file",
        means=floats[:, :3],
        log_scales=np.log(floats[:, 3:6]),
        quats=quats,
        logits=opacity_logits(u8[:, 27] / 255.0),
        sh=((u8[:, 24:27] / 255.0 - 0.5) / SH_C0)[:, None, :],
    )
    return splats, f"antimatter15 .splat, {n} splats, SH degree 0", {}


def read_antimatter_splat(path: str | os.PathLike) -> Splats:
    """Reads an antimatter15 `.splat` file (no header; rows of 32 bytes, SH degree 0).

    The format has no magic bytes: `splat_format` takes a file for one only by its `.splat` suffix, a
    size that is a multiple of 32 and plausible values; this reader checks every row (finite positions,
    positive finite scales). Decoding follows the format's viewer: quaternion (u - 128) / 128 (an
    all-128 quaternion, which no writer makes, becomes the identity), colour u / 255, opacity u / 255.

    Raises:
      SceneFormatError: (naming the file) a size that is no multiple of 32, or an implausible row.
    """
    path = check_input_file(path, ".splat file")
    return decode_dot_splat(path)[0]


def write_antimatter_splat(path: str | os.PathLike, splats: Splats) -> Path:
    """Writes the valid rows of `splats` as an antimatter15 `.splat` file (SH beyond degree 0 is dropped).

    Quantised as the format's converter (antimatter15/splat convert.py) does: rows sorted by
    `importance_order`, RGBA and quaternion bytes truncated, not rounded.
    """
    path = Path(path)
    arrays = valid_rows(path, splats)
    order = np.argsort(np.argsort(np.flatnonzero(np.asarray(splats.valid, bool))))  # row -> position in arrays
    rows = order[importance_order(splats)]
    colour = np.concatenate([SH_C0 * arrays["sh"][:, 0, :] + 0.5, sigmoid(arrays["logits"])[:, None]], -1)
    quats = arrays["quats"] / np.linalg.norm(arrays["quats"], axis=-1, keepdims=True)
    table = np.zeros((len(rows), 32), np.uint8)
    table[:, :12] = arrays["means"][rows].astype("<f4").view(np.uint8)
    table[:, 12:24] = np.exp(arrays["log_scales"][rows]).astype("<f4").view(np.uint8)
    table[:, 24:28] = np.clip(colour[rows] * 255, 0, 255).astype(np.uint8)
    table[:, 28:32] = np.clip(quats[rows] * 128 + 128, 0, 255).astype(np.uint8)
    path.parent.mkdir(parents=True, exist_ok=True)
    write_bytes(path, table.tobytes())
    return path
