"""The reference 3D Gaussian Splatting PLY (Kerbl et al., SIGGRAPH 2023), read and written.

The PLY is binary little-endian, one `vertex` element of float properties
`x y z nx ny nz f_dc_0..2 f_rest_0..M-1 opacity scale_0..2 rot_0..3`: raw parameters before their
activations (logit opacity, log scales, quaternion w first and not unit), the normals zeros (gsplat's
exporter leaves them out). `f_rest` holds the SH coefficients 1..K-1 channel-major: all red ones, then
all green, then all blue, M = 3 (K - 1).

Names: N splats, K SH coefficients per channel ((degree + 1)^2), M = 3 (K - 1) `f_rest` properties.
"""

from __future__ import annotations

import math
import os
import re
from pathlib import Path
from typing import List, Tuple

import numpy as np

from waldo_jax.errors import SceneFormatError, WaldoError, check_input_file
from waldo_jax.io import atomic_file
from waldo_jax.scenes.ply import PlyElement, PlyHeader, read_ply_header
from waldo_jax.splats.formats.common import SH_C0, check_splat_count, scale_quats
from waldo_jax.splats.model import MAX_SH_DEGREE, Splats, make_splats, sh_coefficients

__all__ = ["splat_ply_properties", "read_splat_ply", "write_splat_ply"]

_XYZ = ("x", "y", "z")
_DC = ("f_dc_0", "f_dc_1", "f_dc_2")
_SCALES = ("scale_0", "scale_1", "scale_2")
_ROTS = ("rot_0", "rot_1", "rot_2", "rot_3")
_RGB = ("red", "green", "blue")
_FLOAT_TYPES = ("float", "float32", "double", "float64")
_REST = re.compile(r"f_rest_(\d+)")


def splat_ply_properties(sh_degree: int, normals: bool = True) -> List[str]:
    """The reference PLY's vertex properties in their order, for SH `sh_degree` (0..3)."""
    rest = 3 * (sh_coefficients(sh_degree) - 1)
    return (
        list(_XYZ)
        + (["nx", "ny", "nz"] if normals else [])
        + list(_DC)
        + [f"f_rest_{i}" for i in range(rest)]
        + ["opacity"]
        + list(_SCALES)
        + list(_ROTS)
    )


# ---------------------------------------------------------------------------------------------
# The splat PLY.


def _splat_layout(path: Path, header: PlyHeader, vertex: PlyElement) -> Tuple[List[str], int, bool]:
    """Checks the vertex properties; returns (properties to read, M, colours from red/green/blue)."""
    types = dict(vertex.properties)
    if "packed_position" in types or header.element("chunk") is not None:
        raise SceneFormatError(
            path,
            "a compressed splat PLY (SuperSplat / gsplat 'ply_compressed'): not the reference layout, "
            "read it with load_splat_model or waldo_jax.splats.formats.read_compressed_ply",
        )
    rest: dict = {}
    for name in types:
        if m := _REST.fullmatch(name):  # f_rest_08 is index 8: writers that pad their numbers exist
            if int(m.group(1)) in rest:
                raise SceneFormatError(
                    path, f"{rest[int(m.group(1))]} and {name} are the same SH coefficient f_rest_{int(m.group(1))}"
                )
            rest[int(m.group(1))] = name
    splat_only = set(_DC) | {"opacity"} | set(_SCALES) | set(_ROTS)
    if all(k in types for k in _XYZ) and not rest and not splat_only & set(types):
        raise SceneFormatError(
            path,
            f"a point cloud, not a splat scene (its vertices have {' '.join(types)}; "
            "a splat PLY's have f_dc_0..2, opacity, scale_0..2, rot_0..3)",
        )
    if vertex.has_lists:
        lists = [p for p, t in vertex.properties if t == "list"]
        raise SceneFormatError(
            path, f"the vertex element has list properties ({', '.join(lists)}): not supported in a splat PLY"
        )
    # nerfstudio's `ply_color_mode="rgb"` export writes red/green/blue in place of f_dc.
    from_rgb = not any(k in types for k in _DC) and all(k in types for k in _RGB)
    wanted = list(_XYZ) + ([] if from_rgb else list(_DC)) + ["opacity"] + list(_SCALES) + list(_ROTS)
    missing = [k for k in wanted if k not in types]
    if missing:
        raise SceneFormatError(
            path,
            f"missing splat properties {', '.join(missing)} (a splat PLY's vertices have "
            "x y z f_dc_0..2 f_rest_* opacity scale_0..2 rot_0..3)",
        )
    if header.format != "binary_little_endian":
        raise SceneFormatError(
            path,
            f"{header.format} PLY is not supported: convert it to binary_little_endian (the reference 3DGS layout)",
        )
    m = len(rest)
    gaps = [f"f_rest_{i}" for i in range(m) if i not in rest]
    if gaps:
        beyond = ", ".join(rest[i] for i in sorted(rest) if i >= m)
        raise SceneFormatError(
            path, f"f_rest_* properties are not numbered 0..{m - 1}: missing {', '.join(gaps[:4])} ({beyond} given)"
        )
    k = m // 3 + 1
    if m % 3 or math.isqrt(k) ** 2 != k or math.isqrt(k) - 1 > MAX_SH_DEGREE:
        raise SceneFormatError(
            path,
            f"{m} f_rest_* properties are no SH degree 0..{MAX_SH_DEGREE} (expected 0, 9, 24 "
            "or 45: 3 ((degree + 1)^2 - 1))",
        )
    wanted += [rest[i] for i in range(m)]
    wrong = [f"{p} is {types[p]}" for p in wanted if types[p] not in _FLOAT_TYPES]
    if wrong:
        raise SceneFormatError(path, f"splat properties must be float or double: {', '.join(wrong[:4])}")
    if from_rgb:
        wanted += list(_RGB)
    return wanted, m, from_rgb


def _check_values(path: Path, columns: dict, n: int) -> None:
    """Refuses non-finite values (naming the properties and rows) and zero quaternions (naming a row)."""
    bad_rows = np.zeros(n, bool)
    counts = []
    for name, values in columns.items():
        bad = ~np.isfinite(values)
        if bad.any():
            bad_rows |= bad
            counts.append(f"{name} ({int(bad.sum())} rows)")
    if counts:
        more = f" and {len(counts) - 6} more properties" if len(counts) > 6 else ""
        raise SceneFormatError(
            path,
            f"non-finite values (NaN, infinity, or beyond float32) in {int(bad_rows.sum())} "
            f"of {n} splats: {', '.join(counts[:6])}{more}",
        )
    quats = np.stack([columns[k] for k in _ROTS], -1)
    zero = np.flatnonzero(np.max(np.abs(quats), -1) == 0)  # tiny or huge ones are scaled (`scale_quats`)
    if len(zero):
        more = f" (and {len(zero) - 1} more rows)" if len(zero) > 1 else ""
        raise SceneFormatError(path, f"a zero quaternion (rot_0..3 all 0, no rotation) in row {int(zero[0])}{more}")


def read_splat_ply(path: str | os.PathLike) -> Splats:
    """Reads a 3D Gaussian Splatting PLY in the reference layout.

    Properties are found by name, in any order; other properties (normals, extras) are ignored;
    float64 properties are cast to float32. The SH degree (0..3) follows from the number of
    `f_rest_*` properties; nerfstudio's colour-only export (red/green/blue, no f_dc) gives
    f_dc = (rgb - 0.5) / SH_C0.

    Args:
      path: the .ply file.

    Returns:
      `Splats` with the file's raw values (log-scales, logits, quaternions w first as stored), all
      rows valid; sh[:, 0] = f_dc_0..2 and sh[:, k, c] = f_rest_{c (K - 1) + k - 1} for k >= 1.

    Raises:
      DataNotFoundError: no such file.
      SceneFormatError: (naming the file) not a PLY; an ASCII or big-endian PLY; a point cloud; a
        compressed PLY; missing, non-float or list properties; f_rest_* of no SH degree; zero
        splats; data shorter than the header promises; non-finite values; a zero quaternion.
    """
    path = check_input_file(path, "splat PLY file")
    try:
        with open(path, "rb") as f:
            header = read_ply_header(f, path)
            vertex = header.element("vertex")
            if vertex is None:
                raise SceneFormatError(path, "the PLY file has no 'vertex' element")
            wanted, m, from_rgb = _splat_layout(path, header, vertex)
            rest_names = [name for name in wanted if _REST.fullmatch(name)]
            n = vertex.count
            if n == 0:
                raise SceneFormatError(path, "no splats (element vertex 0)")
            try:
                offset = header.offset_of("vertex")
            except ValueError as e:
                raise SceneFormatError(path, str(e)) from None
            dtype = vertex.dtype("<")
            expected = n * dtype.itemsize
            available = os.fstat(f.fileno()).st_size - offset
            later = header.elements[[e.name for e in header.elements].index("vertex") + 1 :]
            if available < expected:
                raise SceneFormatError(
                    path,
                    f"truncated: {n} splats of {dtype.itemsize} bytes need {expected} bytes "
                    f"of data, the file holds {max(available, 0)}",
                )
            if available > expected and not later:  # other elements (faces, extras) may follow the vertices
                raise SceneFormatError(
                    path,
                    f"{available - expected} bytes follow its {n} splats of {dtype.itemsize} bytes (the element "
                    "vertex count disagrees with the data?)",
                )
            check_splat_count(path, n, m // 3 and math.isqrt(m // 3 + 1) - 1, "a splat PLY", fmt="ply")
            f.seek(offset)
            data = np.fromfile(f, dtype=dtype, count=n)
    except OSError as e:
        raise SceneFormatError(path, f"cannot read file ({e.strerror or e})") from None
    if len(data) != n:  # the file shrank while being read
        raise SceneFormatError(path, f"truncated: {n} splats expected, {len(data)} read")
    with np.errstate(over="ignore"):  # float64 beyond float32 becomes inf, refused below
        columns = {k: data[k].astype(np.float32) for k in wanted}
    if from_rgb:  # integer colours span their type's range (uchar 0..255), float ones 0..1
        for name, dc in zip(_RGB, _DC):
            kind = data.dtype[name]
            top = float(np.iinfo(kind).max) if kind.kind in "iu" else 1.0
            columns[dc] = ((columns.pop(name) / top - 0.5) / SH_C0).astype(np.float32)
    _check_values(path, columns, n)
    k = m // 3 + 1
    rest = np.stack([columns[name] for name in rest_names], -1) if m else np.zeros((n, 0), np.float32)
    sh = np.concatenate(
        [
            np.stack([columns[c] for c in _DC], -1)[:, None, :],  # [N, 1, 3]
            rest.reshape(n, 3, k - 1).transpose(0, 2, 1),
        ],
        axis=1,
    )  # [N, K, 3]
    return make_splats(
        means=np.stack([columns[c] for c in _XYZ], -1),
        log_scales=np.stack([columns[c] for c in _SCALES], -1),
        quats=scale_quats(np.stack([columns[c] for c in _ROTS], -1)),
        logits=columns["opacity"],
        sh=sh,
    )


def write_splat_ply(path: str | os.PathLike, splats: Splats, normals: bool = True) -> Path:
    """Writes the valid rows of `splats` as a reference 3DGS PLY, atomically.

    The layout is the reference `save_ply`'s: binary_little_endian 1.0, `element vertex N`, float32
    properties `x y z nx ny nz f_dc_0..2 f_rest_0..M-1 opacity scale_0..2 rot_0..3` (normals zero;
    left out with `normals=False`, as gsplat writes), raw values, f_rest channel-major.

    Args:
      path: the .ply file (its folder is created).
      splats: the splats; rows with `valid` False are left out.
      normals: write the zero normals nx ny nz, as the reference does.

    Returns:
      `path` as a Path.

    Raises:
      WaldoError: no valid rows, or valid rows with non-finite values or a zero quaternion (which
        `read_splat_ply` would refuse): mark them invalid first.
    """
    path = Path(path)
    valid = np.asarray(splats.valid, bool)
    rows = np.flatnonzero(valid)
    if len(rows) == 0:
        raise WaldoError(f"{path}: no valid splats to write")
    sh = np.asarray(splats.sh, np.float32)[rows]  # [N, K, 3]
    n, k = sh.shape[:2]
    columns = [np.asarray(splats.means, np.float32)[rows]]
    columns += [np.zeros((n, 3), np.float32)] if normals else []
    columns += [
        sh[:, 0, :],
        sh[:, 1:, :].transpose(0, 2, 1).reshape(n, 3 * (k - 1)),
        np.asarray(splats.logits, np.float32)[rows, None],
        np.asarray(splats.log_scales, np.float32)[rows],
        np.asarray(splats.quats, np.float32)[rows],
    ]
    table = np.ascontiguousarray(np.concatenate(columns, axis=1), "<f4")  # [N, properties]
    quats = table[:, -4:]
    with np.errstate(over="ignore", under="ignore"):
        bad = ~np.all(np.isfinite(table), axis=1) | (np.sum(quats * quats, -1) < np.finfo(np.float32).tiny)
    if bad.any():
        raise WaldoError(
            f"{path}: {int(bad.sum())} valid splats have non-finite values or a zero quaternion (first: "
            f"row {int(rows[np.argmax(bad)])}); mark them invalid before writing"
        )
    names = splat_ply_properties(splats.sh_degree, normals)
    header = "".join(
        ["ply\n", "format binary_little_endian 1.0\n", f"element vertex {n}\n"]
        + [f"property float {name}\n" for name in names]
        + ["end_header\n"]
    )
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_file(path) as f:
        f.write(header.encode("ascii"))
        f.write(memoryview(table).cast("B"))
    return path
