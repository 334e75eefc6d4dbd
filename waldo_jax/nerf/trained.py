"""The one renderer of a trained field, its held-out PSNR and the calibration of its marching step.

A trained run is one pytree, `TrainedField` (params, occupancy grid, `TrainConfig`, and the scene's near,
far, background and box), and renders with `waldo_jax.render.marched`: `render_setup` turns it into that
renderer's grid, render config and march config (a dense-trained field goes through a single,
always-occupied cell). `calibrate_render_step` picks the
run's marching step from its own quality/speed curve. Names: `P` poses of `H x W` pixels.
See docs/design.md, "Training".
"""

from __future__ import annotations

import math
from typing import Any, Dict, List, Optional, Sequence, Tuple

import flax.struct
import jax
import jax.numpy as jnp
import numpy as np

from waldo_jax.metrics import psnr_from_mse
from waldo_jax.nerf.config import TrainConfig, TrainConfigError, check_scene
from waldo_jax.nerf.field import make_field
from waldo_jax.nerf.samplers import make_sampler
from waldo_jax.render import marched
from waldo_jax.render.volume import RenderConfig
from waldo_jax.types import Intrinsics, RenderOutput, Scene

__all__ = [
    "RENDER_STEP_CANDIDATES",
    "RENDER_STEP_TOLERANCE_DB",
    "TrainedField",
    "calibrate_render_step",
    "eval_background",
    "evaluate",
    "render_setup",
    "render_trained",
    "render_trained_counted",
]

# Rendering marches with the training step times `TrainConfig.render_step_scale`. Its value comes from
# each run's own quality/speed curve (`calibrate_render_step`): the largest of these scales whose
# held-out PSNR is within RENDER_STEP_TOLERANCE_DB of the training step's. Measured on the CPU-trained
# fox (benchmarks/results/render_trained_fox_*): x2 -0.01 dB, x3 -0.03 dB (70 instead of 203
# evaluations per ray), x4 -0.09 dB; on lego_tiny x2 already loses 1.4 dB, so no fixed scale serves both.
RENDER_STEP_CANDIDATES = (2.0, 3.0, 4.0)
RENDER_STEP_TOLERANCE_DB = 0.05
# Held-out views rendered per candidate scale (spread over the split).
_CALIBRATION_VIEWS = 3


@flax.struct.dataclass
class TrainedField:
    """A trained radiance field and the scene settings it renders with, as one pytree.

    Attributes:
      params: the field's parameters (leaves).
      occupancy: the occupancy grid (the sampler's state, leaves), or None (dense sampler).
      config: the training config (static: field, sampler, eval_samples, render_step_scale).
      near, far: float32 [] ray bounds (world units).
      background: float32 [3] colour behind the volume.
      aabb: float32 [2, 3] box to sample in.
    """

    params: Any
    occupancy: Any
    config: TrainConfig = flax.struct.field(pytree_node=False)
    near: Any = None
    far: Any = None
    background: Any = None
    aabb: Any = None

    @classmethod
    def create(
        cls, params, occupancy, config: TrainConfig, near: float, far: float, background=(1.0, 1.0, 1.0), aabb=None
    ) -> "TrainedField":
        """A trained field with float32 settings; `aabb=None` samples the field's own box (`config.field.aabb`)."""
        aabb = config.field.aabb if aabb is None else aabb
        return cls(
            params=params,
            occupancy=occupancy,
            config=config,
            near=np.float32(near),
            far=np.float32(far),
            background=np.asarray(background, np.float32),
            aabb=np.asarray(aabb, np.float32).reshape(2, 3),
        )

    @classmethod
    def for_scene(cls, params, occupancy, config: TrainConfig, scene) -> "TrainedField":
        """A trained field rendered with the near, far and box of `scene` (a `Scene` or a checkpoint's
        `SceneRecord`), on its background (`eval_background`: black for opaque scenes)."""
        return cls.create(params, occupancy, config, scene.near, scene.far, eval_background(scene), scene.aabb)

    @classmethod
    def from_result(cls, result, scene) -> "TrainedField":
        """The field a `train.TrainResult` holds, rendered with the settings of its training `scene`."""
        return cls.for_scene(result.params, result.occupancy, result.config, scene)

    @classmethod
    def from_checkpoint(cls, checkpoint) -> "TrainedField":
        """The field of a loaded `checkpoint.Checkpoint`, rendered with its training scene's settings."""
        return cls.for_scene(checkpoint.params, checkpoint.occupancy, checkpoint.config, checkpoint.scene)


def render_setup(
    field: TrainedField, step_scale: Optional[float] = None, sizes_of: Optional[float] = None
) -> marched.MarchSetup:
    """What `render.marched` needs to render a trained field: `MarchSetup(grid, render config, march config)`.

    Args:
      field: the trained field and its render settings.
      step_scale: the marching step over the training step (default `config.render_step_scale`, or 1).
      sizes_of: a scale <= step_scale whose march's static sizes (candidates K, samples S) to use, so
        several step scales render with one compiled program (`calibrate_render_step`). The image is
        the same: the extra candidates lie beyond the grid's box and are masked. Default: step_scale's.
    """
    config = field.config
    sampler = make_sampler(config)
    scale = step_scale if step_scale is not None else (config.render_step_scale or 1.0)
    scale = float(scale)
    if not (math.isfinite(scale) and scale > 0):
        raise TrainConfigError(f"the render step scale must be a positive number, got {step_scale!r}")
    render_config = RenderConfig.create(
        near=field.near,
        far=field.far,
        aabb=np.asarray(field.aabb, np.float32).reshape(2, 3),
        background=field.background,
        ray_chunk=1,
    )
    march = sampler.view_march(scale)
    if sizes_of is not None:
        if not 0 < float(sizes_of) <= scale:
            raise TrainConfigError(f"sizes_of must lie in (0, step scale {scale}], got {sizes_of!r}")
        sizes = sampler.view_march(float(sizes_of))
        march = march.replace(max_steps=sizes.max_steps, max_samples=sizes.max_samples)
    return marched.MarchSetup(sampler.view_grid(field.occupancy), render_config, march)


def _splits_by_default() -> bool:
    """Whether `render_trained` with no mesh splits the poses over the local devices: where there are
    several accelerators. A CPU's host devices (one per core, `waldo_jax._xla_flags`) are left to the
    renderers measured faster split over them (splats); a NeRF there renders on one, as it always did."""
    return jax.local_device_count() > 1 and jax.default_backend() != "cpu"


def _render_counted(
    field: TrainedField,
    c2w,
    intrinsics: Intrinsics,
    mesh,
    step_scale: Optional[float],
    packing: Optional[marched.Packing],
    sizes_of: Optional[float] = None,
):
    """(RenderOutput [P, H, W], evaluations int32 [P, H, W]) on one device, or sharded over several."""
    setup = render_setup(field, step_scale, sizes_of)
    field_fn = make_field(field.config.field)
    c2w = jnp.asarray(np.asarray(c2w, np.float32))
    if mesh is None and not _splits_by_default():
        views = marched.render_marched(field_fn, field.params, setup, c2w, intrinsics, packing)
        return views.output, views.evaluations
    return marched.render_marched_sharded(field_fn, field.params, setup, c2w, intrinsics, packing, mesh)


def render_trained_counted(
    field: TrainedField,
    c2w,
    intrinsics: Intrinsics,
    *,
    step_scale: Optional[float] = None,
    packing: Optional[marched.Packing] = None,
) -> marched.MarchedViews:
    """`render_trained` on one device, with what it cost (`render.marched.MarchedViews`: evaluations per
    pixel, passes per block)."""
    return marched.render_marched(
        make_field(field.config.field),
        field.params,
        render_setup(field, step_scale),
        jnp.asarray(np.asarray(c2w, np.float32)),
        intrinsics,
        packing,
    )


def render_trained(
    field: TrainedField,
    c2w,
    intrinsics: Intrinsics,
    *,
    mesh=None,
    step_scale: Optional[float] = None,
    packing: Optional[marched.Packing] = None,
) -> RenderOutput:
    """Renders P views of a trained field in one call with the marched renderer (`render.marched`).

    With more than one local accelerator (or a `mesh`), the poses are split over the devices
    (`render.marched.render_marched_sharded`); a CPU's host devices are used only with a `mesh`.

    Args:
      field: the trained field (params, occupancy grid, config) and its near, far, background and box
        (`TrainedField.create`, `.from_result`, `.from_checkpoint`).
      c2w: [P, 4, 4] or [P, 3, 4] camera-to-world matrices.
      intrinsics: shared intrinsics (their width and height set the image size).
      mesh: a one-axis mesh named "poses" to shard over (default: all local accelerators if more than one).
      step_scale: the marching step over the training step (default `config.render_step_scale`).
      packing: the renderer's static sizes (default `render.marched.Packing.for_backend()`).

    Returns:
      RenderOutput with rgb [P, H, W, 3], depth [P, H, W], acc [P, H, W] (device arrays).
    """
    return _render_counted(field, c2w, intrinsics, mesh, step_scale, packing)[0]


def eval_background(scene: Scene) -> np.ndarray:
    """The colour float32 [3] a scene's views are rendered and compared on: its background, or black."""
    return np.zeros(3, np.float32) if scene.background is None else np.asarray(scene.background, np.float32)


def evaluate(
    params,
    sampler_state,
    config: TrainConfig,
    scene: Scene,
    step_scale: Optional[float] = None,
    views: Optional[Sequence[int]] = None,
    sizes_of: Optional[float] = None,
) -> Dict[str, Any]:
    """Held-out PSNR: renders the views of `scene` (all, or the indices `views`) and compares with its images.

    RGBA scenes are compared on the background their images were composited on (`scene.background`);
    opaque ones are rendered on black. `sizes_of`: see `render_setup`.

    Returns:
      {"psnr": mean of per-image PSNR (dB), "psnr_per_image": list, "mse": mean MSE,
        "evaluations_per_ray": mean field evaluations per ray, "step_scale": the marching step used,
        "images": float32 [P, H, W, 3] renders (host)}.
    """
    check_scene(scene, "test scene")
    index = np.arange(scene.n_images) if views is None else np.asarray(views, np.int64)
    c2w = np.asarray(scene.c2w, np.float32)[index]
    field = TrainedField.for_scene(params, sampler_state, config, scene)
    out, evaluations = _render_counted(field, c2w, scene.intrinsics, None, step_scale, None, sizes_of)
    rendered = np.asarray(jax.device_get(out.rgb), np.float32)
    images = np.asarray(scene.images, np.float64)[index]
    mse = np.mean((rendered.astype(np.float64) - images) ** 2, axis=(1, 2, 3))
    psnr = psnr_from_mse(mse)
    scale = step_scale if step_scale is not None else (config.render_step_scale or 1.0)
    return {
        "psnr": float(np.mean(psnr)),
        "psnr_per_image": psnr.tolist(),
        "mse": float(np.mean(mse)),
        "evaluations_per_ray": float(np.mean(np.asarray(evaluations, np.float64))),
        "step_scale": float(scale),
        "images": rendered,
    }


def calibrate_render_step(
    params,
    sampler_state,
    config: TrainConfig,
    scene: Scene,
    reference: Optional[Dict[str, Any]] = None,
    candidates: Sequence[float] = RENDER_STEP_CANDIDATES,
    tolerance_db: float = RENDER_STEP_TOLERANCE_DB,
) -> Tuple[float, List[Dict[str, Any]]]:
    """The marching step to render a trained run with, from its own quality/speed curve.

    Renders up to `_CALIBRATION_VIEWS` held-out views (spread over the split) with the march `scale`
    times coarser than training, for each scale of `candidates` in increasing order, and keeps the
    largest whose PSNR on those views is within `tolerance_db` of the training step's (scale 1);
    stops at the first that is not. Every scale renders with the static sizes of the finest march
    (`render_setup`'s `sizes_of`), so the curve costs one compiled program, not one per scale (on the
    2-core CPU a program of 3 views of lego_tiny takes seconds to compile, more than it runs).

    Args:
      params, sampler_state, config: the trained run.
      scene: its held-out views.
      reference: `evaluate` at scale 1 on all of `scene` (when None, the chosen views are rendered here).
      candidates: scales to try, increasing.
      tolerance_db: the PSNR the render may lose.

    Returns:
      (scale, curve): the chosen scale (1.0 when none qualifies) and one entry per scale tried
      {"step_scale", "psnr_views", "delta_db", "evaluations_per_ray"}.
    """
    count = min(_CALIBRATION_VIEWS, scene.n_images)
    views = np.unique(np.linspace(0, scene.n_images - 1, count).round().astype(np.int64))
    finest = min([1.0] + [float(c) for c in candidates])
    if reference is None:
        reference = evaluate(params, sampler_state, config, scene, step_scale=1.0, views=views, sizes_of=finest)
        base = reference["psnr"]
    else:
        base = float(np.mean(np.asarray(reference["psnr_per_image"])[views]))
    curve = [
        {
            "step_scale": 1.0,
            "psnr_views": base,
            "delta_db": 0.0,
            "evaluations_per_ray": reference["evaluations_per_ray"],
        }
    ]
    chosen = 1.0
    for scale in candidates:
        result = evaluate(params, sampler_state, config, scene, step_scale=scale, views=views, sizes_of=finest)
        delta = result["psnr"] - base
        curve.append(
            {
                "step_scale": float(scale),
                "psnr_views": result["psnr"],
                "delta_db": delta,
                "evaluations_per_ray": result["evaluations_per_ray"],
            }
        )
        if delta < -tolerance_db:
            break
        chosen = float(scale)
    return chosen, curve
