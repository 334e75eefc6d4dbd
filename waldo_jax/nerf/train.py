"""Training an Instant-NGP radiance field on a posed image set (Müller et al., SIGGRAPH 2022, Sec. 5.4).

`train` is the loop: it runs the jitted chunks of `waldo_jax.nerf.step` with one host sync per chunk
(progress, history, the rays marched next), then calibrates the run's rendering step on held-out
views (`waldo_jax.nerf.trained`). The same key and config give bit-identical parameters on the same
backend. Names: `R` rays per batch, `N` training images. See docs/design.md, "Training".
"""

from __future__ import annotations

import dataclasses
import time
from typing import Any, Callable, Dict, List, NamedTuple, Optional, Tuple

import jax
import jax.numpy as jnp
import numpy as np

from waldo_jax.nerf.config import TrainConfig, TrainHParams, check_scene
from waldo_jax.nerf.trained import calibrate_render_step, eval_background, evaluate
from waldo_jax.nerf.step import (
    TrainData,
    TrainInputs,
    TrainState,
    chunk_end,
    chunk_fn,
    first_rays,
    init_train_state,
    next_rays,
    warmup_steps,
)
from waldo_jax.render.volume import RenderConfig
from waldo_jax.scenes.images import downscale_scene, fit_factor
from waldo_jax.types import PRNGKey, Scene

__all__ = [
    "EVAL_MAX_PIXELS",
    "HeldOut",
    "TrainInputs",
    "TrainResult",
    "evaluate_held_out",
    "held_out_views",
    "train",
    "training_inputs",
]

# The held-out views are rendered with at most this many pixels each (the test images area-filtered by
# the least whole factor that fits, `held_out_views`). The end-of-run evaluation renders every test view
# once and three of them at four marching steps (`calibrate_render_step`): at the fox's full 1080x1920,
# about 75 minutes on the 2-core CPU (estimated from 3,900 rays/s at 540x960 at the training step, on
# the fox the fast preset trains in 5-6 minutes there); at 180x320 (2**16 = 256x256 pixels), minutes.
# PSNR rises as the views shrink (that fox: 23.96 dB at 540x960, 24.34 at 270x480, 25.16 at 135x240).
EVAL_MAX_PIXELS = 2**16


class HeldOut(NamedTuple):
    """How `train` evaluates its held-out views.

    Attributes:
      max_pixels: the views are rendered and compared at most this many pixels each, their images
        area-filtered by the least whole factor that fits (`held_out_views`); None: full size.
      at_end: False leaves the end-of-run evaluation to `evaluate_held_out` (so that a caller can save
        the trained field first): `psnr_test` None and the render step as the config has it.
    """

    max_pixels: Optional[int] = EVAL_MAX_PIXELS
    at_end: bool = True


def training_inputs(
    key: PRNGKey, train_scene: Scene, config: TrainConfig, hparams: Optional[TrainHParams] = None
) -> TrainInputs:
    """Initial state, training key stream, device data and render config of a run.

    `key` is split into the initialisation key and the training stream, exactly as `train` does,
    so a Python loop over `make_train_step` (with `make_occupancy_update` before every
    `occupancy_update_every`-th step, and the R of `TrainResult.history`) reproduces `train`.
    """
    check_scene(train_scene, "training scene")
    hparams = hparams or TrainHParams.for_config(config)
    key_init, key_train = jax.random.split(key)
    data = TrainData.from_scene(train_scene)
    state = init_train_state(key_init, config, hparams, pixels=int(np.prod(data.images.shape[:3])))
    render_config = RenderConfig.create(
        near=train_scene.near,
        far=train_scene.far,
        aabb=np.asarray(train_scene.aabb, np.float32).reshape(2, 3),
        background=eval_background(train_scene),
        num_samples=config.num_samples,
        ray_chunk=1,
    )
    return TrainInputs(state, key_train, data, hparams.as_arrays(), render_config)


class TrainResult(NamedTuple):
    """What `train` returns.

    Attributes:
      params: trained field parameters (device arrays).
      occupancy: the occupancy grid (sampler state), or None for the dense sampler.
      history: one dict per chunk {"step", "loss", "psnr", "rays", "samples", "rays_marched", "warmup",
        "seconds"} (means over the chunk's steps of the batch loss, PSNR, rays trained and field
        evaluations that counted; R, the rays marched per step; whether the chunk was in the warm-up;
        training wall-clock so far), plus {"step", "seconds", "psnr_test"} for held-out evaluations.
      psnr_test: held-out PSNR (dB) at the end, as the run renders (its `config.render_step_scale`),
        or None without a test scene.
      seconds: wall-clock of the training loop (compilation included, evaluations excluded).
      compile_seconds: wall-clock of the chunks that compiled a program (one per rung of rays marched
        (the warm-up's chunks share it); their training time included).
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
      eval_size: (width, height) the held-out views were rendered and compared at (`held_out_views`),
        or None without a test scene.
      eval_downscale: the factor from the test images' size to `eval_size` (1: full size).
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
    eval_size: Optional[Tuple[int, int]] = None
    eval_downscale: int = 1


def _device_name() -> str:
    device = jax.devices()[0]
    kind = getattr(device, "device_kind", "") or ""
    return f"{device.platform}:{kind}" if kind else device.platform


@dataclasses.dataclass
class _Timing:
    """Wall-clock and rays trained of a run's chunks, those that compiled a program kept apart."""

    train_seconds: float = 0.0
    compile_seconds: float = 0.0
    steady_seconds: float = 0.0
    steady_rays: int = 0
    all_rays: int = 0

    def add(self, elapsed: float, rays_trained: int, compiled: bool) -> None:
        self.train_seconds += elapsed
        self.all_rays += rays_trained
        if compiled:  # this call compiled: its time is mostly compilation
            self.compile_seconds += elapsed
        else:
            self.steady_seconds += elapsed
            self.steady_rays += rays_trained

    def rays_per_second(self) -> float:
        """Chunks that compiled count as compilation (their steps' own time included: an overestimate by
        at most a chunk per compiled program); the rate is that of the others."""
        if self.steady_seconds > 0:
            return self.steady_rays / self.steady_seconds
        return self.all_rays / max(self.train_seconds, 1e-9)  # every chunk compiled


def _timed_chunk(program, inputs: TrainInputs, end_step: int, timing: _Timing):
    """Runs one chunk from `inputs.state` up to `end_step` (the host sync of the chunk) and times it:
    (state, metrics on the host)."""
    programs = program._cache_size()
    start = time.perf_counter()
    end = jnp.int32(end_step)
    state, metrics = program(inputs.state, inputs.train_key, inputs.data, inputs.hparams, inputs.render_config, end)
    metrics = jax.device_get(metrics)  # the host sync of this chunk
    elapsed = time.perf_counter() - start
    timing.add(elapsed, int(np.sum(metrics["rays"])), compiled=program._cache_size() > programs)
    return state, metrics


def _chunk_entry(
    metrics: Dict[str, Any], done: int, taken: int, rays: int, warmup: bool, seconds: float
) -> Dict[str, Any]:
    """A chunk's history entry: means over its `taken` steps (see `TrainResult.history`)."""
    rays_trained = int(np.sum(metrics["rays"]))
    return {
        "step": done,
        "loss": float(np.nanmean(metrics["loss"])),
        "psnr": float(np.nanmean(metrics["psnr"])),
        "rays": rays_trained / max(taken, 1),
        "samples": float(np.sum(metrics["samples"])) / max(taken, 1),
        "rays_marched": rays,
        "warmup": warmup,
        "seconds": seconds,
    }


def _evaluates_after(config: TrainConfig, done: int, taken: int) -> bool:
    """Whether the chunk that took the run from `done - taken` to `done` steps crossed an `eval_every` mark
    (the last chunk excepted: the run is evaluated at its end anyway)."""
    return (
        bool(config.eval_every)
        and done < config.steps
        and (done // config.eval_every) > ((done - taken) // config.eval_every)
    )


class _Chunks(NamedTuple):
    """What the loop over chunks leaves (`_train_chunks`)."""

    state: TrainState
    history: List[Dict[str, Any]]
    timing: _Timing
    stopped: bool


def _train_chunks(
    inputs: TrainInputs,
    config: TrainConfig,
    test_scene: Optional[Scene],
    progress: bool,
    on_chunk: Optional[Callable[[TrainState, Dict[str, Any]], bool]],
) -> _Chunks:
    """The training loop: chunks of steps until `config.steps` (or `on_chunk` stops it), with progress,
    history and the `eval_every` held-out evaluations."""
    from tqdm.auto import tqdm

    history: List[Dict[str, Any]] = []
    timing = _Timing()
    rays = first_rays(config)
    done, stopped = 0, False
    bar = tqdm(total=config.steps, disable=not progress, unit="step", dynamic_ncols=True)
    try:
        while done < config.steps:
            warmup = done < warmup_steps(config)
            state, metrics = _timed_chunk(chunk_fn(config, rays), inputs, chunk_end(config, done), timing)
            inputs = inputs._replace(state=state)
            # The steps taken from the state's own count (a step whose loss is NaN still counts, so the
            # next chunk starts where this one ended).
            taken = int(jax.device_get(state.step)) - done
            done += taken
            entry = _chunk_entry(metrics, done, taken, rays, warmup, timing.train_seconds)
            history.append(entry)
            bar.update(taken)
            bar.set_postfix(loss=f"{entry['loss']:.4g}", psnr=f"{entry['psnr']:.2f}", rays=rays)
            if done >= warmup_steps(config):  # R stays the first chunk's through the warm-up
                rays = next_rays(config, metrics, rays)
            if test_scene is not None and _evaluates_after(config, done, taken):
                psnr = evaluate(state.params, state.sampler_state, config, test_scene)["psnr"]
                history.append({"step": done, "seconds": timing.train_seconds, "psnr_test": psnr})
                bar.set_postfix(loss=f"{entry['loss']:.4g}", psnr=f"{entry['psnr']:.2f}", test=f"{psnr:.2f}")
            if on_chunk is not None and on_chunk(state, entry) and done < config.steps:
                stopped = True
                break
    finally:
        bar.close()
    return _Chunks(inputs.state, history, timing, stopped)


def held_out_views(test_scene: Scene, max_pixels: Optional[int] = EVAL_MAX_PIXELS) -> Tuple[Scene, int]:
    """The held-out views as they are evaluated: (the scene, the factor), its images area-filtered by the
    least whole factor that brings each to at most `max_pixels` pixels (None: full size, factor 1).

    PSNR is compared at that size: the render and the filtered image are both 1/factor of the
    original's resolution, so fine detail counts less than at full size (train.json records the size)."""
    if max_pixels is None:
        return test_scene, 1
    if isinstance(max_pixels, bool) or not isinstance(max_pixels, (int, np.integer)) or max_pixels < 1:
        raise ValueError(f"the held-out views' pixel budget must be a positive integer or None, got {max_pixels!r}")
    factor = fit_factor(test_scene.width, test_scene.height, int(max_pixels))
    return downscale_scene(test_scene, factor), factor


def train(
    key: PRNGKey,
    train_scene: Scene,
    config: TrainConfig,
    test_scene: Optional[Scene] = None,
    progress: bool = True,
    hparams: Optional[TrainHParams] = None,
    on_chunk: Optional[Callable[[TrainState, Dict[str, Any]], bool]] = None,
    held_out: HeldOut = HeldOut(),
) -> TrainResult:
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
      held_out: the held-out views' size (default at most `EVAL_MAX_PIXELS` pixels each) and whether
        the end-of-run evaluation is done here (`HeldOut`).

    Returns:
      A `TrainResult`. Same key, scene and config give bit-identical params on the same device.

    Raises:
      TrainConfigError: a scene is unusable for training.
    """
    given_test = test_scene
    if test_scene is not None:
        check_scene(test_scene, "test scene")
        test_scene, _ = held_out_views(test_scene, held_out.max_pixels)  # for the `eval_every` evaluations
    hparams = hparams or TrainHParams.for_config(config)
    chunks = _train_chunks(training_inputs(key, train_scene, config, hparams), config, test_scene, progress, on_chunk)
    state, timing = chunks.state, chunks.timing
    result = TrainResult(
        params=state.params,
        occupancy=state.sampler_state,
        history=chunks.history,
        psnr_test=None,
        seconds=timing.train_seconds,
        compile_seconds=timing.compile_seconds,
        rays_per_second=timing.rays_per_second(),
        steps=int(state.step),
        config=config,
        hparams=hparams,
        device=_device_name(),
        n_train=train_scene.n_images,
        n_test=0 if test_scene is None else test_scene.n_images,
        stopped=chunks.stopped,
    )
    if not held_out.at_end or given_test is None:
        return result
    return evaluate_held_out(result, given_test, held_out.max_pixels, progress)


def evaluate_held_out(
    result: TrainResult,
    test_scene: Scene,
    eval_max_pixels: Optional[int] = EVAL_MAX_PIXELS,
    progress: bool = False,
) -> TrainResult:
    """The end-of-run evaluation of a trained run: the final held-out PSNR, as the run renders.

    The views are taken at most `eval_max_pixels` pixels each (`held_out_views`); when the run's
    `config.render_step_scale` is None its marching step is calibrated on them first
    (`calibrate_render_step`) and stored in the returned config. `progress` prints one line first
    (how many views, at what size).

    Returns:
      `result` with `psnr_test`, `config`, `psnr_test_training_step`, `render_step_curve`,
      `eval_size`, `eval_downscale` set and the evaluation appended to a copy of its history.
    """
    check_scene(test_scene, "test scene")
    full = (test_scene.width, test_scene.height)
    scene, factor = held_out_views(test_scene, eval_max_pixels)
    config = result.config
    scale = config.render_step_scale
    if progress:
        size = f"{scene.width}x{scene.height}" + (f" (1/{factor} of {full[0]}x{full[1]})" if factor > 1 else "")
        calibrating = ", the render step calibrated on 3 of them first" if scale is None else ""
        print(f"held-out evaluation: {scene.n_images} views at {size}{calibrating}", flush=True)
    curve: List[Dict[str, Any]] = []
    if scale is None:
        scale, curve = calibrate_render_step(result.params, result.occupancy, config, scene)
        config = config.replace(render_step_scale=scale)
    final = evaluate(result.params, result.occupancy, config, scene)
    psnr_test = final["psnr"]
    entry = {
        "step": result.steps,
        "seconds": result.seconds,
        "psnr_test": psnr_test,
        "render_step_scale": scale,
        "evaluations_per_ray": final["evaluations_per_ray"],
        "eval_size": [scene.width, scene.height],
    }
    return result._replace(
        history=list(result.history) + [entry],
        psnr_test=psnr_test,
        config=config,
        n_test=scene.n_images,
        psnr_test_training_step=psnr_test if scale == 1.0 else None,
        render_step_curve=curve,
        eval_size=(scene.width, scene.height),
        eval_downscale=factor,
    )
