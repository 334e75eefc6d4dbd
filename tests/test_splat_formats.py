"""The splat file formats besides the reference PLY (waldo_jax.splats.formats): hand-built bytes decoded to
hand-computed values, writer round trips within each format's quantisation, renders that agree, the real
donut converted to each format, and one clear error per broken file."""

from __future__ import annotations

import gzip
import io
import json
import math
import os
import struct
import zipfile

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import zstandard
from PIL import Image

from conftest import _missing
from waldo_jax import paths
from waldo_jax.cameras import look_at
from waldo_jax.errors import MemoryBudgetError, SceneFormatError, WaldoError
from waldo_jax.pipeline.splat_sources import is_splat_spec
from waldo_jax.splats import formats as F
from waldo_jax.splats.io import SH_C0, load_splat_model, read_splat_ply, write_splat_ply
from waldo_jax.splats.model import make_splats
from waldo_jax.splats.render import SplatRenderConfig, render_splats
from waldo_jax.splats.sh import sh_basis
from waldo_jax.types import Intrinsics

SQRT1_2 = math.sqrt(0.5)


def _logit(p):
    return math.log(p / (1 - p))


def _random_splats(n: int, degree: int, seed: int = 0, spread: float = 3.0):
    rng = np.random.default_rng(seed)
    k = (degree + 1) ** 2
    return make_splats(
        means=rng.uniform(-spread, spread, (n, 3)),
        log_scales=rng.uniform(-6.0, 0.0, (n, 3)),
        quats=rng.normal(size=(n, 4)),
        logits=rng.normal(size=n) * 3,
        sh=np.concatenate([rng.normal(size=(n, 1, 3)), rng.normal(size=(n, k - 1, 3)) * 0.3], 1),
    )


def _arrays(splats, rows=None):
    a = {k: np.asarray(getattr(splats, k), np.float64) for k in ("means", "log_scales", "quats", "logits", "sh")}
    a["quats"] /= np.linalg.norm(a["quats"], axis=-1, keepdims=True)
    a["opacity"] = 1 / (1 + np.exp(-a.pop("logits")))
    return a if rows is None else {k: v[rows] for k, v in a.items()}


def _quat_error(a, b):
    """Largest difference of unit quaternions up to sign (q and -q are one rotation)."""
    return float(np.max(np.minimum(np.abs(a - b).max(-1), np.abs(a + b).max(-1))))


def _within(decoded, reference, tol):
    """Each field of `decoded` within `tol[field]` of `reference` (absolute)."""
    for key, bound in tol.items():
        error = _quat_error(decoded[key], reference[key]) if key == "quats" else np.abs(decoded[key] - reference[key])
        assert np.max(error) <= bound, (key, float(np.max(error)), bound)


# ---------------------------------------------------------------------------------------------
# Hand-built files.


def test_dot_splat_row_decodes_to_hand_computed_values(tmp_path):
    row = struct.pack("<6f", 1.0, 2.0, -3.0, 0.5, 1.0, 2.0) + bytes([255, 128, 0, 191, 192, 128, 64, 128])
    path = tmp_path / "one.splat"
    path.write_bytes(row)
    assert F.splat_format(path) == "splat"
    s = F.read_antimatter_splat(path)
    np.testing.assert_allclose(s.means[0], [1, 2, -3])
    np.testing.assert_allclose(s.log_scales[0], [math.log(0.5), 0.0, math.log(2.0)], atol=1e-7)
    np.testing.assert_allclose(s.sh[0, 0], [(1 - 0.5) / SH_C0, (128 / 255 - 0.5) / SH_C0, -0.5 / SH_C0], rtol=1e-6)
    np.testing.assert_allclose(s.logits[0], _logit(191 / 255), rtol=1e-6)
    np.testing.assert_allclose(s.quats[0], [0.5, 0.0, -0.5, 0.0])  # (u - 128) / 128, w first
    assert s.sh_degree == 0


def _spz_legacy_body(version, sections, degree=1, flags=0, extensions=b"", count=1, frac=12):
    return struct.pack("<IIIBBBB", 0x5053474E, version, count, degree, frac, flags, 0) + sections + extensions


# One splat of degree 1: x = 4096 / 2^12 = 1, y = -2048 / 2^12 = -0.5, z = 3 / 2^12.
_POSITION = bytes([0x00, 0x10, 0x00, 0x00, 0xF8, 0xFF, 0x03, 0x00, 0x00])
_ALPHA, _COLOUR, _SCALE = bytes([128]), bytes([0, 255, 128]), bytes([160, 0, 255])
_SH = bytes([0, 128, 255, 64, 192, 128, 128, 128, 1])  # coefficient-major: (r, g, b) of coefficient 1, 2, 3
# Smallest three: largest w (3); x = 511 -> +sqrt(1/2); y = 0; z = sign bit, 0 -> -0.
_ROT_V3 = struct.pack("<I", (3 << 30) | (511 << 20) | (0 << 10) | (1 << 9))
_ROT_V2 = bytes([255, 128, 0])  # x y z = u / 127.5 - 1


def _check_spz_splat(s, quat):
    np.testing.assert_allclose(s.means[0], [1.0, -0.5, 3 / 4096])
    np.testing.assert_allclose(s.log_scales[0], [0.0, -10.0, 255 / 16 - 10])
    np.testing.assert_allclose(s.logits[0], _logit(128 / 255), rtol=1e-5)
    np.testing.assert_allclose(s.sh[0, 0], [-0.5 / 0.15, (1 - 0.5) / 0.15, (128 / 255 - 0.5) / 0.15], atol=1e-6)
    np.testing.assert_allclose(s.sh[0, 1:], [[-1, 0, 127 / 128], [-0.5, 0.5, 0], [0, 0, -127 / 128]])
    np.testing.assert_allclose(s.quats[0], quat, atol=1e-6)


def test_spz_versions_decode_to_hand_computed_values(tmp_path):
    sections = _POSITION + _ALPHA + _COLOUR + _SCALE
    v2_quat = [0.0, 1.0, 128 / 127.5 - 1, -1.0]  # x y z = u / 127.5 - 1; |xyz| > 1, so w = 0
    cases = {
        "v3_gzip": gzip.compress(_spz_legacy_body(3, sections + _ROT_V3 + _SH)),
        "v3_raw": _spz_legacy_body(3, sections + _ROT_V3 + _SH),
        "v2_gzip": gzip.compress(_spz_legacy_body(2, sections + _ROT_V2 + _SH)),
    }
    for name, data in cases.items():
        path = tmp_path / f"{name}.spz"
        path.write_bytes(data)
        assert F.splat_format(path) == "spz"
        _check_spz_splat(F.read_spz(path), [SQRT1_2, SQRT1_2, 0, 0] if "v3" in name else v2_quat)
    # Version 1: float16 positions, x y z rotation bytes.
    half = np.array([1.5, -0.25, 2.0], "<f2").tobytes()
    path = tmp_path / "v1.spz"
    path.write_bytes(gzip.compress(_spz_legacy_body(1, half + _ALPHA + _COLOUR + _SCALE + _ROT_V2 + _SH)))
    np.testing.assert_allclose(F.read_spz(path).means[0], [1.5, -0.25, 2.0])


def test_spz_v4_container_and_safe_orbit_extension(tmp_path):
    streams = [_POSITION, _ALPHA, _COLOUR, _SCALE, _ROT_V3, _SH]
    packed = [zstandard.ZstdCompressor().compress(s) for s in streams]
    orbit = struct.pack("<II3f", 0xADBE0002, 12, -0.25, 0.75, 2.5) + struct.pack("<II", 0x12340001, 2) + b"xy"
    toc = 32 + len(orbit)
    header = struct.pack("<IIIBBBBI12x", 0x5053474E, 4, 1, 1, 12, 0x3, 6, toc)
    table = b"".join(struct.pack("<QQ", len(p), len(s)) for p, s in zip(packed, streams))
    path = tmp_path / "v4.spz"
    path.write_bytes(header + orbit + table + b"".join(packed))
    read = F.read_splat_file(path)
    _check_spz_splat(read.splats, [SQRT1_2, SQRT1_2, 0, 0])
    assert read.extras["antialiased"] and read.extras["version"] == 4
    assert read.extras["safe_orbit"] == {"elevation_min": -0.25, "elevation_max": 0.75, "radius_min": 2.5}
    assert read.extras["unknown_extensions"] == ["0x12340001"]
    assert "safe orbit: elevation -0.25 to 0.75 rad, radius >= 2.5" in load_splat_model(path).source
    # A safe orbit that is none (NaN, an infinite elevation, a negative radius) is left out with a warning:
    # it had been printed as "elevation nan to inf rad, radius >= -1".
    bad = struct.pack("<II3f", 0xADBE0002, 12, math.nan, math.inf, -1.0)
    path.write_bytes(
        struct.pack("<IIIBBBBI12x", 0x5053474E, 4, 1, 1, 12, 0x3, 6, 32 + len(bad)) + bad + table + b"".join(packed)
    )
    with pytest.warns(
        UserWarning, match=r"safe-orbit extension \(elevation nan to inf rad, radius >= -1\) is no orbit"
    ):
        read = F.read_splat_file(path)
    assert "safe_orbit" not in read.extras


def test_compressed_ply_decodes_to_hand_computed_values(tmp_path):
    bounds = [0, 0, 0, 2, 4, 8, -2, -2, -2, 0, 0, 0, 0, 0.5, 0, 1, 1, 1]
    position = (2047 << 21) | (0 << 11) | 1023
    rotation = (0 << 30) | (1023 << 20) | (511 << 10) | 0  # largest rot_0 (w)
    colour = (255 << 24) | (0 << 16) | (51 << 8) | 255
    scale = (0 << 21) | (1023 << 11) | 2047
    lines = ["ply", "format binary_little_endian 1.0", "element chunk 1"]
    lines += [f"property float {p}" for p in F.CHUNK_BOUNDS + F.CHUNK_COLOURS]
    lines += ["element vertex 1"] + [f"property uint {p}" for p in F.PACKED]
    lines += ["element sh 1"] + [f"property uchar f_rest_{i}" for i in range(9)]
    data = ("\n".join(lines) + "\nend_header\n").encode() + struct.pack("<18f", *bounds)
    data += struct.pack("<4I", position, rotation, scale, colour) + bytes([0, 255, 128, 0, 0, 0, 0, 0, 64])
    path = tmp_path / "hand.ply"
    path.write_bytes(data)
    assert F.splat_format(path) == "compressed_ply"
    s = F.read_compressed_ply(path)
    np.testing.assert_allclose(s.means[0], [2.0, 0.0, 8 * 1023 / 2047], rtol=1e-6)
    np.testing.assert_allclose(s.log_scales[0], [-2.0, 0.0, 0.0], atol=1e-6)
    b, c = (511 / 1023 - 0.5) * math.sqrt(2), -0.5 * math.sqrt(2)
    a = 0.5 * math.sqrt(2)
    np.testing.assert_allclose(s.quats[0], [math.sqrt(max(0, 1 - a * a - b * b - c * c)), a, b, c], atol=1e-6)
    np.testing.assert_allclose(s.sh[0, 0], [0.5 / SH_C0, (0.5 - 0.5) / SH_C0, (0.2 - 0.5) / SH_C0], atol=1e-6)
    np.testing.assert_allclose(s.logits[0], _logit(1 - 0.25 / 255), rtol=1e-6)  # byte 255: its interval's middle
    # f_rest channel-major: red coefficients 1..3 = bytes 0, 255, 128 -> -4, 4, (128.5 / 256 - 0.5) * 8.
    np.testing.assert_allclose(s.sh[0, 1:, 0], [-4.0, 4.0, (128.5 / 256 - 0.5) * 8], atol=1e-6)
    np.testing.assert_allclose(s.sh[0, 3, 2], (64.5 / 256 - 0.5) * 8, atol=1e-6)


def _webp(rgba) -> bytes:
    buffer = io.BytesIO()
    Image.fromarray(np.asarray(rgba, np.uint8), "RGBA").save(buffer, "WEBP", lossless=True, exact=True)
    return buffer.getvalue()


def _sog_files(version=2, count=2):
    """A two-splat SOG: (meta, {name: bytes}) with hand-picked bytes."""
    lo = [[[0, 255, 10, 255], [255, 255, 0, 255]]]
    hi = [[[0, 255, 20, 255], [128, 0, 0, 255]]]
    quats = [[[255, 0, 128, 252], [128, 128, 128, 7]]]  # largest w; an invalid tag -> identity
    scales = [[[0, 1, 2, 255], [255, 3, 4, 255]]]
    sh0 = [[[0, 1, 2, 255], [3, 4, 5, 0]]]
    labels = [[[1, 0, 0, 255], [0, 0, 0, 255]]]
    centroids = np.zeros((1, 192, 4), np.uint8)
    centroids[0, 3:6, :3] = [[1, 2, 3], [4, 5, 6], [7, 8, 9]]  # label 1, coefficients 1..3
    files = {
        "means_l.webp": _webp(lo),
        "means_u.webp": _webp(hi),
        "quats.webp": _webp(quats),
        "scales.webp": _webp(scales),
        "sh0.webp": _webp(sh0),
        "shN_labels.webp": _webp(labels),
        "shN_centroids.webp": _webp(centroids),
    }
    means = {"mins": [-1.0, 0.0, 0.5], "maxs": [1.0, 2.0, 0.5], "files": ["means_l.webp", "means_u.webp"]}
    shn_files = ["shN_centroids.webp", "shN_labels.webp"]
    if version == 2:
        meta = {
            "version": 2,
            "count": count,
            "means": means,
            "scales": {"codebook": list(np.linspace(-8, 0, 256)), "files": ["scales.webp"]},
            "quats": {"files": ["quats.webp"]},
            "sh0": {"codebook": list(np.linspace(-2, 2, 256)), "files": ["sh0.webp"]},
            "shN": {"count": 2, "bands": 1, "codebook": list(np.linspace(-1, 1, 256)), "files": shn_files},
        }
    else:
        meta = {
            "means": {**means, "shape": [count, 3]},
            "scales": {"mins": [-8, -8, -8], "maxs": [0, 0, 0], "files": ["scales.webp"]},
            "quats": {"files": ["quats.webp"]},
            "sh0": {"mins": [-2, -2, -2, -5], "maxs": [2, 2, 2, 5], "files": ["sh0.webp"]},
            "shN": {"mins": -1.0, "maxs": 1.0, "files": shn_files},
        }
    return meta, files


def _write_sog(folder, meta, files, bundle):
    folder.mkdir(parents=True, exist_ok=True)
    if bundle:
        path = folder / "scene.sog"
        with zipfile.ZipFile(path, "w") as z:
            z.writestr("meta.json", json.dumps(meta))
            for name, data in files.items():
                z.writestr(name, data)
        return path
    for name, data in files.items():
        (folder / name).write_bytes(data)
    (folder / "meta.json").write_text(json.dumps(meta))
    return folder / "meta.json"


def test_sog_images_that_rgba_conversion_would_change_are_refused(tmp_path):
    """A lossy WebP where the positions' 16 bits are stored, or a 16-bit PNG (clipped by the conversion to
    RGBA8), had been read silently; each is refused naming the image. A meta.json that lacks one section is
    read as a SOG, so that the section it lacks is named (it had been "a JSON file without 'frames'")."""
    meta, files = _sog_files()
    buffer = io.BytesIO()
    Image.fromarray(np.zeros((1, 2, 4), np.uint8), "RGBA").save(buffer, "WEBP", quality=10)
    lossy = _write_sog(tmp_path / "lossy", meta, {**files, "means_l.webp": buffer.getvalue()}, bundle=True)
    with pytest.raises(SceneFormatError, match="'means_l.webp' is a lossy WebP: the splats' positions need it"):
        F.read_sog(lossy)
    buffer = io.BytesIO()
    Image.fromarray(np.full((1, 2), 40000, np.uint16)).save(buffer, "PNG")
    deep = _write_sog(tmp_path / "deep", meta, {**files, "scales.webp": buffer.getvalue()}, bundle=True)
    with pytest.raises(SceneFormatError, match=r"'scales.webp' is of mode I;16 \(not 8 bits a channel\)"):
        F.read_sog(deep)
    partial = _write_sog(tmp_path / "partial", {k: v for k, v in meta.items() if k != "sh0"}, files, bundle=False)
    assert F.splat_format(partial) == "sog"
    with pytest.raises(SceneFormatError, match="'sh0' must be an object with a 'files' list"):
        F.read_splat_file(partial)


def _inverse_log(v):
    return math.copysign(math.exp(abs(v)) - 1, v)


@pytest.mark.parametrize("version", [1, 2])
@pytest.mark.parametrize("bundle", [True, False])
def test_sog_decodes_to_hand_computed_values(tmp_path, version, bundle):
    path = _write_sog(tmp_path / "sog", *_sog_files(version), bundle=bundle)
    assert F.splat_format(path) == "sog"
    s = F.read_sog(path)
    x0 = _inverse_log(-1 + 2 * 0 / 65535)
    y0 = _inverse_log(0 + 2 * (255 + 256 * 255) / 65535)
    z1 = _inverse_log(0.5)  # mins == maxs: the span counts as 1, u = 0
    np.testing.assert_allclose(s.means[0, :2], [x0, y0], rtol=1e-6)
    np.testing.assert_allclose(s.means[1, 2], z1, rtol=1e-6)
    np.testing.assert_allclose(s.means[1, 0], _inverse_log(-1 + 2 * (255 + 256 * 128) / 65535), rtol=1e-6)
    a, b, c = ((u / 255 * 2 - 1) / math.sqrt(2) for u in (255, 0, 128))
    np.testing.assert_allclose(s.quats[0], [math.sqrt(max(0, 1 - a * a - b * b - c * c)), a, b, c], atol=1e-6)
    np.testing.assert_allclose(s.quats[1], [1, 0, 0, 0])
    book = np.linspace(-8, 0, 256) if version == 2 else -8 + 8 * np.arange(256) / 255
    np.testing.assert_allclose(s.log_scales[1], book[[255, 3, 4]], rtol=1e-6)
    colours = np.linspace(-2, 2, 256) if version == 2 else -2 + 4 * np.arange(256) / 255
    np.testing.assert_allclose(s.sh[1, 0], colours[[3, 4, 5]], rtol=1e-6)
    if version == 2:
        np.testing.assert_allclose(s.logits, [_logit(1 - 0.25 / 255), _logit(0.25 / 255)], rtol=1e-6)
    else:
        np.testing.assert_allclose(s.logits, [5.0, -5.0], rtol=1e-6)  # a lerped logit
    rest = np.linspace(-1, 1, 256) if version == 2 else -1 + 2 * np.arange(256) / 255
    np.testing.assert_allclose(s.sh[0, 1:], rest[[[1, 2, 3], [4, 5, 6], [7, 8, 9]]], rtol=1e-6)
    np.testing.assert_allclose(s.sh[1, 1:], rest[np.zeros((3, 3), int)], rtol=1e-6)  # label 0: zero texels


# ---------------------------------------------------------------------------------------------
# Writers: the reference's quantisation, round trips, axes.


def test_writers_quantise_as_their_references(tmp_path):
    """Single values through each writer against the reference writer's formula, worked by hand."""
    splats = make_splats(
        means=[[1.00006103515625, -0.5, 0.0]],  # x 4096.25 fixed: rounds to 4096
        log_scales=[[-9.96875, 0.0, 5.0]],  # (s + 10) 16 = 0.5 -> 1 (half away from zero), 160, 240
        quats=[[1.0, 0.0, 0.0, 0.0]],
        logits=[0.0],  # 127.5 -> 128
        sh=[[[0.0, 1.0, -1.0], [0.1, -0.1, 0.06], [0, 0, 0], [0, 0, 0]]],
    )
    F.write_spz(tmp_path / "a.spz", splats, version=3)
    raw = gzip.decompress((tmp_path / "a.spz").read_bytes())[16:]
    assert raw[:9] == bytes([0x00, 0x10, 0x00, 0x00, 0xF8, 0xFF, 0, 0, 0])
    assert raw[9] == 128 and raw[13:16] == bytes([1, 160, 240])
    # colour: f_dc 0.15 255 + 127.5 -> 127.5 (128), 165.75 (166), 89.25 (89)
    assert raw[10:13] == bytes([128, 166, 89])
    assert raw[16:20] == struct.pack("<I", 3 << 30)  # identity: largest w, the rest 0
    # SH degree 1, 5 bits (buckets of 8): 0.1 -> 13 + 128 = 141 -> 144; -0.1 -> 115 -> 112; 0.06 -> 136
    assert raw[20:23] == bytes([144, 112, 136])
    splat_row = (F.write_antimatter_splat(tmp_path / "a.splat", splats)).read_bytes()
    assert splat_row[24:32] == bytes([127, 199, 55, 127, 255, 128, 128, 128])  # truncated, not rounded


def test_spz_round_trips_within_quantisation(tmp_path):
    splats = _random_splats(300, 3)
    reference = _arrays(splats)
    for version in (2, 3, 4):
        path = F.write_spz(tmp_path / f"v{version}.spz", splats, version=version)
        decoded = _arrays(F.read_spz(path))
        # 9 bits of sqrt(1/2) per component; version 2's 8-bit x y z rebuild w = sqrt(1 - |xyz|^2), which
        # loses precision as w nears 0 (an error e in |xyz|^2 gives sqrt(e) in w).
        quat_tol = 0.004 if version >= 3 else 0.1
        _within(decoded, reference, {"means": 0.5 / 4096 + 1e-6, "log_scales": 0.5 / 16 + 1e-6, "quats": quat_tol})
        _within(decoded, reference, {"opacity": 0.5 / 255 + 1e-6})
        # SH: degree 1 in buckets of 8/128, degrees 2-3 of 16/128 (plus the 1/128 of the first rounding).
        error = np.abs(decoded["sh"][:, 1:] - np.clip(reference["sh"][:, 1:], -1, 127 / 128))  # bytes 0..255
        assert error[:, :3].max() <= 5 / 128 and error[:, 3:].max() <= 9 / 128
        dc = np.abs(decoded["sh"][:, 0] - np.clip(reference["sh"][:, 0], -127.5 / 38.25, 127.5 / 38.25))
        assert dc.max() <= 0.5 / (0.15 * 255) + 1e-5


def test_compressed_ply_round_trips_within_its_chunks(tmp_path):
    splats = _random_splats(600, 2, spread=1.0)
    path = F.write_compressed_ply(tmp_path / "c.ply", splats)
    decoded = _arrays(F.read_compressed_ply(path))
    reference = _arrays(splats, F.morton_order(np.asarray(splats.means)))
    chunks = -(-600 // 256)
    means = reference["means"].reshape(-1, 3)
    extent = max(np.ptp(means[i * 256 : (i + 1) * 256], 0).max() for i in range(chunks))
    _within(decoded, reference, {"means": extent / 2046 + 1e-6, "quats": 0.0015, "opacity": 0.5 / 255 + 1e-6})
    _within(decoded, reference, {"log_scales": 6.0 / 2046 + 1e-6})
    rest = np.clip(reference["sh"][:, 1:], -4, 4 - 8 / 256)
    assert np.abs(decoded["sh"][:, 1:] - rest).max() <= 8 / 256 + 1e-6
    colour_range = np.ptp(SH_C0 * reference["sh"][:, 0], 0).max()
    assert np.abs(decoded["sh"][:, 0] - reference["sh"][:, 0]).max() <= colour_range / 510 / SH_C0 + 1e-5


def test_dot_splat_round_trip_and_order(tmp_path):
    splats = _random_splats(100, 1)
    path = F.write_antimatter_splat(tmp_path / "s.splat", splats)
    decoded = _arrays(F.read_antimatter_splat(path))
    reference = _arrays(splats, F.importance_order(splats))
    _within(decoded, reference, {"means": 0.0, "log_scales": 1e-6, "quats": 2 / 128, "opacity": 1 / 255 + 1e-6})
    colour = np.clip(SH_C0 * reference["sh"][:, 0] + 0.5, 0, 1)
    assert np.abs(SH_C0 * decoded["sh"][:, 0] + 0.5 - colour).max() <= 1 / 255 + 1e-6
    assert decoded["sh"].shape[1] == 1  # degree 0: the format has no SH rest
    size = np.exp(reference["log_scales"].sum(-1)) * reference["opacity"]
    assert np.all(np.diff(size) <= 1e-12)  # biggest, most opaque first


@pytest.mark.slow
def test_sh_sign_table_matches_the_basis_under_axis_flips():
    """Coefficient k's sign under (sx, sy, sz) is Y_k(flipped d) / Y_k(d), for every named system."""
    d = jnp.asarray(np.random.default_rng(1).normal(size=(64, 3)), jnp.float32)
    d = d / jnp.linalg.norm(d, axis=-1, keepdims=True)
    for system in range(1, 9):
        flips = F.spz_axis_flips(system)
        means, quats, sh = F.flip_axes(np.zeros((1, 3)), np.zeros((1, 4)), np.ones((1, 16, 3)), flips)
        expected = np.asarray(sh_basis(d * jnp.asarray(flips), 3) / sh_basis(d, 3))
        np.testing.assert_allclose(expected, np.broadcast_to(sh[0, :, 0], expected.shape), rtol=1e-4)
    assert F.spz_axis_flips(4) == (1.0, -1.0, -1.0) and F.spz_axis_flips(6) == (1.0, 1.0, 1.0)


def test_spz_coordinate_system_extension_is_converted_to_ply_axes(tmp_path):
    body = _spz_legacy_body(3, _POSITION + _ALPHA + _COLOUR + _SCALE + _ROT_V3 + _SH, flags=2)
    plain, rub = tmp_path / "plain.spz", tmp_path / "rub.spz"
    plain.write_bytes(gzip.compress(body))
    rub.write_bytes(gzip.compress(body + struct.pack("<III", 0xADBE0003, 4, 4)))  # stored RUB
    a, b = F.read_spz(plain), F.read_spz(rub)
    np.testing.assert_allclose(b.means, a.means * np.array([1, -1, -1]))
    np.testing.assert_allclose(b.quats, a.quats * np.array([1, 1, -1, -1]))
    np.testing.assert_allclose(b.sh[:, 1:], a.sh[:, 1:] * np.array([-1, -1, 1])[None, :, None])
    assert "stored in RUB" in F.read_splat_file(rub).details


# ---------------------------------------------------------------------------------------------
# The same scene in two formats renders the same.


@pytest.mark.slow
def test_formats_render_like_the_reference_ply(tmp_path):
    rng = np.random.default_rng(3)
    n = 24
    splats = make_splats(
        means=rng.uniform(-0.6, 0.6, (n, 3)),
        log_scales=rng.uniform(-2.8, -1.8, (n, 3)),
        quats=rng.normal(size=(n, 4)),
        logits=rng.uniform(-1, 3, n),
        sh=np.concatenate([rng.uniform(-1.5, 1.5, (n, 1, 3)), rng.normal(size=(n, 3, 3)) * 0.2], 1),
    )
    write_splat_ply(tmp_path / "ref.ply", splats)
    files = {
        "spz": F.write_spz(tmp_path / "s.spz", splats),
        "compressed_ply": F.write_compressed_ply(tmp_path / "c.ply", splats),
    }
    c2w = jax.vmap(look_at, in_axes=(0, None, None))(
        jnp.array([[0.0, 0.5, 3.0], [2.5, -0.5, 1.5]]), jnp.zeros(3), jnp.array([0.0, 1.0, 0.0])
    )
    intrinsics = Intrinsics.create(32, 32, 40.0)
    config = SplatRenderConfig(tile_size=8, chunk=16, max_pairs=2048, pose_chunk=2)
    render = jax.jit(render_splats, static_argnames="config")
    reference = np.asarray(render(read_splat_ply(tmp_path / "ref.ply"), c2w, intrinsics, config).rgb)
    assert reference.std() > 0.05  # the scene is visible
    for name, path in files.items():
        rgb = np.asarray(render(load_splat_model(path).splats, c2w, intrinsics, config).rgb)
        assert np.abs(rgb - reference).mean() < 0.01, name
        assert np.abs(rgb - reference).max() < 0.12, name


# ---------------------------------------------------------------------------------------------
# The real donut, loading, sniffing.


def _donut_ply():
    data = paths.data_dir()
    path = None if data is None else data / "splats/donut/point_cloud.ply"
    if path is None or not path.exists():
        _missing(f"data file 'splats/donut/point_cloud.ply' ({path or 'WALDO_DATA unset and no ../shared'})")
    return path


def test_donut_converts_to_each_format_and_back(tmp_path):
    splats = read_splat_ply(_donut_ply())
    reference = _arrays(splats)
    converted = {
        "splat": (F.write_antimatter_splat(tmp_path / "d.splat", splats), F.importance_order(splats)),
        "spz": (F.write_spz(tmp_path / "d.spz", splats), None),
        "compressed_ply": (F.write_compressed_ply(tmp_path / "d.ply", splats), None),
    }
    converted["compressed_ply"] = (converted["compressed_ply"][0], F.morton_order(np.asarray(splats.means)))
    for name, (path, order) in converted.items():
        model = load_splat_model(path)
        assert F.splat_format(path) == name and model.splats.count == 45_624 and model.ply_path == path
        assert model.source.endswith(f": {path}")
        decoded, expected = _arrays(model.splats), reference if order is None else _arrays(splats, order)
        means_tol = {"splat": 0.0, "spz": 0.5 / 4096 + 1e-6, "compressed_ply": 0.01}[name]
        _within(decoded, expected, {"means": means_tol, "quats": 0.03, "opacity": 1 / 255 + 1e-6})
    folder = tmp_path / "only"
    folder.mkdir()
    (folder / "scene.spz").write_bytes(converted["spz"][0].read_bytes())
    assert load_splat_model(folder).ply_path == folder / "scene.spz" and is_splat_spec(str(folder))


def test_sniffing_and_splat_sources(tmp_path):
    splats = _random_splats(8, 0)
    ply = write_splat_ply(tmp_path / "a.ply", splats)
    assert F.splat_format(ply) == "ply" and F.read_splat_file(ply).format == "ply"
    odd = tmp_path / "odd.bin"
    odd.write_bytes(F.write_spz(tmp_path / "x.spz", splats, version=3).read_bytes())  # content, not suffix
    assert F.splat_format(odd) == "spz" and is_splat_spec(str(odd))
    sog = _write_sog(tmp_path / "sog", *_sog_files(), bundle=False)
    assert is_splat_spec(str(tmp_path / "sog")) and load_splat_model(tmp_path / "sog").ply_path == sog
    not_splat = tmp_path / "rows.splat"
    not_splat.write_bytes(np.full(8, -1.0, "<f4").tobytes())  # 32 bytes, negative scales
    assert F.splat_format(not_splat) is None
    # Read as a .splat all the same (it has no magic bytes), so the decoder names what is wrong, where the
    # generic "not a splat file of any format" line had been all a user saw.
    with pytest.raises(SceneFormatError, match="rows.splat: not a .splat file: 1 of 1 rows have a non-finite"):
        F.read_splat_file(not_splat)
    uneven = tmp_path / "uneven.splat"
    uneven.write_bytes(F.write_antimatter_splat(tmp_path / "x.splat", splats).read_bytes() + b"\0" * 7)
    with pytest.raises(SceneFormatError, match="263 bytes is no whole number of 32-byte splats"):
        F.read_splat_file(uneven)
    assert F.splat_format(tmp_path) is None and F.splat_format(tmp_path / "missing.spz") is None
    two = tmp_path / "two"
    two.mkdir()
    for name in ("a.spz", "b.spz"):
        (two / name).write_bytes(odd.read_bytes())
    with pytest.raises(SceneFormatError, match=r"several splat files here \(a\.spz, b\.spz\)"):
        load_splat_model(two)


# ---------------------------------------------------------------------------------------------
# Broken files: one clear line naming the file.


def _spz_v3(tmp_path):
    return F.write_spz(tmp_path / "ok.spz", _random_splats(20, 1), version=3).read_bytes()


def _spz_v4(tmp_path):
    return F.write_spz(tmp_path / "ok4.spz", _random_splats(20, 1), version=4).read_bytes()


def _sog_zip(tmp_path, edit):
    meta, files = _sog_files()
    edit(meta, files)
    return _write_sog(tmp_path / "bad_sog", meta, files, bundle=True).read_bytes()


_MIB2 = bytes(2**21)


def _with(name, data):
    """An edit of a SOG's files that replaces file `name` by `data`."""
    return lambda meta, files: files.update({name: data})


BROKEN = {
    "unknown": ("x.dat", lambda t: b"hello, world" * 10, r"not a splat file of any format read here \(formats read: "),
    "splat size": ("x.splat", lambda t: bytes(33), r"not a .splat file: 33 bytes is no whole number of 32-byte splats"),
    "gzip cut": ("x.spz", lambda t: _spz_v3(t)[:-30], r"corrupt SPZ gzip stream"),
    "gzip not spz": ("x.spz", lambda t: gzip.compress(b"NGSP" + bytes(12)), r"SPZ version 0 is not read"),
    "spz short": ("x.spz", lambda t: gzip.compress(gzip.decompress(_spz_v3(t))[:-5]), r"truncated SPZ: 20 splats"),
    "spz zero": ("x.spz", lambda t: gzip.compress(struct.pack("<IIIBBBB", 0x5053474E, 3, 0, 0, 12, 0, 0)),
                 r"SPZ header claims 0 splats"),
    "spz degree": ("x.spz", lambda t: gzip.compress(struct.pack("<IIIBBBB", 0x5053474E, 3, 1, 7, 12, 0, 0)),
                   r"SPZ SH degree 7"),
    "v4 cut": ("x.spz", lambda t: _spz_v4(t)[:-10], r"SPZ stream 5 holds"),
    "v4 corrupt": ("x.spz", lambda t: _spz_v4(t)[:-12] + bytes(12), r"corrupt SPZ zstd stream"),
    "v4 header": ("x.spz", lambda t: _spz_v4(t)[:20], r"truncated SPZ: the 32-byte header is cut"),
    "compressed cut": ("x.ply", lambda t: F.write_compressed_ply(t / "c.ply", _random_splats(20, 1)).read_bytes()[:-9],
                       r"truncated or malformed compressed PLY data"),
    "chunk count": ("x.ply", lambda t: b"ply\nformat binary_little_endian 1.0\nelement chunk 2\n"
                    + b"".join(f"property float {p}\n".encode() for p in F.CHUNK_BOUNDS)
                    + b"element vertex 3\n" + b"".join(f"property uint {p}\n".encode() for p in F.PACKED)
                    + b"end_header\n" + bytes(2 * 48 + 3 * 16), r"3 splats need 1 chunks of 256, the file has 2"),
    "sog image": ("x.sog", lambda t: _sog_zip(t, lambda m, f: f.pop("quats.webp")),
                  r"the SOG lacks its file 'quats\.webp'"),
    "sog webp": ("x.sog", lambda t: _sog_zip(t, lambda m, f: f.update({"scales.webp": b"RIFF...."})),
                 r"the SOG's image 'scales\.webp' cannot be decoded"),
    "sog count": ("x.sog", lambda t: _sog_zip(t, lambda m, f: m.update(count=9)), r"has 2 texels for 9 splats"),
    "sog codebook": ("x.sog", lambda t: _sog_zip(t, lambda m, f: m["scales"].update(codebook=[1, 2])),
                     r"scales\.codebook must be 256 finite numbers"),
    "sog json": ("meta.json", lambda t: b'{"means": 1, "scales": 2, "quats": 3, "sh0": [', r"not a splat file of any"),
    # Sizes and types a header or meta.json gives: refused before anything that large is inflated or decoded.
    "gzip bomb": ("x.spz", lambda t: gzip.compress(gzip.decompress(_spz_v3(t)) + bytes(64 * 2**20), 1),
                  r"the SPZ stream inflates past what its 20 splats need"),
    "spz count": ("x.spz", lambda t: gzip.compress(struct.pack("<IIIBBBB", 0x5053474E, 3, 2**31 - 1, 3, 12, 0, 0)),
                  r"reading its 2,147,483,647 splats \(an SPZ file, SH degree 3\) would take .* GiB"),
    "v4 count": ("x.spz", lambda t: _spz_v4(t)[:8] + struct.pack("<I", 2**31 - 1) + _spz_v4(t)[12:],
                 r"reading its 2,147,483,647 splats \(an SPZ file"),
    "sog image size": ("x.sog", lambda t: _sog_zip(t, _with("scales.webp", _webp(np.zeros((256, 256, 4))))),
                       r"the SOG's image 'scales\.webp' is 256x256: expected at most 16,388 texels"),
    "sog member size": ("x.sog", lambda t: _sog_zip(t, lambda m, f: f.update({"sh0.webp": f["sh0.webp"] + _MIB2})),
                        r"the SOG's file 'sh0\.webp' holds more than 1 MiB"),
    "sog centroid width": ("x.sog", lambda t: _sog_zip(t, _with("shN_centroids.webp", _webp(np.zeros((1, 100, 4))))),
                           r"shN centroid image is 100 wide, expected 192"),
    "sog count huge": ("x.sog", lambda t: _sog_zip(t, lambda m, f: m.update(count=2**40)),
                       r"reading its 1,099,511,627,776 splats \(a SOG"),
    "sog files empty": ("x.sog", lambda t: _sog_zip(t, lambda m, f: m["quats"].update(files=[])),
                        r"'quats' must be an object with a 'files' list of at least 1 file"),
    "sog file names": ("x.sog", lambda t: _sog_zip(t, lambda m, f: m["means"].update(files=[5, 6])),
                       r"'means' must be an object with a 'files' list of at least 2 file"),
    "sog v1 shape": ("x.sog", lambda t: _sog_zip(t, lambda m, f: (m.pop("version"), m.pop("count"),
                                                                   m["means"].update(shape=5))),
                     r"no positive splat count \(got None\)"),
    "sog big int": ("x.sog", lambda t: _sog_zip(t, lambda m, f: m.update(count=10**400)),
                    r"no positive splat count \(got inf\)"),
    # Decompression bounded by what the header needs, not by what a stream says of itself.
    "v4 zstd bomb": ("x.spz", lambda t: _spz_v4_bomb(t, stated=True), r"SPZ stream 0 inflates past the 180 bytes"),
    "v4 zstd lying size": ("x.spz", lambda t: _spz_v4_bomb(t, stated=False), r"corrupt SPZ zstd stream \(stream 0"),
    # Container and codec errors of any kind: the file's error.
    "sog encrypted": ("x.sog", lambda t: _encrypted(_sog_zip(t, lambda m, f: None)),
                      r"cannot read the SOG's file 'meta\.json' \(RuntimeError: .*encrypted"),
    "sog broken png": ("x.sog", lambda t: _sog_zip(t, _with("shN_centroids.webp", _broken_png())),
                       r"the SOG's image 'shN_centroids\.webp' cannot be decoded \(SyntaxError: broken PNG"),
    "sog tiff": ("x.sog", lambda t: _sog_zip(t, _with("scales.webp", _image_bytes("TIFF"))),
                 r"the SOG's image 'scales\.webp' cannot be decoded \(not a WebP or PNG image\)"),
    # Values checked in float32, where they are used.
    "sog means beyond float32": ("x.sog", lambda t: _sog_zip(t, lambda m, f: m["means"].update(maxs=[90.0] * 3)),
                                 r"means\.maxs \[90\.0, 90\.0, 90\.0\] give positions .* beyond float32"),
    "sog codebook 1e300": ("x.sog", lambda t: _sog_zip(t, lambda m, f: m["sh0"].update(codebook=[1e300] * 256)),
                           r"sh0\.codebook must be 256 finite numbers \(float32"),
    # A header count that disagrees with the data.
    "spz count fewer": ("x.spz", lambda t: _spz_count(t, 10), r"holds .* bytes after the sections of its header's 10"),
    "spz trailing junk": ("x.spz", lambda t: _spz_v3(t) + b"junkjunk", r"8 bytes follow the SPZ gzip stream"),
    "v4 trailing": ("x.spz", lambda t: _spz_v4(t) + bytes(7), r"7 bytes follow the SPZ's 6 streams"),
    "compressed count fewer": ("x.ply", lambda t: _compressed_fewer(t),
                               r"its elements \(chunk 2, vertex 300, sh 300\) need .*disagree with the data"),
    "sog count fewer": ("x.sog", lambda t: _sog_zip(t, lambda m, f: (m.update(count=2), f.update(
                        {k: _webp(np.zeros((8, 4, 4))) for k in f if k != "shN_centroids.webp"}))),
                        r"is 4x8: its count 2 leaves more than four rows of texels unused"),
    "sog sizes differ": ("x.sog", lambda t: _sog_zip(t, _with("sh0.webp", _webp(np.zeros((1, 3, 4))))),
                         r"the SOG's images differ in size"),
    # Types: a bool is not a number.
    "sog version bool": ("x.sog", lambda t: _sog_zip(t, lambda m, f: m.update(version=True)),
                         r"SOG version True is not read"),
    "sog bands bool": ("x.sog", lambda t: _sog_zip(t, lambda m, f: m["shN"].update(bands=True)),
                       r"shN\.bands must be 1, 2 or 3, got True"),
    "sog codebook bool": ("x.sog", lambda t: _sog_zip(t, lambda m, f: m["scales"].update(codebook=[True] * 256)),
                          r"scales\.codebook must be 256 finite numbers"),
    "splat named otherwise": ("x.bin", lambda t: F.write_antimatter_splat(t / "d.splat", _random_splats(4, 0))
                              .read_bytes(), r"is told by its \.splat extension"),
}  # fmt: skip


def _spz_v4_bomb(tmp_path, stated: bool) -> bytes:
    """A one-splat SPZ v4 whose position stream (180 bytes of 20 splats in the table) is a zstd frame of 64 MiB
    of zeros, its size stated in the frame (`stated`) or a frame claiming 1 TiB for 180 bytes of data."""
    n, sizes = 20, [20 * 9, 20, 60, 60, 80]
    streams = [zstandard.ZstdCompressor(level=1).compress(bytes(size)) for size in sizes]
    if stated:
        buffer = io.BytesIO()
        with zstandard.ZstdCompressor(level=1).stream_writer(buffer, size=64 * 2**20, closefd=False) as w:
            for _ in range(64):
                w.write(bytes(2**20))
        streams[0] = buffer.getvalue()
    else:
        data = zstandard.ZstdCompressor(level=1, write_content_size=False).compress(bytes(sizes[0]))
        descriptor = data[4]
        assert descriptor & 0xC0 == 0 and not descriptor & 0x20  # no size stated, a window byte
        streams[0] = data[:4] + bytes([descriptor | 0xC0, data[5]]) + struct.pack("<Q", 2**40) + data[6:]
    header = struct.pack("<IIIBBBBI12x", 0x5053474E, 4, n, 0, 12, 0, len(streams), 32)
    table = b"".join(struct.pack("<QQ", len(c), size) for c, size in zip(streams, sizes))
    return header + table + b"".join(streams)


def _encrypted(raw: bytes) -> bytes:
    """A zip with the 'encrypted' flag set on every member (zipped with a password)."""
    raw = bytearray(raw)
    for signature, offset in ((b"PK\x03\x04", 6), (b"PK\x01\x02", 8)):
        i = raw.find(signature)
        while i >= 0:
            raw[i + offset] |= 1
            i = raw.find(signature, i + 4)
    return bytes(raw)


def _image_bytes(fmt: str) -> bytes:
    buffer = io.BytesIO()
    Image.fromarray(np.zeros((1, 2, 4), np.uint8), "RGBA").save(buffer, fmt)
    return buffer.getvalue()


def _broken_png() -> bytes:
    """A 192 x 1 PNG (a centroid image's size) whose IDAT length is 100 bytes short: decoding it reads a
    chunk header from the middle of the data, and Pillow raises SyntaxError('broken PNG file')."""
    buffer = io.BytesIO()
    noise = np.random.default_rng(0).integers(0, 256, (1, 192, 4)).astype(np.uint8)
    Image.fromarray(noise, "RGBA").save(buffer, "PNG")
    raw = bytearray(buffer.getvalue())
    i = raw.find(b"IDAT")
    raw[i - 4 : i] = struct.pack(">I", struct.unpack(">I", raw[i - 4 : i])[0] - 100)
    return bytes(raw)


def _spz_count(tmp_path, count: int) -> bytes:
    raw = bytearray(gzip.decompress(_spz_v3(tmp_path)))
    struct.pack_into("<I", raw, 8, count)
    return gzip.compress(bytes(raw))


def _compressed_fewer(tmp_path) -> bytes:
    """A compressed PLY of 400 splats (2 chunks) whose header says 300 (still 2 chunks)."""
    raw = F.write_compressed_ply(tmp_path / "c.ply", _random_splats(400, 1)).read_bytes()
    return raw.replace(b"element vertex 400", b"element vertex 300", 1).replace(b"element sh 400", b"element sh 300", 1)


@pytest.mark.parametrize("case", list(BROKEN))
def test_broken_file_is_one_clear_line(tmp_path, case):
    name, build, message = BROKEN[case]
    path = tmp_path / name
    path.write_bytes(build(tmp_path))
    with pytest.raises(WaldoError, match=message) as info:
        load_splat_model(path)
    text = str(info.value)
    assert text.startswith(f"{path}: ") and "\n" not in text


def test_compressed_ply_through_read_splat_ply_says_how_to_read_it(tmp_path):
    path = F.write_compressed_ply(tmp_path / "c.ply", _random_splats(4, 0))
    with pytest.raises(SceneFormatError, match=r"a compressed splat PLY .* read it with load_splat_model"):
        read_splat_ply(path)


# ---------------------------------------------------------------------------------------------
# Sniffing, non-regular files and memory.


def test_a_compressed_ply_with_a_long_header_is_sniffed_as_compressed(tmp_path):
    """150 KB of comment lines (the header limit is 1 MiB): the sniffer once read 64 KiB, called it a plain
    PLY, and the plain reader refused it."""
    raw = F.write_compressed_ply(tmp_path / "c.ply", _random_splats(300, 0)).read_bytes()
    pad = b"".join(b"comment %06d exported by some tool, padding padding padding\n" % i for i in range(2500))
    path = tmp_path / "long.ply"
    path.write_bytes(raw.replace(b"comment written by waldo_jax\n", pad, 1))
    assert F.splat_format(path) == "compressed_ply"
    np.testing.assert_array_equal(load_splat_model(path).splats.means, F.read_compressed_ply(tmp_path / "c.ply").means)


def test_a_fifo_named_in_a_sog_folder_is_refused_not_waited_on(tmp_path):
    """A SOG folder whose quats image is a FIFO: one line naming it (the reader once blocked forever)."""
    meta, files = _sog_files()
    path = _write_sog(tmp_path / "sog", meta, files, bundle=False)
    (tmp_path / "sog" / "quats.webp").unlink()
    os.mkfifo(tmp_path / "sog" / "quats.webp")
    with pytest.raises(WaldoError, match=r"quats\.webp: a FIFO, socket or device"):
        load_splat_model(path)


@pytest.mark.parametrize("fmt", ["ply", "spz", "compressed_ply", "splat"])
def test_header_count_check_is_the_readers_measured_peak(tmp_path, monkeypatch, fmt):
    """The memory a count is checked against is each reader's measured peak per splat (`PEAK_BYTES_PER_SPLAT`:
    a 583 KB .spz declaring 30M splats took 11.7 GB against a check of 5.4 GB), not 4 x the splats' floats:
    on a machine with memory between the two the reader refuses before decoding."""
    from waldo_jax.splats.formats import common

    n, degree = 4000, 1
    splats = _random_splats(n, degree, spread=1.0)
    path = {
        "ply": lambda: write_splat_ply(tmp_path / "s.ply", splats),
        "spz": lambda: F.write_spz(tmp_path / "s.spz", splats, version=3),
        "compressed_ply": lambda: F.write_compressed_ply(tmp_path / "c.ply", splats),
        "splat": lambda: F.write_antimatter_splat(tmp_path / "s.splat", splats),
    }[fmt]()
    degree = 0 if fmt == "splat" else degree
    need = common.peak_bytes(fmt, n, degree)
    old = n * (3 + 3 + 4 + 1 + 3 * (degree + 1) ** 2) * 4 * 4
    assert need > old
    monkeypatch.setattr("waldo_jax.errors.host_memory_bytes", lambda: int(0.5 * (need + old)))
    with pytest.raises(MemoryBudgetError, match=r"reading its 4,000 splats"):
        F.read_splat_file(path)


def test_a_sogs_images_count_in_its_memory_check(tmp_path, monkeypatch):
    """A SOG's decoded images count by their texels, read from their headers (a 3 KB .sog of count 20M with
    4473 x 4473 images took 7.9 GB): two splats in 4096-texel images need their images' memory."""
    meta, files = _sog_files()
    files.update({k: _webp(np.zeros((1, 4096, 4))) for k in files if k != "shN_centroids.webp"})
    path = _write_sog(tmp_path / "sog", meta, files, bundle=True)
    monkeypatch.setattr("waldo_jax.errors.host_memory_bytes", lambda: 100_000)
    with pytest.raises(MemoryBudgetError, match=r"reading its 2 splats \(a SOG, SH degree 3\) would take"):
        F.read_splat_file(path)
