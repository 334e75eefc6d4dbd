"""How other tools map a transforms.json world into their own: Instant-NGP's unit cube, nerfstudio's
normalised world.

* Instant-NGP (`src/nerf_loader.cu`, `load_nerf`; `nerf_loader.h`, `nerf_matrix_to_ngp`): a world point
  p goes to cycle(p * scale + offset), `cycle` NGP's xyz <- yzx axis rotation, and a camera's y and z
  axes flip; the transforms.json keys `from_mitsuba`, `scale`, `offset` and `aabb` set scale and
  offset (`ngp_frame`). A `from_mitsuba` file keeps Mitsuba's camera axes and NGP does not cycle.
* nerfstudio (`nerfstudio_dataparser.py`): its model's world is D A^-1 P with translation times
  s / a, for the saved `dataparser_transforms.json` (D, s) and the file's `applied_transform` A (or
  nerfstudio's COLMAP default) and `applied_scale` a (`nerfstudio_applied`, `nerfstudio_pose_transform`).

`waldo_jax.scenes.camera_paths` writes camera paths in these worlds; the transforms loader reads the
same keys for the scene box. Tested against re-implementations of both tools' readers
(tests/consumer_parsers.py).
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path
from typing import Any, Dict, Optional, Tuple

import numpy as np

from waldo_jax.errors import is_finite_number
from waldo_jax.scenes.common import numeric_array, value_text

__all__ = [
    "NGP_DEFAULT_SCALE",
    "NGP_DEFAULT_OFFSET",
    "NERFSTUDIO_COLMAP_APPLIED_TRANSFORM",
    "MITSUBA_TO_OPENGL",
    "NgpFrame",
    "ngp_frame",
    "to_ngp",
    "from_ngp",
    "read_dataparser_transform",
    "nerfstudio_applied",
    "nerfstudio_pose_transform",
]

NGP_DEFAULT_SCALE = 0.33  # NGP's NERF_SCALE
NGP_DEFAULT_OFFSET = (0.5, 0.5, 0.5)
NGP_MITSUBA_SCALE = 0.66  # nerf_loader with from_mitsuba: scale 0.66, offset 0.25 x scale
# nerfstudio's `applied_transform` for COLMAP data written before the key existed (its dataparsers
# assume it when transforms.json has no `applied_transform` and a colmap/sparse/0 folder exists).
NERFSTUDIO_COLMAP_APPLIED_TRANSFORM = ((0.0, 1.0, 0.0, 0.0), (1.0, 0.0, 0.0, 0.0), (0.0, 0.0, -1.0, 0.0))
# A from_mitsuba file's camera axes (x left, y up, z forward) -> OpenGL's (x right, y up, z backward).
MITSUBA_TO_OPENGL = np.diag([-1.0, 1.0, -1.0, 1.0])
_CYCLE = [1, 2, 0]  # NGP's rows: x <- y, y <- z, z <- x


@dataclasses.dataclass(frozen=True)
class NgpFrame:
    """How Instant-NGP maps a transforms.json world into its unit cube: p -> cycle(p * scale + offset).

    Attributes:
      scale: world units -> NGP units.
      offset: (3,) NGP-unit offset, added before the axis cycle.
      from_mitsuba: the file's cameras use Mitsuba's axes and NGP does not cycle the world axes.
    """

    scale: float = NGP_DEFAULT_SCALE
    offset: Tuple[float, float, float] = NGP_DEFAULT_OFFSET
    from_mitsuba: bool = False

    @classmethod
    def create(cls, scale: float = NGP_DEFAULT_SCALE, offset=NGP_DEFAULT_OFFSET, from_mitsuba: bool = False):
        """A frame with `offset` a number or 3 numbers."""
        offset = np.broadcast_to(np.asarray(offset, np.float64), (3,))
        return cls(float(scale), tuple(float(v) for v in offset), bool(from_mitsuba))

    @classmethod
    def of_info(cls, info: Dict[str, Any]) -> "NgpFrame":
        """The frame a source's info records (`ngp_scale`, `ngp_offset`, `ngp_from_mitsuba`, as results.json
        keeps them in `source_info`); NGP's defaults where absent."""
        return cls.create(
            info.get("ngp_scale", cls.scale),
            info.get("ngp_offset", cls.offset),
            bool(info.get("ngp_from_mitsuba", False)),
        )


def _numbers_array(value: Any) -> np.ndarray:
    """`value` as float64 if it is numbers or nested lists of them (no strings or booleans: "1" and true
    are no matrix entries), else an empty array (refused by the caller's shape check, naming the key)."""
    array = numeric_array(value)
    return np.zeros(0) if array is None else array


def _finite(value: Any, what: str) -> float:
    if not is_finite_number(value):
        raise ValueError(f"'{what}' must be a finite number, got {value_text(value)}")
    return float(value)


def ngp_frame(meta: Dict[str, Any], start: NgpFrame = NgpFrame()) -> NgpFrame:
    """The `NgpFrame` Instant-NGP's loader (`src/nerf_loader.cu`, `load_nerf`) makes of one transforms dict.

    In NGP's order: `normal_mts_args` or `from_mitsuba` set from_mitsuba, which sets scale 0.66 and
    offset 0.25 x 0.66; `scale`; `offset` (a number or three); `aabb` ([[min], [max]]) sets scale = 1 /
    its longest side and offset = 0.5 - centre x scale, so the box's centre lands on NGP's 0.5.
    `start` carries the values of the files NGP read before (it reads a folder's files in turn).

    Raises:
      ValueError: a malformed value (the message names the key).
    """
    scale, offset, mitsuba = start.scale, np.asarray(start.offset, np.float64), start.from_mitsuba
    if "normal_mts_args" in meta:
        mitsuba = True
    if "from_mitsuba" in meta:
        flag = meta["from_mitsuba"]
        if not (isinstance(flag, bool) or (type(flag) is int and flag in (0, 1))):
            raise ValueError(f"'from_mitsuba' must be true or false, got {meta['from_mitsuba']!r}")
        mitsuba = bool(meta["from_mitsuba"])
    if mitsuba:
        scale, offset = NGP_MITSUBA_SCALE, np.full(3, 0.25 * NGP_MITSUBA_SCALE)
    if "scale" in meta:
        scale = _finite(meta["scale"], "scale")
    if "offset" in meta:
        value = meta["offset"]
        if isinstance(value, list) and len(value) == 3:
            offset = np.array([_finite(v, "offset") for v in value])
        elif isinstance(value, list):
            raise ValueError(f"'offset' must be a number or 3 numbers, got {value!r}")
        else:
            offset = np.full(3, _finite(value, "offset"))
    if "aabb" in meta:
        box = _numbers_array(meta["aabb"])
        if box.shape != (2, 3) or not np.all(np.isfinite(box)):
            raise ValueError(f"'aabb' must be [[min x, y, z], [max x, y, z]] of finite numbers, got {meta['aabb']!r}")
        length = max(1e-6, float(np.max(np.abs(box[1] - box[0]))))
        scale = 1.0 / length
        offset = 0.5 - 0.5 * (box[0] + box[1]) * scale
    if not scale > 0:
        raise ValueError(f"'scale' must be positive, got {scale:g}")
    return NgpFrame(float(scale), tuple(float(v) for v in offset), bool(mitsuba))


def _ngp_args(frame: Optional[NgpFrame], scale, offset, from_mitsuba) -> NgpFrame:
    return frame if frame is not None else NgpFrame.create(scale, offset, from_mitsuba)


def to_ngp(
    c2w: np.ndarray,
    scale: float = NGP_DEFAULT_SCALE,
    offset=NGP_DEFAULT_OFFSET,
    from_mitsuba: bool = False,
    frame: Optional[NgpFrame] = None,
) -> np.ndarray:
    """Instant-NGP's camera matrix [3, 4] of an OpenGL camera-to-world matrix in the scene's frame.

    NGP's `nerf_matrix_to_ngp` of the file's matrix: y and z columns negated, translation x scale +
    offset, rows cycled (not for from_mitsuba, whose file matrix is c2w @ MITSUBA_TO_OPENGL: the
    extra column flips cancel). `frame`, when given, replaces scale / offset / from_mitsuba.
    """
    frame = _ngp_args(frame, scale, offset, from_mitsuba)
    m = np.array(c2w, np.float64)[:3, :4]
    m[:, 1:3] *= -1.0
    m[:, 3] = m[:, 3] * frame.scale + np.asarray(frame.offset)
    return m if frame.from_mitsuba else m[_CYCLE]


def from_ngp(
    matrix: np.ndarray,
    scale: float = NGP_DEFAULT_SCALE,
    offset=NGP_DEFAULT_OFFSET,
    from_mitsuba: bool = False,
    frame: Optional[NgpFrame] = None,
) -> np.ndarray:
    """The inverse of `to_ngp`: a [4, 4] OpenGL camera-to-world matrix in the scene's frame."""
    frame = _ngp_args(frame, scale, offset, from_mitsuba)
    m = np.empty((3, 4))
    if frame.from_mitsuba:
        m[:] = np.asarray(matrix, np.float64)[:3, :4]
    else:
        m[_CYCLE] = np.asarray(matrix, np.float64)[:3, :4]
    m[:, 3] = (m[:, 3] - np.asarray(frame.offset)) / frame.scale
    m[:, 1:3] *= -1.0
    return np.concatenate([m, [[0.0, 0.0, 0.0, 1.0]]])


# ---------------------------------------------------------------------------------------------
# nerfstudio.


def _homogeneous(m: np.ndarray) -> np.ndarray:
    return np.concatenate([np.asarray(m, np.float64)[:3, :4], [[0.0, 0.0, 0.0, 1.0]]])


def read_dataparser_transform(meta: Dict[str, Any]) -> Tuple[np.ndarray, float]:
    """(transform [4, 4], scale) of a nerfstudio `dataparser_transforms.json` dict; ValueError when malformed."""
    if not isinstance(meta, dict) or "transform" not in meta or "scale" not in meta:
        raise ValueError('expected nerfstudio\'s dataparser_transforms.json: {"transform": 3x4, "scale": s}')
    # Numbers only: float("0.5") and float(True) read text and booleans as scales, np.asarray "1" as an entry.
    transform = _numbers_array(meta["transform"])
    scale = meta["scale"]
    if isinstance(scale, bool) or not isinstance(scale, (int, float)) or abs(scale) > 1e300:
        raise ValueError(f"dataparser scale must be a number between 1e-09 and 1e+09, got {value_text(scale)}")
    scale = float(scale)
    shape = list(transform.shape)  # as the file gives it: a 3x4 is made 4x4 below
    if transform.shape == (3, 4):
        transform = _homogeneous(transform)
    if transform.shape != (4, 4):
        raise ValueError(f"dataparser transform must be a 3x4 matrix, got shape {shape}")
    if not np.all(np.isfinite(transform)):
        raise ValueError("dataparser transform holds a value that is not a finite number")
    if not (scale > 0 and math.isfinite(scale)):
        raise ValueError(f"dataparser scale must be positive, got {scale:g}")
    if abs(np.linalg.det(transform[:3, :3])) < 1e-9:
        raise ValueError("dataparser transform has a singular rotation part")
    rotation = transform[:3, :3]
    if not np.allclose(rotation @ rotation.T, np.eye(3), atol=1e-4) or np.linalg.det(rotation) < 0:
        # nerfstudio's is a rotation (its orientation fixes the sign); a mirror or a scale here would write
        # exports whose camera rotations are not rotations
        raise ValueError("dataparser transform's 3x3 part is not a rotation (orthonormal, determinant +1)")
    if not 1e-9 <= scale <= 1e9:  # a scale of 1e300 wrote exports of infinities (null in JSON) with exit 0
        raise ValueError(f"dataparser scale must be between 1e-09 and 1e+09, got {scale:g}")
    return transform, scale


def nerfstudio_applied(meta: Dict[str, Any], folder: Optional[Path] = None) -> Tuple[Optional[np.ndarray], float, str]:
    """(applied_transform [3, 4] or None, applied_scale, where it came from) as nerfstudio's dataparser takes them.

    From `nerfstudio_dataparser.py`: the file's `applied_transform`; without it, the legacy COLMAP
    transform when `folder`/colmap/sparse/0 exists; `applied_scale` (1 without it).

    Raises:
      ValueError: a malformed value (the message names the key).
    """
    applied, source = None, "none"
    if "applied_transform" in meta:
        applied = _numbers_array(meta["applied_transform"])
        if applied.shape != (3, 4) or not np.all(np.isfinite(applied)):
            raise ValueError("'applied_transform' must be a finite 3x4 matrix")
        if abs(np.linalg.det(applied[:, :3])) < 1e-9:
            raise ValueError("'applied_transform' has a singular rotation part")
        source = "applied_transform"
    elif folder is not None and (Path(folder) / "colmap" / "sparse" / "0").is_dir():
        applied, source = np.asarray(NERFSTUDIO_COLMAP_APPLIED_TRANSFORM, np.float64), "nerfstudio's COLMAP default"
    applied_scale = 1.0
    if "applied_scale" in meta:
        applied_scale = _finite(meta["applied_scale"], "applied_scale")
        if not applied_scale > 0:
            raise ValueError(f"'applied_scale' must be positive, got {applied_scale:g}")
    return applied, applied_scale, source


def nerfstudio_pose_transform(
    dataparser: Tuple[np.ndarray, float], applied_transform: Optional[np.ndarray] = None, applied_scale: float = 1.0
) -> Tuple[np.ndarray, float]:
    """(T [4, 4], s): nerfstudio's world pose of a transforms.json pose P is T P with its translation times s.

    `dataparser` is `read_dataparser_transform` of the model's file (D, scale); T = D A^-1 and
    s = scale / applied_scale, undoing what nerfstudio folded into the saved file.
    """
    transform, scale = dataparser
    if applied_transform is not None:
        transform = np.asarray(transform, np.float64) @ np.linalg.inv(_homogeneous(applied_transform))
    return np.asarray(transform, np.float64), float(scale) / float(applied_scale)
