"""Reading PLY files: the header (`parse_ply_header`, `read_ply_header`) and the x, y, z vertex
positions of a point cloud, with its vertex colours on request (ASCII or binary), e.g. nerfstudio's
`sparse_pc.ply`. The splat reader (`waldo_jax.splats.io`) shares the header parser.
"""

from __future__ import annotations

import collections
import dataclasses
import os
import re
from typing import Optional, Tuple

import numpy as np

from waldo_jax.errors import SceneFormatError, read_input_file
from waldo_jax.scenes.common import input_file, one_line_errors

__all__ = ["PlyElement", "PlyHeader", "parse_ply_header", "read_ply_header", "read_ply_points"]

_PLY_TYPES = {
    "char": "i1",
    "int8": "i1",
    "uchar": "u1",
    "uint8": "u1",
    "short": "i2",
    "int16": "i2",
    "ushort": "u2",
    "uint16": "u2",
    "int": "i4",
    "int32": "i4",
    "uint": "u4",
    "uint32": "u4",
    "float": "f4",
    "float32": "f4",
    "double": "f8",
    "float64": "f8",
}
_FORMATS = ("ascii", "binary_little_endian", "binary_big_endian")
# A header longer than this is no PLY header (a splat scene's is about 1.5 kB).
_MAX_HEADER_BYTES = 1 << 20
_END_HEADER = re.compile(rb"\nend_header\r?\n")


@dataclasses.dataclass(frozen=True)
class PlyElement:
    """One `element` of a PLY header: its name, row count and (property name, type) pairs, the type
    one of `_PLY_TYPES`'s keys or "list"."""

    name: str
    count: int
    properties: Tuple[Tuple[str, str], ...]

    @property
    def has_lists(self) -> bool:
        return any(t == "list" for _, t in self.properties)

    def dtype(self, order: str = "<") -> np.dtype:
        """The NumPy structured dtype of one binary row (scalar properties only)."""
        return np.dtype([(p, order + _PLY_TYPES[t]) for p, t in self.properties])


@dataclasses.dataclass(frozen=True)
class PlyHeader:
    """A parsed PLY header: `format` is "ascii", "binary_little_endian" or "binary_big_endian";
    `body_start` is the byte offset of the data after `end_header`."""

    format: str
    elements: Tuple[PlyElement, ...]
    body_start: int

    def element(self, name: str) -> Optional[PlyElement]:
        return next((e for e in self.elements if e.name == name), None)

    def offset_of(self, name: str) -> int:
        """Byte offset of element `name`'s binary data (ValueError if a list element precedes it)."""
        offset = self.body_start
        for element in self.elements:
            if element.name == name:
                return offset
            if element.has_lists:
                raise ValueError(f"element {element.name!r} with list properties precedes the {name!r} element")
            offset += element.count * element.dtype().itemsize
        raise KeyError(name)


def _is_version_one(text: str) -> bool:
    """A PLY format line's version that reads as 1 ("1.0", "1")."""
    try:
        return float(text) == 1.0
    except ValueError:
        return False


def parse_ply_header(raw: bytes, path: str | os.PathLike) -> PlyHeader:
    """Parses the header at the start of `raw` (the file's first bytes, the whole header at least).

    Raises:
      SceneFormatError: no 'ply' magic or no `end_header` line, a malformed line, an unknown format
        or property type, or a property name used twice in an element.
    """
    first = raw[:5].replace(b"\r", b"")
    if not first.startswith(b"ply\n"):
        raise SceneFormatError(path, "not a PLY file (no 'ply' magic or no 'end_header')")
    fmt, elements, pos = None, [], raw.index(b"\n") + 1
    while True:
        newline = raw.find(b"\n", pos, _MAX_HEADER_BYTES)
        if newline < 0 and raw[pos:].strip() == b"end_header":  # a file that ends with its header
            newline = len(raw)
        if newline < 0 and len(raw) > _MAX_HEADER_BYTES:
            raise SceneFormatError(path, f"PLY header without 'end_header' in its first {_MAX_HEADER_BYTES:,} bytes")
        if newline < 0:
            raise SceneFormatError(path, "not a PLY file (no 'ply' magic or no 'end_header')")
        line = raw[pos:newline].decode("ascii", errors="replace").strip()
        pos = newline + 1
        words = line.split()
        if not words or words[0] in ("comment", "obj_info"):
            continue
        if words == ["end_header"]:
            break
        if words[0] == "format" and len(words) >= 2:
            fmt = words[1]
            if len(words) != 3 or not _is_version_one(words[2]):  # the only PLY version there is
                raise SceneFormatError(path, f"PLY format line {line!r}: expected version 1.0")
        elif words[0] == "element" and len(words) == 3 and words[2].isdigit():
            elements.append((words[1], int(words[2]), []))
        elif words[0] == "property" and elements and len(words) == 3 and words[1] in _PLY_TYPES:
            elements[-1][2].append((words[2], words[1]))
        elif words[0] == "property" and elements and len(words) == 5 and words[1] == "list":
            elements[-1][2].append((words[4], "list"))
        elif words[0] == "property" and elements and len(words) == 3:
            raise SceneFormatError(path, f"unknown PLY property type {words[1]!r} (of {words[2]!r})")
        elif words[0] in ("element", "property"):
            raise SceneFormatError(path, f"bad PLY header line {line!r}")
    if fmt not in _FORMATS:
        raise SceneFormatError(path, f"unsupported PLY format {fmt!r}")
    for name, _, props in elements:
        twice = sorted(p for p, uses in collections.Counter(p for p, _ in props).items() if uses > 1)
        if twice:
            raise SceneFormatError(path, f"PLY element {name!r} has the properties {', '.join(twice)} twice")
    return PlyHeader(fmt, tuple(PlyElement(n, c, tuple(p)) for n, c, p in elements), min(pos, len(raw)))


def read_ply_header(file, path: str | os.PathLike) -> PlyHeader:
    """Parses the header of an open binary `file` (read from its start), leaving the file anywhere."""
    file.seek(0)
    raw = b""
    while not _END_HEADER.search(raw) and len(raw) < _MAX_HEADER_BYTES:
        chunk = file.read(1 << 16)
        if not chunk:
            break
        raw += chunk
    return parse_ply_header(raw, path)


def _colour_scale(ply_type: str) -> float:
    """What divides a colour of this PLY type to [0, 1]: the integer maximum, 1 for floats."""
    dtype = np.dtype(_PLY_TYPES[ply_type])
    return float(np.iinfo(dtype).max) if dtype.kind in "iu" else 1.0


def read_ply_points(path: str | os.PathLike, colors: bool = False):
    """Reads the x, y, z vertex coordinates (and the red, green, blue colours) of an ASCII or binary PLY file.

    Supports vertex elements of scalar properties (list properties, e.g. faces, may follow the
    vertices but not precede them in a binary file).

    Args:
      path: the .ply file.
      colors: also return the vertex colours.

    Returns:
      float32 [P, 3] vertex positions; with `colors`, (positions, colours), the colours float32
      [P, 3] in [0, 1] (integer properties divided by their type's maximum, e.g. uchar by 255; float
      properties as they are), or None when the vertices have no red, green and blue properties.

    Raises:
      SceneFormatError: the file is not a PLY point cloud this reader understands.
    """
    with one_line_errors():  # a file name with a newline or an escape stays on one line
        path = input_file(path, "PLY file")  # a FIFO would block, /dev/zero never end
        raw = read_input_file(path, "PLY file", lambda problem: SceneFormatError(path, problem))
        header = parse_ply_header(raw, path)
        vertex = header.element("vertex")
        if vertex is None:
            raise SceneFormatError(path, "PLY file has no 'vertex' element")
        prop_names = [p for p, _ in vertex.properties]
        if not all(k in prop_names for k in "xyz"):
            raise SceneFormatError(path, f"PLY vertices lack x, y, z properties (have {prop_names})")
        if vertex.has_lists:
            raise SceneFormatError(path, "PLY vertex element has list properties: not supported")
        rgb = ("red", "green", "blue")
        has_colours = colors and all(k in prop_names for k in rgb)
        wanted = list("xyz") + (list(rgb) if has_colours else [])
        count = vertex.count
        try:
            if header.format == "ascii":
                lines = raw[header.body_start :].decode("ascii").split("\n")
                skip = sum(e.count for e in header.elements[: header.elements.index(vertex)])
                rows = [ln.split() for ln in lines[skip : skip + count]]
                table = np.array([[float(r[prop_names.index(k)]) for k in wanted] for r in rows], np.float64)
                if len(table) != count:
                    raise ValueError(f"{len(table)} vertex lines, header says {count}")
            else:
                order = "<" if header.format == "binary_little_endian" else ">"
                offset, row = header.offset_of("vertex"), vertex.dtype(order).itemsize
                if offset + count * row > len(raw):  # a count past the file, checked before NumPy sees it
                    need = offset + count * row
                    raise ValueError(f"the header's {count} vertices need {need} bytes, the file has {len(raw)}")
                data = np.frombuffer(raw, dtype=vertex.dtype(order), count=count, offset=offset)
                table = np.stack([data[k].astype(np.float64) for k in wanted], -1)
        except (ValueError, IndexError, KeyError, UnicodeDecodeError, TypeError) as e:
            raise SceneFormatError(path, f"malformed PLY vertex data ({e})") from None
        table = table.reshape(-1, len(wanted))
        if not np.all(np.isfinite(table[:, :3])):
            raise SceneFormatError(path, "PLY vertices have non-finite coordinates")
        with np.errstate(over="ignore"):
            points = table[:, :3].astype(np.float32)
        if not np.all(np.isfinite(points)):
            raise SceneFormatError(path, "PLY vertices have coordinates beyond float32's range (about 3.4e38)")
        if not colors:
            return points
        if not has_colours:
            return points, None
        types = dict(vertex.properties)
        scale = np.array([_colour_scale(types[k]) for k in rgb])
        rgb_values = table[:, 3:] / scale
        if not np.all(np.isfinite(rgb_values)):
            raise SceneFormatError(path, "PLY vertices have non-finite colours")
        return points, rgb_values.astype(np.float32)
