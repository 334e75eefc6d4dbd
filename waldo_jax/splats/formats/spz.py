"""Niantic .spz. Reference: nianticlabs/spz src/cc/load-spz.cc, splat-utils.h, splat-types.h,
extensions/cc/*.cc, README.md. Sections in this order: positions (24-bit fixed point, or float16 in
version 1), alphas (sigmoid * 255), colours (f_dc * 0.15 * 255 + 127.5), scales ((log + 10) * 16),
rotations (versions 1-2: x y z bytes; 3+: smallest three in 32 bits), SH (u - 128) / 128, coefficient
major (all channels of a coefficient together). Versions 1-3: a 16-byte header and the sections in one
gzip stream, extension records after them; version 4: a 32-byte plain header, extension records, a
table of (compressed, uncompressed) sizes and one zstd stream per non-empty section.
"""

from __future__ import annotations

import gzip
import io
import math
import os
import struct
import warnings
import zlib
from pathlib import Path
from typing import Optional, Tuple

import numpy as np

from waldo_jax.errors import SceneFormatError, WaldoError, check_input_file
from waldo_jax.io import write_bytes
from waldo_jax.splats.formats.common import (
    check_splat_count,
    finish_splats,
    opacity_logits,
    read_splat_bytes,
    round_half_away,
    sigmoid,
    to_uint8,
    valid_rows,
)
from waldo_jax.splats.model import MAX_SH_DEGREE, Splats, sh_coefficients

_NGSP = 0x5053474E
_SPZ_COLOUR_SCALE = np.float32(0.15)
_EXT_SAFE_ORBIT = 0xADBE0002
_EXT_COORDINATES = 0xADBE0003
_SPZ_MAX_DEGREE = 4
_SQRT1_2 = np.float32(0.707106781186547524401)
# Sign of each SH coefficient 1..15 under axis flips (sx, sy, sz): the parity of its basis function in
# x, y and z (waldo_jax.splats.sh; the same table as the reference's CoordinateConverter.flipSh).
_SH_PARITY = np.array(
    [
        [0, 1, 0], [0, 0, 1], [1, 0, 0],
        [1, 1, 0], [0, 1, 1], [0, 0, 0], [1, 0, 1], [0, 0, 0],
        [0, 1, 0], [1, 1, 1], [0, 1, 0], [0, 0, 1], [1, 0, 0], [0, 0, 1], [1, 0, 0],
    ]
)  # fmt: skip
_CS_NAMES = ("LDB", "RDB", "LUB", "RUB", "LDF", "RDF", "LUF", "RUF")


def spz_axis_flips(coordinate_system: int) -> Tuple[float, float, float]:
    """(sx, sy, sz): the axis signs that take SPZ's named coordinate system 1..8 (LDB, RDB, LUB, RUB, LDF,
    RDF, LUF, RUF) to a PLY's RDF (x right, y down, z forward). RUB (4) gives (1, -1, -1)."""
    bits = int(coordinate_system) - 1
    return (1.0 if bits & 1 else -1.0, -1.0 if bits & 2 else 1.0, 1.0 if bits & 4 else -1.0)


def flip_axes(means, quats_wxyz, sh, flips) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Means, quaternions and SH with axes negated by `flips` (sx, sy, sz), a reflection or rotation."""
    s = np.asarray(flips, np.float32)
    quat_sign = np.array([1.0, s[1] * s[2], s[0] * s[2], s[0] * s[1]], np.float32)
    k = sh.shape[1]
    coeff_sign = np.concatenate([[1.0], np.prod(np.where(_SH_PARITY[: k - 1] == 1, s, 1.0), axis=1)])
    return means * s, quats_wxyz * quat_sign, sh * coeff_sign[None, :, None].astype(np.float32)


def _smallest_three_decode(raw: np.ndarray) -> np.ndarray:
    """[N, 4] bytes of SPZ's 2 + 3 x 10 bit quaternions to [N, 4] quaternions x y z w."""
    comp = np.ascontiguousarray(raw, np.uint8).view("<u4").reshape(-1).astype(np.uint32)
    n = comp.shape[0]
    largest = (comp >> 30).astype(np.int64)
    # The lowest 10 bits hold the highest-numbered component that is not the largest.
    slots = np.array([[i for i in (3, 2, 1, 0) if i != skip] for skip in range(4)])[largest]  # [N, 3]
    q = np.zeros((n, 4), np.float32)
    rows = np.arange(n)
    for s in range(3):
        mag = ((comp >> (10 * s)) & 511).astype(np.float32)
        sign = np.where((comp >> (10 * s + 9)) & 1, -1.0, 1.0).astype(np.float32)
        q[rows, slots[:, s]] = _SQRT1_2 * mag / np.float32(511) * sign
    q[rows, largest] = np.sqrt(np.maximum(0.0, 1.0 - np.sum(q * q, -1)))
    return q


def _smallest_three_encode(quats_xyzw: np.ndarray) -> np.ndarray:
    """[N, 4] quaternions x y z w to [N, 4] bytes, as the reference's packQuaternionSmallestThree."""
    q = quats_xyzw.astype(np.float32)
    q = q / np.sqrt(np.sum(q * q, -1, keepdims=True))
    n = q.shape[0]
    largest = np.argmax(np.abs(q), -1)  # the first of equals, as the reference's strict >
    negate = q[np.arange(n), largest] < 0
    comp = largest.astype(np.uint32)
    for i in range(4):
        keep = largest != i
        negbit = ((q[:, i] < 0) ^ negate).astype(np.uint32)
        mag = np.floor(np.float32(511) * (np.abs(q[:, i]) / _SQRT1_2) + np.float32(0.5)).astype(np.uint32)
        comp = np.where(keep, (comp << 10) | (negbit << 9) | mag, comp)
    return comp.astype("<u4").view(np.uint8).reshape(n, 4)


def _spz_extensions(path: Path, block: bytes) -> dict:
    """The extension records [u32 type][u32 length][payload] of `block`: the two the reference knows."""
    found, pos = {}, 0
    while pos + 8 <= len(block):
        kind, length = struct.unpack_from("<II", block, pos)
        payload = block[pos + 8 : pos + 8 + length]
        if len(payload) < length:
            raise SceneFormatError(path, f"SPZ extension 0x{kind:08X} claims {length} bytes, {len(payload)} remain")
        if kind == _EXT_SAFE_ORBIT and length >= 12:
            lo, hi, radius = struct.unpack_from("<fff", payload)
            if all(math.isfinite(v) for v in (lo, hi, radius)) and lo <= hi and radius >= 0:
                found["safe_orbit"] = {"elevation_min": lo, "elevation_max": hi, "radius_min": radius}
            else:  # only described (`scene info`), never used: a record that cannot hold is left out, said
                warnings.warn(
                    f"{path}: its safe-orbit extension (elevation {lo:g} to {hi:g} rad, radius >= {radius:g}) "
                    "is no orbit; it is left out",
                    stacklevel=2,
                )
        elif kind == _EXT_COORDINATES and length >= 4:
            found["coordinate_system"] = struct.unpack_from("<I", payload)[0]
        else:
            found.setdefault("unknown_extensions", []).append(f"0x{kind:08X}")
        pos += 8 + length
    if pos != len(block):
        raise SceneFormatError(
            path, f"SPZ extension records end {len(block) - pos} bytes before their block (a count that disagrees?)"
        )
    return found


def _zstd_decompress(path: Path, data: bytes, size: int, what: str) -> bytes:
    """A zstd stream inflated in steps, at most `size` + 1 bytes: the size a frame's header states is not
    trusted (a frame claiming 1 TiB is refused, not allocated); any decoder error is the file's error."""
    try:
        import zstandard
    except ImportError:
        raise SceneFormatError(
            path, "an SPZ version 4 file (zstd streams): reading it needs the 'zstandard' package"
        ) from None
    parts, got = [], 0
    try:
        with zstandard.ZstdDecompressor().stream_reader(io.BytesIO(data), read_across_frames=True) as reader:
            while got <= size:
                part = reader.read(min(size + 1 - got, 1 << 24))
                if not part:
                    break
                parts.append(part)
                got += len(part)
    except Exception as e:  # noqa: BLE001 (a decoder's error on bad bytes, of whatever kind, is the file's)
        raise SceneFormatError(path, f"corrupt SPZ zstd stream ({what}: {type(e).__name__}: {e})") from None
    if got > size:
        raise SceneFormatError(path, f"SPZ {what} inflates past the {size} bytes its header's splats need")
    return b"".join(parts)


# Bytes a version 1-3 stream may hold after its sections (extension records: a few dozen in practice).
_MAX_TRAILING_BYTES = 2**20


def _section_sizes(version: int, n: int, degree: int) -> list:
    dim = sh_coefficients(degree) - 1
    return [n * (6 if version == 1 else 9), n, 3 * n, 3 * n, n * (4 if version >= 3 else 3), 3 * n * dim]


def _gunzip(path: Path, raw: bytes) -> bytes:
    """A gzipped SPZ stream inflated no further than its header's splats need (and their extension records):
    the header is read first, its count checked against the memory, then the rest inflated up to that size."""
    try:
        stream = zlib.decompressobj(wbits=31)
        head = stream.decompress(raw, 16)
        if len(head) == 16 and struct.unpack_from("<I", head)[0] == _NGSP:
            version, n, degree = struct.unpack_from("<IIB", head, 4)
            if 1 <= version <= 3 and 0 < n <= 2**31 - 1 and degree <= _SPZ_MAX_DEGREE:
                check_splat_count(path, n, degree, "an SPZ file", fmt="spz")
                limit = sum(_section_sizes(version, n, degree)) + _MAX_TRAILING_BYTES
                body = stream.decompress(stream.unconsumed_tail, limit)
                if not stream.eof and (stream.unconsumed_tail or len(stream.decompress(b"", 1))):
                    raise SceneFormatError(
                        path, f"the SPZ stream inflates past what its {n} splats need ({16 + limit} bytes)"
                    )
                if not stream.eof:
                    raise SceneFormatError(path, "corrupt SPZ gzip stream (it ends before its end marker: cut?)")
                if stream.unused_data:
                    raise SceneFormatError(
                        path, f"{len(stream.unused_data)} bytes follow the SPZ gzip stream (a damaged or joined file?)"
                    )
                return head + body
        return head + stream.decompress(stream.unconsumed_tail, 16)  # a header the caller refuses by name
    except zlib.error as e:
        raise SceneFormatError(path, f"corrupt SPZ gzip stream ({e})") from None


def _spz_sections(path: Path, raw: bytes):
    """(header fields, the six sections' bytes, extension records) of an SPZ file of any version."""
    if raw[:2] == b"\x1f\x8b":
        raw = _gunzip(path, raw)
    if len(raw) < 16 or struct.unpack_from("<I", raw)[0] != _NGSP:
        raise SceneFormatError(path, "not an SPZ file (no NGSP magic)")
    version, n, degree, frac, flags = struct.unpack_from("<IIBBB", raw, 4)
    if not 1 <= version <= 4:
        raise SceneFormatError(path, f"SPZ version {version} is not read (versions 1 to 4 are)")
    if n == 0 or n > 2**31 - 1:
        raise SceneFormatError(path, f"SPZ header claims {n} splats")
    if degree > _SPZ_MAX_DEGREE:
        raise SceneFormatError(path, f"SPZ SH degree {degree} (the format's are 0 to {_SPZ_MAX_DEGREE})")
    check_splat_count(path, n, degree, "an SPZ file", fmt="spz")
    sizes = _section_sizes(version, n, degree)
    header = {"version": version, "count": n, "degree": degree, "fractional_bits": frac, "flags": flags}
    if version < 4:
        need = 16 + sum(sizes)
        if len(raw) < need:
            raise SceneFormatError(path, f"truncated SPZ: {n} splats need {need} bytes, the stream holds {len(raw)}")
        if len(raw) > need and not flags & 2:
            raise SceneFormatError(
                path,
                f"the SPZ stream holds {len(raw) - need} bytes after the sections of its header's {n} splats "
                "(and no extensions flag): its count disagrees with its data",
            )
        bounds = np.cumsum([16] + sizes)
        sections = [raw[a:b] for a, b in zip(bounds[:-1], bounds[1:])]
        extensions = _spz_extensions(path, raw[need:]) if flags & 2 else {}
        return header, sections, extensions
    if len(raw) < 32:
        raise SceneFormatError(path, "truncated SPZ: the 32-byte header is cut")
    streams, toc = struct.unpack_from("<BI", raw, 15)
    wanted = [s for s in sizes if s]
    if streams != len(wanted) or toc < 32 or toc + 16 * streams > len(raw):
        raise SceneFormatError(
            path, f"SPZ header lists {streams} streams at byte {toc} (expected {len(wanted)} in {len(raw)} bytes)"
        )
    extensions = _spz_extensions(path, raw[32:toc]) if flags & 2 else {}
    pos, sections = toc + 16 * streams, []
    for i, size in enumerate(wanted):
        packed, unpacked = struct.unpack_from("<QQ", raw, toc + 16 * i)
        if unpacked != size or pos + packed > len(raw):
            raise SceneFormatError(
                path, f"SPZ stream {i} holds {unpacked} bytes in {packed} (expected {size}; the file is cut?)"
            )
        data = _zstd_decompress(path, raw[pos : pos + packed], size, f"stream {i}")
        if len(data) != size:
            raise SceneFormatError(path, f"SPZ stream {i} unpacks to {len(data)} bytes, expected {size}")
        sections.append(data)
        pos += packed
    if pos != len(raw):
        raise SceneFormatError(path, f"{len(raw) - pos} bytes follow the SPZ's {streams} streams (a damaged file?)")
    sections += [b""] * (6 - len(sections))  # SH is the only section that may be empty
    return header, sections, extensions


def decode_spz(path: Path):
    """(Splats, details line, extras) of an SPZ file, versions 1-4, axes turned to waldo_jax's RDF frame."""
    header, (pos, alpha, colour, scale, rot, sh), extensions = _spz_sections(path, read_splat_bytes(path, "SPZ file"))
    n, version, degree = header["count"], header["version"], header["degree"]
    if version == 1:
        means = np.frombuffer(pos, "<f2").reshape(n, 3).astype(np.float32)
    else:
        b = np.frombuffer(pos, np.uint8).reshape(n * 3, 3).astype(np.int32)
        fixed = b[:, 0] | (b[:, 1] << 8) | (b[:, 2] << 16)
        fixed = np.where(fixed & 0x800000, fixed - (1 << 24), fixed)
        means = (fixed.astype(np.float32) * np.float32(1.0 / (1 << header["fractional_bits"]))).reshape(n, 3)
    rot_bytes = np.frombuffer(rot, np.uint8)
    if version >= 3:
        xyzw = _smallest_three_decode(rot_bytes.reshape(n, 4))
    else:
        xyz = rot_bytes.reshape(n, 3).astype(np.float32) / np.float32(127.5) - np.float32(1.0)
        xyzw = np.concatenate([xyz, np.sqrt(np.maximum(0.0, 1.0 - np.sum(xyz * xyz, -1, keepdims=True)))], -1)
    dc = (np.frombuffer(colour, np.uint8).reshape(n, 3) / np.float32(255) - np.float32(0.5)) / _SPZ_COLOUR_SCALE
    dim = sh_coefficients(degree) - 1
    rest = (np.frombuffer(sh, np.uint8).reshape(n, dim, 3).astype(np.float32) - 128.0) / 128.0
    kept = min(dim, sh_coefficients(MAX_SH_DEGREE) - 1)  # degree 4 is beyond the renderer: dropped
    sh_all = np.concatenate([dc[:, None, :], rest[:, :kept]], 1).astype(np.float32)
    quats = xyzw[:, [3, 0, 1, 2]]
    stored = extensions.get("coordinate_system")
    if stored is not None and stored not in (0, 6):
        if not 1 <= stored <= 8:
            raise SceneFormatError(
                path, f"SPZ data stored in coordinate system {stored} (a 90-degree-rotated family): not read"
            )
        means, quats, sh_all = flip_axes(means, quats, sh_all, spz_axis_flips(stored))
    splats = finish_splats(
        path,
        "the SPZ file",
        means=means,
        log_scales=np.frombuffer(scale, np.uint8).reshape(n, 3) / np.float32(16) - np.float32(10),
        quats=quats,
        logits=opacity_logits(np.frombuffer(alpha, np.uint8) / 255.0),
        sh=sh_all,
    )
    antialiased = bool(header["flags"] & 1)
    extras = {"version": version, "antialiased": antialiased, **extensions}
    words = [f"SPZ version {version}", f"{n} splats", f"SH degree {degree}"]
    words += ["SH degree 4 dropped to 3"] if degree > MAX_SH_DEGREE else []
    words += ["antialiased (Mip-Splatting)"] if antialiased else []
    if stored:
        words.append(f"stored in {_CS_NAMES[stored - 1] if 1 <= stored <= 8 else stored}")
    if "safe_orbit" in extensions:
        o = extensions["safe_orbit"]
        words.append(
            f"safe orbit: elevation {o['elevation_min']:.3g} to {o['elevation_max']:.3g} rad, "
            f"radius >= {o['radius_min']:.3g}"
        )
    return splats, ", ".join(words), extras


def read_spz(path: str | os.PathLike) -> Splats:
    """Reads a Niantic `.spz` file, versions 1 to 4.

    Coordinates are taken as stored (see docs/splats.md: the reference tools store a PLY's own axes);
    a file whose `SPZ_ADOBE_coordinate_system` extension names another system of the R/L, U/D, F/B
    family is flipped to RDF (a rotated-family system is refused). SH of degree 4 is cut to degree 3.
    Use `read_splat_file` for the version, flags and the safe-orbit camera extension.

    Raises:
      SceneFormatError: (naming the file) no NGSP magic, an unknown version, a corrupt gzip or zstd
        stream, a size that disagrees with the header, non-finite decoded values.
    """
    path = check_input_file(path, "SPZ file")
    return decode_spz(path)[0]


def write_spz(
    path: str | os.PathLike,
    splats: Splats,
    version: int = 4,
    sh1_bits: int = 5,
    sh_rest_bits: int = 4,
    antialiased: bool = False,
    safe_orbit: Optional[Tuple[float, float, float]] = None,
) -> Path:
    """Writes the valid rows of `splats` as a Niantic `.spz` file, quantised as the reference's saveSpz.

    Positions 24-bit fixed point with 12 fractional bits (|x| < 2048), bytes rounded half away from
    zero and clamped, SH rounded to `sh1_bits` (degree 1) and `sh_rest_bits` (degrees 2, 3) of 8, no
    axis conversion (as the reference's own ply_to_spz).

    Args:
      path: the .spz file.
      splats: the splats.
      version: 2 or 3 (gzip) or 4 (zstd streams, the reference's default; needs `zstandard`).
      sh1_bits, sh_rest_bits: SH precision, 1 to 8 (the reference's defaults 5 and 4).
      antialiased: set the header's antialiased flag (splats trained with Mip-Splatting's filter).
      safe_orbit: (elevation_min, elevation_max, radius_min) to store as SPZ_ADOBE_safe_orbit_camera.
    """
    path = Path(path)
    if version not in (2, 3, 4):
        raise ValueError(f"SPZ version must be 2, 3 or 4, got {version!r}")
    if not (1 <= sh1_bits <= 8 and 1 <= sh_rest_bits <= 8):
        raise ValueError(f"SPZ SH bits must lie in 1..8, got {sh1_bits} and {sh_rest_bits}")
    a = valid_rows(path, splats)
    n, k = a["sh"].shape[:2]
    fixed = round_half_away(a["means"] * np.float32(1 << 12)).astype(np.int64)
    if np.any(np.abs(fixed) >= 1 << 23):
        raise WaldoError(f"{path}: SPZ positions must lie within +-2048 (24-bit fixed point); these reach further")
    positions = np.stack([fixed & 0xFF, (fixed >> 8) & 0xFF, (fixed >> 16) & 0xFF], -1).astype(np.uint8)
    quats = a["quats"][:, [1, 2, 3, 0]]  # x y z w
    if version >= 3:
        rotations = _smallest_three_encode(quats)
    else:
        unit = quats / np.sqrt(np.sum(quats * quats, -1, keepdims=True))
        unit = unit * np.where(unit[:, 3:] < 0, np.float32(-127.5), np.float32(127.5)) + np.float32(127.5)
        rotations = to_uint8(unit[:, :3])
    rest = a["sh"][:, 1:, :]
    q = (round_half_away(rest * np.float32(128)) + 128).astype(np.int64)
    bucket = np.where(np.arange(k - 1) < 3, 1 << (8 - sh1_bits), 1 << (8 - sh_rest_bits))[None, :, None]
    q = np.clip(np.trunc((q + bucket // 2) / bucket).astype(np.int64) * bucket, 0, 255).astype(np.uint8)
    sections = [
        positions.tobytes(),
        to_uint8(sigmoid(a["logits"]) * np.float32(255)).tobytes(),
        to_uint8(a["sh"][:, 0, :] * (_SPZ_COLOUR_SCALE * np.float32(255)) + np.float32(127.5)).tobytes(),
        to_uint8((a["log_scales"] + np.float32(10)) * np.float32(16)).tobytes(),
        rotations.tobytes(),
        q.tobytes(),
    ]
    extensions = b""
    if safe_orbit is not None:
        extensions = struct.pack("<II3f", _EXT_SAFE_ORBIT, 12, *(float(v) for v in safe_orbit))
    flags = (1 if antialiased else 0) | (2 if extensions else 0)
    degree = splats.sh_degree
    if version < 4:
        body = struct.pack("<IIIBBBB", _NGSP, version, n, degree, 12, flags, 0) + b"".join(sections) + extensions
        data = gzip.compress(body, compresslevel=6, mtime=0)
    else:
        import zstandard

        compressor = zstandard.ZstdCompressor(level=12)
        streams = [compressor.compress(s) for s in sections if s]
        toc = 32 + len(extensions)
        header = struct.pack("<IIIBBBBI12x", _NGSP, version, n, degree, 12, flags, len(streams), toc)
        table = b"".join(struct.pack("<QQ", len(c), len(s)) for c, s in zip(streams, [s for s in sections if s]))
        data = header + extensions + table + b"".join(streams)
    path.parent.mkdir(parents=True, exist_ok=True)
    write_bytes(path, data)
    return path
