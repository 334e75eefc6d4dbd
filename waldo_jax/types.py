"""Shared pytrees and type aliases of waldo_jax.

Every module takes its shared structures from here, so a `Pose` or an `Intrinsics` means one thing
across cameras, rendering, fields and search.

Conventions fixed here and used everywhere:
  * World and camera frames follow NeRF/OpenGL: a camera looks along its local -z axis, +y is up in
    the image and +x is right. A camera-to-world matrix `c2w` is [4, 4] (or [3, 4]); its columns are
    the camera's right, up, backward axes and its origin, in world coordinates.
  * Pixel coordinates (u, v) have their origin at the top-left corner of the top-left pixel; the
    centre of pixel (i, j) (column i, row j) is (i + 0.5, j + 0.5). `cx, cy` use the same frame.
  * Images are float32 [H, W, 3] in [0, 1].
"""

from __future__ import annotations

import dataclasses
from typing import Any, Callable, Dict, NamedTuple, Optional, Tuple

import flax.struct
import jax
import jax.numpy as jnp
import numpy as np

Array = jax.Array
PRNGKey = jax.Array
# A radiance field for one point: (params, x [3], d [3] unit view direction) -> (sigma [], rgb [3]).
Field = Callable[..., Tuple[Array, Array]]

__all__ = ["Array", "Field", "Intrinsics", "Pose", "PRNGKey", "RenderOutput", "RunOptions", "Scene"]


@flax.struct.dataclass
class Pose:
    """The paper's camera pose parameterisation: origin, look-at point and up vector.

    Fields are arrays of shape [..., 3] so that one `Pose` can hold a whole population.

    Attributes:
      origin: camera centre in world coordinates, [..., 3].
      target: the look-at point in world coordinates, [..., 3].
      up: the up vector (need not be unit length nor orthogonal to the view direction), [..., 3].
    """

    origin: Array
    target: Array
    up: Array


@flax.struct.dataclass
class Intrinsics:
    """A pinhole camera with optional OpenCV radial-tangential distortion.

    `width` and `height` set array shapes, so they are static (not pytree leaves); the focal lengths,
    principal point and distortion are leaves and may be traced.

    Attributes:
      width: image width in pixels (static).
      height: image height in pixels (static).
      fx, fy: focal lengths in pixels.
      cx, cy: principal point in pixels (pixel centres at i + 0.5).
      distortion: OPENCV coefficients (k1, k2, p1, p2), [4]; zeros for an ideal pinhole.
    """

    width: int = flax.struct.field(pytree_node=False)
    height: int = flax.struct.field(pytree_node=False)
    fx: Array = 1.0
    fy: Array = 1.0
    cx: Array = 0.0
    cy: Array = 0.0
    distortion: Array = (0.0, 0.0, 0.0, 0.0)

    @classmethod
    def create(
        cls,
        width: int,
        height: int,
        fx: float,
        fy: float | None = None,
        cx: float | None = None,
        cy: float | None = None,
        distortion=None,
    ) -> "Intrinsics":
        """Builds intrinsics with float32 leaves; `fy` defaults to `fx`, the principal point to the centre."""
        width, height = int(width), int(height)
        if width <= 0 or height <= 0:
            raise ValueError(f"image size must be positive, got {width}x{height}")
        fy = fx if fy is None else fy
        cx = width / 2.0 if cx is None else cx
        cy = height / 2.0 if cy is None else cy
        dist = np.zeros(4, np.float32) if distortion is None else np.asarray(distortion, np.float32)
        if dist.shape != (4,):
            raise ValueError(f"distortion must be (k1, k2, p1, p2), got shape {dist.shape}")
        return cls(
            width=width,
            height=height,
            fx=jnp.float32(fx),
            fy=jnp.float32(fy),
            cx=jnp.float32(cx),
            cy=jnp.float32(cy),
            distortion=jnp.asarray(dist),
        )

    @classmethod
    def from_fov(cls, width: int, height: int, fov_x: float) -> "Intrinsics":
        """Square-pixel pinhole from a horizontal field of view in radians.

        Raises:
          ValueError: `fov_x` is not in (0, pi) (e.g. degrees passed as radians: 60 rad would give a negative
            focal length and a mirrored camera).
        """
        if not 0.0 < float(fov_x) < np.pi:
            raise ValueError(f"fov_x must be in (0, pi) radians, got {fov_x!r} (degrees? use np.radians)")
        fx = 0.5 * width / np.tan(0.5 * fov_x)
        return cls.create(width, height, fx)

    @property
    def shape(self) -> Tuple[int, int]:
        """(height, width), the image shape."""
        return (self.height, self.width)

    @property
    def has_distortion(self) -> bool:
        """True when any distortion coefficient is non-zero (needs concrete values)."""
        return bool(np.any(np.asarray(self.distortion) != 0.0))

    def scaled(self, width: int, height: int) -> "Intrinsics":
        """The same camera imaged at another resolution (e.g. for downscaled rendering).

        Focal lengths and principal point scale with the image size per axis; the distortion
        coefficients act on normalised coordinates and are unchanged.
        """
        width, height = int(width), int(height)
        if width <= 0 or height <= 0:
            raise ValueError(f"image size must be positive, got {width}x{height}")
        sx = width / self.width
        sy = height / self.height
        return self.replace(
            width=width,
            height=height,
            fx=self.fx * sx,
            fy=self.fy * sy,
            cx=self.cx * sx,
            cy=self.cy * sy,
        )

    def downscaled(self, factor: float) -> "Intrinsics":
        """The camera at 1/factor of the resolution, sizes rounded as image resizers do."""
        if factor <= 0:
            raise ValueError(f"downscale factor must be positive, got {factor}")
        return self.scaled(max(1, int(round(self.width / factor))), max(1, int(round(self.height / factor))))

    def with_max_side(self, resolution: int) -> "Intrinsics":
        """The camera rescaled so that its longer side has `resolution` pixels (aspect kept)."""
        scale = resolution / max(self.width, self.height)
        return self.scaled(max(1, int(round(self.width * scale))), max(1, int(round(self.height * scale))))

    def to_dict(self) -> dict:
        """Plain-Python description (for JSON files and checkpoints)."""
        k1, k2, p1, p2 = (float(v) for v in np.asarray(self.distortion))
        return {
            "width": self.width,
            "height": self.height,
            "fx": float(self.fx),
            "fy": float(self.fy),
            "cx": float(self.cx),
            "cy": float(self.cy),
            "k1": k1,
            "k2": k2,
            "p1": p1,
            "p2": p2,
        }

    @classmethod
    def from_dict(cls, d: dict) -> "Intrinsics":
        """Inverse of `to_dict`."""
        return cls.create(
            d["width"],
            d["height"],
            d["fx"],
            d["fy"],
            d["cx"],
            d["cy"],
            [d.get("k1", 0.0), d.get("k2", 0.0), d.get("p1", 0.0), d.get("p2", 0.0)],
        )


@flax.struct.dataclass
class RenderOutput:
    """What the volume renderer returns, for one ray, one image or a population.

    Attributes:
      rgb: composited colour, [..., 3] in [0, 1].
      depth: expected ray distance of the termination point, [...] (0 where nothing is hit).
      acc: accumulated opacity, [...] in [0, 1].
    """

    rgb: Array
    depth: Array
    acc: Array


@dataclasses.dataclass(frozen=True, eq=False)
class Scene:
    """A posed image set on the host (NumPy), as every loader and the procedural room return it.

    Attributes:
      images: float32 [N, H, W, 3] in [0, 1], RGBA inputs composited on `background`.
      c2w: float32 [N, 4, 4] camera-to-world matrices, OpenGL convention (see module docstring).
      intrinsics: one `Intrinsics` for all N images, at the loaded (possibly downscaled) resolution.
      aabb: float32 [2, 3] scene bounding box (min corner, max corner) in world units, for sampling.
      near, far: ray-distance bounds for sampling, in world units.
      file_names: N image paths relative to the scene folder.
      format: the detected format: "instant-ngp", "nerfstudio", "blender", "llff" or "procedural".
      name: a short name (the folder name).
      split: which images these are: "all", "train", "val" or "test".
      path: the scene folder ("" for a generated scene).
      skipped_missing: frames listed by the scene file whose image file does not exist.
      alphas: float32 [N, H, W] opacity of RGBA inputs (None for opaque images); lets training
        re-composite on random backgrounds.
      background: float32 [3], the colour RGBA images were composited on (None for opaque inputs).
      applied_transform: float32 [3, 4] or None: the world transform nerfstudio recorded as already
        applied to the poses (maps the original COLMAP world into this scene's world).
      metadata: free-form extra facts of the format (aabb_scale, scale/offset, downscale, ...).
    """

    images: np.ndarray
    c2w: np.ndarray
    intrinsics: Intrinsics
    aabb: np.ndarray
    near: float
    far: float
    file_names: Tuple[str, ...]
    format: str
    name: str = ""
    split: str = "all"
    path: str = ""
    skipped_missing: int = 0
    alphas: Optional[np.ndarray] = None
    background: Optional[np.ndarray] = None
    applied_transform: Optional[np.ndarray] = None
    metadata: Dict[str, Any] = dataclasses.field(default_factory=dict)

    @property
    def n_images(self) -> int:
        return int(self.images.shape[0])

    @property
    def height(self) -> int:
        return int(self.images.shape[1])

    @property
    def width(self) -> int:
        return int(self.images.shape[2])

    def summary(self) -> Dict[str, Any]:
        """A JSON-ready summary (what `waldo scene info --json` prints)."""
        origins = self.c2w[:, :3, 3]
        return {
            "name": self.name,
            "path": self.path,
            "format": self.format,
            "split": self.split,
            "n_images": self.n_images,
            "width": self.width,
            "height": self.height,
            "skipped_missing": int(self.skipped_missing),
            "intrinsics": self.intrinsics.to_dict(),
            "near": float(self.near),
            "far": float(self.far),
            "aabb": np.asarray(self.aabb, np.float64).round(6).tolist(),
            "camera_origin_min": origins.min(0).round(6).tolist() if len(origins) else None,
            "camera_origin_max": origins.max(0).round(6).tolist() if len(origins) else None,
            "rgba": self.alphas is not None,
            "applied_transform": None
            if self.applied_transform is None
            else np.asarray(self.applied_transform, np.float64).round(6).tolist(),
            "metadata": self.metadata,
        }


class RunOptions(NamedTuple):
    """How a run folder is made from a scene on disk (`nerf.runs.train_scene_run`, `splats.runs.fit_scene_run`).

    Attributes:
      downscale: the scene's image downscale (default: its format's own).
      seed: the PRNG seed of the training.
      force: write into a non-empty output folder.
      progress: show a progress bar.
    """

    downscale: Optional[float] = None
    seed: int = 0
    force: bool = False
    progress: bool = True
