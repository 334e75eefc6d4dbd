"""Splat runs: `waldo train SCENE --model splat` as a function, writing the reference 3DGS layout.

A splat run folder holds what the reference code writes, so other tools open it as they open theirs:

  point_cloud/iteration_<steps>/point_cloud.ply   the fitted splats (`waldo_jax.splats.io`);
  cameras.json                                     the training cameras (OpenCV axes, as the reference);
  train.json                                       the scene it was fitted to (path, split, downscale,
                                                   background), its held-out PSNR, cost and history.

It is itself a SOURCE (`waldo_jax.pipeline.splat_sources`): the training images are read again from
the scene named in train.json.
"""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path
from typing import Any, Dict, Optional, Tuple

import jax
import numpy as np

from waldo_jax import io
from waldo_jax.errors import MAX_TRAIN_STEPS, WaldoError
from waldo_jax.scenes import load_splits
from waldo_jax.scenes.ply import read_ply_points
from waldo_jax.splats.fit import FitConfig, FitResult, fit_splats
from waldo_jax.splats.io import SplatCameras, write_splat_model
from waldo_jax.types import RunOptions, Scene

__all__ = ["TRAIN_JSON", "SPARSE_POINTS", "fit_scene_run", "sparse_points"]

TRAIN_JSON = "train.json"
SPARSE_POINTS = "sparse_pc.ply"  # nerfstudio's sparse COLMAP points, beside transforms.json


def sparse_points(scene: Scene) -> Tuple[Optional[np.ndarray], Optional[np.ndarray], str]:
    """The scene's sparse points and colours (nerfstudio's `sparse_pc.ply`), or (None, None, why not)."""
    folder = Path(scene.path) if scene.path else None
    if folder is None or not (folder / SPARSE_POINTS).is_file():
        return None, None, f"no {SPARSE_POINTS} beside the scene"
    points, colors = read_ply_points(folder / SPARSE_POINTS, colors=True)
    return points, colors, str(folder / SPARSE_POINTS)


def fit_scene_run(
    scene_path: str,
    out: str | Path,
    steps: Optional[int] = None,
    capacity: Optional[int] = None,
    config: Optional[FitConfig] = None,
    options: RunOptions = RunOptions(),
) -> Tuple[FitResult, Dict[str, Any], Path]:
    """Fits splats to a scene on disk and writes a splat run folder `out`.

    Every value and `out` are checked before the scene is loaded (a fit is never lost to a folder it
    cannot write). `options`: the scene's downscale, the seed, whether to write into a non-empty `out`
    (force), progress.

    Returns:
      (the `FitResult`, the train.json contents, the run folder).

    Raises:
      WaldoError: a bad value (named as its `waldo train` flag), scene or output folder.
    """
    config = FitConfig() if config is None else config
    overrides: Dict[str, Any] = {}
    if steps is not None:
        if isinstance(steps, bool) or not isinstance(steps, int) or not 1 <= steps <= MAX_TRAIN_STEPS:
            raise WaldoError(f"--steps must be an integer between 1 and {MAX_TRAIN_STEPS}, got {steps!r}")
        overrides["steps"] = steps
    if capacity is not None:
        if isinstance(capacity, bool) or not isinstance(capacity, int) or not 16 <= capacity <= 2**24:
            raise WaldoError(f"--capacity must be an integer between 16 and {2**24}, got {capacity!r}")
        overrides["capacity"] = capacity
        overrides["init_count"] = min(config.init_count, capacity // 2)
    config = dataclasses.replace(config, **overrides)
    out = io.check_output_dir(out, force=options.force)
    train_scene, test_scene = load_splits(scene_path, options.downscale, stacklevel=3, model="a splat fit")
    points, colors, points_from = sparse_points(train_scene)

    def ready() -> None:  # the step program fits this machine: the run folder is made now, before any step
        made = io.prepare_output_dir(out, force=options.force)
        if not os.access(made, os.W_OK):
            raise WaldoError(f"{made}: not a writable folder to save the run in")

    log = lambda message: print(message, flush=True)  # noqa: E731
    result = fit_splats(
        jax.random.key(options.seed),
        train_scene,
        config,
        test_scene,
        points,
        colors,
        log=log if options.progress else None,
        ready=ready,
    )
    cameras = SplatCameras(
        c2w=np.asarray(train_scene.c2w, np.float32),
        intrinsics=(train_scene.intrinsics,) * train_scene.n_images,
        names=tuple(train_scene.file_names),
    )
    ply = write_splat_model(out, result.splats, result.steps, cameras=cameras)
    background = (np.zeros(3) if train_scene.background is None else np.asarray(train_scene.background)).tolist()
    stats = {
        "model": "splat",
        "psnr_test": result.psnr_test,
        "steps": result.steps,
        "seconds": round(result.seconds, 3),
        "splats": int(result.splats.count),
        "capacity": config.capacity,
        "sh_degree": result.splats.sh_degree,
        "init": result.history[0].get("init"),
        "init_points": points_from,
        "max_pairs": result.max_pairs,
        "steps_with_pair_overflow": result.overflow_views,
        "max_pairs_capped": result.max_pairs_capped,
        "step_memory_bytes": result.step_memory,
        "densify_dropped": result.densify_dropped,
        "device": jax.devices()[0].platform,
        "n_train": train_scene.n_images,
        "n_test": None if test_scene is None else test_scene.n_images,
        "seed": options.seed,
        "scene_path": str(Path(scene_path).resolve()),
        "scene_format": train_scene.format,
        "split": train_scene.split,
        "downscale": train_scene.metadata.get("downscale"),
        "image_size": [train_scene.width, train_scene.height],
        "background": background,
        "file_names": list(train_scene.file_names),
        "point_cloud": str(ply.relative_to(out)),
        "config": {k: v for k, v in dataclasses.asdict(config).items() if k != "render"},
        "history": list(result.history),
    }
    io.write_json(out / TRAIN_JSON, stats)
    return result, stats, out
