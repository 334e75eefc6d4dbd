"""Reading the x, y, z vertex positions of a PLY point cloud (ASCII or binary), e.g. nerfstudio's `sparse_pc.ply`."""

from __future__ import annotations

import os
from pathlib import Path
from typing import List, Tuple

import numpy as np

from waldo_jax.errors import SceneFormatError

__all__ = ["read_ply_points"]

_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}


def read_ply_points(path: str | os.PathLike) -> np.ndarray:
    """Reads the x, y, z vertex coordinates of an ASCII or binary PLY file.

    Supports vertex elements of scalar properties (list properties, e.g. faces, may follow the
    vertices but not precede them in a binary file).

    Args:
      path: the .ply file.

    Returns:
      float32 [P, 3] vertex positions.

    Raises:
      SceneFormatError: the file is not a PLY point cloud this reader understands.
    """
    path = Path(path)
    try:
        raw = path.read_bytes()
    except OSError as e:
        raise SceneFormatError(path, f"cannot read file ({e.strerror or e})") from None
    end = raw.find(b"end_header")
    if not raw.startswith(b"ply") or end < 0:
        raise SceneFormatError(path, "not a PLY file (no 'ply' magic or no 'end_header')")
    body_start = raw.index(b"\n", end) + 1 if b"\n" in raw[end:] else len(raw)
    header = raw[:end].decode("ascii", errors="replace").splitlines()
    fmt = None
    elements: List[Tuple[str, int, List[Tuple[str, str]]]] = []  # (name, count, [(prop, type)])
    for line in header[1:]:
        words = line.split()
        if not words or words[0] in ("comment", "obj_info"):
            continue
        if words[0] == "format" and len(words) >= 2:
            fmt = words[1]
        elif words[0] == "element" and len(words) == 3:
            try:
                elements.append((words[1], int(words[2]), []))
            except ValueError:
                raise SceneFormatError(path, f"bad PLY header line {line!r}") from None
        elif words[0] == "property" and elements:
            ptype = "list" if words[1] == "list" else words[1]
            elements[-1][2].append((words[-1], ptype))
    if fmt not in ("ascii", "binary_little_endian", "binary_big_endian"):
        raise SceneFormatError(path, f"unsupported PLY format {fmt!r}")
    names = [e[0] for e in elements]
    if "vertex" not in names:
        raise SceneFormatError(path, "PLY file has no 'vertex' element")
    v_index = names.index("vertex")
    _, count, props = elements[v_index]
    prop_names = [p for p, _ in props]
    if not all(k in prop_names for k in "xyz"):
        raise SceneFormatError(path, f"PLY vertices lack x, y, z properties (have {prop_names})")
    if any(t == "list" for _, t in props):
        raise SceneFormatError(path, "PLY vertex element has list properties: not supported")
    try:
        if fmt == "ascii":
            lines = raw[body_start:].decode("ascii").split("\n")
            skip = sum(e[1] for e in elements[:v_index])
            rows = [ln.split() for ln in lines[skip : skip + count]]
            table = np.array([[float(r[prop_names.index(k)]) for k in "xyz"] for r in rows], np.float64)
            if len(table) != count:
                raise ValueError(f"{len(table)} vertex lines, header says {count}")
        else:
            order = "<" if fmt == "binary_little_endian" else ">"
            offset = body_start
            for name, n, eprops in elements[:v_index]:
                if any(t == "list" for _, t in eprops):
                    raise ValueError(f"element {name!r} with list properties precedes the vertices")
                offset += n * sum(np.dtype(_PLY_TYPES[t]).itemsize for _, t in eprops)
            dtype = np.dtype([(p, order + _PLY_TYPES[t]) for p, t in props])
            data = np.frombuffer(raw, dtype=dtype, count=count, offset=offset)
            table = np.stack([data[k].astype(np.float64) for k in "xyz"], -1)
    except (ValueError, IndexError, KeyError, UnicodeDecodeError, TypeError) as e:
        raise SceneFormatError(path, f"malformed PLY vertex data ({e})") from None
    table = table.reshape(-1, 3)
    if not np.all(np.isfinite(table)):
        raise SceneFormatError(path, "PLY vertices have non-finite coordinates")
    return table.astype(np.float32)
