"""Training configuration of the hash-grid NeRF: static shapes apart from numeric hyper-parameters.

`TrainConfig` is plain, hashable Python that sets shapes (one compilation per value; `TrainConfig.preset`
builds the paper's setup or a CPU-sized one from a scene); `TrainHParams` is a pytree of Instant-NGP's
optimiser numbers (traced, so a sweep can vmap over it). Both are checked here, at the edge, and
`TrainConfigError` names the offending value. The rationale is in docs/design.md, "Training".
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any, Dict, Optional

import flax.struct
import jax
import jax.numpy as jnp
import numpy as np

from waldo_jax.cameras import camera_focus
from waldo_jax.errors import MAX_INT32, MAX_TRAIN_STEPS, NumberError, WaldoError, check_float32
from waldo_jax.nerf.field import NGPFieldConfig
from waldo_jax.nerf.hashgrid import HashGridConfig
from waldo_jax.types import Array, Scene

__all__ = ["LOSSES", "PRESETS", "SAMPLERS", "TrainConfig", "TrainConfigError", "TrainHParams", "check_scene"]

PRESETS = ("fast", "quality")
LOSSES = ("mse", "huber")
SAMPLERS = ("dense", "occupancy")
PIXEL_SAMPLINGS = ("uniform", "error")

# Instant-NGP (base.json): decay starts at step 20k and repeats every 10k, of ~35k steps.
_DECAY_START_FRACTION = 0.5
_DECAY_INTERVAL_FRACTION = 0.15
_DECAY_BASE = 0.33
# Config keys of older checkpoints that no longer mean anything (ignored by `TrainConfig.from_dict`).
_OBSOLETE_KEYS = ("eval_ray_chunk",)


class TrainConfigError(WaldoError, ValueError):
    """A training configuration or its input scene is invalid (the message names the value)."""


# ----------------------------------------------------------------------------------------------
# Configuration: static shapes (TrainConfig) apart from numeric hyper-parameters (TrainHParams).


def _positive_int(name: str, value: Any, minimum: int = 1) -> int:
    """An int in [minimum, MAX_INT32]: counts become int32 arrays under jit (10**12 steps would wrap)."""
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or not minimum <= value <= MAX_INT32:
        raise TrainConfigError(f"TrainConfig.{name} must be an int >= {minimum} (at most {MAX_INT32}), got {value!r}")
    return int(value)


# The render's marching step over the training's: 0.01 marches 100x the samples, 100 a hundredth of them.
RENDER_STEP_SCALES = (0.01, 100.0)
# Instant-NGP's largest aabb_scale: its occupancy grid has at most 8 cascades, the last 2**7 times the first.
MAX_AABB_SCALE = 128.0


def _positive_float(name: str, value: Any, allow_zero: bool = False) -> float:
    """A finite number that stays finite (and, unless `allow_zero`, > 0) in float32, where it is used."""
    try:
        number = check_float32(value, f"TrainConfig.{name}", positive=not allow_zero)
    except NumberError as e:
        raise TrainConfigError(str(e)) from None
    if number < 0:
        raise TrainConfigError(f"TrainConfig.{name} must be a non-negative finite number, got {value!r}")
    return number


@dataclasses.dataclass(frozen=True)
class TrainConfig:
    """Static, shape-setting training configuration (hashable; one compilation per distinct value).

    Attributes:
      field: the Instant-NGP field (aabb = the whole scene box, hash grid, MLP widths).
      aabb_scale: Instant-NGP's aabb_scale: the occupancy grid's base box is the field's box shrunk
        by it, with 1 + ceil(log2(aabb_scale)) cascades covering the rest.
      steps: optimisation steps.
      rays_per_batch: R, rays drawn per step (dense). With the occupancy sampler the most rays a step
        marches: the rays marched adapt to the budget chunk by chunk (a power-of-two fraction of
        this), and they enter the batch in random order until their packed samples fill
        `samples_per_batch` (Instant-NGP's dynamic batch, with fixed shapes).
      num_samples: samples per training ray: the stratified count (dense) or the most samples one
        ray may keep in occupied space (occupancy; capped at the K candidates that cross the grid,
        so a large value means no cap, as in Instant-NGP).
      samples_per_batch: occupancy sampler: field evaluations per step (packed rows across rays).
      first_rays: occupancy sampler: the rays the steps march until the warm-up ends, a rung of the
        ladder (`rays_per_batch` halved, down to 128); None: the rung whose rays fill the budget
        with the grid all occupied. Each rung the run marches compiles its own program; rays past
        those the budget holds are marched and left out, so a rung above the one the budget fills
        trains the same rays (the pixels are drawn in the same order) and costs only their
        marching: a short run that starts on the rung it will keep compiles one program less.
      eval_samples: rendering (held-out PSNR, `waldo render`, `waldo explore`): the most samples a
        ray keeps in occupied space (occupancy), or the samples across the field's box (dense).
      chunk: steps between host syncs (progress bar, history, the rays marched per step); rounded
        to whole periods of `occupancy_update_every` steps.
      loss: "mse" or "huber" on rgb.
      sampler: "dense" or "occupancy" (see `waldo_jax.nerf.samplers`).
      occupancy_resolution: G, cells per side of each occupancy cascade.
      occupancy_update_every: steps between occupancy-grid updates (Instant-NGP: 16).
      occupancy_warmup: steps during which every cell is re-sampled at each update (NGP: 256).
      occupancy_decay: factor on the stored densities at each update (NGP: 0.95).
      steps_per_diagonal: the marching step is the base box's diagonal / this (NGP: 1024).
      cone_angle: marching steps grow as t * cone_angle (NGP: 0 for synthetic, 1/256 for real scenes).
      random_background: per-ray random background colour (else the scene's background, or black).
      eval_every: steps between held-out evaluations recorded in the history (0: at the end only).
      render_step_scale: rendering marches with the training step (steps_per_diagonal, cone_angle)
        times this; None: `train` measures the run's quality/speed curve on its held-out views and
        sets it (`calibrate_render_step`); renders use 1 while it is None.
      preset_name: the preset this config came from ("custom" otherwise), recorded for reports.
      pixel_sampling: how a step draws its rays' pixels: "uniform" over all training pixels, or "error":
        a quarter uniformly and the rest in proportion to each pixel's squared error when it was last
        trained (Instant-NGP's error map, at full resolution; the loss is not reweighted, so hard pixels,
        fine detail and edges, are trained more often). It keeps one float32 per training pixel on the
        device and sums them every step: nothing for the room's 48 x 64 x 64 pixels, but 357 MB and a
        cumulative sum of 89M values a step for the fox's 43 views at 1080 x 1920 (load such scenes
        downscaled, or keep "uniform").
    """

    field: NGPFieldConfig = NGPFieldConfig()
    aabb_scale: float = 1.0
    steps: int = 2000
    rays_per_batch: int = 1024
    num_samples: int = 64
    samples_per_batch: int = 2**15
    first_rays: Optional[int] = None
    eval_samples: int = 128
    chunk: int = 50
    loss: str = "mse"
    sampler: str = "dense"
    occupancy_resolution: int = 64
    occupancy_update_every: int = 16
    occupancy_warmup: int = 256
    occupancy_decay: float = 0.95
    steps_per_diagonal: float = 1024.0
    cone_angle: float = 0.0
    random_background: bool = True
    eval_every: int = 0
    render_step_scale: Optional[float] = None
    preset_name: str = "custom"
    pixel_sampling: str = "uniform"

    def __post_init__(self):
        object.__setattr__(self, "steps", _positive_int("steps", self.steps))
        if self.steps > MAX_TRAIN_STEPS:
            raise TrainConfigError(f"TrainConfig.steps must be at most {MAX_TRAIN_STEPS:,}, got {self.steps:,}")
        for name in (
            "rays_per_batch",
            "num_samples",
            "samples_per_batch",
            "eval_samples",
            "chunk",
            "occupancy_resolution",
            "occupancy_update_every",
        ):
            object.__setattr__(self, name, _positive_int(name, getattr(self, name)))
        if self.first_rays is not None:
            object.__setattr__(self, "first_rays", _positive_int("first_rays", self.first_rays))
            ratio, rest = divmod(self.rays_per_batch, self.first_rays)
            low = min(128, self.rays_per_batch)
            if rest or ratio & (ratio - 1) or self.first_rays < low or (ratio > 1 and self.sampler != "occupancy"):
                raise TrainConfigError(
                    f"TrainConfig.first_rays must be rays_per_batch ({self.rays_per_batch}) halved down to "
                    f"{low} at the least (the occupancy sampler's ladder; the dense sampler's is rays_per_batch "
                    f"alone), got {self.first_rays}"
                )
        for name in ("eval_every", "occupancy_warmup"):
            object.__setattr__(self, name, _positive_int(name, getattr(self, name), minimum=0))
        object.__setattr__(self, "aabb_scale", _positive_float("aabb_scale", self.aabb_scale))
        if self.aabb_scale > MAX_AABB_SCALE:
            raise TrainConfigError(
                f"TrainConfig.aabb_scale must be at most {MAX_AABB_SCALE:g} (Instant-NGP's largest: "
                f"{MAX_AABB_SCALE:g} = 2**7 takes its 8 occupancy cascades), got {self.aabb_scale:g}"
            )
        object.__setattr__(self, "steps_per_diagonal", _positive_float("steps_per_diagonal", self.steps_per_diagonal))
        object.__setattr__(self, "cone_angle", _positive_float("cone_angle", self.cone_angle, allow_zero=True))
        if self.render_step_scale is not None:
            scale = _positive_float("render_step_scale", self.render_step_scale)
            if not RENDER_STEP_SCALES[0] <= scale <= RENDER_STEP_SCALES[1]:  # 1e-40 made the step's inverse overflow
                raise TrainConfigError(
                    f"TrainConfig.render_step_scale must be between {RENDER_STEP_SCALES[0]:g} and "
                    f"{RENDER_STEP_SCALES[1]:g} (the render's marching step over the training's), got {scale:g}"
                )
            object.__setattr__(self, "render_step_scale", scale)
        object.__setattr__(self, "occupancy_decay", _positive_float("occupancy_decay", self.occupancy_decay))
        if self.occupancy_decay > 1.0:
            raise TrainConfigError(f"TrainConfig.occupancy_decay must be in (0, 1], got {self.occupancy_decay}")
        object.__setattr__(self, "random_background", bool(self.random_background))
        object.__setattr__(self, "preset_name", str(self.preset_name))
        if self.loss not in LOSSES:
            raise TrainConfigError(f"TrainConfig.loss must be one of {', '.join(LOSSES)}, got {self.loss!r}")
        if self.pixel_sampling not in PIXEL_SAMPLINGS:
            raise TrainConfigError(
                f"TrainConfig.pixel_sampling must be one of {', '.join(PIXEL_SAMPLINGS)}, got {self.pixel_sampling!r}"
            )
        if self.sampler not in SAMPLERS:
            raise TrainConfigError(f"TrainConfig.sampler must be one of {', '.join(SAMPLERS)}, got {self.sampler!r}")
        if not isinstance(self.field, NGPFieldConfig):
            raise TrainConfigError(f"TrainConfig.field must be an NGPFieldConfig, got {type(self.field).__name__}")

    def replace(self, **changes) -> "TrainConfig":
        """A copy with some fields changed (validated again)."""
        try:
            return dataclasses.replace(self, **changes)
        except TypeError as e:
            raise TrainConfigError(f"invalid TrainConfig change: {e}") from None

    @classmethod
    def preset(cls, name: str, scene: Scene, **overrides) -> "TrainConfig":
        """A named configuration for a scene.

        Both presets take the field's box from `scene.aabb`, Instant-NGP's `aabb_scale` from
        `scene.metadata.get("aabb_scale", 1)`, and the occupancy sampler. Cone-angle stepping (1/256) is
        used for real captures, constant steps for synthetic (Blender, procedural) scenes.
          * "quality": the paper's setup: hash grid L = 16, T = 2**19, N_max = 2048 * aabb_scale;
            a 128**3 occupancy grid; steps of 1/1024 of the base box's diagonal; 2**18 samples per
            batch from up to 2**14 rays (dense: 4096 rays of 128 samples); 20k steps.
          * "fast": sized for a CPU or a quick look, matched to the images' resolution: N_max gives
            two grid cells per pixel footprint (at the cameras' median distance to what they look
            at; at most the paper's) with T = 2**16; a 64**3 occupancy grid; 1.5 marching steps per
            pixel footprint; 2**15 samples per batch from up to 4096 rays (dense: 1024 rays of 64
            samples); 1000 steps.
            NGP's grid warm-up (256 steps, decay 0.95: the grid cannot empty before ~250 steps) is
            shortened to 64 steps with decay 0.8, so that it empties within the first ~60 steps of
            the short run (NGP spends under 1% of its 35k steps there).

        Args:
          name: "fast" or "quality".
          scene: the training scene.
          **overrides: TrainConfig fields to change (e.g. steps=...).

        Raises:
          TrainConfigError: unknown preset name or invalid override.
        """
        if name not in PRESETS:
            raise TrainConfigError(f"unknown preset {name!r}: expected one of {', '.join(PRESETS)}")
        aabb = np.asarray(scene.aabb, np.float64).reshape(2, 3)
        aabb_scale = float(scene.metadata.get("aabb_scale", 1) or 1)
        if not 0 < aabb_scale <= MAX_AABB_SCALE:  # before the hash grid below is sized by it
            raise TrainConfigError(
                f"{scene.path or scene.name}: the scene's aabb_scale {aabb_scale:g} is outside (0, "
                f"{MAX_AABB_SCALE:g}], Instant-NGP's range (its 8 occupancy cascades reach 2**7)"
            )
        paper_n_max = int(round(2048 * aabb_scale))
        # The sizes below are the sampler's: a dense sampler given as an override takes the dense ones
        # (the occupancy sampler's 4,096 rays x 1,024 samples, dense, were 13 GB a step).
        sampler = overrides.get("sampler", "occupancy")
        synthetic = scene.format in ("blender", "procedural")
        base_diagonal = float(np.linalg.norm(aabb[1] - aabb[0])) / aabb_scale
        values: Dict[str, Any] = dict(
            aabb_scale=aabb_scale, sampler=sampler, preset_name=name, cone_angle=0.0 if synthetic else 1.0 / 256.0
        )
        if name == "quality":
            hashgrid = HashGridConfig(L=16, T=2**19, F=2, N_min=16, N_max=paper_n_max)
            values.update(steps=20000, chunk=100, occupancy_resolution=128, steps_per_diagonal=1024.0)
            if sampler == "occupancy":
                values.update(rays_per_batch=2**14, num_samples=1024, samples_per_batch=2**18, eval_samples=1024)
            else:
                values.update(rays_per_batch=4096, num_samples=128, eval_samples=256)
        else:
            footprint = _pixel_footprint(scene)
            n_max = int(min(paper_n_max, max(64, math.ceil(2.0 * float(np.max(aabb[1] - aabb[0])) / footprint))))
            hashgrid = HashGridConfig(L=16, T=2**16, F=2, N_min=16, N_max=n_max)
            values.update(
                steps=1000,
                chunk=50,
                occupancy_resolution=64,
                occupancy_warmup=64,
                occupancy_decay=0.8,
                steps_per_diagonal=float(min(1024.0, max(64.0, 1.5 * base_diagonal / footprint))),
            )
            if sampler == "occupancy":
                values.update(rays_per_batch=4096, num_samples=1024, samples_per_batch=2**15, eval_samples=1024)
            else:
                values.update(rays_per_batch=1024, num_samples=64, eval_samples=128)
        values["field"] = NGPFieldConfig(aabb=aabb, hashgrid=hashgrid)
        values.update(overrides)
        try:
            return cls(**values)
        except TypeError as e:
            raise TrainConfigError(f"invalid TrainConfig override: {e}") from None

    def to_dict(self) -> Dict[str, Any]:
        """Plain-Python description (JSON-ready; inverse of `from_dict`)."""
        out = {f.name: getattr(self, f.name) for f in dataclasses.fields(self) if f.name != "field"}
        field = self.field
        out["field"] = {
            "aabb": list(field.aabb),
            "hashgrid": dataclasses.asdict(field.hashgrid),
            "density_hidden": list(field.density_hidden),
            "geo_features": field.geo_features,
            "color_hidden": list(field.color_hidden),
            "sh_degree": field.sh_degree,
            "use_bias": field.use_bias,
        }
        return out

    @classmethod
    def from_dict(cls, d: Dict[str, Any]) -> "TrainConfig":
        """Inverse of `to_dict`; raises TrainConfigError naming a missing or invalid entry."""
        try:
            values = {k: v for k, v in dict(d).items() if k not in _OBSOLETE_KEYS}
            field = dict(values.pop("field"))
            hashgrid = HashGridConfig(**field.pop("hashgrid"))
            values["field"] = NGPFieldConfig(hashgrid=hashgrid, **field)
            return cls(**values)
        except (KeyError, TypeError, ValueError, AttributeError, OverflowError) as e:
            raise TrainConfigError(f"invalid training config: {e}") from None


def _pixel_footprint(scene: Scene) -> float:
    """World size of one pixel at the cameras' median distance to their common focus point (host)."""
    c2w = np.asarray(scene.c2w, np.float64)
    focus = camera_focus(c2w)
    distance = float(np.median(np.linalg.norm(c2w[:, :3, 3] - focus, axis=-1)))
    focal = float(max(np.asarray(scene.intrinsics.fx), np.asarray(scene.intrinsics.fy)))
    return max(distance, 1e-6) / max(focal, 1e-6)


@flax.struct.dataclass
class TrainHParams:
    """Numeric hyper-parameters (a pytree: traced, never recompiles, can be vmapped over).

    The learning rate at step k is `learning_rate * decay_base ** n(k)`, with n(k) = 0 before
    `decay_start` and 1 + floor((k - decay_start) / decay_interval) from then on (Instant-NGP's
    ExponentialDecay, which multiplies the rate by `decay_base` at decay_start and every interval).

    Attributes:
      learning_rate: Adam step size (Instant-NGP: 1e-2).
      beta1, beta2, eps: Adam moments and epsilon (0.9, 0.99, 1e-15).
      decay_start, decay_interval: steps (floats, so that they are ordinary leaves).
      decay_base: factor per decay (0.33).
      weight_decay: L2 regularisation added to the MLP gradients (Instant-NGP: 1e-6); not on the hash table.
      huber_delta: transition of the Huber loss (used when `TrainConfig.loss == "huber"`).
    """

    learning_rate: Array = 1e-2
    beta1: Array = 0.9
    beta2: Array = 0.99
    eps: Array = 1e-15
    decay_start: Array = 1000.0
    decay_interval: Array = 300.0
    decay_base: Array = _DECAY_BASE
    weight_decay: Array = 1e-6
    huber_delta: Array = 0.1

    @classmethod
    def for_config(cls, config: TrainConfig, **overrides) -> "TrainHParams":
        """Instant-NGP's values, with the decay schedule scaled to `config.steps`."""
        values = dict(
            decay_start=float(max(1, round(_DECAY_START_FRACTION * config.steps))),
            decay_interval=float(max(1, round(_DECAY_INTERVAL_FRACTION * config.steps))),
        )
        values.update(overrides)
        return cls(**values)

    def as_arrays(self) -> "TrainHParams":
        """The same values as float32 arrays (a stable pytree for `jit`)."""
        return jax.tree.map(lambda v: jnp.asarray(v, jnp.float32), self)

    def learning_rate_at(self, step: Array) -> Array:
        """The decayed learning rate at (integer) step `step`."""
        step = jnp.asarray(step, jnp.float32)
        decays = jnp.where(
            step >= self.decay_start,
            1.0 + jnp.floor((step - self.decay_start) / jnp.maximum(self.decay_interval, 1.0)),
            0.0,
        )
        return self.learning_rate * self.decay_base**decays


def check_scene(scene: Scene, what: str) -> None:
    """Raises `TrainConfigError` for a scene that training or evaluation cannot use.

    Args:
      scene: the scene (images [N, H, W, 3] matching its intrinsics, N >= 1).
      what: how the message names it ("training scene", "test scene").
    """
    if not isinstance(scene, Scene):
        raise TrainConfigError(f"{what} must be a waldo_jax.types.Scene, got {type(scene).__name__}")
    if scene.n_images < 1:
        raise TrainConfigError(f"{what} {scene.name or scene.path!r} has no images")
    if scene.images.ndim != 4 or scene.images.shape[-1] != 3:
        raise TrainConfigError(f"{what} images must be [N, H, W, 3], got {list(scene.images.shape)}")
    if (scene.intrinsics.height, scene.intrinsics.width) != (scene.height, scene.width):
        raise TrainConfigError(
            f"{what}: intrinsics are {scene.intrinsics.width}x{scene.intrinsics.height} but the images "
            f"are {scene.width}x{scene.height}"
        )
