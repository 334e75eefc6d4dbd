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
     step-wise exponential decay as an optax schedule).

Samplers (`make_sampler`) are static code plus a pytree state carried in the `TrainState`:
  * "dense": `render.render_ray` with stratified samples in [near, far] clipped to the aabb (no state);
  * "occupancy": Instant-NGP's occupancy grid (`render.occupancy`) and ray marching. The marched
    samples of the batch are packed into `samples_per_batch` field evaluations as rows of
    `_TRAIN_ROW_LENGTH` samples (`render.packed`): rays enter in their random order while their rows
    fit, the rest are left out of the loss, and the composite runs on the packed rows (no
    [rays x samples] array). The rays marched per step adapt to the budget as in Instant-NGP: after
    each chunk the host picks R from a ladder of powers of two so that about 1.25 budgets of samples
    are marched (`_next_rays`).

Steps run in jitted chunks of `lax.scan`s with no host sync inside: a chunk is a scan over *periods*
of `occupancy_update_every` steps, each an occupancy update (the warm-up kind, every cell, in the
first chunk; the partial kind after it: the host knows the phase, so no `lax.cond`) and then a scan of
the period's steps. Steps past `config.steps` in the last chunk are computed and discarded (a select,
not a branch). The host syncs once per chunk (progress, history, the next R). Randomness: `key` is
split once into the initialisation key (field, sampler state) and the training stream; step `i` uses
`fold_in(train_stream, i)`, so the chunking does not change the random numbers, and the same key
and config give bit-identical parameters on the same backend.

Trained fields are rendered by `waldo_jax.render.marched` (`render_trained`): a dense-trained field
through a grid whose cells are all occupied.

Names: `R` rays per batch, `S` samples per ray, `N` training images of `H x W` pixels, `P` poses.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import time
from typing import Any, Callable, Dict, List, NamedTuple, Optional, Sequence, Tuple

import flax.struct
import jax
import jax.numpy as jnp
import numpy as np
import optax

from waldo_jax.cameras import pixel_directions
from waldo_jax.errors import WaldoError
from waldo_jax.nerf.field import NGPFieldConfig, init_field, make_density, make_field
from waldo_jax.nerf.hashgrid import HashGridConfig
from waldo_jax.render import marched, occupancy, packed
from waldo_jax.render.volume import RenderConfig, render_ray
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
    "make_occupancy_update",
    "make_sampler",
    "make_train_step",
    "render_setup",
    "render_trained",
    "render_trained_counted",
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

# Rendering marches with the training step times `TrainConfig.render_step_scale`. Its value comes from
# each run's own quality/speed curve (`calibrate_render_step`): the largest of these scales whose
# held-out PSNR is within RENDER_STEP_TOLERANCE_DB of the training step's. Measured on the CPU-trained
# fox (benchmarks/results/render_trained_fox_*): x2 -0.01 dB, x3 -0.03 dB (70 instead of 203
# evaluations per ray), x4 -0.09 dB; on lego_tiny x2 already loses 1.4 dB, so no fixed scale serves both.
RENDER_STEP_CANDIDATES = (2.0, 3.0, 4.0)
RENDER_STEP_TOLERANCE_DB = 0.05
# Held-out views rendered per candidate scale (spread over the split).
_CALIBRATION_VIEWS = 3
# Samples per packed row in training (`render.packed`). A ray's last row wastes under this many slots,
# and the rays of a step are those whose rows fit the budget: rows of 4 trained 7 % fewer rays a step
# on lego_tiny (about 10 samples a ray) and lost ~0.1 dB at 1000 steps; single-sample rows waste
# nothing, and their segmented sums (log2 S shifted adds over the slots) cost little next to the field.
_TRAIN_ROW_LENGTH = 1
# Config keys of older checkpoints that no longer mean anything (ignored by `TrainConfig.from_dict`).
_OBSOLETE_KEYS = ("eval_ray_chunk",)


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
      rays_per_batch: R, rays drawn per step (dense). With the occupancy sampler the most rays a step
        marches: the rays marched adapt to the budget chunk by chunk (a power-of-two fraction of
        this), and they enter the batch in random order until their packed samples fill
        `samples_per_batch` (Instant-NGP's dynamic batch, with fixed shapes).
      num_samples: samples per training ray: the stratified count (dense) or the most samples one
        ray may keep in occupied space (occupancy; capped at the K candidates that cross the grid,
        so a large value means no cap, as in Instant-NGP).
      samples_per_batch: occupancy sampler: field evaluations per step (packed rows across rays).
      eval_samples: rendering (held-out PSNR, `waldo render`, `waldo explore`): the most samples a
        ray keeps in occupied space (occupancy), or the samples across the field's box (dense).
      chunk: steps between host syncs (progress bar, history, the rays marched per step); rounded
        to whole periods of `occupancy_update_every` steps.
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
      render_step_scale: rendering marches with the training step (steps_per_diagonal, cone_angle)
        times this; None: `train` measures the run's quality/speed curve on its held-out views and
        sets it (`calibrate_render_step`); renders use 1 while it is None.
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
    render_step_scale: Optional[float] = None
    preset_name: str = "custom"

    def __post_init__(self):
        for name in ("steps", "rays_per_batch", "num_samples", "samples_per_batch", "eval_samples", "chunk",
                     "occupancy_resolution", "occupancy_update_every"):
            object.__setattr__(self, name, _positive_int(name, getattr(self, name)))
        for name in ("eval_every", "occupancy_warmup"):
            object.__setattr__(self, name, _positive_int(name, getattr(self, name), minimum=0))
        object.__setattr__(self, "aabb_scale", _positive_float("aabb_scale", self.aabb_scale))
        object.__setattr__(self, "steps_per_diagonal", _positive_float("steps_per_diagonal", self.steps_per_diagonal))
        object.__setattr__(self, "cone_angle", _positive_float("cone_angle", self.cone_angle, allow_zero=True))
        if self.render_step_scale is not None:
            object.__setattr__(self, "render_step_scale",
                               _positive_float("render_step_scale", self.render_step_scale))
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
            values = {k: v for k, v in dict(d).items() if k not in _OBSOLETE_KEYS}
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
#   update(key, state, params, warmup) -> state                    (every occupancy_update_every steps;
#                                                                   warmup: static, every cell)
#   render_rays(key, params, state, origins [R, 3], directions [R, 3], background [R, 3], render_config)
#       -> (RenderOutput [R], included bool [R], stats)            (rays that count in the loss; stats:
#                                                                   int32 [] "samples" and "rows")
#   view_grid(state) -> the occupancy grid views are rendered through (`render.marched`)
#   view_march(scale) -> the MarchConfig of views, `scale` times the training step


class _DenseSampler:
    """Stratified samples in [near, far] ∩ aabb (`render.render_ray` with a key); no state.

    Views are rendered by the marched renderer through a one-cell grid that is always occupied, with
    `eval_samples` steps across the field's box.
    """

    def __init__(self, config: TrainConfig):
        self.config = config
        self.field = make_field(config.field)
        self.box = np.asarray(config.field.aabb, np.float64).reshape(2, 3)

    def init(self, key: PRNGKey, params) -> None:
        """No state."""
        return None

    def update(self, key: PRNGKey, state, params, warmup: bool):
        """No state to update."""
        return state

    def render_rays(self, key: PRNGKey, params, state, origins: Array, directions: Array,
                    background: Array, render_config: RenderConfig) -> Tuple[RenderOutput, Array, Dict[str, Array]]:
        """Renders R training rays [R, 3] on per-ray backgrounds [R, 3]; every ray is included."""
        keys = jax.random.split(key, origins.shape[0])

        def one(k, o, d, bg):
            return render_ray(self.field, params, o, d, render_config.replace(background=bg), k)

        out = jax.vmap(one)(keys, origins, directions, background)
        samples = jnp.int32(origins.shape[0] * render_config.num_samples)
        return out, jnp.ones(origins.shape[:1], bool), {"samples": samples, "rows": samples}

    def view_grid(self, state) -> occupancy.OccupancyGrid:
        """A single always-occupied cell over the field's box."""
        return occupancy.init_occupancy(self.box, 1.0, resolution=1)

    def view_march(self, scale: float) -> occupancy.MarchConfig:
        """eval_samples / scale steps across the box's diagonal."""
        grid = self.view_grid(None)
        return occupancy.MarchConfig.for_grid(grid, self.config.eval_samples / scale)


class _OccupancySampler:
    """Instant-NGP's occupancy grid and ray marching (`waldo_jax.render.occupancy`), with packed rows.

    Each ray is marched (`occupancy.march_ray`: candidates every dt, kept where the grid is occupied,
    compacted to at most S = `num_samples`). The kept samples are packed one ray after another into
    a budget of `samples_per_batch` slots (`render.packed`, rows of `_TRAIN_ROW_LENGTH` samples):
    rays enter in their (random) order while their samples fit, the others are left out of this
    step's loss (`included`), and the field runs on the packed slots only. As with Instant-NGP's dynamic batch
    size, the rays trained per step adapt to the scene (few while the grid is still full, many once
    it is sparse) at a fixed cost per step. The composite runs on the packed rows (`packed.composite_rows`).
    """

    def __init__(self, config: TrainConfig):
        self.config = config
        self.field = make_field(config.field)
        self.density = make_density(config.field)
        aabb = np.asarray(config.field.aabb, np.float64).reshape(2, 3)
        center, half = 0.5 * (aabb[0] + aabb[1]), 0.5 * (aabb[1] - aabb[0]) / config.aabb_scale
        self.base_aabb = np.stack([center - half, center + half])
        self.geometry = occupancy.init_occupancy(self.base_aabb, config.aabb_scale, resolution=1)
        self.march = occupancy.MarchConfig.for_grid(
            self.geometry.replace(resolution=config.occupancy_resolution), config.steps_per_diagonal,
            config.cone_angle, max_samples=config.num_samples)
        self.row_length = _TRAIN_ROW_LENGTH
        self.rows = config.samples_per_batch // self.row_length
        self.max_rows_per_ray = -(-self.march.max_samples // self.row_length)
        if self.rows < self.max_rows_per_ray:
            raise TrainConfigError(
                f"TrainConfig.samples_per_batch ({config.samples_per_batch}) must hold the samples one ray may "
                f"keep, min(num_samples, K) = {self.march.max_samples} (in rows of {self.row_length})")

    def init(self, key: PRNGKey, params):
        """All cells occupied, zero densities (nothing is skipped before the first update)."""
        return occupancy.init_occupancy(self.base_aabb, self.config.aabb_scale,
                                        resolution=self.config.occupancy_resolution)

    def _occupancy_config(self, grid):
        return occupancy.OccupancyConfig.create(
            grid, steps_per_diagonal=self.config.steps_per_diagonal, warmup_steps=self.config.occupancy_warmup,
            decay=self.config.occupancy_decay)

    def update(self, key: PRNGKey, grid, params, warmup: bool):
        """Instant-NGP's decay / sample / threshold update of the grid (`warmup`: every cell)."""
        return occupancy.update_occupancy_phase(key, grid, self.density, jax.lax.stop_gradient(params),
                                                self._occupancy_config(grid), warmup)

    def _march(self, grid, origins: Array, directions: Array, render_config: RenderConfig,
               key: Optional[PRNGKey]) -> Tuple[Array, Array, Array]:
        """t, delta [R, S] and mask bool [R, S] of R rays (random offsets with a key)."""

        def one(o, d, k):
            t_start, t_end = occupancy.ray_interval(grid, o, d, render_config)
            return occupancy.march_ray(grid, o, d, t_start, t_end, self.march, k)

        keys = None if key is None else jax.random.split(key, origins.shape[0])
        return jax.vmap(one, in_axes=(0, 0, None if keys is None else 0))(origins, directions, keys)

    def render_rays(self, key: PRNGKey, params, grid, origins: Array, directions: Array, background: Array,
                    render_config: RenderConfig) -> Tuple[RenderOutput, Array, Dict[str, Array]]:
        """Renders training rays [R, 3]; the leading rays whose rows fit the budget are `included`.

        Stats: "samples", the samples of the included rays (field evaluations that count), and "rows",
        the rows all R marched rays would need (to size the next chunk's R).
        """
        num_rays = origins.shape[0]
        s = self.row_length
        t, delta, mask = self._march(grid, origins, directions, render_config, key)  # [R, S] each
        count = jnp.sum(mask, axis=1, dtype=jnp.int32)  # [R]
        rows = -(-count // s)  # [R]
        included = jnp.cumsum(rows) <= self.rows  # [R], the leading rays that fit
        layout = packed.layout_rows(jnp.where(included, rows, 0), self.rows)
        index, valid = packed.row_samples(layout, jnp.zeros((num_rays,), jnp.int32), count, s)  # [M, s]
        owner = layout.owner[:, None]  # [M, 1]
        index = jnp.minimum(index, self.march.max_samples - 1)
        t_rows = t[owner, index]  # [M, s]
        delta_rows = jnp.where(valid, delta[owner, index], 0.0)  # [M, s]
        ray_dirs = jnp.broadcast_to(directions[layout.owner][:, None, :], (self.rows, s, 3))  # [M, s, 3]
        points = origins[layout.owner][:, None, :] + t_rows[..., None] * ray_dirs  # [M, s, 3]
        sigma, rgb = jax.vmap(self.field, in_axes=(None, 0, 0))(params, points.reshape(-1, 3), ray_dirs.reshape(-1, 3))
        sums = packed.composite_rows(sigma.reshape(self.rows, s), rgb.reshape(self.rows, s, 3), t_rows, delta_rows,
                                     layout, jnp.zeros((num_rays,), jnp.float32), self.max_rows_per_ray)
        out = RenderOutput(rgb=sums.rgb + (1.0 - sums.acc)[:, None] * background, depth=sums.depth, acc=sums.acc)
        stats = {"samples": jnp.sum(jnp.where(included, count, 0)), "rows": jnp.sum(rows)}
        return out, included, stats

    def view_grid(self, grid) -> occupancy.OccupancyGrid:
        """The trained grid itself."""
        return grid

    def view_march(self, scale: float) -> occupancy.MarchConfig:
        """The training march with steps `scale` times longer (NGP's dt_min and cone angle both scaled)."""
        return occupancy.MarchConfig.for_grid(
            self.geometry.replace(resolution=self.config.occupancy_resolution), self.config.steps_per_diagonal / scale,
            self.config.cone_angle * scale, max_samples=self.config.eval_samples)


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


def make_optimizer(hparams: TrainHParams) -> optax.GradientTransformation:
    """Adam with L2 regularisation on the MLPs and Instant-NGP's decay as an optax schedule
    (`hparams.learning_rate_at`, driven by the optimiser's own step count)."""
    return optax.chain(
        optax.add_decayed_weights(hparams.weight_decay, mask=_mlp_mask),
        optax.scale_by_adam(b1=hparams.beta1, b2=hparams.beta2, eps=hparams.eps),
        optax.scale_by_learning_rate(hparams.learning_rate_at),
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
    opt_state = make_optimizer(hparams).init(params)
    sampler_state = make_sampler(config).init(key_sampler, params)
    return TrainState(params=params, opt_state=opt_state, sampler_state=sampler_state, step=jnp.int32(0))


def _sample_batch(key: PRNGKey, data: TrainData, config: TrainConfig,
                  num_rays: Optional[int] = None) -> Tuple[Array, Array, Array, Array]:
    """R = `num_rays` (default `config.rays_per_batch`) rays uniform over all training pixels, with their
    targets and backgrounds.

    Returns:
      origins [R, 3], unit directions [R, 3], target rgb [R, 3], background [R, 3].
    """
    num_rays = config.rays_per_batch if num_rays is None else num_rays
    key_pixel, key_bg = jax.random.split(key)
    n, h, w = data.images.shape[:3]
    flat = jax.random.randint(key_pixel, (num_rays,), 0, n * h * w)  # [R]
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
        background = jax.random.uniform(key_bg, (num_rays, 3))  # [R, 3]
    else:
        background = jnp.broadcast_to(data.background, (num_rays, 3))
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


def make_train_step(config: TrainConfig, rays_per_batch: Optional[int] = None) -> Callable:
    """The training step for one batch, without the occupancy update (pure; jit it or scan it).

    `train` runs `make_occupancy_update(config, warmup)` before every `occupancy_update_every`-th step
    (warmup: steps below `occupancy_warmup`, rounded up to whole periods); a Python loop doing the
    same from `training_inputs` reproduces `train` (see `tests/test_train.py`).

    Args:
      config: the static training configuration.
      rays_per_batch: R, rays marched per step (default `config.rays_per_batch`).

    Returns:
      step(state, train_key, data, hparams, render_config) -> (state, metrics): step `state.step`
      uses `fold_in(train_key, state.step)`. `metrics` holds float32 [] `loss` and `psnr` (of the
      batch MSE, on the composited targets), int32 [] `rays` (the rays in the loss), `samples` (the
      field evaluations of those rays) and `rows` (packed rows all R rays would need).
    """
    sampler = make_sampler(config)
    num_rays = config.rays_per_batch if rays_per_batch is None else int(rays_per_batch)

    def step(state: TrainState, train_key: PRNGKey, data: TrainData, hparams: TrainHParams,
             render_config: RenderConfig):
        key = jax.random.fold_in(train_key, state.step)
        key_batch, key_render, _ = jax.random.split(key, 3)  # the third key is the occupancy update's
        origins, directions, target, background = _sample_batch(key_batch, data, config, num_rays)

        def loss_fn(params):
            out, included, stats = sampler.render_rays(key_render, params, state.sampler_state, origins,
                                                       directions, background, render_config)
            loss, mse = _loss(out.rgb - target, included, config, hparams)
            return loss, (mse, jnp.sum(included, dtype=jnp.int32), stats)

        (loss, (mse, rays, stats)), grads = jax.value_and_grad(loss_fn, has_aux=True)(state.params)
        updates, opt_state = make_optimizer(hparams).update(grads, state.opt_state, state.params)
        params = optax.apply_updates(state.params, updates)
        new_state = state.replace(params=params, opt_state=opt_state, step=state.step + 1)
        return new_state, {"loss": loss, "psnr": _psnr(mse), "rays": rays, "samples": stats["samples"],
                           "rows": stats["rows"]}

    return step


def make_occupancy_update(config: TrainConfig, warmup: bool) -> Callable:
    """The occupancy update that precedes every `occupancy_update_every`-th step (pure).

    Returns:
      update(state, train_key) -> state: the grid updated from `state.params` with the third key of
      `split(fold_in(train_key, state.step), 3)` (`warmup`, static: every cell is sampled).
    """
    sampler = make_sampler(config)

    def update(state: TrainState, train_key: PRNGKey) -> TrainState:
        key_update = jax.random.split(jax.random.fold_in(train_key, state.step), 3)[2]
        return state.replace(sampler_state=sampler.update(key_update, state.sampler_state, state.params, warmup))

    return update


def _periods(config: TrainConfig, warmup: bool) -> int:
    """Periods of `occupancy_update_every` steps in a chunk: the warm-up chunk spans the warm-up."""
    every = config.occupancy_update_every
    if warmup:
        return max(1, -(-config.occupancy_warmup // every))
    return max(1, round(config.chunk / every))


def _warmup_steps(config: TrainConfig) -> int:
    """Steps of the warm-up chunk (0 when there is no warm-up): `occupancy_warmup` rounded up to whole periods."""
    return _periods(config, True) * config.occupancy_update_every if config.occupancy_warmup > 0 else 0


def _select(active: Array, new, old):
    """`new` where `active`, else `old`, leaf by leaf (a select, not a branch: no host sync)."""
    return jax.tree.map(lambda a, b: jnp.where(active, a, b), new, old)


@functools.lru_cache(maxsize=None)
def _chunk_fn(config: TrainConfig, rays_per_batch: int, warmup: bool) -> Callable:
    """A chunk of periods (update, then `occupancy_update_every` steps) in one jitted `lax.scan`
    (cached per config, R and phase; the state is donated)."""
    step = make_train_step(config, rays_per_batch)
    update = make_occupancy_update(config, warmup)

    def chunk(state, train_key, data, hparams, render_config, total_steps):
        skipped = {"loss": jnp.float32(jnp.nan), "psnr": jnp.float32(jnp.nan), "rays": jnp.int32(0),
                   "samples": jnp.int32(0), "rows": jnp.int32(0)}

        def one_step(state, _):
            new_state, metrics = step(state, train_key, data, hparams, render_config)
            active = state.step < total_steps
            return _select(active, new_state, state), _select(active, metrics, skipped)

        def period(state, _):
            state = _select(state.step < total_steps, update(state, train_key), state)
            return jax.lax.scan(one_step, state, None, length=config.occupancy_update_every)

        state, metrics = jax.lax.scan(period, state, None, length=_periods(config, warmup))
        return state, jax.tree.map(lambda m: m.reshape(-1), metrics)

    return jax.jit(chunk, donate_argnums=(0,))


def run_chunk(state: TrainState, train_key: PRNGKey, data: TrainData, hparams: TrainHParams,
              render_config: RenderConfig, config: TrainConfig, total_steps: int,
              rays_per_batch: Optional[int] = None, warmup: bool = False) -> Tuple[TrainState, Dict]:
    """Runs one chunk of whole periods (those steps with step >= total_steps are discarded) in one jitted scan.

    The input state must start a period (`state.step` a multiple of `occupancy_update_every`); its
    buffers are donated: do not use `state` afterwards.

    Returns:
      (state, metrics) with metrics {"loss", "psnr"} float32 [steps] (NaN for discarded steps) and
      {"rays", "samples", "rows"} int32 [steps] (0 for discarded steps).
    """
    rays = config.rays_per_batch if rays_per_batch is None else int(rays_per_batch)
    return _chunk_fn(config, rays, bool(warmup))(state, train_key, data, hparams.as_arrays(), render_config,
                                                  jnp.int32(total_steps))


def rays_ladder(config: TrainConfig) -> Tuple[int, ...]:
    """The rays a step may march: `rays_per_batch` halved down to 128 (Instant-NGP's granularity)."""
    if config.sampler != "occupancy":
        return (config.rays_per_batch,)
    rungs = [config.rays_per_batch]
    while rungs[-1] // 2 >= min(128, config.rays_per_batch) and rungs[-1] % 2 == 0:
        rungs.append(rungs[-1] // 2)
    return tuple(sorted(rungs))


def _fit_rays(config: TrainConfig, rows_per_ray: float) -> int:
    """The smallest rung whose rays need 1.25 budgets of rows at `rows_per_ray` (the top rung at most)."""
    ladder = rays_ladder(config)
    budget_rows = config.samples_per_batch // _TRAIN_ROW_LENGTH
    wanted = 1.25 * budget_rows / max(rows_per_ray, 1e-6)
    return next((r for r in ladder if r >= wanted), ladder[-1])


def _first_rays(config: TrainConfig) -> int:
    """R of the first chunk: the grid is all occupied, so a ray crossing the box keeps about S samples."""
    if config.sampler != "occupancy":
        return config.rays_per_batch
    samples = make_sampler(config).march.max_samples
    return _fit_rays(config, -(-samples // _TRAIN_ROW_LENGTH) / 2.0)


def _next_rays(config: TrainConfig, metrics: Dict[str, np.ndarray], rays: int) -> int:
    """R of the next chunk from the rows per marched ray of the last chunk's last period (Instant-NGP's
    dynamic batch size; the last period best predicts the next steps, e.g. after the warm-up)."""
    if config.sampler != "occupancy":
        return rays
    taken = np.flatnonzero(np.isfinite(metrics["loss"]))[-config.occupancy_update_every:]
    if taken.size == 0:
        return rays
    rows_per_ray = float(np.sum(np.asarray(metrics["rows"], np.float64)[taken])) / (rays * taken.size)
    return _fit_rays(config, rows_per_ray)


# ----------------------------------------------------------------------------------------------
# Rendering and evaluation of a trained field.


def render_setup(config: TrainConfig, sampler_state, near: float, far: float, aabb, background,
                 step_scale: Optional[float] = None) -> Tuple[occupancy.OccupancyGrid, RenderConfig, occupancy.MarchConfig]:
    """What `render.marched` needs to render a trained field: (grid, render config, march config).

    Args:
      config: the training config (sampler, steps, eval_samples, render_step_scale).
      sampler_state: the occupancy grid, or None (dense sampler).
      near, far: ray bounds (world units). aabb: [2, 3] box to sample in. background: colour [3].
      step_scale: the marching step over the training step (default `config.render_step_scale`, or 1).
    """
    sampler = make_sampler(config)
    scale = step_scale if step_scale is not None else (config.render_step_scale or 1.0)
    scale = float(scale)
    if not (math.isfinite(scale) and scale > 0):
        raise TrainConfigError(f"the render step scale must be a positive number, got {step_scale!r}")
    render_config = RenderConfig.create(near=near, far=far, aabb=np.asarray(aabb, np.float32).reshape(2, 3),
                                        background=background, ray_chunk=1)
    return sampler.view_grid(sampler_state), render_config, sampler.view_march(scale)


def _render_counted(params, sampler_state, config: TrainConfig, c2w, intrinsics: Intrinsics, near: float, far: float,
                    background, aabb, mesh, step_scale: Optional[float], packing: Optional[marched.Packing]):
    """(RenderOutput [P, H, W], evaluations int32 [P, H, W]) on one device, or sharded over several."""
    aabb = np.asarray(config.field.aabb if aabb is None else aabb, np.float32).reshape(2, 3)
    grid, render_config, march = render_setup(config, sampler_state, near, far, aabb, background, step_scale)
    field = make_field(config.field)
    c2w = jnp.asarray(np.asarray(c2w, np.float32))
    if mesh is None and jax.local_device_count() == 1:
        views = marched.render_marched(field, params, grid, c2w, intrinsics, render_config, march, packing)
        return views.output, views.evaluations
    return marched.render_marched_sharded(field, params, grid, c2w, intrinsics, render_config, march, packing, mesh)


def render_trained_counted(params, sampler_state, config: TrainConfig, c2w, intrinsics: Intrinsics, near: float,
                           far: float, background=(1.0, 1.0, 1.0), aabb=None, step_scale: Optional[float] = None,
                           packing: Optional[marched.Packing] = None) -> marched.MarchedViews:
    """`render_trained` on one device, with what it cost (`render.marched.MarchedViews`: evaluations per
    pixel, passes per block)."""
    aabb = np.asarray(config.field.aabb if aabb is None else aabb, np.float32).reshape(2, 3)
    grid, render_config, march = render_setup(config, sampler_state, near, far, aabb, background, step_scale)
    return marched.render_marched(make_field(config.field), params, grid, jnp.asarray(np.asarray(c2w, np.float32)),
                                  intrinsics, render_config, march, packing)


def render_trained(params, sampler_state, config: TrainConfig, c2w, intrinsics: Intrinsics, near: float,
                   far: float, background=(1.0, 1.0, 1.0), aabb=None, mesh=None, step_scale: Optional[float] = None,
                   packing: Optional[marched.Packing] = None) -> RenderOutput:
    """Renders P views of a trained field in one call with the marched renderer (`render.marched`).

    With more than one local device (or a `mesh`), the poses are split over the devices
    (`render.marched.render_marched_sharded`).

    Args:
      params: the field's parameters.
      sampler_state: the occupancy grid, or None (dense sampler).
      config: the training config (field, sampler, eval_samples, render_step_scale).
      c2w: [P, 4, 4] or [P, 3, 4] camera-to-world matrices.
      intrinsics: shared intrinsics (their width and height set the image size).
      near, far: ray bounds (world units).
      background: colour [3] behind the volume.
      aabb: [2, 3] sampling box (default: the field's box).
      mesh: a one-axis mesh named "poses" to shard over (default: all local devices if more than one).
      step_scale: the marching step over the training step (default `config.render_step_scale`).
      packing: the renderer's static sizes (default `render.marched.Packing.for_backend()`).

    Returns:
      RenderOutput with rgb [P, H, W, 3], depth [P, H, W], acc [P, H, W] (device arrays).
    """
    return _render_counted(params, sampler_state, config, c2w, intrinsics, near, far, background, aabb, mesh,
                           step_scale, packing)[0]


def _eval_background(scene: Scene) -> np.ndarray:
    return np.zeros(3, np.float32) if scene.background is None else np.asarray(scene.background, np.float32)


def evaluate(params, sampler_state, config: TrainConfig, scene: Scene, step_scale: Optional[float] = None,
             views: Optional[Sequence[int]] = None) -> Dict[str, Any]:
    """Held-out PSNR: renders the views of `scene` (all, or the indices `views`) and compares with its images.

    RGBA scenes are compared on the background their images were composited on (`scene.background`);
    opaque ones are rendered on black.

    Returns:
      {"psnr": mean of per-image PSNR (dB), "psnr_per_image": list, "mse": mean MSE,
       "evaluations_per_ray": mean field evaluations per ray, "step_scale": the marching step used,
       "images": float32 [P, H, W, 3] renders (host)}.
    """
    _check_scene(scene, "test scene")
    index = np.arange(scene.n_images) if views is None else np.asarray(views, np.int64)
    c2w = np.asarray(scene.c2w, np.float32)[index]
    out, evaluations = _render_counted(params, sampler_state, config, c2w, scene.intrinsics, scene.near, scene.far,
                                       _eval_background(scene), scene.aabb, None, step_scale, None)
    rendered = np.asarray(jax.device_get(out.rgb), np.float32)
    images = np.asarray(scene.images, np.float64)[index]
    mse = np.mean((rendered.astype(np.float64) - images) ** 2, axis=(1, 2, 3))
    psnr = -10.0 * np.log10(np.maximum(mse, 1e-12))
    scale = step_scale if step_scale is not None else (config.render_step_scale or 1.0)
    return {"psnr": float(np.mean(psnr)), "psnr_per_image": psnr.tolist(), "mse": float(np.mean(mse)),
            "evaluations_per_ray": float(np.mean(np.asarray(evaluations, np.float64))), "step_scale": float(scale),
            "images": rendered}


def calibrate_render_step(params, sampler_state, config: TrainConfig, scene: Scene,
                          reference: Optional[Dict[str, Any]] = None,
                          candidates: Sequence[float] = RENDER_STEP_CANDIDATES,
                          tolerance_db: float = RENDER_STEP_TOLERANCE_DB) -> Tuple[float, List[Dict[str, Any]]]:
    """The marching step to render a trained run with, from its own quality/speed curve.

    Renders up to `_CALIBRATION_VIEWS` held-out views (spread over the split) with the march `scale`
    times coarser than training, for each scale of `candidates` in increasing order, and keeps the
    largest whose PSNR on those views is within `tolerance_db` of the training step's (scale 1);
    stops at the first that is not.

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
    if reference is None:
        reference = evaluate(params, sampler_state, config, scene, step_scale=1.0, views=views)
        base = reference["psnr"]
    else:
        base = float(np.mean(np.asarray(reference["psnr_per_image"])[views]))
    curve = [{"step_scale": 1.0, "psnr_views": base, "delta_db": 0.0,
              "evaluations_per_ray": reference["evaluations_per_ray"]}]
    chosen = 1.0
    for scale in candidates:
        result = evaluate(params, sampler_state, config, scene, step_scale=scale, views=views)
        delta = result["psnr"] - base
        curve.append({"step_scale": float(scale), "psnr_views": result["psnr"], "delta_db": delta,
                      "evaluations_per_ray": result["evaluations_per_ray"]})
        if delta < -tolerance_db:
            break
        chosen = float(scale)
    return chosen, curve


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
    so a Python loop over `make_train_step` (with `make_occupancy_update` before every
    `occupancy_update_every`-th step, and the R of `TrainResult.history`) reproduces `train`.
    """
    _check_scene(train_scene, "training scene")
    hparams = hparams or TrainHParams.for_config(config)
    key_init, key_train = jax.random.split(key)
    state = init_train_state(key_init, config, hparams)
    data = TrainData.from_scene(train_scene)
    render_config = RenderConfig.create(near=train_scene.near, far=train_scene.far,
                                        aabb=np.asarray(train_scene.aabb, np.float32).reshape(2, 3),
                                        background=_eval_background(train_scene), num_samples=config.num_samples,
                                        ray_chunk=1)
    return TrainInputs(state, key_train, data, hparams.as_arrays(), render_config)


class TrainResult(NamedTuple):
    """What `train` returns.

    Attributes:
      params: trained field parameters (device arrays).
      occupancy: the occupancy grid (sampler state), or None for the dense sampler.
      history: one dict per chunk {"step", "loss", "psnr", "rays", "samples", "rays_marched", "warmup",
        "seconds"} (means over the chunk's steps of the batch loss, PSNR, rays trained and field
        evaluations that counted; R, the rays marched per step; whether the chunk was the warm-up;
        training wall-clock so far), plus {"step", "seconds", "psnr_test"} for held-out evaluations.
      psnr_test: held-out PSNR (dB) at the end, as the run renders (its `config.render_step_scale`),
        or None without a test scene.
      seconds: wall-clock of the training loop (compilation included, evaluations excluded).
      compile_seconds: wall-clock of the chunks that compiled a program (one per rung of rays marched
        and per phase; their training time included).
      rays_per_second: rays trained per second in the chunks that did not compile.
      steps: steps taken.
      config: the static configuration, with the calibrated `render_step_scale` (see `train`).
      hparams: the numeric hyper-parameters.
      device: the device trained on, in words.
      n_train, n_test: images in the training and test scenes (n_test 0 without a test scene).
      psnr_test_training_step: `psnr_test` when the run renders with the training step (scale 1), else
        None (the curve has the training step's PSNR on the calibration views).
      render_step_curve: `calibrate_render_step`'s curve ([] when the scale was not calibrated).
      stopped: True when `on_chunk` stopped the run before `config.steps`.
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
    psnr_test_training_step: Optional[float] = None
    render_step_curve: List[Dict[str, Any]] = []
    stopped: bool = False


def _device_name() -> str:
    device = jax.devices()[0]
    kind = getattr(device, "device_kind", "") or ""
    return f"{device.platform}:{kind}" if kind else device.platform


def train(key: PRNGKey, train_scene: Scene, config: TrainConfig, test_scene: Optional[Scene] = None,
          progress: bool = True, hparams: Optional[TrainHParams] = None,
          on_chunk: Optional[Callable[[TrainState, Dict[str, Any]], bool]] = None) -> TrainResult:
    """Trains an Instant-NGP field on a scene.

    After training, with a `test_scene` and `config.render_step_scale` None, the run's rendering step
    is calibrated on the held-out views (`calibrate_render_step`) and stored in the returned config;
    `psnr_test` is measured with it.

    Args:
      key: PRNG key (consumed): split into the initialisation and training streams.
      train_scene: the training images and cameras.
      config: static configuration (e.g. `TrainConfig.preset("fast", train_scene)`).
      test_scene: held-out views for the final (and `eval_every`) PSNR; None to skip.
      progress: show a tqdm progress bar with the batch loss and PSNR.
      hparams: numeric hyper-parameters (default `TrainHParams.for_config(config)`).
      on_chunk: called after every chunk with the state and the chunk's history entry; its time is
        not training time (evaluate there); returning True stops training after that chunk.

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
    hparams_arrays = hparams.as_arrays()
    total = jnp.int32(config.steps)
    rays = _first_rays(config)
    done, compile_seconds, steady_seconds, steady_rays, all_rays = 0, 0.0, 0.0, 0, 0
    stopped = False
    train_seconds = 0.0
    bar = tqdm(total=config.steps, disable=not progress, unit="step", dynamic_ncols=True)
    try:
        while done < config.steps:
            warmup = done == 0 and _warmup_steps(config) > 0
            chunk_fn = _chunk_fn(config, rays, warmup)
            programs = chunk_fn._cache_size()
            start = time.perf_counter()
            state, metrics = chunk_fn(state, key_train, data, hparams_arrays, render_config, total)
            metrics = jax.device_get(metrics)  # the host sync of this chunk
            elapsed = time.perf_counter() - start
            train_seconds += elapsed
            taken = int(np.sum(np.isfinite(metrics["loss"])))
            done += taken
            rays_trained = int(np.sum(metrics["rays"]))
            all_rays += rays_trained
            if chunk_fn._cache_size() > programs:  # this call compiled: its time is mostly compilation
                compile_seconds += elapsed
            else:
                steady_seconds += elapsed
                steady_rays += rays_trained
            entry = {"step": done, "loss": float(np.nanmean(metrics["loss"])),
                     "psnr": float(np.nanmean(metrics["psnr"])), "rays": rays_trained / max(taken, 1),
                     "samples": float(np.sum(metrics["samples"])) / max(taken, 1), "rays_marched": rays,
                     "warmup": warmup, "seconds": train_seconds}
            history.append(entry)
            bar.update(taken)
            bar.set_postfix(loss=f"{entry['loss']:.4g}", psnr=f"{entry['psnr']:.2f}", rays=rays)
            rays = _next_rays(config, metrics, rays)
            if test_scene is not None and config.eval_every and done < config.steps and (
                    done // config.eval_every) > ((done - taken) // config.eval_every):
                psnr = evaluate(state.params, state.sampler_state, config, test_scene)["psnr"]
                history.append({"step": done, "seconds": train_seconds, "psnr_test": psnr})
                bar.set_postfix(loss=f"{entry['loss']:.4g}", psnr=f"{entry['psnr']:.2f}", test=f"{psnr:.2f}")
            if on_chunk is not None and on_chunk(state, entry) and done < config.steps:
                stopped = True
                break
    finally:
        bar.close()

    # Chunks that compiled count as compilation (their steps' own time included: an overestimate by
    # at most a chunk per compiled program); the rate is that of the others.
    if steady_seconds > 0:
        rays_per_second = steady_rays / steady_seconds
    else:  # every chunk compiled
        rays_per_second = all_rays / max(train_seconds, 1e-9)
    psnr_test = psnr_training_step = None
    curve: List[Dict[str, Any]] = []
    if test_scene is not None:
        scale = config.render_step_scale
        if scale is None:
            scale, curve = calibrate_render_step(state.params, state.sampler_state, config, test_scene)
            config = config.replace(render_step_scale=scale)
        final = evaluate(state.params, state.sampler_state, config, test_scene)
        psnr_test = final["psnr"]
        psnr_training_step = psnr_test if scale == 1.0 else None
        history.append({"step": int(state.step), "seconds": train_seconds, "psnr_test": psnr_test,
                        "render_step_scale": scale, "evaluations_per_ray": final["evaluations_per_ray"]})
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
        psnr_test_training_step=psnr_training_step,
        render_step_curve=curve,
        stopped=stopped,
    )
