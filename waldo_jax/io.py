"""Files at the program's edges: reading images, writing PNGs, labelled contact sheets, run folders
that never overwrite, JSON.

Everything here runs on the host (NumPy / Pillow / imageio), at the edges of the program. Every file
is written atomically (`atomic_file`: a temporary file beside it, renamed into place once complete),
so a failed write (disk full, an interrupt) leaves no half-written or empty file behind; and an
interrupted command removes the output folders it created (`discard_unfinished`, called by
`waldo_jax.cli.interrupt`), so a folder of a run exists only once the run is whole.
"""

from __future__ import annotations

import contextlib
import io as _io
import json
import os
import re
import secrets
import shutil
import stat
import warnings
from pathlib import Path
from typing import Any, BinaryIO, Callable, Dict, Iterator, List, Optional, Sequence

import imageio.v3 as iio
import numpy as np
from PIL import Image, ImageDraw, ImageFont

from waldo_jax.errors import (
    MAX_RESOLUTION,
    MIN_RESOLUTION,
    WaldoError,
    check_input_file,
    host_memory_bytes,
    with_article,
)

__all__ = [
    "atomic_file",
    "write_bytes",
    "write_text",
    "to_uint8",
    "png_bytes",
    "save_png",
    "contact_sheet",
    "check_output_dir",
    "prepare_output_dir",
    "created_output_dirs",
    "discard_unfinished",
    "stale_files",
    "write_json",
    "keep_output_dir",
    "MAX_JSON_DEPTH",
    "MAX_JSON_BYTES",
    "json_depth",
    "parse_json",
    "read_json_file",
    "write_transforms",
    "read_image",
]


# What an interrupted command may leave unfinished (see `discard_unfinished`): the temporary files of
# atomic writes in progress, and the output folders `prepare_output_dir` created, in creation order.
_PENDING: set = set()
_CREATED_DIRS: List[Path] = []
_CREATED_FOR: Dict[Path, Path] = {}  # each folder `prepare_output_dir` returned -> the outermost it created


def _open_temp(path: Path) -> tuple:
    """(name, binary file) of a new temporary file beside `path` (mode 0o666 less the umask)."""
    name = str(path.parent / f".{path.name}.{os.getpid()}.{secrets.token_hex(4)}.tmp")
    try:
        fd = os.open(name, os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_BINARY", 0), 0o666)
    except OSError as e:  # said of the file asked for: the temporary name means nothing to the user
        raise OSError(e.errno, e.strerror, str(path)) from None
    return name, os.fdopen(fd, "wb")


@contextlib.contextmanager
def atomic_file(path: str | os.PathLike) -> Iterator[BinaryIO]:
    """A binary file to write `path` through: a temporary file in the same folder, flushed to disk and
    renamed onto `path` when the block ends; removed (and `path` left as it was) if the block raises."""
    path = Path(path)
    name, f = _open_temp(path)
    _PENDING.add(name)
    try:
        with f:
            yield f
            f.flush()
            os.fsync(f.fileno())
        os.replace(name, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(name)
        raise
    finally:
        _PENDING.discard(name)


def write_bytes(path: str | os.PathLike, data: bytes) -> None:
    """Writes `data` to `path` atomically."""
    with atomic_file(path) as f:
        f.write(data)


def write_text(path: str | os.PathLike, text: str) -> None:
    """Writes UTF-8 `text` to `path` atomically."""
    write_bytes(path, text.encode("utf-8"))


def to_uint8(image: np.ndarray) -> np.ndarray:
    """float [H, W, 3] in [0, 1] (NaN as 0) -> uint8 [H, W, 3]."""
    image = np.nan_to_num(np.asarray(image, np.float32), nan=0.0, posinf=1.0, neginf=0.0)
    return (np.clip(image, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)


def png_bytes(image: np.ndarray) -> bytes:
    """A float [H, W, 3] image in [0, 1] (or uint8) encoded as PNG."""
    image = np.asarray(image)
    buffer = _io.BytesIO()
    Image.fromarray(image if image.dtype == np.uint8 else to_uint8(image)).save(buffer, format="PNG")
    return buffer.getvalue()


def save_png(path: str | os.PathLike, image: np.ndarray) -> None:
    """Writes a float [H, W, 3] image in [0, 1] (or uint8) as PNG, atomically."""
    write_bytes(path, png_bytes(image))


def _font(size: int):
    try:
        return ImageFont.load_default(size=size)
    except TypeError:  # Pillow < 10.1 has a single fixed-size bitmap font
        return ImageFont.load_default()


def contact_sheet(
    images: Sequence[np.ndarray],
    columns: Optional[int] = None,
    labels: Optional[Sequence[Optional[str]]] = None,
    pad: int = 2,
    min_cell: int = 96,
    row_titles: Optional[Sequence[str]] = None,
    caption: Optional[str] = None,
    column_titles: Optional[Sequence[str]] = None,
) -> np.ndarray:
    """Tiles images into one uint8 picture, with an optional label written on each tile.

    Args:
      images: N images [H, W, 3] (float in [0, 1] or uint8) of one size; `None` leaves a cell empty.
      columns: tiles per row (default: about square).
      labels: N strings (or None) written in the tile's top-left corner on a dark band.
      pad: pixels between tiles.
      min_cell: small images are enlarged (nearest neighbour) so that a tile is at least this wide,
        keeping labels readable.
      row_titles: optional title per row, drawn in a band left of the row.
      caption: optional text above the tiles (wrapped to the sheet's width): what the labels' scores are.
      column_titles: optional title per column, drawn in a band above the first row.

    Returns:
      uint8 [H_sheet, W_sheet, 3].
    """
    present = [im for im in images if im is not None]
    if not present:
        raise ValueError("contact_sheet needs at least one image")
    h, w = np.asarray(present[0]).shape[:2]
    scale = max(1, int(np.ceil(min_cell / w)))
    th, tw = h * scale, w * scale
    n = len(images)
    columns = columns or int(np.ceil(np.sqrt(n)))
    rows = int(np.ceil(n / columns))
    title_w = 0
    font = _font(max(10, min(16, tw // 8)))
    if row_titles:
        title_w = 12 + max(int(ImageDraw.Draw(Image.new("RGB", (1, 1))).textlength(t, font=font)) for t in row_titles)
    width = title_w + columns * tw + (columns + 1) * pad
    lines = _wrap(caption, font, width - 12) if caption else []
    line_h = font.getbbox("Ag")[3] + 3
    caption_h = len(lines) * line_h + 6 if lines else 0
    top = caption_h + (line_h + 4 if column_titles else 0)
    sheet = Image.new("RGB", (width, top + rows * th + (rows + 1) * pad), (255, 255, 255))
    draw = ImageDraw.Draw(sheet)
    for n, line in enumerate(lines):
        draw.text((6, 4 + n * line_h), line, fill=(0, 0, 0), font=font)
    for i, image in enumerate(images):
        r, c = divmod(i, columns)
        x0, y0 = title_w + pad + c * (tw + pad), top + pad + r * (th + pad)
        if image is None:
            continue
        tile = to_uint8(image) if np.asarray(image).dtype != np.uint8 else np.asarray(image)
        if tile.shape[:2] != (h, w):
            raise ValueError(f"contact_sheet: image {i} is {tile.shape[1]}x{tile.shape[0]}, expected {w}x{h}")
        tile = np.repeat(np.repeat(tile, scale, 0), scale, 1)
        sheet.paste(Image.fromarray(tile), (x0, y0))
        if labels is not None and labels[i]:
            box = draw.textbbox((x0 + 3, y0 + 2), labels[i], font=font)
            draw.rectangle((box[0] - 2, box[1] - 1, box[2] + 2, box[3] + 1), fill=(0, 0, 0))
            draw.text((x0 + 3, y0 + 2), labels[i], fill=(255, 255, 255), font=font)
    for c, title in enumerate(column_titles or []):
        draw.text((title_w + pad + c * (tw + pad) + 3, caption_h + 2), title, fill=(0, 0, 0), font=font)
    for r, title in enumerate(row_titles or []):
        draw.text((6, top + pad + r * (th + pad) + th // 2 - 6), title, fill=(0, 0, 0), font=font)
    return np.asarray(sheet)


def _wrap(text: str, font, width: int) -> List[str]:
    """`text` in lines no wider than `width` pixels in `font` (a longer single word keeps its own line)."""
    measure = ImageDraw.Draw(Image.new("RGB", (1, 1)))
    lines: List[str] = []
    line = ""
    for word in text.split():
        trial = f"{line} {word}" if line else word
        if line and measure.textlength(trial, font=font) > width:
            lines.append(line)
            line = word
        else:
            line = trial
    return lines + [line] if line else lines


def prepare_output_dir(path: str | os.PathLike, force: bool = False, can_force: bool = True) -> Path:
    """Creates an output folder, refusing to reuse a non-empty one unless `force`.

    `can_force` False: the command has no `--force`, and the error does not suggest one.

    Raises:
      WaldoError: the folder exists and is not empty (and `force` is False), is a file, or cannot be
        created or written (see `check_output_dir`).
    """
    path = check_output_dir(path, force, can_force)
    top = None  # the outermost folder this call creates (parents=True may create several)
    missing = path.absolute()
    while not os.path.lexists(missing) and missing != missing.parent:
        top, missing = missing, missing.parent
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise WaldoError(f"{path}: cannot create the output directory ({e.strerror or e})") from None
    if top is not None:
        _CREATED_DIRS.append(top)
        _CREATED_FOR[path.absolute()] = top
    return path


def created_output_dirs() -> List[Path]:
    """The output folders `prepare_output_dir` created in this process, oldest first (absolute paths;
    the outermost folder each call created)."""
    return list(_CREATED_DIRS)


def keep_output_dir(path: str | os.PathLike) -> bool:
    """Declares the output folder `path` usable as it is, when `prepare_output_dir` created it for this
    command: an interrupt from now on leaves it, and the folders created above it, in place. Any other
    folder (one that existed before, or a part of a larger output folder) is left to the command's rules.
    Returns whether `path` was such a folder."""
    top = _CREATED_FOR.pop(Path(path).absolute(), None)
    if top is None or top not in _CREATED_DIRS:
        return False
    _CREATED_DIRS.remove(top)
    return True


def discard_unfinished(folders: Sequence[Path] = ()) -> List[Path]:
    """Removes what an interrupted command leaves: the temporary files of atomic writes in progress
    (`atomic_file`) and `folders` (the new output folders it created, whose contents are by
    definition incomplete). Never raises. Returns the folders removed."""
    for name in list(_PENDING):
        with contextlib.suppress(OSError):
            os.unlink(name)
    removed = []
    for folder in reversed(list(folders)):
        shutil.rmtree(folder, ignore_errors=True)
        if not os.path.lexists(folder):
            removed.append(Path(folder))
        with contextlib.suppress(ValueError):
            _CREATED_DIRS.remove(Path(folder))
    return removed


def check_output_dir(path: str | os.PathLike, force: bool = False, can_force: bool = True) -> Path:
    """`prepare_output_dir`'s checks without creating anything: call it before slow or fallible work,
    and `prepare_output_dir` once everything is validated, so a bad argument leaves no empty folder
    and a long computation (training) is never lost to an output folder it cannot write.

    Checks: the path is not empty, every name in it fits the file system's limit and the whole path,
    with the files the commands write inside it (`OUTPUT_DEPTH_BYTES`), its path limit; it is no dangling
    link; the folder is a directory (or does not exist yet) and is empty unless `force`, and it (or its
    nearest existing parent) is writable."""
    if not os.fspath(path).strip():
        raise WaldoError("the output folder is empty text: name a folder (. for this one)")
    path = Path(path)
    existing = path.absolute()
    while not os.path.exists(existing) and existing != existing.parent:
        existing = existing.parent
    name_max = _name_max(existing)
    for part in path.parts:
        if len(os.fsencode(part)) > name_max:
            raise WaldoError(
                f"{part[:24]}...: a name of {len(os.fsencode(part))} bytes in --out; this file system "
                f"allows at most {name_max}"
            )
    full, path_max = len(os.fsencode(os.path.abspath(path))), _path_max(existing)
    if full + OUTPUT_DEPTH_BYTES > path_max:
        raise WaldoError(
            f"{str(path)[:24]}...: an output folder path of {full} bytes; with the files written inside it (up "
            f"to {OUTPUT_DEPTH_BYTES} bytes more) it passes this system's limit of {path_max} bytes"
        )
    if os.path.islink(path) and not path.exists():
        raise WaldoError(f"{path}: a link to {os.readlink(path)!r}, which does not exist (or loops)")
    if path.exists() and not path.is_dir():
        raise WaldoError(f"{path}: exists and is not a directory")
    if not existing.is_dir():
        raise WaldoError(f"{path}: cannot create the output directory: {existing} is not a directory")
    if not os.access(existing, os.W_OK | os.X_OK):
        raise WaldoError(f"{path}: cannot write there: {existing} is not writable (permission denied)")
    if path.is_dir() and any(path.iterdir()) and not force:
        advice = "choose another --out or pass --force" if can_force else "choose another --out"
        raise WaldoError(f"{path}: output directory exists and is not empty ({advice})")
    return path


# The longest path a command writes below its output folder, a temporary file of an atomic write included
# (e.g. "closeups/.egps_closeup_07.png.<pid>.<8 hex>.tmp"): 128 bytes leaves room.
OUTPUT_DEPTH_BYTES = 128


def _path_max(folder: Path) -> int:
    """The longest path (bytes) the system allows for files under the existing `folder` (4096 if it cannot be asked)."""
    try:
        return int(os.pathconf(folder, "PC_PATH_MAX"))
    except (AttributeError, OSError, ValueError):
        return 4096


def _name_max(folder: Path) -> int:
    """The longest file name (bytes) the file system of the existing `folder` allows (255 if it cannot be asked)."""
    try:
        return int(os.pathconf(folder, "PC_NAME_MAX"))
    except (AttributeError, OSError, ValueError):
        return 255


def stale_files(folder: str | os.PathLike, pattern: str, keep: Sequence[str]) -> list:
    """Files of `folder` whose names match the regular expression `pattern` and are not in `keep`: what
    an earlier run wrote that a new run into the same folder (`--force`) will not overwrite. The
    caller removes them once its own files are written, so the folder holds one run, not two."""
    keep = set(keep)
    return sorted(
        p for p in Path(folder).iterdir() if p.is_file() and re.fullmatch(pattern, p.name) and p.name not in keep
    )


# Bounds of every JSON file read (scenes, poses, cameras, results, checkpoint headers): nothing waldo_jax
# or the tools it reads writes nests deeper than a few levels or holds more than some MB of JSON; a
# deeper file would exhaust Python's recursion, a larger one the machine's memory.
MAX_JSON_DEPTH = 64
MAX_JSON_BYTES = 512 * 2**20
# What JSON text takes parsed, at most (tracemalloc, CPython 3.11, files of 200,000 items): 8 bytes a byte of
# text (`[0.5,0.5,...]` takes 8.2, strings 6) and more for each container: a list about 64 bytes
# (`[[0],[0],...]` took 24 a byte), a dict about 180 (`[{"a":1},...]` 24 a byte). `_parsed_bytes` counts
# 10 a byte (a list holding its items grows by an eighth), 80 a `[` and 200 a `{` (brackets in strings too:
# an overestimate): at or above every case measured (tests/test_bad_input.py).
_PARSED_PER_BYTE, _PARSED_PER_LIST, _PARSED_PER_DICT = 10, 80, 200


def _parsed_bytes(data: bytes) -> int:
    """An upper estimate of the memory `json.loads` takes for `data` (see `_PARSED_PER_BYTE`)."""
    return _PARSED_PER_BYTE * len(data) + _PARSED_PER_LIST * data.count(b"[") + _PARSED_PER_DICT * data.count(b"{")


_JSON_STRING = re.compile(rb'"(?:[^"\\\n]|\\.)*"')
_DEPTH_CHUNK = 1 << 24


def json_depth(raw: bytes) -> int:
    """The deepest nesting of arrays and objects in JSON text `raw` (brackets inside strings not counted)."""
    stripped = _JSON_STRING.sub(b'""', raw)
    deepest, depth = 0, 0
    for start in range(0, len(stripped), _DEPTH_CHUNK):
        chunk = np.frombuffer(stripped[start : start + _DEPTH_CHUNK], np.uint8)
        step = np.zeros(len(chunk), np.int32)
        step[(chunk == ord("[")) | (chunk == ord("{"))] = 1
        step[(chunk == ord("]")) | (chunk == ord("}"))] = -1
        levels = depth + np.cumsum(step)
        if len(levels):
            deepest, depth = max(deepest, int(levels.max())), int(levels[-1])
    return deepest


def _json_int(text: str):
    """A JSON integer as an int while it fits 64 bits (20 characters with the sign), else as the float it
    rounds to (inf past 1.8e308): readers then refuse it as a number out of range, by its key, instead of
    overflowing in a cast (and Python's int() refuses texts of more than 4,300 digits)."""
    return int(text) if len(text) <= 20 else float(text)


def parse_json(
    raw: str | bytes,
    path: str | os.PathLike,
    what: str = "JSON file",
    error: Optional[Callable[[str], Exception]] = None,
) -> Any:
    """Parses JSON text read from `path`, refusing text over MAX_JSON_BYTES, nesting deeper than
    MAX_JSON_DEPTH, more than the free memory could hold parsed, bytes that are not UTF-8 and malformed
    JSON: `error(problem)` is raised (default: a WaldoError naming `path`), so each reader keeps its own
    error type."""

    def fail(problem: str) -> Exception:
        return WaldoError(f"{path}: {problem}") if error is None else error(problem)

    data = raw.encode("utf-8", "surrogatepass") if isinstance(raw, str) else bytes(raw)
    if len(data) > MAX_JSON_BYTES:
        raise fail(f"{what} of {len(data) / 2**20:.0f} MiB (at most {MAX_JSON_BYTES // 2**20} MiB)")
    depth = json_depth(data)
    if depth > MAX_JSON_DEPTH:
        raise fail(f"{what} nests {depth} levels deep (at most {MAX_JSON_DEPTH})")
    need, available = _parsed_bytes(data), host_memory_bytes()
    if available and need > available:  # checked before parsing: Linux kills, it raises no MemoryError
        raise fail(
            f"{what} of {len(data) / 2**20:,.1f} MiB may take up to {need / 2**30:,.2f} GiB parsed, more than "
            f"the {available / 2**30:.1f} GiB this machine has free"
        )
    try:
        return json.loads(data.decode("utf-8"), parse_int=_json_int)
    except UnicodeDecodeError as e:
        raise fail(f"{what} is not UTF-8 text ({e.reason} at byte {e.start})") from None
    except json.JSONDecodeError as e:
        raise fail(f"malformed JSON at line {e.lineno}, column {e.colno}: {e.msg}") from None
    except RecursionError:  # pragma: no cover - the depth bound keeps the parser far from the limit
        raise fail(f"{what} nests too deep to parse") from None


def read_json_file(
    path: str | os.PathLike, what: str = "JSON file", error: Optional[Callable[[str], Exception]] = None
) -> Any:
    """`parse_json` of the file at `path`, a regular file (not a FIFO, device or folder) whose size is checked
    before it is read."""
    path = Path(path)
    try:
        status = path.stat()
        if not stat.S_ISREG(status.st_mode):  # a FIFO would block the read for ever, a device fill memory
            kind = "a directory" if stat.S_ISDIR(status.st_mode) else "a FIFO, socket or device"
            problem = f"{kind}, where {with_article(what)} was expected"
            raise WaldoError(f"{path}: {problem}") if error is None else error(problem)
        size = status.st_size
        if size > MAX_JSON_BYTES:
            problem = f"{what} of {size / 2**20:.0f} MiB (at most {MAX_JSON_BYTES // 2**20} MiB)"
            raise WaldoError(f"{path}: {problem}") if error is None else error(problem)
        raw = path.read_bytes()
    except OSError as e:
        problem = f"cannot read this {what} ({e.strerror or e})"
        raise (WaldoError(f"{path}: {problem}") if error is None else error(problem)) from None
    return parse_json(raw, path, what, error)


def _json_ready(obj: Any) -> Any:
    """`obj` with NumPy values as Python ones and NaN / infinity as None (they are not JSON)."""
    if isinstance(obj, dict):
        return {k: _json_ready(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_json_ready(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return _json_ready(obj.tolist())
    if isinstance(obj, np.generic):
        obj = obj.item()
    if isinstance(obj, float) and not np.isfinite(obj):
        return None
    return obj


def write_json(path: str | os.PathLike, obj: Any) -> None:
    """Writes JSON atomically, NumPy values converted and NaN / infinity written as null (strict JSON)."""
    write_text(path, json.dumps(_json_ready(obj), indent=2, allow_nan=False) + "\n")


def write_transforms(
    path: str | os.PathLike, c2w: np.ndarray, intrinsics, file_names: Sequence[str], extra: Optional[dict] = None
) -> None:
    """Writes cameras as an instant-ngp/nerfstudio-style `transforms.json` (OpenGL c2w).

    Args:
      path: output file.
      c2w: [N, 4, 4] camera-to-world matrices.
      intrinsics: a `waldo_jax.types.Intrinsics`.
      file_names: N image paths relative to the file's folder.
      extra: more top-level keys.
    """
    d = intrinsics.to_dict()
    meta = {
        "w": d["width"],
        "h": d["height"],
        "fl_x": d["fx"],
        "fl_y": d["fy"],
        "cx": d["cx"],
        "cy": d["cy"],
        "k1": d["k1"],
        "k2": d["k2"],
        "p1": d["p1"],
        "p2": d["p2"],
        "camera_angle_x": float(2 * np.arctan(0.5 * d["width"] / d["fx"])),
        "camera_angle_y": float(2 * np.arctan(0.5 * d["height"] / d["fy"])),
    }
    meta.update(extra or {})
    c2w = np.asarray(c2w, np.float64)
    meta["frames"] = [
        {"file_path": name, "transform_matrix": np.round(m, 8).tolist()} for name, m in zip(file_names, c2w)
    ]
    write_json(path, meta)


# ---------------------------------------------------------------------------------------------
# Reading images.


# Pillow modes whose channels are not R, G, B (A): converted to RGB by Pillow (CMYK, YCbCr), or refused
# (LAB, HSV: Pillow has no conversion of its own). imageio returns the stored channels, which read as RGB
# would score a CMYK photo as its negative.
_CONVERTED_COLOUR_MODES = ("CMYK", "YCbCr")
_OTHER_COLOUR_MODES = ("LAB", "HSV")


def read_image(
    path: str | os.PathLike, keep_alpha: bool = False, what: str = "image file", min_side: int = MIN_RESOLUTION
) -> np.ndarray:
    """An image file as float32 [H, W, 3] in [0, 1] ([H, W, 4] with its alpha if `keep_alpha` and it has one).

    Sides must lie in [min_side, MAX_RESOLUTION] (read from the header, before any decoding; a scored
    image needs MIN_RESOLUTION, a --target crop 2), and every value must be finite and in range: a
    float image (TIFF, EXR) in [0, 1], an integer one in [0, its type's maximum]. An HDR or
    unnormalised image is refused, not clipped.

    Raises:
      DataNotFoundError: no such file. WaldoError: not a regular file, not a readable image, too
        small or too large, with NaN / infinite values or values out of range (the message names the file).
    """
    path = check_input_file(path, what)
    if path.stat().st_size == 0:
        raise WaldoError(f"{path}: an empty file, where {with_article(what)} was expected")
    try:
        with Image.open(path) as header:  # the size without decoding: an 8000x8000 file costs nothing
            width, height, mode = *header.size, header.mode
            # Pillow looks no further than the second frame; imageio would decode every frame of an animation
            # before its shape is refused (a 29 KB GIF of 20 frames at 4096x4096 took 2.25 GB).
            frames = 2 if getattr(header, "is_animated", False) else 1
    except Image.DecompressionBombError as exc:  # Pillow refuses to open it: sized far past MAX_RESOLUTION
        raise WaldoError(
            f"{path}: the image is too large ({str(exc).split(' exceeds')[0]}); sides must lie between {min_side} "
            f"and {MAX_RESOLUTION} pixels"
        ) from None
    except Exception:  # not a format Pillow knows: imageio may still read it; its size is checked below
        width = height = mode = None
        frames = 1
    if frames > 1:
        raise WaldoError(
            f"{path}: an image of several frames (an animation or a multi-page file); waldo reads still "
            "images: save the frame you mean as a PNG"
        )
    if width is not None:
        _check_image_size(path, width, height, min_side)
    if mode in _OTHER_COLOUR_MODES:
        raise WaldoError(
            f"{path}: a {mode} image (another colour space: its channels are not red, green and blue); save it as RGB"
        )
    try:
        with warnings.catch_warnings():  # imageio's plugin probing warns about deprecated plugins on junk files
            warnings.simplefilter("ignore", DeprecationWarning)
            if mode in _CONVERTED_COLOUR_MODES:  # imageio hands their channels over as they are stored
                with Image.open(path) as stored:
                    image = np.asarray(stored.convert("RGB"))
            else:
                image = np.asarray(iio.imread(path))
    except Exception as exc:  # imageio raises many types, some with installation advice on later lines
        first = (str(exc).strip().splitlines() or [type(exc).__name__])[0].replace("``", "`")  # imageio's typo
        raise WaldoError(f"{path}: not a readable image ({first[:160]})") from None
    if image.ndim == 4 and image.shape[0] == 1:  # a still GIF comes as one frame of a stack
        image = image[0]
    if image.ndim == 2:
        image = np.repeat(image[..., None], 3, axis=-1)
    if image.ndim == 3 and image.shape[-1] == 2:  # grey and alpha (a PNG's LA mode): grey as RGB, alpha kept
        image = np.concatenate([np.repeat(image[..., :1], 3, axis=-1), image[..., 1:]], axis=-1)
    if image.ndim != 3 or image.shape[-1] not in (1, 3, 4):
        raise WaldoError(f"{path}: expected a grey, RGB or RGBA image, got an array of shape {image.shape}")
    _check_image_size(path, image.shape[1], image.shape[0], min_side)
    if image.shape[-1] == 1:
        image = np.repeat(image, 3, axis=-1)
    stored = image.dtype
    scale = float(np.iinfo(stored).max) if np.issubdtype(stored, np.integer) else 1.0
    image = image.astype(np.float32) / scale
    if not np.all(np.isfinite(image)):
        raise WaldoError(f"{path}: the image has {int(np.sum(~np.isfinite(image)))} NaN or infinite values")
    low, high = float(image.min()), float(image.max())
    if low < 0.0 or high > 1.0:  # an HDR or unnormalised float image (or signed integers): not clipped silently
        values = f"[{low * scale:g}, {high * scale:g}]"
        raise WaldoError(
            f"{path}: a {stored.name} image with values in {values}, outside the [0, "
            f"{'1' if scale == 1.0 else f'{scale:g}'}] waldo reads; rescale it to [0, 1] (or save it as "
            "8- or 16-bit)"
        )
    if image.shape[-1] == 4 and not keep_alpha:
        image = image[..., :3]
    return image


def _check_image_size(path: Path, width: int, height: int, min_side: int) -> None:
    if not (min_side <= min(width, height) and max(width, height) <= MAX_RESOLUTION):
        raise WaldoError(
            f"{path}: the image is {width}x{height}; sides must lie between {min_side} and {MAX_RESOLUTION} pixels"
        )
