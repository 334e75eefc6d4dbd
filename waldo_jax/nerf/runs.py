"""Run directories: a trained field as `checkpoint.ckpt` + `train.json`, written in one place.

`train_scene_run` is `waldo train` as a function (scene folder -> run directory); `train_run` trains
on scenes already in memory (the demo's procedural room) and writes the same two files, so every
run directory has the same `train.json` keys (`train_stats`), whoever trained it.
"""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path
from typing import Any, Dict, NamedTuple, Optional, Tuple

import jax

from waldo_jax import io
from waldo_jax.errors import MAX_INT32, MAX_TRAIN_STEPS, WaldoError, check_float32
from waldo_jax.nerf.checkpoint import CHECKPOINT_NAME, save_checkpoint
from waldo_jax.nerf.config import PIXEL_SAMPLINGS, PRESETS, SAMPLERS, TrainConfig, TrainConfigError
from waldo_jax.nerf.train import EVAL_MAX_PIXELS, HeldOut, TrainResult, evaluate_held_out, train
from waldo_jax.scenes import load_splits
from waldo_jax.types import RunOptions, Scene

__all__ = [
    "TRAIN_JSON",
    "SAMPLER_CHOICES",
    "Sampling",
    "load_splits",
    "train_stats",
    "train_run",
    "evaluate_run",
    "train_scene_run",
]

TRAIN_JSON = "train.json"
SAMPLER_CHOICES = ("auto",) + SAMPLERS  # auto = occupancy


class Sampling(NamedTuple):
    """How `waldo train` picks what a step trains on (`train_scene_run`).

    Attributes:
      samples: where along the rays: "auto" (= "occupancy") or a `TrainConfig.sampler`.
      pixels: which pixels: "uniform" or "error" (`TrainConfig.pixel_sampling`).
    """

    samples: str = "auto"
    pixels: str = "uniform"


def train_stats(
    result: TrainResult, scene: Scene, preset: str, seed: int, scene_path: Optional[str] = None
) -> Dict[str, Any]:
    """The contents of train.json: the run's quality, cost, settings and loss history (JSON-able).

    `scene_path` is the path the user gave (a folder or a scene file), recorded resolved; default:
    the scene's folder, or None for a scene built in memory.
    """
    config = result.config
    path = scene_path or scene.path
    last = next((h for h in reversed(result.history) if "loss" in h), {})
    return {
        "psnr_test": result.psnr_test,
        "psnr_test_training_step": result.psnr_test_training_step,
        "render_step_scale": config.render_step_scale,
        "render_step_curve": result.render_step_curve,
        "eval_image_size": None if result.eval_size is None else list(result.eval_size),
        "eval_downscale": None if result.eval_size is None else result.eval_downscale,
        "steps": result.steps,
        "seconds": round(result.seconds, 3),
        "compile_seconds": round(result.compile_seconds, 3),
        "rays_per_second": round(result.rays_per_second, 1),
        "device": result.device,
        "n_train": result.n_train,
        "n_test": result.n_test,
        "preset": preset,
        "sampler": config.sampler,
        "seed": seed,
        "scene_path": str(Path(path).resolve()) if path else None,
        "scene_format": scene.format,
        "downscale": scene.metadata.get("downscale"),
        "image_size": [scene.width, scene.height],
        "train_loss": last.get("loss"),
        "train_psnr": last.get("psnr"),
        "checkpoint": CHECKPOINT_NAME,
        "config": config.to_dict(),
        "hparams": {f.name: float(getattr(result.hparams, f.name)) for f in dataclasses.fields(result.hparams)},
        "history": result.history,
    }


def train_run(
    seed: int,
    scene: Scene,
    config: TrainConfig,
    test_scene: Optional[Scene],
    out: Path,
    progress: bool = True,
    scene_path: Optional[str] = None,
    eval_max_pixels: Optional[int] = EVAL_MAX_PIXELS,
) -> Tuple[TrainResult, Dict[str, Any]]:
    """Trains on `scene` (held-out PSNR on `test_scene`) and writes OUT/checkpoint.ckpt and OUT/train.json.

    The two files are written as soon as training ends (the held-out PSNR not yet measured, the
    render step as `config` has it) and again after the held-out evaluation; when `out` is a command's
    own output folder (`io.prepare_output_dir`'s), it is kept from then on (`io.keep_output_dir`), so an
    interrupted evaluation loses no training. The preset recorded is `config.preset_name`.

    Args:
      seed: the training seed (`jax.random.key(seed)`).
      scene, config, test_scene: as `waldo_jax.nerf.train.train`.
      out: an existing folder (see `waldo_jax.io.prepare_output_dir`).
      progress: a progress bar.
      scene_path: the path the scene was loaded from, as given (recorded in train.json).
      eval_max_pixels: the held-out views' size (`waldo_jax.nerf.train.held_out_views`; None: full size).

    Returns:
      (the `TrainResult`, whose config holds the calibrated render step, and the train.json contents).

    Raises:
      WaldoError: `out` is not an existing, writable folder (checked before training, so a
        training is never lost to it).
    """
    out = Path(out)
    if not out.is_dir() or not os.access(out, os.W_OK):
        raise WaldoError(f"{out}: not an existing writable folder to save the run in")
    result = train(
        jax.random.key(seed),
        scene,
        config,
        test_scene,
        progress=progress,
        held_out=HeldOut(eval_max_pixels, at_end=False),
    )
    _check_trained(result, scene_path or scene.path)
    stats = _save_run(out, result, scene, seed, scene_path)
    if test_scene is not None:  # the trained field is on disk first: an interrupted evaluation loses no training
        result, stats = evaluate_run(result, (scene, test_scene), out, seed, scene_path, eval_max_pixels, progress)
    return result, stats


def _check_trained(result: TrainResult, scene_path: str) -> None:
    """Refuses to save a field whose parameters hold NaN or infinity (the training diverged: a checkpoint
    of it would render nothing and be refused when read), naming the scene and the first such array."""
    bad = [
        jax.tree_util.keystr(name)
        for name, leaf in jax.tree_util.tree_leaves_with_path(result.params)
        if not bool(jax.numpy.all(jax.numpy.isfinite(leaf)))
    ]
    if bad:
        raise WaldoError(
            f"{scene_path}: the training diverged: after {result.steps} steps {len(bad)} of the field's parameter "
            f"arrays hold NaN or infinity (e.g. {bad[0]}); no run was saved. Check the scene's cameras "
            "(their distortion, focal length and poses) and train again"
        )


def evaluate_run(
    result: TrainResult,
    scenes: Tuple[Scene, Scene],
    out: Path,
    seed: int,
    scene_path: Optional[str] = None,
    eval_max_pixels: Optional[int] = EVAL_MAX_PIXELS,
    progress: bool = True,
) -> Tuple[TrainResult, Dict[str, Any]]:
    """`train_run`'s second half, for a run trained by `train_run` without a test scene: the held-out
    evaluation (`evaluate_held_out`), then OUT/checkpoint.ckpt and OUT/train.json written again with it.
    When `out` is a command's own output folder it is kept from then on (`io.keep_output_dir`).

    Args:
      result: the run's `TrainResult`.
      scenes: (the training scene, the held-out views).
      out, seed, scene_path, eval_max_pixels, progress: as `train_run`.

    Returns:
      (the evaluated `TrainResult`, the train.json contents).
    """
    scene, test_scene = scenes
    out = Path(out)
    if io.keep_output_dir(out) and progress:
        print(f"wrote {out / CHECKPOINT_NAME} (kept if the evaluation is interrupted)", flush=True)
    result = evaluate_held_out(result, test_scene, eval_max_pixels, progress)
    return result, _save_run(out, result, scene, seed, scene_path)


def _save_run(out: Path, result: TrainResult, scene: Scene, seed: int, scene_path: Optional[str]) -> Dict[str, Any]:
    """Writes OUT/checkpoint.ckpt and OUT/train.json of `result`; returns the train.json contents."""
    stats = train_stats(result, scene, result.config.preset_name, seed, scene_path)
    save_checkpoint(
        out / CHECKPOINT_NAME,
        result.params,
        result.config,
        scene,
        result.occupancy,
        info={k: v for k, v in stats.items() if k != "history"},
    )
    io.write_json(out / TRAIN_JSON, stats)
    return stats


def _positive(flag: str, value: Optional[float]) -> None:
    """Refuses a flag's value that is not positive and finite in float32, where it is used."""
    if value is not None:
        check_float32(value, flag, positive=True)


def train_scene_run(
    scene_path: str,
    out: str | Path,
    preset: str = "fast",
    steps: Optional[int] = None,
    sampling: Sampling = Sampling(),
    render_step_scale: Optional[float] = None,
    options: RunOptions = RunOptions(),
    eval_max_pixels: Optional[int] = EVAL_MAX_PIXELS,
) -> Tuple[TrainResult, Dict[str, Any], Path]:
    """`waldo train` as a function: the scene on disk -> a run directory `out`.

    Every value is checked, and `out` too (empty, writable, a valid name), before the scene is loaded:
    a training is never lost to a folder it cannot write. `sampling`: the samples' sampler and the
    pixels' (`Sampling`). `options`: the scene's downscale, the seed,
    whether to write into a non-empty `out` (force), progress. `eval_max_pixels`: the held-out views'
    size (`waldo_jax.nerf.train.held_out_views`; None: full size).

    Returns:
      (the `TrainResult`, the train.json contents, the run directory).

    Raises:
      WaldoError: a bad value (named as its `waldo train` flag), scene or output folder.
    """
    if preset not in PRESETS:
        raise WaldoError(f"unknown preset {preset!r}: expected one of {', '.join(PRESETS)}")
    if sampling.samples not in SAMPLER_CHOICES:
        raise WaldoError(f"unknown sampler {sampling.samples!r}: expected one of {', '.join(SAMPLER_CHOICES)}")
    if sampling.pixels not in PIXEL_SAMPLINGS:
        raise WaldoError(f"unknown pixel sampling {sampling.pixels!r}: expected one of {', '.join(PIXEL_SAMPLINGS)}")
    if steps is not None and not 1 <= steps <= MAX_TRAIN_STEPS:
        raise WaldoError(f"--steps must be a positive integer of at most {MAX_TRAIN_STEPS}, got {steps}")
    _positive("--downscale", options.downscale)
    _positive("--render-step-scale", render_step_scale)
    if eval_max_pixels is not None and not 1 <= eval_max_pixels <= MAX_INT32:
        raise WaldoError(
            f"--eval-max-pixels must be a number of pixels between 1 and {MAX_INT32}, got {eval_max_pixels}"
        )
    out = io.check_output_dir(out, force=options.force)
    train_scene, test_scene = load_splits(scene_path, options.downscale, stacklevel=3)
    overrides: Dict[str, Any] = {
        "sampler": "occupancy" if sampling.samples == "auto" else sampling.samples,
        "pixel_sampling": sampling.pixels,
    }
    if steps is not None:
        overrides["steps"] = steps
    if render_step_scale is not None:
        overrides["render_step_scale"] = render_step_scale
    try:  # the whole config checked before the run folder is made
        config = TrainConfig.preset(preset, train_scene, **overrides)
    except TrainConfigError as e:
        raise TrainConfigError(str(e).replace("TrainConfig.render_step_scale", "--render-step-scale")) from None
    out = io.prepare_output_dir(out, force=options.force)
    result, stats = train_run(
        options.seed,
        train_scene,
        config,
        test_scene,
        out,
        options.progress,
        scene_path,
        eval_max_pixels,
    )
    return result, stats, out
