"""Compressed PLY (PlayCanvas / SuperSplat; gsplat's ply_compressed). Reference: playcanvas/splat-transform
src/lib/readers/decompress-ply.ts, src/lib/writers/write-compressed-ply.ts, compressed-chunk.ts;
nerfstudio-project/gsplat gsplat/exporter.py. Splats in Morton order, chunks of 256: per chunk the
min/max of x y z, of the log-scales and (optionally) of the colours SH_C0 f_dc + 0.5; per splat 4
uint32: position and scale 11-10-11 bits normalised in the chunk's range, rotation 2 + 3 x 10 bits
(the largest component's index among rot_0..3, then the other three times sqrt(1/2) + 1/2), colour
8-8-8-8 (r g b in the chunk's range, sigmoid opacity); SH rest as bytes of (v / 8 + 1/2) * 256.
"""

from __future__ import annotations

import math
import os
from pathlib import Path

import numpy as np

from waldo_jax.errors import SceneFormatError, check_input_file
from waldo_jax.io import write_bytes
from waldo_jax.scenes.ply import PlyHeader, parse_ply_header
from waldo_jax.splats.formats.common import (
    SH_C0,
    check_splat_count,
    finish_splats,
    opacity_logits,
    read_splat_bytes,
    rest_from_channel_major,
    sh_degree_of_rest,
    sigmoid,
    valid_rows,
)
from waldo_jax.splats.model import Splats

_CHUNK = 256
CHUNK_BOUNDS = ["min_x", "min_y", "min_z", "max_x", "max_y", "max_z"]
CHUNK_BOUNDS += ["min_scale_x", "min_scale_y", "min_scale_z", "max_scale_x", "max_scale_y", "max_scale_z"]
CHUNK_COLOURS = ["min_r", "min_g", "min_b", "max_r", "max_g", "max_b"]
PACKED = ["packed_position", "packed_rotation", "packed_scale", "packed_color"]
_TRIPLE = (("x", 21, 11), ("y", 11, 10), ("z", 0, 11))  # axis, shift, bits of an 11-10-11 field


def _part1by2(v: np.ndarray) -> np.ndarray:
    v = v.astype(np.uint32) & 0x3FF
    v = (v ^ (v << 16)) & 0xFF0000FF
    v = (v ^ (v << 8)) & 0x0300F00F
    v = (v ^ (v << 4)) & 0x030C30C3
    return (v ^ (v << 2)) & 0x09249249


def morton_order(means: np.ndarray) -> np.ndarray:
    """Indices of `means` [N, 3] in 30-bit Morton order, as splat-transform sorts before chunking (a run
    of more than 256 equal codes is sorted again within its own bounds)."""
    means = np.asarray(means, np.float32)
    order = np.arange(len(means))

    def sort(indices: np.ndarray) -> np.ndarray:
        points = means[indices].astype(np.float64)
        low, extent = points.min(0), np.ptp(points, 0)
        if not np.all(np.isfinite(extent)) or not np.any(extent):
            return indices
        scale = np.where(extent == 0, 0.0, 1024.0 / np.where(extent == 0, 1.0, extent))
        cells = np.minimum(1023, (points - low) * scale).astype(np.uint32)
        codes = (_part1by2(cells[:, 2]) << 2) + (_part1by2(cells[:, 1]) << 1) + _part1by2(cells[:, 0])
        by_code = np.argsort(codes, kind="stable")
        indices, codes = indices[by_code], codes[by_code]
        starts = np.flatnonzero(np.diff(codes, prepend=codes[0] - 1) != 0)
        ends = np.append(starts[1:], len(codes))
        for a, b in zip(starts, ends):
            if b - a > _CHUNK:
                indices[a:b] = sort(indices[a:b])
        return indices

    return sort(order) if len(order) else order


def _unorm(value: np.ndarray, shift: int, bits: int) -> np.ndarray:
    top = (1 << bits) - 1
    return ((value >> shift) & top).astype(np.float64) / top


def _pack_unorm(value: np.ndarray, bits: int) -> np.ndarray:
    top = (1 << bits) - 1
    return np.clip(np.floor(value * top + 0.5), 0, top).astype(np.uint32)


def _lerp(low, high, t):
    return low * (1.0 - t) + high * t


def decode_compressed_ply(path: Path):
    """(Splats, details line, extras) of a PlayCanvas / SuperSplat compressed PLY (see the module's layout)."""
    raw = read_splat_bytes(path, "compressed PLY")
    header: PlyHeader = parse_ply_header(raw, path)
    chunk, vertex, sh = header.element("chunk"), header.element("vertex"), header.element("sh")
    if header.format != "binary_little_endian":
        raise SceneFormatError(path, f"a compressed PLY must be binary_little_endian, not {header.format}")
    if chunk is None or vertex is None:
        raise SceneFormatError(path, "a compressed splat PLY needs a 'chunk' and a 'vertex' element")
    ctypes, vtypes = dict(chunk.properties), dict(vertex.properties)
    has_colours = all(k in ctypes for k in CHUNK_COLOURS)
    missing = [k for k in CHUNK_BOUNDS if ctypes.get(k) not in ("float", "float32")]
    missing += [k for k in PACKED if vtypes.get(k) not in ("uint", "uint32")]
    if missing:
        raise SceneFormatError(
            path, f"compressed PLY: missing or mistyped properties {', '.join(missing[:4])} (float chunk bounds, "
            "uint packed_* vertex properties)"
        )  # fmt: skip
    n = vertex.count
    if n == 0:
        raise SceneFormatError(path, "no splats (element vertex 0)")
    if chunk.count != -(-n // _CHUNK):
        raise SceneFormatError(path, f"{n} splats need {-(-n // _CHUNK)} chunks of 256, the file has {chunk.count}")
    rest_names = [p for p, _ in sh.properties] if sh is not None else []
    degree = sh_degree_of_rest(path, len(rest_names), "sh properties")
    if sh is not None and (sh.count != n or any(t not in ("uchar", "uint8") for _, t in sh.properties)):
        raise SceneFormatError(path, f"the 'sh' element must hold {n} rows of uchar f_rest_*")
    try:
        tables = {}
        for element in (chunk, vertex) + ((sh,) if sh is not None else ()):
            tables[element.name] = np.frombuffer(
                raw, element.dtype("<"), count=element.count, offset=header.offset_of(element.name)
            )
    except (ValueError, KeyError) as e:
        raise SceneFormatError(path, f"truncated or malformed compressed PLY data ({e})") from None
    end = header.body_start + sum(e.count * e.dtype("<").itemsize for e in header.elements if not e.has_lists)
    if len(raw) != end or any(e.has_lists for e in header.elements):
        raise SceneFormatError(
            path,
            f"its elements ({', '.join(f'{e.name} {e.count}' for e in header.elements)}) need "
            f"{end - header.body_start} bytes of data, the file holds {len(raw) - header.body_start}: "
            "the header's counts disagree with the data",
        )
    check_splat_count(path, n, degree, "a compressed PLY", fmt="compressed_ply")
    c, v = tables["chunk"], tables["vertex"]
    of = np.arange(n) // _CHUNK
    bounds = {k: c[k].astype(np.float64)[of] for k in CHUNK_BOUNDS + (CHUNK_COLOURS if has_colours else [])}
    pos, scl = v["packed_position"], v["packed_scale"]
    means = np.stack([_lerp(bounds[f"min_{a}"], bounds[f"max_{a}"], _unorm(pos, s, b)) for a, s, b in _TRIPLE], -1)
    log_scales = np.stack(
        [_lerp(bounds[f"min_scale_{a}"], bounds[f"max_scale_{a}"], _unorm(scl, s, b)) for a, s, b in _TRIPLE], -1
    )
    col = v["packed_color"]
    rgb = np.stack([_unorm(col, s, 8) for s in (24, 16, 8)], -1)
    if has_colours:
        rgb = np.stack([_lerp(bounds[f"min_{ch}"], bounds[f"max_{ch}"], rgb[:, i]) for i, ch in enumerate("rgb")], -1)
    rot = v["packed_rotation"]
    abc = np.stack([(_unorm(rot, s, 10) - 0.5) * math.sqrt(2.0) for s in (20, 10, 0)], -1)
    largest = (rot >> 30).astype(np.int64)
    others = np.array([[i for i in range(4) if i != skip] for skip in range(4)])[largest]
    quats = np.zeros((n, 4))
    quats[np.arange(n)[:, None], others] = abc
    quats[np.arange(n), largest] = np.sqrt(np.maximum(0.0, 1.0 - np.sum(abc * abc, -1)))
    sh_all = ((rgb - 0.5) / SH_C0)[:, None, :]
    if degree:
        u = np.stack([tables["sh"][name] for name in rest_names], -1)
        unit = np.where(u == 0, 0.0, np.where(u == 255, 1.0, (u + 0.5) / 256.0))
        sh_all = np.concatenate([sh_all, rest_from_channel_major((unit - 0.5) * 8.0, n)], 1)
    splats = finish_splats(
        path,
        "the compressed PLY",
        means=means,
        log_scales=log_scales,
        quats=quats,
        logits=opacity_logits(_unorm(col, 0, 8)),
        sh=sh_all,
    )
    return splats, f"compressed PLY, {n} splats in {chunk.count} chunks, SH degree {degree}", {}


def read_compressed_ply(path: str | os.PathLike) -> Splats:
    """Reads a compressed splat PLY (PlayCanvas SuperSplat / splat-transform, gsplat's `ply_compressed`).

    Chunk colour bounds are optional (older SuperSplat files: the colour bytes are then the colours
    themselves); an `sh` element of 0, 9, 24 or 45 uchar `f_rest_*` gives the SH degree.

    Raises:
      SceneFormatError: (naming the file) a missing or mistyped property, a chunk count that does not
        match ceil(N / 256), an SH count of no degree, data shorter than the header promises.
    """
    path = check_input_file(path, "compressed PLY")
    return decode_compressed_ply(path)[0]


def write_compressed_ply(path: str | os.PathLike, splats: Splats) -> Path:
    """Writes the valid rows of `splats` as a compressed PLY, as splat-transform's writer does.

    Rows in `morton_order`; per chunk of 256 the bounds of positions, log-scales (clamped to +-20) and
    colours (float32 SH_C0 f_dc + 0.5); values at or below a chunk's minimum pack to 0, at or above its
    maximum to 1, and to 0 in a range under 1e-5; fields rounded (floor(v (2^bits - 1) + 1/2)); SH bytes
    trunc((v / 8 + 1/2) 256) clamped to 0..255.
    """
    path = Path(path)
    a = valid_rows(path, splats)
    order = morton_order(a["means"])
    means, log_scales = a["means"][order].astype(np.float64), a["log_scales"][order].astype(np.float64)
    colours = (a["sh"][order, 0, :] * np.float32(SH_C0) + np.float32(0.5)).astype(np.float32).astype(np.float64)
    quats = a["quats"][order].astype(np.float64)
    n, k = a["sh"].shape[:2]
    chunks = -(-n // _CHUNK)
    pad = chunks * _CHUNK - n  # the last chunk repeats its last splat, which leaves its bounds as they are

    def chunked(x):
        return np.concatenate([x, np.repeat(x[-1:], pad, 0)]).reshape(chunks, _CHUNK, -1)

    def normalise(x):
        lo, hi = x.min(1, keepdims=True), x.max(1, keepdims=True)
        return lo, hi, normalise_in(x, lo, hi)

    def normalise_in(x, lo, hi):
        t = np.where(hi - lo < 1e-5, 0.0, (x - lo) / np.where(hi - lo == 0, 1.0, hi - lo))
        return np.where(x <= lo, 0.0, np.where(x >= hi, 1.0, t))

    p_lo, p_hi, p = normalise(chunked(means))
    s = chunked(log_scales)
    s_lo, s_hi = np.clip(s.min(1, keepdims=True), -20, 20), np.clip(s.max(1, keepdims=True), -20, 20)
    s = normalise_in(s, s_lo, s_hi)
    c_lo, c_hi, c = normalise(chunked(colours))
    p, s, c = (x.reshape(-1, 3)[:n] for x in (p, s, c))

    def pack111011(t):
        return (_pack_unorm(t[:, 0], 11) << 21) | (_pack_unorm(t[:, 1], 10) << 11) | _pack_unorm(t[:, 2], 11)

    unit = quats / np.linalg.norm(quats, axis=-1, keepdims=True)
    largest = np.argmax(np.abs(unit), -1)
    unit = unit * np.where(unit[np.arange(n), largest] < 0, -1.0, 1.0)[:, None]
    rotation = largest.astype(np.uint32)
    for i in range(4):
        packed = _pack_unorm(unit[:, i] * (math.sqrt(2.0) * 0.5) + 0.5, 10)
        rotation = np.where(largest != i, (rotation << 10) | packed, rotation)
    opacity = sigmoid(a["logits"][order]).astype(np.float64)
    colour = (_pack_unorm(c[:, 0], 8) << 24) | (_pack_unorm(c[:, 1], 8) << 16) | (_pack_unorm(c[:, 2], 8) << 8)
    colour |= _pack_unorm(opacity, 8)
    vertex = np.stack([pack111011(p), rotation.astype(np.uint32), pack111011(s), colour], -1).astype("<u4")
    bounds = np.concatenate([p_lo, p_hi, s_lo, s_hi, c_lo, c_hi], -1).reshape(chunks, 18).astype("<f4")
    rest = a["sh"][order, 1:, :].transpose(0, 2, 1).reshape(n, 3 * (k - 1)).astype(np.float64)
    sh_bytes = np.clip(np.trunc((rest / 8 + 0.5) * 256), 0, 255).astype(np.uint8)
    lines = ["ply", "format binary_little_endian 1.0", "comment written by waldo_jax", f"element chunk {chunks}"]
    lines += [f"property float {p}" for p in CHUNK_BOUNDS + CHUNK_COLOURS]
    lines += [f"element vertex {n}"] + [f"property uint {p}" for p in PACKED]
    if k > 1:
        lines += [f"element sh {n}"] + [f"property uchar f_rest_{i}" for i in range(3 * (k - 1))]
    data = ("\n".join(lines) + "\nend_header\n").encode("ascii") + bounds.tobytes() + vertex.tobytes()
    path.parent.mkdir(parents=True, exist_ok=True)
    write_bytes(path, data + (sh_bytes.tobytes() if k > 1 else b""))
    return path
