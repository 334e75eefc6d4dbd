"""Training an Instant-NGP radiance field on a posed image set (Müller et al., SIGGRAPH 2022, Sec. 5.4).

`train` is the loop: it runs the jitted chunks of `waldo_jax.nerf.step` with one host sync per chunk
(progress, history, the rays marched next), then calibrates the run's rendering step on held-out
views (`waldo_jax.nerf.trained`). The same key and config give bit-identical parameters on the same
backend. Names: `R` rays per batch, `N` training images. See docs/design.md, "Training".
"""

from __future__ import annotations

import dataclasses
import time
from typing import Any, Callable, Dict, List, NamedTuple, Optional

import jax
import jax.numpy as jnp
import numpy as np

from waldo_jax.nerf.config import TrainConfig, TrainHParams, check_scene
from waldo_jax.nerf.trained import calibrate_render_step, eval_background, evaluate
from waldo_jax.nerf.step import (
    TrainData,
    TrainInputs,
    TrainState,
    chunk_fn,
    first_rays,
    init_train_state,
    next_rays,
    warmup_steps,
)
from waldo_jax.render.volume import RenderConfig
from waldo_jax.types import PRNGKey, Scene

__all__ = ["TrainInputs", "TrainResult", "train", "training_inputs"]


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
    state = init_train_state(key_init, config, hparams)
    data = TrainData.from_scene(train_scene)
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


def _timed_chunk(program, inputs: TrainInputs, total, timing: _Timing):
    """Runs one chunk from `inputs.state` (the host sync of the chunk) and times it: (state, metrics on the host)."""
    programs = program._cache_size()
    start = time.perf_counter()
    state, metrics = program(inputs.state, inputs.train_key, inputs.data, inputs.hparams, inputs.render_config, total)
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
    total = jnp.int32(config.steps)
    rays = first_rays(config)
    done, stopped = 0, False
    bar = tqdm(total=config.steps, disable=not progress, unit="step", dynamic_ncols=True)
    try:
        while done < config.steps:
            warmup = done == 0 and warmup_steps(config) > 0
            state, metrics = _timed_chunk(chunk_fn(config, rays, warmup), inputs, total, timing)
            inputs = inputs._replace(state=state)
            taken = int(np.sum(np.isfinite(metrics["loss"])))
            done += taken
            entry = _chunk_entry(metrics, done, taken, rays, warmup, timing.train_seconds)
            history.append(entry)
            bar.update(taken)
            bar.set_postfix(loss=f"{entry['loss']:.4g}", psnr=f"{entry['psnr']:.2f}", rays=rays)
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


class _HeldOut(NamedTuple):
    """The end-of-run evaluation (`_held_out`)."""

    config: TrainConfig
    psnr_test: Optional[float]
    psnr_training_step: Optional[float]
    curve: List[Dict[str, Any]]
    entry: Optional[Dict[str, Any]]


def _held_out(state: TrainState, config: TrainConfig, test_scene: Optional[Scene], seconds: float) -> _HeldOut:
    """The final held-out PSNR, as the run renders: its step calibrated first when `config` has none."""
    if test_scene is None:
        return _HeldOut(config, None, None, [], None)
    scale = config.render_step_scale
    curve: List[Dict[str, Any]] = []
    if scale is None:
        scale, curve = calibrate_render_step(state.params, state.sampler_state, config, test_scene)
        config = config.replace(render_step_scale=scale)
    final = evaluate(state.params, state.sampler_state, config, test_scene)
    psnr_test = final["psnr"]
    entry = {
        "step": int(state.step),
        "seconds": seconds,
        "psnr_test": psnr_test,
        "render_step_scale": scale,
        "evaluations_per_ray": final["evaluations_per_ray"],
    }
    return _HeldOut(config, psnr_test, psnr_test if scale == 1.0 else None, curve, entry)


def train(
    key: PRNGKey,
    train_scene: Scene,
    config: TrainConfig,
    test_scene: Optional[Scene] = None,
    progress: bool = True,
    hparams: Optional[TrainHParams] = None,
    on_chunk: Optional[Callable[[TrainState, Dict[str, Any]], bool]] = None,
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

    Returns:
      A `TrainResult`. Same key, scene and config give bit-identical params on the same device.

    Raises:
      TrainConfigError: a scene is unusable for training.
    """
    if test_scene is not None:
        check_scene(test_scene, "test scene")
    hparams = hparams or TrainHParams.for_config(config)
    chunks = _train_chunks(training_inputs(key, train_scene, config, hparams), config, test_scene, progress, on_chunk)
    state, history, timing = chunks.state, chunks.history, chunks.timing
    held_out = _held_out(state, config, test_scene, timing.train_seconds)
    if held_out.entry is not None:
        history.append(held_out.entry)
    return TrainResult(
        params=state.params,
        occupancy=state.sampler_state,
        history=history,
        psnr_test=held_out.psnr_test,
        seconds=timing.train_seconds,
        compile_seconds=timing.compile_seconds,
        rays_per_second=timing.rays_per_second(),
        steps=int(state.step),
        config=held_out.config,
        hparams=hparams,
        device=_device_name(),
        n_train=train_scene.n_images,
        n_test=0 if test_scene is None else test_scene.n_images,
        psnr_test_training_step=held_out.psnr_training_step,
        render_step_curve=held_out.curve,
        stopped=chunks.stopped,
    )
