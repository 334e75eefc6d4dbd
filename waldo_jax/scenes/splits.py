"""A scene's training and held-out splits, by the format's own hold-out rule."""

from __future__ import annotations

import warnings
from typing import Optional, Tuple

from waldo_jax.errors import MAX_RESOLUTION, MIN_RESOLUTION, SceneFormatError, WaldoError
from waldo_jax.scenes.loader import load_scene
from waldo_jax.types import Scene

__all__ = ["load_splits"]


def load_splits(
    scene_path: str, downscale: Optional[float], stacklevel: int = 2, model: str = "a NeRF"
) -> Tuple[Scene, Optional[Scene]]:
    """(training scene, held-out scene or None) with the format's own hold-out.

    Blender scenes hold out transforms_test.json (else _val); other formats every 8th image. A scene
    without held-out views warns (at `stacklevel`, pointing at the caller) and returns None for it.
    NeRF and splat runs share this rule, so their held-out PSNRs compare. `model` names what is
    trained in the error for too small images.
    """
    train_scene = load_scene(scene_path, downscale=downscale, split="train")
    if min(train_scene.width, train_scene.height) < MIN_RESOLUTION:
        how = f"--downscale {downscale:g} leaves" if downscale else "the scene has"
        raise WaldoError(
            f"{scene_path}: {how} {train_scene.width}x{train_scene.height} training images; {model} "
            f"needs sides of at least {MIN_RESOLUTION} pixels"
        )
    if max(train_scene.width, train_scene.height) > MAX_RESOLUTION:  # renders of its poses and int32 ray indices
        how = f"--downscale {downscale:g} leaves" if downscale else "the scene has"
        raise WaldoError(
            f"{scene_path}: {how} {train_scene.width}x{train_scene.height} training images; {model} "
            f"takes sides of at most {MAX_RESOLUTION} pixels (pass --downscale)"
        )
    test_scene = None
    splits = ("test", "val") if train_scene.format == "blender" else ("test",)
    for split in splits:
        try:
            with warnings.catch_warnings():  # the train split already warned about skipped frames
                warnings.simplefilter("ignore", UserWarning)
                test_scene = load_scene(scene_path, downscale=downscale, split=split)
            break
        except SceneFormatError as e:
            problem = str(e)
    if test_scene is None:
        warnings.warn(f"{scene_path}: no held-out views ({problem}); psnr_test will be null", stacklevel=stacklevel)
    return train_scene, test_scene
