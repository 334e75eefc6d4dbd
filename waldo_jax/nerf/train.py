"""Training an Instant-NGP radiance field on a posed image set (Müller et al., SIGGRAPH 2022, Sec. 5.4).

One training step:
  1. draw `R` rays uniformly over ALL pixels of ALL training images (a flat pixel index per ray), and
     build each ray on the fly from its image's `c2w` and the shared intrinsics with
     `cameras.pixel_directions` through the pixel centre. Nothing is precomputed per pixel: the
     device holds only the images (and alphas), so memory stays that of the image set whatever its
     size, and the cost (an undistortion per ray) is negligible against the field evaluations;
  2. draw a background colour per ray, uniform in [0, 1]^3 (Instant-NGP's random background). The
     target is `rgb * a + (1 - a) * bg` (opaque images have a = 1) and `bg` is also the background
     the ray is rendered on, so the field is pushed to be transparent exactly where the data is and
     to be opaque elsewhere;
  3. render the rays with a *sampler* (below), take the loss on rgb (MSE or Huber), and take an Adam
     step (lr 1e-2, betas 0.9 / 0.99, eps 1e-15, L2 weight decay on the MLPs, Instant-NGP's
     step-wise exponential decay).

Samplers are pluggable (`make_sampler`): a sampler is static code plus a pytree state carried in the
`TrainState`, with `init`, `update` (called every `occupancy_update_every` steps inside the scan, by
`lax.cond`) and batched renderers for training rays and for whole views:
  * "dense": `render.render_ray` with stratified samples in [near, far] clipped to the aabb (no state);
  * "occupancy": Instant-NGP's occupancy grid (`occupancy.update_occupancy`, state carried through
    the scan) and ray marching (`occupancy.march_ray`); the marched samples of the whole batch are
    packed into a fixed budget of field evaluations (`_OccupancySampler`), so rays through empty
    space cost no field evaluation and the number of rays trained per step adapts, as in
    Instant-NGP, while every shape stays fixed.

Steps run `chunk` at a time in one `jax.lax.scan` (one dispatch and one host sync per chunk); steps
past `config.steps` inside the last chunk are skipped with `lax.cond`, so one compiled chunk serves
any number of steps. Randomness: `key` is split once into the initialisation key (field, sampler
state) and the training stream; step `i` uses `fold_in(train_stream, i)`, so a chunked run and a
step-by-step run see the same numbers, and the same key gives bit-identical parameters.

Names: `R` rays per batch, `S` samples per ray, `N` training images of `H x W` pixels, `P` poses.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import time
from typing import Any, Callable, Dict, List, NamedTuple, Optional, Tuple

import flax.struct
import jax
import jax.numpy as jnp
import numpy as np
import optax

from waldo_jax.cameras import camera_rays, pixel_directions
from waldo_jax.errors import WaldoError
from waldo_jax.nerf.field import NGPFieldConfig, init_field, make_density, make_field, make_field_batch
from waldo_jax.nerf.hashgrid import HashGridConfig
from waldo_jax.nerf import occupancy
from waldo_jax.render import (RenderConfig, composite, render_ray, render_views, render_views_sharded,
                              shard_over_poses, volume_weights)
from waldo_jax.types import Array, Intrinsics, PRNGKey, RenderOutput, Scene

__all__ = [
    "PRESETS",
    "TrainConfig",
    "TrainConfigError",
    "TrainData",
    "TrainHParams",
    "TrainInputs",
    "TrainResult",
    "TrainState",
    "evaluate",
    "init_train_state",
    "make_sampler",
    "make_train_step",
    "render_trained",
    "run_chunk",
    "train",
    "training_inputs",
]

PRESETS = ("fast", "quality")
LOSSES = ("mse", "huber")
SAMPLERS = ("dense", "occupancy")

# Instant-NGP (base.json): decay starts at step 20k and repeats every 10k, of ~35k steps.
_DECAY_START_FRACTION = 0.5
_DECAY_INTERVAL_FRACTION = 0.15
_DECAY_BASE = 0.33


class TrainConfigError(WaldoError, ValueError):
    """A training configuration or its input scene is invalid (the message names the value)."""


# ----------------------------------------------------------------------------------------------
# Configuration: static shapes (TrainConfig) apart from numeric hyper-parameters (TrainHParams).


def _positive_int(name: str, value: Any, minimum: int = 1) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < minimum:
        raise TrainConfigError(f"TrainConfig.{name} must be an int >= {minimum}, got {value!r}")
    return int(value)


def _positive_float(name: str, value: Any, allow_zero: bool = False) -> float:
    try:
        number = float(value)
    except (TypeError, ValueError):
        raise TrainConfigError(f"TrainConfig.{name} must be a number, got {value!r}") from None
    if isinstance(value, bool) or not math.isfinite(number) or number < 0 or (number == 0 and not allow_zero):
        raise TrainConfigError(f"TrainConfig.{name} must be a {'non-negative' if allow_zero else 'positive'} "
                               f"finite number, got {value!r}")
    return number


@dataclasses.dataclass(frozen=True)
class TrainConfig:
    """Static, shape-setting training configuration (hashable; one compilation per distinct value).

    Attributes:
      field: the Instant-NGP field (aabb = the whole scene box, hash grid, MLP widths).
      aabb_scale: Instant-NGP's aabb_scale: the occupancy grid's base box is the field's box shrunk
        by it, with 1 + ceil(log2(aabb_scale)) cascades covering the rest.
      steps: optimisation steps.
      rays_per_batch: R, rays drawn per step. With the occupancy sampler this is the most rays a
        step can train on: rays enter the batch in random order until their marched samples fill
        `samples_per_batch` (Instant-NGP's dynamic batch, with fixed shapes).
      num_samples: samples per training ray: the stratified count (dense) or the most samples one
        ray may keep in occupied space (occupancy; capped at the K candidates that cross the grid,
        so a large value means no cap, as in Instant-NGP).
      samples_per_batch: occupancy sampler: field evaluations per step (packed across rays).
      eval_samples: samples per ray when rendering views (held-out PSNR, `waldo render`): the
        stratified count (dense) or the per-ray cap (occupancy, as num_samples).
      chunk: steps per `lax.scan` between host syncs (progress bar, history).
      loss: "mse" or "huber" on rgb.
      sampler: "dense" or "occupancy" (see the module docstring).
      occupancy_resolution: G, cells per side of each occupancy cascade.
      occupancy_update_every: steps between occupancy-grid updates (Instant-NGP: 16).
      occupancy_warmup: steps during which every cell is re-sampled at each update (NGP: 256).
      occupancy_decay: factor on the stored densities at each update (NGP: 0.95).
      steps_per_diagonal: the marching step is the base box's diagonal / this (NGP: 1024).
      cone_angle: marching steps grow as t * cone_angle (NGP: 0 for synthetic, 1/256 for real scenes).
      random_background: per-ray random background colour (else the scene's background, or black).
      eval_every: steps between held-out evaluations recorded in the history (0: at the end only).
      eval_ray_chunk: rays rendered together when rendering views.
      preset_name: the preset this config came from ("custom" otherwise), recorded for reports.
    """

    field: NGPFieldConfig = NGPFieldConfig()
    aabb_scale: float = 1.0
    steps: int = 2000
    rays_per_batch: int = 1024
    num_samples: int = 64
    samples_per_batch: int = 2**15
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
    eval_ray_chunk: int = 4096
    preset_name: str = "custom"

    def __post_init__(self):
        for name in ("steps", "rays_per_batch", "num_samples", "samples_per_batch", "eval_samples", "chunk",
                     "occupancy_resolution", "occupancy_update_every", "eval_ray_chunk"):
            object.__setattr__(self, name, _positive_int(name, getattr(self, name)))
        for name in ("eval_every", "occupancy_warmup"):
            object.__setattr__(self, name, _positive_int(name, getattr(self, name), minimum=0))
        object.__setattr__(self, "aabb_scale", _positive_float("aabb_scale", self.aabb_scale))
        object.__setattr__(self, "steps_per_diagonal", _positive_float("steps_per_diagonal", self.steps_per_diagonal))
        object.__setattr__(self, "cone_angle", _positive_float("cone_angle", self.cone_angle, allow_zero=True))
        object.__setattr__(self, "occupancy_decay", _positive_float("occupancy_decay", self.occupancy_decay))
        if self.occupancy_decay > 1.0:
            raise TrainConfigError(f"TrainConfig.occupancy_decay must be in (0, 1], got {self.occupancy_decay}")
        object.__setattr__(self, "random_background", bool(self.random_background))
        object.__setattr__(self, "preset_name", str(self.preset_name))
        if self.loss not in LOSSES:
            raise TrainConfigError(f"TrainConfig.loss must be one of {', '.join(LOSSES)}, got {self.loss!r}")
        if self.sampler not in SAMPLERS:
            raise TrainConfigError(
                f"TrainConfig.sampler must be one of {', '.join(SAMPLERS)}, got {self.sampler!r}")
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
        `scene.metadata.get("aabb_scale", 1)`, and the occupancy sampler when
        `waldo_jax.nerf.occupancy` is available (else the dense one). Cone-angle stepping (1/256) is
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
        paper_n_max = int(round(2048 * aabb_scale))
        sampler = "occupancy"
        synthetic = scene.format in ("blender", "procedural")
        base_diagonal = float(np.linalg.norm(aabb[1] - aabb[0])) / aabb_scale
        values: Dict[str, Any] = dict(aabb_scale=aabb_scale, sampler=sampler, preset_name=name,
                                      cone_angle=0.0 if synthetic else 1.0 / 256.0)
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
            values.update(steps=1000, chunk=50, occupancy_resolution=64, occupancy_warmup=64, occupancy_decay=0.8,
                          steps_per_diagonal=float(min(1024.0, max(64.0, 1.5 * base_diagonal / footprint))))
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
            values = dict(d)
            field = dict(values.pop("field"))
            hashgrid = HashGridConfig(**field.pop("hashgrid"))
            values["field"] = NGPFieldConfig(hashgrid=hashgrid, **field)
            return cls(**values)
        except (KeyError, TypeError, ValueError, AttributeError) as e:
            raise TrainConfigError(f"invalid training config: {e}") from None


def _pixel_footprint(scene: Scene) -> float:
    """World size of one pixel at the cameras' median distance to their common focus point (host)."""
    from waldo_jax.scenes import camera_focus

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


# ----------------------------------------------------------------------------------------------
# State and data.


@flax.struct.dataclass
class TrainState:
    """What evolves during training.

    Attributes:
      params: the field's parameters.
      opt_state: the optimiser's state (Adam moments and step count).
      sampler_state: the sampler's state (the occupancy grid, or None for the dense sampler).
      step: int32 [], steps taken.
    """

    params: Any
    opt_state: Any
    sampler_state: Any
    step: Array


@flax.struct.dataclass
class TrainData:
    """The training images on the device.

    Attributes:
      images: float32 [N, H, W, 3], colour premultiplied by alpha (`rgb * a`; the images as they are
        for opaque scenes).
      alphas: float32 [N, H, W] opacities, or None for opaque images.
      c2w: float32 [N, 3, 4] camera-to-world matrices.
      intrinsics: the shared camera.
      background: float32 [3], used when the background is not random.
    """

    images: Array
    alphas: Optional[Array]
    c2w: Array
    intrinsics: Intrinsics
    background: Array

    @classmethod
    def from_scene(cls, scene: Scene) -> "TrainData":
        """Moves a scene's images and cameras to the device (RGBA images as premultiplied colour)."""
        images = np.asarray(scene.images, np.float32)
        alphas = None
        background = np.zeros(3, np.float32) if scene.background is None else np.asarray(scene.background, np.float32)
        if scene.alphas is not None:
            alphas = np.asarray(scene.alphas, np.float32)
            # Scene.images are `rgb * a + (1 - a) * background`: subtracting the background term
            # leaves the premultiplied colour `rgb * a` exactly, without dividing by a.
            images = images - (1.0 - alphas[..., None]) * background
        return cls(
            images=jnp.asarray(images),
            alphas=None if alphas is None else jnp.asarray(alphas),
            c2w=jnp.asarray(np.asarray(scene.c2w, np.float32)[:, :3, :4]),
            intrinsics=scene.intrinsics,
            background=jnp.asarray(background),
        )


def _check_scene(scene: Scene, what: str) -> None:
    """Clear errors for scenes training cannot use."""
    if not isinstance(scene, Scene):
        raise TrainConfigError(f"{what} must be a waldo_jax.types.Scene, got {type(scene).__name__}")
    if scene.n_images < 1:
        raise TrainConfigError(f"{what} {scene.name or scene.path!r} has no images")
    if scene.images.ndim != 4 or scene.images.shape[-1] != 3:
        raise TrainConfigError(f"{what} images must be [N, H, W, 3], got {list(scene.images.shape)}")
    if (scene.intrinsics.height, scene.intrinsics.width) != (scene.height, scene.width):
        raise TrainConfigError(
            f"{what}: intrinsics are {scene.intrinsics.width}x{scene.intrinsics.height} but the images "
            f"are {scene.width}x{scene.height}")


# ----------------------------------------------------------------------------------------------
# Samplers.
#
# A sampler is static code (one object per TrainConfig) with a pytree state carried in TrainState:
#   init(key, params) -> state
#   update(key, state, params, step) -> state                      (every occupancy_update_every steps)
#   render_rays(key, params, state, origins [R, 3], directions [R, 3], background [R, 3], render_config)
#       -> (RenderOutput [R], included bool [R])                   (rays that count in the loss)
#   render_views(params, state, c2w [P, 4, 4], intrinsics, render_config) -> RenderOutput [P, H, W]
#   render_views_sharded(params, state, c2w, intrinsics, render_config, mesh) -> the same, poses split
#       over the devices of a one-axis mesh "poses" (`render.shard_over_poses`)


class _DenseSampler:
    """Stratified samples in [near, far] ∩ aabb (`render.render_ray` with a key); no state."""

    def __init__(self, config: TrainConfig):
        self.config = config
        self.field = make_field(config.field)

    def init(self, key: PRNGKey, params) -> None:
        """No state."""
        return None

    def update(self, key: PRNGKey, state, params, step: Array):
        """No state to update."""
        return state

    def render_rays(self, key: PRNGKey, params, state, origins: Array, directions: Array,
                    background: Array, render_config: RenderConfig) -> Tuple[RenderOutput, Array]:
        """Renders R training rays [R, 3] on per-ray backgrounds [R, 3]; every ray is included."""
        keys = jax.random.split(key, origins.shape[0])

        def one(k, o, d, bg):
            return render_ray(self.field, params, o, d, render_config.replace(background=bg), k)

        out = jax.vmap(one)(keys, origins, directions, background)
        return out, jnp.ones(origins.shape[:1], bool)

    def render_views(self, params, state, c2w: Array, intrinsics: Intrinsics,
                     render_config: RenderConfig) -> RenderOutput:
        """Renders P views [P, 4, 4] deterministically (bin midpoints), S = render_config.num_samples."""
        return render_views(self.field, params, c2w, intrinsics, render_config)

    def render_views_sharded(self, params, state, c2w: Array, intrinsics: Intrinsics, render_config: RenderConfig,
                             mesh=None) -> RenderOutput:
        """`render_views` with the poses split over the devices of `mesh` (the same images)."""
        return render_views_sharded(self.field, params, c2w, intrinsics, render_config, mesh=mesh)


class _OccupancySampler:
    """Instant-NGP's occupancy grid and ray marching (`waldo_jax.nerf.occupancy`), with packed samples.

    Each ray is marched (`occupancy.march_ray`: candidates every dt, kept where the grid is
    occupied, compacted to at most S = `num_samples`). The kept samples of the whole batch are then
    *packed* into a fixed budget of `samples_per_batch` field evaluations, so a ray that crosses
    empty space costs nothing and the field runs on occupied samples only (Instant-NGP's compaction):
      * training: rays enter in their (random) order while the running count of samples fits the
        budget; the rest are left out of this step's loss (`included`). As with Instant-NGP's
        dynamic batch size, the rays trained per step adapt to the scene (few while the grid is
        still full, many once it is sparse) at a fixed cost per step;
      * views: Instant-NGP's early ray termination. A `lax.while_loop` packs the next segment of
        samples of every live ray into a fixed budget per pass, composites front to back carrying
        each ray's colour, depth, opacity and optical depth, and retires a ray once its
        transmittance is below 1e-4 (`occupancy.render_samples_early_stop`): nothing behind an
        opaque surface is evaluated. Training keeps the full composite of every kept sample (its
        results, and gradients through the tail, are unchanged).
    The weights and composite are those of `render.volume_weights` / `render.composite`; masked
    samples have zero length (delta = 0) and so zero weight.
    """

    def __init__(self, config: TrainConfig):
        self.config = config
        self.field = make_field(config.field)
        self.field_batch = make_field_batch(config.field)
        self.density = make_density(config.field)
        aabb = np.asarray(config.field.aabb, np.float64).reshape(2, 3)
        center, half = 0.5 * (aabb[0] + aabb[1]), 0.5 * (aabb[1] - aabb[0]) / config.aabb_scale
        self.base_aabb = np.stack([center - half, center + half])
        geometry = occupancy.init_occupancy(self.base_aabb, config.aabb_scale, resolution=1)
        self.cascades = geometry.cascades
        self.max_steps = _march_steps(geometry.base_diagonal, self.cascades, config.occupancy_resolution,
                                      config.steps_per_diagonal, config.cone_angle)
        if config.samples_per_batch < min(config.num_samples, self.max_steps):
            raise TrainConfigError(
                f"TrainConfig.samples_per_batch ({config.samples_per_batch}) must be at least the samples one "
                f"ray may keep, min(num_samples, K) = {min(config.num_samples, self.max_steps)}")

    def init(self, key: PRNGKey, params):
        """All cells occupied, zero densities (nothing is skipped before the first update)."""
        return occupancy.init_occupancy(self.base_aabb, self.config.aabb_scale,
                                             resolution=self.config.occupancy_resolution)

    def _occupancy_config(self, grid):
        return occupancy.OccupancyConfig.create(
            grid, steps_per_diagonal=self.config.steps_per_diagonal, warmup_steps=self.config.occupancy_warmup,
            decay=self.config.occupancy_decay)

    def march_config(self, num_samples: int):
        """The march: K candidates (enough to cross the whole grid), at most min(num_samples, K) kept."""
        return occupancy.MarchConfig.create(
            max_steps=self.max_steps, max_samples=min(num_samples, self.max_steps),
            steps_per_diagonal=self.config.steps_per_diagonal, cone_angle=self.config.cone_angle)

    def update(self, key: PRNGKey, grid, params, step: Array):
        """Instant-NGP's decay / sample / threshold update of the grid from the current densities."""
        return occupancy.update_occupancy(key, grid, self.density, jax.lax.stop_gradient(params), step,
                                               self._occupancy_config(grid))

    def _march(self, grid, origins: Array, directions: Array, render_config: RenderConfig, num_samples: int,
               key: Optional[PRNGKey]) -> Tuple[Array, Array, Array]:
        """t, delta [N, S] and mask bool [N, S] of N rays (random offsets with a key)."""
        march_config = self.march_config(num_samples)

        def one(o, d, k):
            t_start, t_end = occupancy.ray_interval(grid, o, d, render_config)
            return occupancy.march_ray(grid, o, d, t_start, t_end, march_config, k)

        keys = None if key is None else jax.random.split(key, origins.shape[0])
        return jax.vmap(one, in_axes=(0, 0, None if keys is None else 0))(origins, directions, keys)

    def _render_packed(self, params, origins: Array, directions: Array, background: Array, t: Array,
                       delta: Array, mask: Array, included: Array, budget: int) -> RenderOutput:
        """Composites the rays marked `included` [N] from at most `budget` packed field evaluations.

        The caller guarantees that the included rays' valid samples fit the budget.
        """
        num_rays, num_samples = t.shape
        valid = (mask & included[:, None]).reshape(-1)  # [N * S]
        slot = jnp.where(valid, jnp.cumsum(valid.astype(jnp.int32)) - 1, budget)  # [N * S]
        source = jnp.zeros((budget,), jnp.int32).at[slot].set(
            jnp.arange(num_rays * num_samples, dtype=jnp.int32), mode="drop")  # [B] sample of each slot
        ray = source // num_samples  # [B]
        points = origins[ray] + t.reshape(-1)[source][:, None] * directions[ray]  # [B, 3]
        sigma_packed, rgb_packed = self.field_batch(params, points, directions[ray])  # [B], [B, 3]
        take = jnp.minimum(slot, budget - 1)  # [N * S]
        sigma = jnp.where(valid, sigma_packed[take], 0.0).reshape(num_rays, num_samples)  # [N, S]
        rgb = jnp.where(valid[:, None], jnp.nan_to_num(rgb_packed[take]), 0.0)
        rgb = rgb.reshape(num_rays, num_samples, 3)  # [N, S, 3]
        w = jax.vmap(volume_weights)(sigma, delta)  # [N, S]
        return jax.vmap(composite)(w, rgb, t, background)

    def render_rays(self, key: PRNGKey, params, grid, origins: Array, directions: Array, background: Array,
                    render_config: RenderConfig) -> Tuple[RenderOutput, Array]:
        """Renders training rays [R, 3]; the leading rays whose samples fit the budget are `included`."""
        t, delta, mask = self._march(grid, origins, directions, render_config, self.config.num_samples, key)
        counts = jnp.sum(mask, axis=-1, dtype=jnp.int32)  # [R]
        included = jnp.cumsum(counts) <= self.config.samples_per_batch  # [R]
        out = self._render_packed(params, origins, directions, background, t, delta, mask, included,
                                  self.config.samples_per_batch)
        return out, included

    def render_ray_batch_counted(self, params, grid, origins: Array, directions: Array, background: Array,
                                 render_config: RenderConfig, num_samples: int, budget: int,
                                 active: Optional[Array] = None,
                                 max_segment: Optional[int] = None) -> Tuple[RenderOutput, Array, Array]:
        """Renders EVERY ray of a batch [N, 3] deterministically, `budget` field evaluations per pass,
        with Instant-NGP's early ray termination (`occupancy.render_samples_early_stop`).

        Each ray is marched (at most min(num_samples, K) samples in occupied cells); pass after pass,
        the next segment of samples of every live ray is packed into the budget and composited front
        to back, and a ray retires once its transmittance is below the march's min_transmittance
        (1e-4) or its samples run out, so nothing behind an opaque surface is evaluated. The colour
        differs from the composite of all samples by less than 1e-4 times max |rgb - background|.

        Args:
          params: the field's parameters. grid: the occupancy grid.
          origins, directions: [N, 3]. background: [N, 3].
          render_config: near, far and box. num_samples: the per-ray cap on marched samples.
          budget: field evaluations per pass (static, >= 1).
          active: bool [N], rays to render (default all); the others get no sample (background).
          max_segment: most samples a ray takes per pass (static; None: no cap).

        Returns:
          (`RenderOutput` with rgb [N, 3], depth [N], acc [N]; evaluations int32 [N], the field
          evaluations spent on each ray; passes int32 [], each evaluating `budget` slots).
        """
        march_config = self.march_config(num_samples)
        t, delta, mask = self._march(grid, origins, directions, render_config, num_samples, None)  # [N, S] each
        if active is not None:
            mask = mask & active[:, None]
        return occupancy.render_samples_early_stop(self.field, params, origins, directions, t, delta, mask, background,
                                                   march_config.min_transmittance, budget, max_segment)

    def render_ray_batch(self, params, grid, origins: Array, directions: Array, background: Array,
                         render_config: RenderConfig, num_samples: int, budget: int) -> RenderOutput:
        """`render_ray_batch_counted` without the counts: the rendered rays [N]."""
        return self.render_ray_batch_counted(params, grid, origins, directions, background, render_config,
                                             num_samples, budget)[0]

    def render_views(self, params, grid, c2w: Array, intrinsics: Intrinsics,
                     render_config: RenderConfig) -> RenderOutput:
        """Renders P views [P, 4, 4] (midpoint samples, early ray termination), at most
        render_config.num_samples per ray."""
        return self.render_views_counted(params, grid, c2w, intrinsics, render_config)[0]

    def render_views_counted(self, params, grid, c2w: Array, intrinsics: Intrinsics,
                             render_config: RenderConfig) -> Tuple[RenderOutput, Array, Array]:
        """`render_views` and what it cost (for benchmarks).

        Returns:
          (the same `RenderOutput` [P, H, W]; evaluations int32 [P, H, W], the field evaluations spent on
          each pixel's ray; passes int32 [P, num_chunks], the passes of each chunk of
          `config.eval_ray_chunk` rays, each evaluating `view_budget()` slots).
        """
        return _marched_views(self.config, render_config.num_samples)(params, grid, c2w, intrinsics, render_config)

    def view_budget(self) -> int:
        """Field evaluations (slots) per pass of `render_views`, for each chunk of `config.eval_ray_chunk` rays."""
        return self.config.eval_ray_chunk * _VIEW_SAMPLES_PER_RAY_PER_PASS

    def render_views_sharded(self, params, grid, c2w: Array, intrinsics: Intrinsics, render_config: RenderConfig,
                             mesh=None) -> RenderOutput:
        """`render_views` with the poses split over the devices of `mesh` (the same images)."""
        return shard_over_poses(_marched_local(self.config, render_config.num_samples),
                                (params, grid, intrinsics, render_config), c2w, mesh)


def _march_steps(base_diagonal: float, cascades: int, resolution: int, steps_per_diagonal: float,
                 cone_angle: float, cap: int = 8192) -> int:
    """K, the candidates a ray needs to cross the grid's whole outer box from t = 0 (host-side)."""
    dt_min = base_diagonal / steps_per_diagonal
    dt_max = max(dt_min, base_diagonal * 2.0 ** (cascades - 1) / resolution)
    length = base_diagonal * 2.0 ** (cascades - 1)
    t, steps = 0.0, 0
    while t < length and steps < cap:
        t += min(max(t * cone_angle, dt_min), dt_max)
        steps += 1
    return steps


# Views: field evaluations per ray of a chunk in one pass. Each pass costs the whole budget; with early
# termination a converged field needs a few dozen samples per ray, so passes of 8 per ray leave little
# of the last pass unused, and the few rays that need many samples take long segments once the others
# have retired.
_VIEW_SAMPLES_PER_RAY_PER_PASS = 8


@functools.lru_cache(maxsize=None)
def _marched_views(config: TrainConfig, num_samples: int) -> Callable:
    """Jitted renderer of P views with the occupancy sampler, with its counts (cached per config and
    sample count; `render_views` drops the counts, so both share one compilation)."""
    return jax.jit(_marched_views_fn(config, num_samples, counted=True))


@functools.lru_cache(maxsize=None)
def _marched_local(config: TrainConfig, num_samples: int) -> Callable:
    """The marched renderer in `render.shard_over_poses`' calling convention (one object per config)."""
    views = _marched_views_fn(config, num_samples)

    def local(replicated, posed):
        params, grid, intrinsics, render_config = replicated
        return views(params, grid, posed[0], intrinsics, render_config)

    return local


def _marched_views_fn(config: TrainConfig, num_samples: int, counted: bool = False) -> Callable:
    """The (unjitted) renderer of P views with the occupancy sampler and early ray termination.

    views(params, grid, c2w [P, 4, 4], intrinsics, render_config) -> RenderOutput [P, H, W], or with
    `counted` (RenderOutput, evaluations int32 [P, H, W], passes int32 [P, num_chunks]).
    """
    sampler = make_sampler(config)
    budget = sampler.view_budget()

    def views(params, grid, c2w, intrinsics, render_config):
        h, w = intrinsics.height, intrinsics.width
        num_rays = h * w
        chunk = max(1, min(config.eval_ray_chunk, num_rays))
        num_chunks = -(-num_rays // chunk)
        pad = num_chunks * chunk - num_rays
        # Padding rays (cropped below) are not marched: they cost no field evaluation.
        active = (jnp.arange(num_chunks * chunk) < num_rays).reshape(num_chunks, chunk)

        def crop(a):  # [num_chunks, chunk, ...] -> [H, W, ...]
            return a.reshape((num_chunks * chunk,) + a.shape[2:])[:num_rays].reshape((h, w) + a.shape[2:])

        def one_view(m):
            origins, directions = camera_rays(m, intrinsics)  # [H, W, 3] each
            origins = jnp.pad(origins.reshape(-1, 3), ((0, pad), (0, 0))).reshape(num_chunks, chunk, 3)
            directions = jnp.pad(directions.reshape(-1, 3), ((0, pad), (0, 0)), constant_values=1.0 / math.sqrt(3.0))
            directions = directions.reshape(num_chunks, chunk, 3)
            background = jnp.broadcast_to(render_config.background, (chunk, 3))
            out, evaluations, passes = jax.lax.map(
                lambda args: sampler.render_ray_batch_counted(params, grid, args[0], args[1], background,
                                                              render_config, num_samples, budget, args[2]),
                (origins, directions, active))
            return jax.tree.map(crop, out), crop(evaluations), passes

        out, evaluations, passes = jax.lax.map(one_view, jnp.asarray(c2w, jnp.float32)[:, :3, :4])
        return (out, evaluations, passes) if counted else out

    return views


@functools.lru_cache(maxsize=None)
def make_sampler(config: TrainConfig):
    """The sampler of a config (one object per config, so compiled functions are shared)."""
    if config.sampler == "occupancy":
        return _OccupancySampler(config)
    return _DenseSampler(config)


# ----------------------------------------------------------------------------------------------
# The training step.


def _mlp_mask(params) -> Any:
    """True for MLP weights (weight decay applies), False for the hash table."""
    return {k: jax.tree.map(lambda _: k != "hash", v) for k, v in params.items()}


def _optimizer(hparams: TrainHParams, step: Array, params) -> optax.GradientTransformation:
    """Adam with L2 regularisation on the MLPs and the decayed learning rate of `step`."""
    return optax.chain(
        optax.add_decayed_weights(hparams.weight_decay, mask=_mlp_mask(params)),
        optax.scale_by_adam(b1=hparams.beta1, b2=hparams.beta2, eps=hparams.eps),
        optax.scale(-hparams.learning_rate_at(step)),
    )


def init_train_state(key: PRNGKey, config: TrainConfig, hparams: Optional[TrainHParams] = None) -> TrainState:
    """Initial field parameters, optimiser state and sampler state.

    Args:
      key: PRNG key (consumed: split into the field's and the sampler's keys).
      config: static training configuration.
      hparams: numeric hyper-parameters (only their structure matters here).
    """
    hparams = (hparams or TrainHParams.for_config(config)).as_arrays()
    key_field, key_sampler = jax.random.split(key)
    params = init_field(key_field, config.field)
    opt_state = _optimizer(hparams, jnp.int32(0), params).init(params)
    sampler_state = make_sampler(config).init(key_sampler, params)
    return TrainState(params=params, opt_state=opt_state, sampler_state=sampler_state, step=jnp.int32(0))


def _sample_batch(key: PRNGKey, data: TrainData, config: TrainConfig) -> Tuple[Array, Array, Array, Array]:
    """R rays uniform over all training pixels, with their targets and backgrounds.

    Returns:
      origins [R, 3], unit directions [R, 3], target rgb [R, 3], background [R, 3].
    """
    key_pixel, key_bg = jax.random.split(key)
    n, h, w = data.images.shape[:3]
    flat = jax.random.randint(key_pixel, (config.rays_per_batch,), 0, n * h * w)  # [R]
    image, rest = flat // (h * w), flat % (h * w)
    row, col = rest // w, rest % w
    dirs_cam = jax.vmap(lambda u, v: pixel_directions(data.intrinsics, u, v))(
        col.astype(jnp.float32) + 0.5, row.astype(jnp.float32) + 0.5)  # [R, 3]
    c2w = data.c2w[image]  # [R, 3, 4]
    directions = jnp.einsum("rij,rj->ri", c2w[:, :, :3], dirs_cam)  # [R, 3]
    directions = directions / jnp.linalg.norm(directions, axis=-1, keepdims=True)
    origins = c2w[:, :, 3]  # [R, 3]
    premultiplied = data.images[image, row, col]  # [R, 3]
    if config.random_background:
        background = jax.random.uniform(key_bg, (config.rays_per_batch, 3))  # [R, 3]
    else:
        background = jnp.broadcast_to(data.background, (config.rays_per_batch, 3))
    if data.alphas is not None:
        alpha = data.alphas[image, row, col][:, None]  # [R, 1]
        target = premultiplied + (1.0 - alpha) * background  # = rgb * a + (1 - a) * bg
    else:
        target = premultiplied
    return origins, directions, target, background


def _loss(residual: Array, included: Array, config: TrainConfig, hparams: TrainHParams) -> Tuple[Array, Array]:
    """(loss, MSE): means over the included rays [R] of residuals [R, 3] (masked, divided by the count)."""
    weight = included.astype(jnp.float32)[:, None] / (3.0 * jnp.maximum(jnp.sum(included), 1))  # [R, 1]
    squared = residual**2  # [R, 3]
    mse = jnp.sum(weight * squared)
    if config.loss == "huber":
        return jnp.sum(weight * optax.huber_loss(residual, delta=hparams.huber_delta)), mse
    return mse, mse


def _psnr(mse: Array) -> Array:
    """PSNR in dB of images in [0, 1] from their MSE."""
    return -10.0 * jnp.log10(jnp.maximum(mse, jnp.finfo(jnp.float32).tiny))


def make_train_step(config: TrainConfig) -> Callable:
    """The training step for one batch (pure; jit it or scan it).

    Returns:
      step(state, train_key, data, hparams, render_config) -> (state, metrics): `train_key` is the
      training stream; step `state.step` uses `fold_in(train_key, state.step)`. `metrics` holds
      float32 [] `loss` and `psnr` (of the batch MSE, on the composited targets) and int32 [] `rays`,
      the rays in the loss (all R for the dense sampler).
    """
    sampler = make_sampler(config)

    def step(state: TrainState, train_key: PRNGKey, data: TrainData, hparams: TrainHParams,
             render_config: RenderConfig):
        key = jax.random.fold_in(train_key, state.step)
        key_batch, key_render, key_update = jax.random.split(key, 3)
        origins, directions, target, background = _sample_batch(key_batch, data, config)
        sampler_state = jax.lax.cond(
            state.step % config.occupancy_update_every == 0,
            lambda s: sampler.update(key_update, s, state.params, state.step),
            lambda s: s,
            state.sampler_state,
        ) if state.sampler_state is not None else None

        def loss_fn(params):
            out, included = sampler.render_rays(key_render, params, sampler_state, origins, directions,
                                                background, render_config)
            loss, mse = _loss(out.rgb - target, included, config, hparams)
            return loss, (mse, jnp.sum(included, dtype=jnp.int32))

        (loss, (mse, rays)), grads = jax.value_and_grad(loss_fn, has_aux=True)(state.params)
        optimizer = _optimizer(hparams, state.step, state.params)
        updates, opt_state = optimizer.update(grads, state.opt_state, state.params)
        params = optax.apply_updates(state.params, updates)
        new_state = TrainState(params=params, opt_state=opt_state, sampler_state=sampler_state,
                               step=state.step + 1)
        return new_state, {"loss": loss, "psnr": _psnr(mse), "rays": rays}

    return step


@functools.lru_cache(maxsize=None)
def _chunk_fn(config: TrainConfig) -> Callable:
    """`config.chunk` steps in one `lax.scan`, jitted (cached per config, state donated)."""
    step = make_train_step(config)

    def chunk(state, train_key, data, hparams, render_config, total_steps):
        def body(state, _):
            active = state.step < total_steps
            skipped = {"loss": jnp.float32(jnp.nan), "psnr": jnp.float32(jnp.nan), "rays": jnp.int32(0)}
            new_state, metrics = jax.lax.cond(
                active,
                lambda s: step(s, train_key, data, hparams, render_config),
                lambda s: (s, skipped),
                state,
            )
            return new_state, metrics

        return jax.lax.scan(body, state, None, length=config.chunk)

    return jax.jit(chunk, donate_argnums=(0,))


def run_chunk(state: TrainState, train_key: PRNGKey, data: TrainData, hparams: TrainHParams,
              render_config: RenderConfig, config: TrainConfig, total_steps: int) -> Tuple[TrainState, Dict]:
    """Runs `config.chunk` steps (those with step >= total_steps are skipped) in one jitted scan.

    The input state's buffers are donated: do not use `state` afterwards.

    Returns:
      (state, metrics) with metrics {"loss", "psnr"} float32 [chunk] (NaN for skipped steps) and
      {"rays"} int32 [chunk] (0 for skipped steps).
    """
    return _chunk_fn(config)(state, train_key, data, hparams.as_arrays(), render_config,
                             jnp.int32(total_steps))


# ----------------------------------------------------------------------------------------------
# Rendering and evaluation of a trained field.


def _render_config(config: TrainConfig, near: float, far: float, aabb, background, num_samples: int,
                   pose_chunk: int = 1) -> RenderConfig:
    return RenderConfig.create(near=near, far=far, aabb=np.asarray(aabb, np.float32).reshape(2, 3),
                               background=background, num_samples=num_samples,
                               ray_chunk=config.eval_ray_chunk, pose_chunk=pose_chunk)


def render_trained(params, sampler_state, config: TrainConfig, c2w, intrinsics: Intrinsics, near: float,
                   far: float, background=(1.0, 1.0, 1.0), aabb=None, mesh=None) -> RenderOutput:
    """Renders P views of a trained field in one call, with the config's sampler.

    With more than one local device (or a `mesh`), the poses are split over the devices
    (`render.shard_over_poses`); the images are the same as on one device.

    Args:
      params: the field's parameters.
      sampler_state: the occupancy grid, or None (dense sampler).
      config: the training config (field, sampler, eval_samples).
      c2w: [P, 4, 4] or [P, 3, 4] camera-to-world matrices.
      intrinsics: shared intrinsics (their width and height set the image size).
      near, far: ray bounds (world units).
      background: colour [3] behind the volume.
      aabb: [2, 3] sampling box (default: the field's box).
      mesh: a one-axis mesh named "poses" to shard over (default: all local devices if more than one).

    Returns:
      RenderOutput with rgb [P, H, W, 3], depth [P, H, W], acc [P, H, W] (device arrays).
    """
    aabb = np.asarray(config.field.aabb if aabb is None else aabb, np.float32).reshape(2, 3)
    render_config = _render_config(config, near, far, aabb, background, config.eval_samples)
    c2w = jnp.asarray(np.asarray(c2w, np.float32))
    sampler = make_sampler(config)
    if mesh is None and jax.local_device_count() == 1:
        return sampler.render_views(params, sampler_state, c2w, intrinsics, render_config)
    return sampler.render_views_sharded(params, sampler_state, c2w, intrinsics, render_config, mesh)


def _eval_background(scene: Scene) -> np.ndarray:
    return np.zeros(3, np.float32) if scene.background is None else np.asarray(scene.background, np.float32)


def evaluate(params, sampler_state, config: TrainConfig, scene: Scene) -> Dict[str, Any]:
    """Held-out PSNR: renders every view of `scene` and compares with its images.

    RGBA scenes are compared on the background their images were composited on (`scene.background`);
    opaque ones are rendered on black.

    Returns:
      {"psnr": mean of per-image PSNR (dB), "psnr_per_image": list, "mse": mean MSE,
       "images": float32 [P, H, W, 3] renders (host)}.
    """
    _check_scene(scene, "test scene")
    out = render_trained(params, sampler_state, config, scene.c2w, scene.intrinsics, scene.near, scene.far,
                         _eval_background(scene), aabb=scene.aabb)
    rendered = np.asarray(jax.device_get(out.rgb), np.float32)
    mse = np.mean((rendered.astype(np.float64) - np.asarray(scene.images, np.float64)) ** 2, axis=(1, 2, 3))
    psnr = -10.0 * np.log10(np.maximum(mse, 1e-12))
    return {"psnr": float(np.mean(psnr)), "psnr_per_image": psnr.tolist(), "mse": float(np.mean(mse)),
            "images": rendered}


# ----------------------------------------------------------------------------------------------
# The training loop.


class TrainInputs(NamedTuple):
    """Everything a training run starts from (see `training_inputs`)."""

    state: TrainState
    train_key: PRNGKey
    data: TrainData
    hparams: TrainHParams
    render_config: RenderConfig


def training_inputs(key: PRNGKey, train_scene: Scene, config: TrainConfig,
                    hparams: Optional[TrainHParams] = None) -> TrainInputs:
    """Initial state, training key stream, device data and render config of a run.

    `key` is split into the initialisation key and the training stream, exactly as `train` does,
    so a Python loop over `make_train_step(config)` from these inputs reproduces `train`.
    """
    _check_scene(train_scene, "training scene")
    hparams = hparams or TrainHParams.for_config(config)
    key_init, key_train = jax.random.split(key)
    state = init_train_state(key_init, config, hparams)
    data = TrainData.from_scene(train_scene)
    render_config = _render_config(config, train_scene.near, train_scene.far, train_scene.aabb,
                                   _eval_background(train_scene), config.num_samples)
    return TrainInputs(state, key_train, data, hparams.as_arrays(), render_config)


class TrainResult(NamedTuple):
    """What `train` returns.

    Attributes:
      params: trained field parameters (device arrays).
      occupancy: the occupancy grid (sampler state), or None for the dense sampler.
      history: one dict per chunk {"step", "loss", "psnr", "rays", "seconds"} (means over the chunk's
        steps of the batch loss, PSNR and rays trained; training wall-clock so far), plus
        {"step", "seconds", "psnr_test"} for held-out evaluations.
      psnr_test: held-out PSNR (dB) at the end, or None without a test scene.
      seconds: wall-clock of the training loop (compilation included, evaluations excluded).
      compile_seconds: wall-clock of the first chunk beyond the others' mean (≈ compilation).
      rays_per_second: rays trained per second, after compilation (chunks after the first).
      steps: steps taken.
      config: the static configuration.
      hparams: the numeric hyper-parameters.
      device: the device trained on, in words.
      n_train, n_test: images in the training and test scenes (n_test 0 without a test scene).
    """

    params: Any
    occupancy: Any
    history: List[Dict[str, Any]]
    psnr_test: Optional[float]
    seconds: float
    compile_seconds: float
    rays_per_second: float
    steps: int
    config: TrainConfig
    hparams: TrainHParams
    device: str
    n_train: int
    n_test: int


def _device_name() -> str:
    device = jax.devices()[0]
    kind = getattr(device, "device_kind", "") or ""
    return f"{device.platform}:{kind}" if kind else device.platform


def train(key: PRNGKey, train_scene: Scene, config: TrainConfig, test_scene: Optional[Scene] = None,
          progress: bool = True, hparams: Optional[TrainHParams] = None) -> TrainResult:
    """Trains an Instant-NGP field on a scene.

    Args:
      key: PRNG key (consumed): split into the initialisation and training streams.
      train_scene: the training images and cameras.
      config: static configuration (e.g. `TrainConfig.preset("fast", train_scene)`).
      test_scene: held-out views for the final (and `eval_every`) PSNR; None to skip.
      progress: show a tqdm progress bar with the batch loss and PSNR.
      hparams: numeric hyper-parameters (default `TrainHParams.for_config(config)`).

    Returns:
      A `TrainResult`. Same key, scene and config give bit-identical params on the same device.

    Raises:
      TrainConfigError: a scene is unusable for training.
    """
    from tqdm.auto import tqdm

    if test_scene is not None:
        _check_scene(test_scene, "test scene")
    hparams = hparams or TrainHParams.for_config(config)
    state, key_train, data, _, render_config = training_inputs(key, train_scene, config, hparams)

    history: List[Dict[str, Any]] = []
    n_chunks = -(-config.steps // config.chunk)
    chunk_seconds: List[float] = []
    chunk_rays: List[int] = []
    train_seconds = 0.0
    bar = tqdm(total=config.steps, disable=not progress, unit="step", dynamic_ncols=True)
    try:
        for _ in range(n_chunks):
            start = time.perf_counter()
            state, metrics = run_chunk(state, key_train, data, hparams, render_config, config, config.steps)
            metrics = jax.device_get(metrics)  # the host sync of this chunk
            elapsed = time.perf_counter() - start
            chunk_seconds.append(elapsed)
            train_seconds += elapsed
            done = int(state.step)
            taken = int(np.sum(np.isfinite(metrics["loss"])))
            chunk_rays.append(int(np.sum(metrics["rays"])))
            entry = {"step": done, "loss": float(np.nanmean(metrics["loss"])),
                     "psnr": float(np.nanmean(metrics["psnr"])), "rays": chunk_rays[-1] / max(taken, 1),
                     "seconds": train_seconds}
            history.append(entry)
            bar.update(taken)
            bar.set_postfix(loss=f"{entry['loss']:.4g}", psnr=f"{entry['psnr']:.2f}")
            if test_scene is not None and config.eval_every and done < config.steps and (
                    done // config.eval_every) > ((done - taken) // config.eval_every):
                psnr = evaluate(state.params, state.sampler_state, config, test_scene)["psnr"]
                history.append({"step": done, "seconds": train_seconds, "psnr_test": psnr})
                bar.set_postfix(loss=f"{entry['loss']:.4g}", psnr=f"{entry['psnr']:.2f}", test=f"{psnr:.2f}")
    finally:
        bar.close()

    # The first chunk compiles; the rate is that of the others (all of them for a one-chunk run).
    if len(chunk_seconds) > 1:
        steady = float(np.mean(chunk_seconds[1:]))
        compile_seconds = max(0.0, chunk_seconds[0] - steady)
        rays_per_second = sum(chunk_rays[1:]) / max(sum(chunk_seconds[1:]), 1e-9)
    else:
        compile_seconds = 0.0
        rays_per_second = sum(chunk_rays) / max(train_seconds, 1e-9)
    psnr_test = None
    if test_scene is not None:
        psnr_test = evaluate(state.params, state.sampler_state, config, test_scene)["psnr"]
        history.append({"step": int(state.step), "seconds": train_seconds, "psnr_test": psnr_test})
    return TrainResult(
        params=state.params,
        occupancy=state.sampler_state,
        history=history,
        psnr_test=psnr_test,
        seconds=train_seconds,
        compile_seconds=compile_seconds,
        rays_per_second=rays_per_second,
        steps=int(state.step),
        config=config,
        hparams=hparams,
        device=_device_name(),
        n_train=train_scene.n_images,
        n_test=0 if test_scene is None else test_scene.n_images,
    )
