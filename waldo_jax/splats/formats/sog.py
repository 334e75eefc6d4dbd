"""PlayCanvas SOG. Reference: playcanvas/splat-transform src/lib/readers/read-sog.ts (version 2),
read-sog-v1.ts (version 1, meta without "version"), src/lib/writers/write-sog.ts. Texel i (row-major)
of each WebP image holds splat i. Means: 16 bits split over means_l / means_u, a lerp between the
meta's mins and maxs of sign(x) ln(|x| + 1). Quats: three bytes of the smaller components times
sqrt(2), the alpha byte 252 + the index (w x y z) of the largest. Version 2: scales and sh0 index
256-entry codebooks, sh0's alpha is sigmoid(opacity) * 255; shN is a palette of `count` centroids
(16-bit labels in shN_labels' r g), a centroid's coefficient j in texel (label % 64 * K' + j,
label // 64) of shN_centroids, whose r g b index the shN codebook. Version 1: lerps between mins and
maxs instead of codebooks (sh0's alpha a logit), shN's band from the centroid image's width.
"""

from __future__ import annotations

import io
import math
import os
import warnings
import zipfile
from pathlib import Path
from typing import Optional

import numpy as np

from waldo_jax.io import parse_json
from waldo_jax.errors import SceneFormatError, WaldoError, check_input_file
from waldo_jax.splats.formats.common import (
    SOG_IMAGE_BYTES_PER_TEXEL,
    check_splat_count,
    finish_splats,
    opacity_logits,
)
from waldo_jax.splats.model import Splats, sh_coefficients

_SOG_BANDS_V1 = {192: 1, 512: 2, 960: 3}
# A WebP image's file per texel (lossless WebP of noise-like data takes about 4 bytes a texel), and the
# centroid image's height: labels are 16 bits, so at most 65,536 centroids in rows of 64.
_IMAGE_FILE_BYTES_PER_TEXEL = 8
# meta.json holds a few codebooks of 256 numbers: kilobytes.
_MAX_META_BYTES = 16 * 2**20
_MAX_CENTROID_ROWS = 65536 // 64
# SOG images are lossless WebP (splat-transform writes nothing else); PNG is lossless too. Other formats'
# decoders (TIFF's libtiff) print their own lines on damaged data.
_IMAGE_FORMATS = ("WEBP", "PNG")
_FLOAT32_MAX = float(np.finfo(np.float32).max)


class _SogFiles:
    """The files of a SOG: the members of a `.sog` zip, or the files beside its meta.json."""

    def __init__(self, path: Path):
        self.path = path
        self.zip = None
        self._raw: dict = {}
        if path.suffix.lower() != ".json":
            try:
                self.zip = zipfile.ZipFile(path)
            except Exception as e:  # noqa: BLE001 (any error of the zip reader on bad bytes is the file's)
                raise SceneFormatError(path, f"not a readable .sog zip ({type(e).__name__}: {e})") from None

    def read(self, name: str, limit: int) -> bytes:
        """The bytes of file `name`, refused past `limit` bytes before more than that is read or inflated."""
        if not isinstance(name, str) or not name or "\0" in name:
            raise SceneFormatError(self.path, f"SOG meta.json names a file {name!r} (not a file name)")
        if name in self._raw:
            return self._raw[name]
        try:
            if self.zip is not None:
                size = self.zip.getinfo(name).file_size
                data = b""
                if size <= limit:
                    with self.zip.open(name) as member:
                        data = member.read(limit + 1)  # streamed: the size in the zip's directory may lie
            else:
                target = self.path.parent / name
                if not target.resolve().is_relative_to(self.path.parent.resolve()):
                    raise SceneFormatError(self.path, f"SOG file {name!r} lies outside the SOG's folder")
                if not target.exists():
                    raise KeyError(name)
                check_input_file(target, f"SOG file (named in {self.path.name})")  # a FIFO would block
                size = target.stat().st_size
                data = b""
                if size <= limit:
                    with open(target, "rb") as f:
                        data = f.read(limit + 1)
        except KeyError:
            raise SceneFormatError(self.path, f"the SOG lacks its file {name!r}") from None
        except WaldoError:
            raise
        except Exception as e:  # noqa: BLE001 (encrypted members, bad zip data, I/O: the file's error)
            raise SceneFormatError(
                self.path, f"cannot read the SOG's file {name!r} ({type(e).__name__}: {e})"
            ) from None
        if max(size, len(data)) > limit:
            raise SceneFormatError(
                self.path, f"the SOG's file {name!r} holds more than {limit / 2**20:,.0f} MiB (its splats need less)"
            )
        self._raw[name] = data
        return data

    def _open(self, name: str, max_texels: int):
        """Image `name` opened (its header read, nothing decoded), refused when it holds more than `max_texels`."""
        from PIL import Image

        raw = self.read(name, _IMAGE_FILE_BYTES_PER_TEXEL * max_texels + 2**20)
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", Image.DecompressionBombWarning)  # its size is checked below
                image = Image.open(io.BytesIO(raw), formats=_IMAGE_FORMATS)
        except Image.UnidentifiedImageError:
            raise SceneFormatError(
                self.path, f"the SOG's image {name!r} cannot be decoded (not a WebP or PNG image)"
            ) from None
        except Exception as e:  # noqa: BLE001 (Pillow raises many kinds on bad bytes: SyntaxError for a PNG)
            raise SceneFormatError(
                self.path, f"the SOG's image {name!r} cannot be decoded ({type(e).__name__}: {e})"
            ) from None
        w, h = image.size
        if w * h > max_texels:
            image.close()
            raise SceneFormatError(
                self.path, f"the SOG's image {name!r} is {w}x{h}: expected at most {max_texels:,} texels"
            )
        return image

    def size(self, name: str, max_texels: int) -> tuple:
        """(width, height) of image `name` from its header, without decoding it."""
        with self._open(name, max_texels) as image:
            return image.size

    def image(self, name: str, max_texels: int) -> np.ndarray:
        """The RGBA texels of WebP image `name`, uint8 [height, width, 4]; its size read from its header is
        refused before decoding when it holds more than `max_texels` texels."""
        image = self._open(name, max_texels)
        try:
            with image:
                self._check_still_8_bit(name, image)
                return np.asarray(image.convert("RGBA"))
        except SceneFormatError:
            raise
        except MemoryError:
            raise
        except Exception as e:  # noqa: BLE001 (any decoder error on bad bytes is the file's)
            raise SceneFormatError(
                self.path, f"the SOG's image {name!r} cannot be decoded ({type(e).__name__}: {e})"
            ) from None

    def _check_still_8_bit(self, name: str, image) -> None:
        """Refuses what RGBA conversion would change silently: an image of several frames (the first had
        been read), one of more than 8 bits a channel (clipped), and a lossy WebP where the splats' positions
        are stored (its 16 bits split over `means_l` and `means_u` are exact only losslessly)."""
        if getattr(image, "is_animated", False):
            raise SceneFormatError(self.path, f"the SOG's image {name!r} has several frames; SOG's images are still")
        if image.mode not in _EIGHT_BIT_MODES:
            raise SceneFormatError(
                self.path, f"the SOG's image {name!r} is of mode {image.mode} (not 8 bits a channel); SOG's are RGBA8"
            )
        if name.startswith("means") and _lossy_webp(self._raw.get(name, b"")):
            raise SceneFormatError(
                self.path,
                f"the SOG's image {name!r} is a lossy WebP: the splats' positions need it lossless (its texels are "
                "the low and high bytes of 16-bit coordinates)",
            )

    def texels(self, name: str, count: int) -> np.ndarray:
        """The first `count` texels of image `name` in row-major order, uint8 [count, 4]."""
        texels = self.image(name, _max_texels(count)).reshape(-1, 4)
        if len(texels) < count:
            raise SceneFormatError(self.path, f"the SOG's image {name!r} has {len(texels)} texels for {count} splats")
        return texels[:count]


# Pillow modes of 8 bits a channel that convert to RGBA without losing anything.
_EIGHT_BIT_MODES = ("RGBA", "RGB", "L", "LA", "P", "PA", "RGBX", "RGBa", "La")


def _lossy_webp(raw: bytes) -> bool:
    """Whether WebP bytes hold a lossy ("VP8 ") bitstream, from their RIFF chunks (False for anything else)."""
    if raw[:4] != b"RIFF" or raw[8:12] != b"WEBP":
        return False
    at = 12
    while at + 8 <= len(raw):
        fourcc, size = raw[at : at + 4], int.from_bytes(raw[at + 4 : at + 8], "little")
        if fourcc == b"VP8 ":
            return True
        if fourcc == b"VP8L":
            return False
        at += 8 + size + (size & 1)
    return False


def _max_texels(count: int) -> int:
    """The most texels an image of `count` splats may hold: writers make it about sqrt(count) square,
    rounded up to whole blocks; twice the count and a 4096 x 4 margin is far above what they write."""
    return 2 * count + 4 * 4096


def _inverse_log(v: np.ndarray) -> np.ndarray:
    with np.errstate(over="ignore"):
        return np.sign(v) * (np.exp(np.abs(v)) - 1.0)


def _sog_field(meta: dict, key: str, path: Path, files: int = 1):
    value = meta.get(key)
    names = value.get("files") if isinstance(value, dict) else None
    if not isinstance(names, list) or len(names) < files or not all(isinstance(n, str) for n in names):
        raise SceneFormatError(
            path, f"SOG meta.json: '{key}' must be an object with a 'files' list of at least {files} file name(s)"
        )
    return value


def _numbers(path: Path, value, count: Optional[int], what: str) -> np.ndarray:
    """`value` as float64 [count]: numbers (not bools) that float32, the splats' type, holds finite."""
    items = value if isinstance(value, list) else []
    try:
        array = np.asarray(value, np.float64)
    except (TypeError, ValueError, OverflowError):
        array = np.zeros(0)
    if (
        array.ndim != 1
        or (count is not None and len(array) != count)
        or any(isinstance(v, bool) for v in items)
        or not np.all(np.abs(array) <= _FLOAT32_MAX)
    ):
        raise SceneFormatError(
            path, f"SOG meta.json: {what} must be {count or 'a list of'} finite numbers (float32: |x| <= 3.4e38)"
        )
    return array


def _check_means_range(path: Path, mins: np.ndarray, maxs: np.ndarray) -> None:
    """Refuses means.mins / maxs whose positions, sign(v) (exp(|v|) - 1), leave float32 (maxs 90: 1.2e39)."""
    for key, ends in (("mins", mins), ("maxs", maxs)):
        with np.errstate(over="ignore"):
            positions = _inverse_log(ends).astype(np.float32)
        if not np.all(np.isfinite(positions)):
            raise SceneFormatError(
                path,
                f"SOG meta.json: means.{key} {ends.tolist()} give positions sign(v) (exp(|v|) - 1) beyond float32 "
                f"(|v| must be at most {math.log1p(_FLOAT32_MAX):.2f})",
            )


def _check_image_sizes(path: Path, files: "_SogFiles", names: list, count: int) -> int:
    """Checks, from the images' headers, that each per-splat image holds `count` texels in whole rows as
    writers lay them out (count reaching into the last four rows: a count smaller than the data is refused)
    and that they share one size; returns their texels in all."""
    sizes = {name: files.size(name, _max_texels(count)) for name in names}
    for name, (w, h) in sizes.items():
        if w * h < count:
            raise SceneFormatError(path, f"the SOG's image {name!r} has {w * h} texels for {count} splats")
        if count <= w * (h - 4):
            raise SceneFormatError(
                path,
                f"the SOG's image {name!r} is {w}x{h}: its count {count} leaves more than four rows of "
                "texels unused (the count disagrees with the data)",
            )
    if len(set(sizes.values())) > 1:
        listed = ", ".join(f"{name} {w}x{h}" for name, (w, h) in sizes.items())
        raise SceneFormatError(path, f"the SOG's images differ in size ({listed}): one texel per splat in each")
    return sum(w * h for w, h in sizes.values())


def decode_sog(path: Path):
    """(Splats, details line, extras) of a SOG scene: a bundled `.sog` or a `meta.json` beside its WebP images."""
    files = _SogFiles(path)
    raw = files.read("meta.json" if files.zip is not None else path.name, _MAX_META_BYTES)
    meta = parse_json(raw, path, "SOG meta.json", lambda problem: SceneFormatError(path, f"SOG meta.json: {problem}"))
    if not isinstance(meta, dict):
        raise SceneFormatError(path, "SOG meta.json must hold a JSON object")
    version = meta.get("version", 1)
    if isinstance(version, bool) or version not in (1, 2):
        raise SceneFormatError(path, f"SOG version {version!r} is not read (versions 1 and 2 are)")
    means_meta = _sog_field(meta, "means", path, files=2)
    shape = means_meta.get("shape")
    count = meta.get("count") if version == 2 else (shape[0] if isinstance(shape, list) and shape else None)
    if isinstance(count, bool) or not isinstance(count, int) or count <= 0:
        raise SceneFormatError(path, f"SOG meta.json: no positive splat count (got {count!r})")
    shn = meta.get("shN")
    degree = 3 if isinstance(shn, dict) else 0  # at most 3: the check before any image is read
    check_splat_count(path, count, degree, "a SOG", fmt="sog")
    mins, maxs = (_numbers(path, means_meta.get(k), 3, f"means.{k}") for k in ("mins", "maxs"))
    _check_means_range(path, mins, maxs)
    names = means_meta["files"]
    per_splat = names[:2] + [_sog_field(meta, k, path)["files"][0] for k in ("quats", "scales", "sh0")]
    if isinstance(shn, dict):
        shn_names = shn.get("files")
        if not isinstance(shn_names, list) or len(shn_names) < 2 or not all(isinstance(n, str) for n in shn_names):
            raise SceneFormatError(path, "SOG meta.json: shN needs two files (centroids, labels)")
        per_splat.append(shn_names[1])
    texels = _check_image_sizes(path, files, per_splat, count)
    if isinstance(shn, dict):
        texels += math.prod(files.size(shn["files"][0], 64 * 15 * _MAX_CENTROID_ROWS))
    # The decoded images, from their headers' sizes, besides the splats' own arrays.
    check_splat_count(path, count, degree, "a SOG", fmt="sog", extra_bytes=texels * SOG_IMAGE_BYTES_PER_TEXEL)
    lo, hi = files.texels(names[0], count), files.texels(names[1], count)
    quantised = lo[:, :3].astype(np.float64) + 256.0 * hi[:, :3]
    span = np.where(maxs - mins == 0, 1.0, maxs - mins)
    means = _inverse_log(mins + span * quantised / 65535.0)
    q = files.texels(_sog_field(meta, "quats", path)["files"][0], count)
    tag = q[:, 3].astype(np.int64)
    abc = (q[:, :3] / 255.0 * 2.0 - 1.0) / math.sqrt(2.0)
    largest = np.clip(tag - 252, 0, 3)
    others = np.array([[i for i in range(4) if i != skip] for skip in range(4)])[largest]
    quats = np.zeros((count, 4))
    quats[np.arange(count)[:, None], others] = abc
    quats[np.arange(count), largest] = np.sqrt(np.maximum(0.0, 1.0 - np.sum(abc * abc, -1)))
    quats[(tag < 252) | (tag > 255)] = (1.0, 0.0, 0.0, 0.0)
    scales_meta, sh0_meta = _sog_field(meta, "scales", path), _sog_field(meta, "sh0", path)
    s = files.texels(scales_meta["files"][0], count)[:, :3]
    c = files.texels(sh0_meta["files"][0], count)
    if version == 2:
        scale_book = _numbers(path, scales_meta.get("codebook"), 256, "scales.codebook")
        colour_book = _numbers(path, sh0_meta.get("codebook"), 256, "sh0.codebook")
        log_scales, dc = scale_book[s], colour_book[c[:, :3]]
        logits = opacity_logits(c[:, 3] / 255.0)
    else:
        s_lo, s_hi = (_numbers(path, scales_meta.get(k), 3, f"scales.{k}") for k in ("mins", "maxs"))
        c_lo, c_hi = (_numbers(path, sh0_meta.get(k), 4, f"sh0.{k}") for k in ("mins", "maxs"))
        log_scales = s_lo + (s_hi - s_lo) * s / 255.0
        lerped = c_lo + (c_hi - c_lo) * c / 255.0
        dc, logits = lerped[:, :3], lerped[:, 3]
    sh_all = dc[:, None, :]
    degree = 0
    if isinstance(shn, dict):
        sh_all, degree = _sog_rest(path, files, meta["shN"], version, count, sh_all)
    splats = finish_splats(path, "the SOG", means, log_scales, quats, logits, sh_all)
    return splats, f"SOG version {version}, {count} splats, SH degree {degree}", {"version": version}


def _sog_rest(path: Path, files: _SogFiles, shn: dict, version: int, count: int, sh_dc: np.ndarray):
    """sh [N, K, 3] with the SOG's palette of SH rest appended to the DC term, and the degree."""
    names = shn.get("files")
    if not isinstance(names, list) or len(names) < 2:
        raise SceneFormatError(path, "SOG meta.json: shN needs two files (centroids, labels)")
    grid = files.image(names[0], 64 * 15 * _MAX_CENTROID_ROWS)
    height, width = grid.shape[:2]
    if version == 2:
        degree = shn.get("bands")
        if isinstance(degree, bool) or degree not in (1, 2, 3):
            raise SceneFormatError(path, f"SOG meta.json: shN.bands must be 1, 2 or 3, got {degree!r}")
        book = _numbers(path, shn.get("codebook"), 256, "shN.codebook")
        palette = shn.get("count")
        if isinstance(palette, bool) or not isinstance(palette, int) or palette < 0:
            raise SceneFormatError(path, f"SOG meta.json: shN.count must be a count, got {palette!r}")
    else:
        degree = _SOG_BANDS_V1.get(width)
        if degree is None:
            raise SceneFormatError(path, f"SOG shN centroid image is {width} wide: no SH degree (192, 512 or 960)")
        low, high = (float(_numbers(path, [shn.get(k)], 1, f"shN.{k}")[0]) for k in ("mins", "maxs"))
        book = low + (high - low) * np.arange(256) / 255.0
    coefficients = sh_coefficients(degree) - 1
    if width != 64 * coefficients:
        raise SceneFormatError(path, f"SOG shN centroid image is {width} wide, expected {64 * coefficients}")
    if version == 1:
        palette = (width // coefficients) * height
    labels_rgba = files.texels(names[1], count)
    labels = labels_rgba[:, 0].astype(np.int64) | (labels_rgba[:, 1].astype(np.int64) << 8)
    cols = (labels % 64)[:, None] * coefficients + np.arange(coefficients)[None, :]  # [N, K']
    rows = np.minimum(labels // 64, height - 1)[:, None]
    texels = grid[rows, np.minimum(cols, width - 1), :3]  # [N, K', 3]
    rest = book[texels]
    rest[(labels >= palette) | (labels // 64 >= height)] = 0.0
    return np.concatenate([sh_dc, rest], 1), degree


def read_sog(path: str | os.PathLike) -> Splats:
    """Reads a PlayCanvas SOG scene: a bundled `.sog` zip, or a `meta.json` with its WebP images beside it.

    Versions 1 (no "version" in meta.json) and 2 (codebooks), as splat-transform reads them. Images are
    decoded with Pillow (its WebP support is needed); streamed SOG (`lod-meta.json`) is not read.

    Raises:
      SceneFormatError: (naming the file) a meta.json that is no JSON or lacks a field, a missing or
        undecodable image, an image with fewer texels than splats, a wrong centroid image width.
    """
    path = check_input_file(path, "SOG file")
    return decode_sog(path)[0]
