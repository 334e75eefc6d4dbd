"""One training step of the hash-grid NeRF and the jitted chunks of steps that `train` runs.

A step draws `R` rays uniformly over all pixels of all training images (built on the fly from the
cameras), renders them with the config's sampler on random backgrounds, and takes an Adam step on the
rgb loss. A chunk is one jitted `lax.scan` over periods (an occupancy update, then
`occupancy_update_every` steps) with no host sync inside; between chunks the host picks the next R from
`rays_ladder` (Instant-NGP's dynamic batch). Names: `R` rays, `N` images of `H x W` pixels.
See docs/design.md, "Training".
"""

from __future__ import annotations

import functools
from typing import Any, Callable, Dict, NamedTuple, Optional, Tuple

import flax.struct
import jax
import jax.numpy as jnp
import numpy as np
import optax

from waldo_jax.cameras import pixel_directions
from waldo_jax.metrics import psnr_from_mse
from waldo_jax.nerf.config import TrainConfig, TrainHParams
from waldo_jax.nerf.field import init_field
from waldo_jax.nerf.samplers import TRAIN_ROW_LENGTH, make_sampler
from waldo_jax.render.volume import RenderConfig
from waldo_jax.types import Array, Intrinsics, PRNGKey, Scene

__all__ = [
    "TrainData",
    "TrainInputs",
    "TrainState",
    "chunk_end",
    "chunk_fn",
    "first_rays",
    "init_train_state",
    "make_occupancy_update",
    "make_optimizer",
    "make_train_step",
    "next_rays",
    "rays_ladder",
    "run_chunk",
    "warmup_steps",
]


@flax.struct.dataclass
class TrainState:
    """What evolves during training.

    Attributes:
      params: the field's parameters.
      opt_state: the optimiser's state (Adam moments and step count).
      sampler_state: the sampler's state (the occupancy grid, or None for the dense sampler).
      step: int32 [], steps taken.
      pixel_error: float32 [N * H * W], each training pixel's squared error when a ray last trained it
        (`TrainConfig.pixel_sampling == "error"`; 1 for pixels not yet drawn), or None.
    """

    params: Any
    opt_state: Any
    sampler_state: Any
    step: Array
    pixel_error: Optional[Array] = None


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


def init_train_state(
    key: PRNGKey, config: TrainConfig, hparams: Optional[TrainHParams] = None, pixels: Optional[int] = None
) -> TrainState:
    """Initial field parameters, optimiser state, sampler state and (error sampling) pixel errors.

    Args:
      key: PRNG key (consumed: split into the field's and the sampler's keys).
      config: static training configuration.
      hparams: numeric hyper-parameters (only their structure matters here).
      pixels: N * H * W, the training pixels (needed when `config.pixel_sampling == "error"`).
    """
    hparams = (hparams or TrainHParams.for_config(config)).as_arrays()
    key_field, key_sampler = jax.random.split(key)
    params = init_field(key_field, config.field)
    opt_state = make_optimizer(hparams).init(params)
    sampler_state = make_sampler(config).init(key_sampler, params)
    pixel_error = None
    if config.pixel_sampling == "error":
        if pixels is None:
            raise ValueError("init_train_state: error pixel sampling needs the number of training pixels")
        pixel_error = jnp.ones((int(pixels),), jnp.float32)
    return TrainState(
        params=params, opt_state=opt_state, sampler_state=sampler_state, step=jnp.int32(0), pixel_error=pixel_error
    )


# Error sampling draws this share of a step's rays uniformly over all pixels and the rest in proportion
# to each pixel's last squared error (so that no pixel is starved once it is learned).
ERROR_UNIFORM_SHARE = 0.25


def _draw_pixels(key: PRNGKey, num_rays: int, pixels: int, pixel_error: Optional[Array]) -> Array:
    """int32 [R] flat pixel indices: uniform, or by `pixel_error` [pixels] (inverse CDF, one binary search
    per ray): probability `ERROR_UNIFORM_SHARE / pixels + (1 - ERROR_UNIFORM_SHARE) * e / sum(e)`."""
    if pixel_error is None:
        return jax.random.randint(key, (num_rays,), 0, pixels)
    error = jnp.maximum(jnp.nan_to_num(pixel_error, nan=1.0, posinf=1.0), 0.0)  # [pixels]
    share = jnp.maximum(jnp.sum(error), 1e-30)
    weight = ERROR_UNIFORM_SHARE / pixels + (1.0 - ERROR_UNIFORM_SHARE) * error / share  # [pixels], sums to 1
    cdf = jnp.cumsum(weight)  # [pixels]
    u = jax.random.uniform(key, (num_rays,)) * cdf[-1]  # [R]
    return jnp.minimum(jnp.searchsorted(cdf, u, side="right"), pixels - 1).astype(jnp.int32)


def _updated_errors(pixel_error: Optional[Array], flat: Array, residual: Array, included: Array) -> Optional[Array]:
    """`pixel_error` with the drawn pixels `flat` [R] set to their rays' mean squared residual [R, 3]
    (where `included`; a pixel drawn twice keeps the larger: a max-scatter, the same on every backend)."""
    if pixel_error is None:
        return None
    squared = jnp.where(included, jnp.mean(jax.lax.stop_gradient(residual) ** 2, axis=-1), -1.0)  # [R]
    drawn = jnp.full_like(pixel_error, -1.0).at[flat].max(squared)  # [pixels], -1 where not trained
    return jnp.where(drawn >= 0.0, drawn, pixel_error)


def _sample_batch(
    key: PRNGKey,
    data: TrainData,
    config: TrainConfig,
    num_rays: Optional[int] = None,
    pixel_error: Optional[Array] = None,
) -> Tuple[Array, Array, Array, Array, Array]:
    """R = `num_rays` (default `config.rays_per_batch`) rays over all training pixels, with their targets
    and backgrounds: uniform, or by `pixel_error` [N * H * W] (`_draw_pixels`).

    Returns:
      origins [R, 3], unit directions [R, 3], target rgb [R, 3], background [R, 3], flat pixel indices [R].
    """
    num_rays = config.rays_per_batch if num_rays is None else num_rays
    key_pixel, key_bg = jax.random.split(key)
    n, h, w = data.images.shape[:3]
    flat = _draw_pixels(key_pixel, num_rays, n * h * w, pixel_error)  # [R]
    image, rest = flat // (h * w), flat % (h * w)
    row, col = rest // w, rest % w
    dirs_cam = jax.vmap(lambda u, v: pixel_directions(data.intrinsics, u, v))(
        col.astype(jnp.float32) + 0.5, row.astype(jnp.float32) + 0.5
    )  # [R, 3]
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
    return origins, directions, target, background, flat


def _loss(residual: Array, included: Array, config: TrainConfig, hparams: TrainHParams) -> Tuple[Array, Array]:
    """(loss, MSE): means over the included rays [R] of residuals [R, 3] (masked, divided by the count)."""
    weight = included.astype(jnp.float32)[:, None] / (3.0 * jnp.maximum(jnp.sum(included), 1))  # [R, 1]
    squared = residual**2  # [R, 3]
    mse = jnp.sum(weight * squared)
    if config.loss == "huber":
        return jnp.sum(weight * optax.huber_loss(residual, delta=hparams.huber_delta)), mse
    return mse, mse


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

    def step(
        state: TrainState, train_key: PRNGKey, data: TrainData, hparams: TrainHParams, render_config: RenderConfig
    ):
        key = jax.random.fold_in(train_key, state.step)
        key_batch, key_render, _ = jax.random.split(key, 3)  # the third key is the occupancy update's
        origins, directions, target, background, flat = _sample_batch(
            key_batch, data, config, num_rays, state.pixel_error
        )

        def loss_fn(params):
            out, included, stats = sampler.render_rays(
                key_render, params, state.sampler_state, origins, directions, background, render_config
            )
            residual = out.rgb - target  # [R, 3]
            loss, mse = _loss(residual, included, config, hparams)
            return loss, (mse, included, residual, stats)

        (loss, (mse, included, residual, stats)), grads = jax.value_and_grad(loss_fn, has_aux=True)(state.params)
        rays = jnp.sum(included, dtype=jnp.int32)
        updates, opt_state = make_optimizer(hparams).update(grads, state.opt_state, state.params)
        params = optax.apply_updates(state.params, updates)
        pixel_error = _updated_errors(state.pixel_error, flat, residual, included)
        new_state = state.replace(params=params, opt_state=opt_state, step=state.step + 1, pixel_error=pixel_error)
        return new_state, {
            "loss": loss,
            "psnr": psnr_from_mse(mse),
            "rays": rays,
            "samples": stats["samples"],
            "rows": stats["rows"],
        }

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


def _periods(config: TrainConfig) -> int:
    """Periods of `occupancy_update_every` steps in a chunk program (`config.chunk` steps, rounded)."""
    return max(1, round(config.chunk / config.occupancy_update_every))


def warmup_steps(config: TrainConfig) -> int:
    """Steps of the warm-up (0 when there is none): `occupancy_warmup` rounded up to whole periods. Every
    occupancy update before this step samples every cell; the rays marched stay those of the first chunk."""
    if config.occupancy_warmup <= 0:
        return 0
    every = config.occupancy_update_every
    return max(1, -(-config.occupancy_warmup // every)) * every


def chunk_end(config: TrainConfig, done: int) -> int:
    """The step at which the chunk starting at step `done` ends: a chunk program's periods, cut at the end
    of the warm-up (the rays marched are chosen again only after it) and at `config.steps`."""
    end = done + _periods(config) * config.occupancy_update_every
    warm = warmup_steps(config)
    if done < warm:
        end = min(end, warm)
    return min(end, config.steps)


@functools.lru_cache(maxsize=None)
def chunk_fn(config: TrainConfig, rays_per_batch: int) -> Callable:
    """A chunk of periods (update, then `occupancy_update_every` steps) in one jitted `lax.scan`
    (cached per config and R; the state is donated).

    One program serves every chunk of a run at that R, the warm-up's included: a period's update samples
    every cell while `state.step < warmup_steps(config)` (a `lax.cond`, once a period), and the steps
    from `end_step` on are skipped by a `lax.cond` (not computed and discarded), so a short chunk (the
    last, or the warm-up's tail) costs only its own steps. On a GPU each `lax.cond` reads its predicate
    on the host, once a step: as the scan's own loop test does.

    Returns:
      chunk(state, train_key, data, hparams, render_config, end_step) -> (state, metrics), as
      `run_chunk` (hparams as arrays, end_step int32 []).
    """
    step = make_train_step(config, rays_per_batch)
    updates = (make_occupancy_update(config, False), make_occupancy_update(config, True))
    warm = warmup_steps(config)

    def chunk(state, train_key, data, hparams, render_config, end_step):
        skipped = {
            "loss": jnp.float32(jnp.nan),
            "psnr": jnp.float32(jnp.nan),
            "rays": jnp.int32(0),
            "samples": jnp.int32(0),
            "rows": jnp.int32(0),
        }

        def one_step(state, _):
            return jax.lax.cond(
                state.step < end_step,
                lambda s: step(s, train_key, data, hparams, render_config),
                lambda s: (s, skipped),
                state,
            )

        def update(state):
            return jax.lax.cond(state.step < warm, updates[1], updates[0], state, train_key)

        def period(state, _):
            state = jax.lax.cond(state.step < end_step, update, lambda s: s, state)
            return jax.lax.scan(one_step, state, None, length=config.occupancy_update_every)

        state, metrics = jax.lax.scan(period, state, None, length=_periods(config))
        return state, jax.tree.map(lambda m: m.reshape(-1), metrics)

    return jax.jit(chunk, donate_argnums=(0,))


class TrainInputs(NamedTuple):
    """Everything a chunk of training steps runs from (`train.training_inputs` makes the first).

    Attributes:
      state: the `TrainState`.
      train_key: the training key stream (step i uses `fold_in(train_key, i)`).
      data: the training images and cameras on the device.
      hparams: the numeric hyper-parameters (as float32 arrays: `TrainHParams.as_arrays`).
      render_config: near, far, box and samples per ray of the training renders.
    """

    state: TrainState
    train_key: PRNGKey
    data: TrainData
    hparams: TrainHParams
    render_config: RenderConfig


def run_chunk(
    inputs: TrainInputs,
    config: TrainConfig,
    end_step: int,
    rays_per_batch: Optional[int] = None,
) -> Tuple[TrainState, Dict]:
    """Runs one chunk program from `inputs.state` (its steps from `end_step` on are skipped) in one jitted scan.

    The input state (`inputs.state`) must start a period (`state.step` a multiple of
    `occupancy_update_every`); its buffers are donated: do not use it afterwards. `train` ends each
    chunk at `chunk_end(config, step)`.

    Returns:
      (state, metrics) with metrics {"loss", "psnr"} float32 [steps] (NaN for skipped steps) and
      {"rays", "samples", "rows"} int32 [steps] (0 for skipped steps).
    """
    rays = config.rays_per_batch if rays_per_batch is None else int(rays_per_batch)
    return chunk_fn(config, rays)(
        inputs.state,
        inputs.train_key,
        inputs.data,
        inputs.hparams.as_arrays(),
        inputs.render_config,
        jnp.int32(end_step),
    )


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
    budget_rows = config.samples_per_batch // TRAIN_ROW_LENGTH
    wanted = 1.25 * budget_rows / max(rows_per_ray, 1e-6)
    return next((r for r in ladder if r >= wanted), ladder[-1])


def first_rays(config: TrainConfig) -> int:
    """R of the first chunk: `config.first_rays` where given, else the grid is all occupied, so a ray
    crossing the box keeps about S samples."""
    if config.first_rays is not None:
        return config.first_rays
    if config.sampler != "occupancy":
        return config.rays_per_batch
    samples = make_sampler(config).march.max_samples
    return _fit_rays(config, -(-samples // TRAIN_ROW_LENGTH) / 2.0)


def next_rays(config: TrainConfig, metrics: Dict[str, np.ndarray], rays: int) -> int:
    """R of the next chunk from the rows per marched ray of the last chunk's last period (Instant-NGP's
    dynamic batch size; the last period best predicts the next steps, e.g. after the warm-up).

    Args:
      config: the training config (the dense sampler keeps `rays`).
      metrics: the last chunk's host metrics: "loss" float32 [steps] (NaN for discarded steps) and
        "rows" int32 [steps].
      rays: R of the last chunk.
    """
    if config.sampler != "occupancy":
        return rays
    taken = np.flatnonzero(np.isfinite(metrics["loss"]))[-config.occupancy_update_every :]
    if taken.size == 0:
        return rays
    rows_per_ray = float(np.sum(np.asarray(metrics["rows"], np.float64)[taken])) / (rays * taken.size)
    return _fit_rays(config, rows_per_ray)
