"""The splat file formats people share besides the reference 3DGS PLY: reading, sniffing, writing.

Every reader returns `Splats` in the reference layout's raw parameters (`waldo_jax.splats.model`):
means, log-scales, quaternions w first, opacity logits, sh [N, K, 3] with sh[:, 0] = f_dc and
colour = SH_C0 f_dc + 0.5. Formats (`FORMATS` names them; `splat_format` tells one from its content):

  ply             the reference layout, read by `waldo_jax.splats.io.read_splat_ply`;
  compressed_ply  PlayCanvas / SuperSplat chunked PLY, also gsplat's `ply_compressed` export;
  splat           antimatter15's `.splat`: 32-byte rows, no header, degree 0;
  spz             Niantic's `.spz`, versions 1 to 3 (gzip) and 4 (zstd streams);
  sog             PlayCanvas SOG, versions 1 and 2: a `.sog` zip or a `meta.json` beside WebP images.

glTF `KHR_gaussian_splatting` is not read. Coordinates are taken as stored, in the frame of the PLY the
file was made from (see docs/splats.md, "Formats", for the SPZ axes). Stored bytes are u; quantised
opacities end at 0 and 1, whose logits are infinite: the end bytes decode to the middle of their
rounding interval instead (`common.opacity_logits`).

One module per format (`dot_splat`, `spz`, `compressed_ply`, `sog`, each citing its reference), their
shared helpers in `common`; this package tells the formats apart and reads any of them.
"""

from __future__ import annotations

import dataclasses
import gzip
import io
import os
import zipfile
import zlib
from pathlib import Path
from typing import Dict, Optional

import numpy as np

from waldo_jax.io import parse_json
from waldo_jax.errors import SceneFormatError, WaldoError, check_input_file
from waldo_jax.scenes.ply import read_ply_header
from waldo_jax.splats.formats.common import SH_C0 as SH_C0
from waldo_jax.splats.formats.compressed_ply import CHUNK_BOUNDS as CHUNK_BOUNDS
from waldo_jax.splats.formats.compressed_ply import CHUNK_COLOURS as CHUNK_COLOURS
from waldo_jax.splats.formats.compressed_ply import PACKED as PACKED
from waldo_jax.splats.formats.compressed_ply import decode_compressed_ply
from waldo_jax.splats.formats.compressed_ply import morton_order as morton_order
from waldo_jax.splats.formats.compressed_ply import read_compressed_ply as read_compressed_ply
from waldo_jax.splats.formats.compressed_ply import write_compressed_ply as write_compressed_ply
from waldo_jax.splats.formats.dot_splat import decode_dot_splat
from waldo_jax.splats.formats.ply import read_splat_ply as read_splat_ply
from waldo_jax.splats.formats.dot_splat import importance_order as importance_order
from waldo_jax.splats.formats.dot_splat import read_antimatter_splat as read_antimatter_splat
from waldo_jax.splats.formats.dot_splat import write_antimatter_splat as write_antimatter_splat
from waldo_jax.splats.formats.sog import decode_sog
from waldo_jax.splats.formats.sog import read_sog as read_sog
from waldo_jax.splats.formats.spz import flip_axes as flip_axes
from waldo_jax.splats.formats.spz import decode_spz
from waldo_jax.splats.formats.spz import read_spz as read_spz
from waldo_jax.splats.formats.spz import spz_axis_flips as spz_axis_flips
from waldo_jax.splats.formats.spz import write_spz as write_spz
from waldo_jax.splats.model import Splats

__all__ = [
    "FORMATS",
    "SplatFile",
    "splat_format",
    "find_splat_file",
    "read_splat_file",
    "read_antimatter_splat",
    "write_antimatter_splat",
    "read_spz",
    "write_spz",
    "read_compressed_ply",
    "write_compressed_ply",
    "read_sog",
    "morton_order",
    "importance_order",
    "spz_axis_flips",
]

FORMATS: Dict[str, str] = {
    "ply": "3DGS PLY (reference layout)",
    "compressed_ply": "compressed PLY (SuperSplat / gsplat ply_compressed)",
    "splat": "antimatter15 .splat",
    "spz": "Niantic .spz (versions 1-4)",
    "sog": "PlayCanvas SOG (.sog, or meta.json beside WebP images)",
}
_READ = "; ".join(FORMATS.values())


@dataclasses.dataclass(frozen=True, eq=False)
class SplatFile:
    """A splat file read by `read_splat_file`.

    Attributes:
      splats: the splats, all rows valid.
      format: a key of `FORMATS`.
      path: the file read (a SOG's `meta.json` or `.sog`).
      details: what the file said about itself, in words (version, SH degree, flags, extensions).
      extras: the same as data, e.g. {"version": 4, "antialiased": True, "safe_orbit": {...}}.
    """

    splats: Splats
    format: str
    path: Path
    details: str
    extras: dict


# ---------------------------------------------------------------------------------------------
# Telling the formats apart.


def _is_sog_meta(data: bytes) -> bool:
    try:
        meta = parse_json(data, "meta.json")
    except WaldoError:
        return False
    # Two of its four sections make it a SOG's meta.json, so that the SOG reader names the one it lacks
    # (a meta.json without sh0 had been "a JSON file without 'frames'", a scene's words).
    return isinstance(meta, dict) and sum(k in meta for k in ("means", "scales", "quats", "sh0")) >= 2


def _plausible_dot_splat(raw: bytes) -> bool:
    """True when 32-byte rows decode to finite positions and finite positive scales."""
    rows = np.frombuffer(raw, "<f4", count=len(raw) // 4).reshape(-1, 8)[:, :6]
    with np.errstate(invalid="ignore"):
        return bool(np.all(np.isfinite(rows)) and np.all(rows[:, 3:] > 0))


def splat_format(path: str | os.PathLike) -> Optional[str]:
    """The format of the splat file at `path` (a key of `FORMATS`), from its content, else None.

    PLY (`ply\\n`; `compressed_ply` when it has a `chunk` element or `packed_position`), SPZ (`NGSP`, or
    gzip whose first bytes are `NGSP`), SOG (a zip holding `meta.json`, or a JSON file with two or more of
    `means`, `scales`, `quats` and `sh0`) are told by their magic bytes. A `.splat` file has none: it is one when
    its name ends in `.splat`, its size is a non-zero multiple of 32 and its first 4,096 rows decode to
    finite positions and finite positive scales. A folder, a missing or unreadable file gives None.
    """
    path = Path(path)
    try:
        if not path.is_file():
            return None
        size = path.stat().st_size
        with open(path, "rb") as f:
            head = f.read(1 << 16)
    except OSError:
        return None
    if head.startswith(b"ply\n") or head.startswith(b"ply\r\n"):
        try:
            with open(path, "rb") as f:  # the whole header (up to its limit), not only the first 64 KiB
                header = read_ply_header(f, path)
        except SceneFormatError:
            return "ply"
        except OSError:
            return None
        vertex = header.element("vertex")
        packed = vertex is not None and "packed_position" in dict(vertex.properties)
        return "compressed_ply" if packed or header.element("chunk") is not None else "ply"
    if head[:4] == b"NGSP":
        return "spz"
    if head[:2] == b"\x1f\x8b":
        try:
            with gzip.GzipFile(fileobj=io.BytesIO(head)) as g:
                return "spz" if g.read(4) == b"NGSP" else None
        except (OSError, EOFError, zlib.error):
            return None
    if head[:4] == b"PK\x03\x04":
        try:
            with zipfile.ZipFile(path) as z:
                return "sog" if "meta.json" in z.namelist() else None
        except (OSError, zipfile.BadZipFile, ValueError):
            return None
    if head.lstrip()[:1] == b"{" and size < (64 << 20):
        try:
            return "sog" if _is_sog_meta(path.read_bytes()) else None
        except OSError:
            return None
    if path.suffix.lower() == ".splat" and size and size % 32 == 0:
        return "splat" if _plausible_dot_splat(head[: min(len(head), 4096 * 32)]) else None
    return None


def find_splat_file(folder: str | os.PathLike) -> Optional[Path]:
    """The one splat file (any format but a plain PLY) directly in `folder`, or None when there is none.

    A SOG folder's `meta.json` counts as its file. Raises a SceneFormatError when there are several.
    """
    folder = Path(folder)
    try:
        entries = sorted(p for p in folder.iterdir() if p.is_file())
    except OSError as e:
        raise SceneFormatError(folder, f"cannot list this folder ({e.strerror or e})") from None
    found = [p for p in entries if p.suffix.lower() in (".splat", ".spz", ".sog", ".json", ".ply")]
    found = [p for p in found if splat_format(p) not in (None, "ply")]
    if len(found) > 1:
        names = ", ".join(p.name for p in found[:4])
        raise SceneFormatError(folder, f"several splat files here ({names}): name the one to read")
    return found[0] if found else None


def _has_other_magic(path: Path) -> bool:
    """Whether the file starts with another format's magic bytes (PLY, SPZ, gzip, zip, JSON)."""
    try:
        with open(path, "rb") as f:
            head = f.read(8)
    except OSError:
        return False
    return head.startswith((b"ply\n", b"ply\r\n", b"NGSP", b"\x1f\x8b", b"PK\x03\x04")) or head.lstrip()[:1] == b"{"


def read_splat_file(path: str | os.PathLike) -> SplatFile:
    """Reads a splat file of any format in `FORMATS`, told from its content (`splat_format`).

    Raises:
      DataNotFoundError: no such file.
      SceneFormatError: (naming the file) a file of no format read here (the message lists them), or
        a malformed file of one (see each reader).
    """
    path = check_input_file(path, "splat file")
    fmt = splat_format(path)
    if fmt is None and path.suffix.lower() == ".splat" and not _has_other_magic(path):
        fmt = "splat"  # a .splat has no magic bytes: its decoder names what is wrong (size, rows, scales)
    if fmt is None:
        raise SceneFormatError(
            path,
            f"not a splat file of any format read here (formats read: {_READ}; glTF is not read; an antimatter15 "
            "file, which has no magic bytes, is told by its .splat extension)",
        )
    if fmt == "ply":
        splats = read_splat_ply(path)
        return SplatFile(splats, fmt, path, f"splat PLY, SH degree {splats.sh_degree}", {})
    reader = {
        "compressed_ply": decode_compressed_ply,
        "splat": decode_dot_splat,
        "spz": decode_spz,
        "sog": decode_sog,
    }[fmt]
    splats, details, extras = reader(path)
    return SplatFile(splats, fmt, path, details, extras)
