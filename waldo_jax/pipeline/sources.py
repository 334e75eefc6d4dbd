"""What a search explores: a `Source` = training views + a batched renderer, from a SOURCE string.

SOURCE is what `waldo explore` and `waldo render` accept:
  * `procedural` or `procedural:SEED`: the procedural Waldo room (`waldo_jax.procedural`), rendered
    by its analytic field; its training views are the room's training cameras rendered by that
    same field (they are the "real images" of this scene);
  * a run directory of `waldo train` (or of `waldo demo`): the trained hash-grid field renders, and
    the training images are read again from the scene folder the checkpoint names (their file
    names are in the checkpoint). A run trained on the procedural room keeps the room, so its
    oracles (`waldo_oracle`) still apply and renders can be compared with the analytic truth.

A `Source`'s renderers are `jax.tree_util.Partial`s c2w [P, 4, 4] -> rgb [P, H, W, 3] whose
arrays (the room, the field's parameters, the occupancy grid) are traced arguments, so they can be
called inside the search's jit and compile once per image size.
"""

from __future__ import annotations

import dataclasses
import functools
import warnings
from pathlib import Path
from typing import Any, Dict, Optional, Tuple

import jax
import jax.numpy as jnp
import numpy as np

from waldo_jax.errors import WaldoError, check_resolution, check_seed
from waldo_jax.nerf.checkpoint import load_checkpoint
from waldo_jax.nerf.field import make_field
from waldo_jax.nerf.trained import render_setup
from waldo_jax.procedural import make_room, room_field, room_render_config, room_scene
from waldo_jax.render import render_views
from waldo_jax.render.marched import render_marched
from waldo_jax.scenes import load_scene
from waldo_jax.types import Array, Intrinsics, Scene

__all__ = ["Source", "SourceError", "procedural_source", "run_source", "resize_images",
           "parse_procedural", "room_renderer", "field_renderer", "DEFAULT_PROCEDURAL_RESOLUTION",
           "DEFAULT_PROCEDURAL_VIEWS", "MAX_PROCEDURAL_VIEWS", "check_views"]

DEFAULT_PROCEDURAL_RESOLUTION = 64
DEFAULT_PROCEDURAL_VIEWS = 24
MAX_PROCEDURAL_VIEWS = 1000  # the paper's high budget in images: more training views than that are surely a typo
_ROOM_SAMPLES = 128


class SourceError(WaldoError, ValueError):
    """A SOURCE that cannot be opened (the message names it and says why)."""


@dataclasses.dataclass(frozen=True, eq=False)
class Source:
    """A scene to explore.

    Attributes:
      spec: the SOURCE string it came from.
      kind: "procedural", "run" (a NeRF of `waldo train`) or "splats" (`pipeline.splat_sources`).
      name: a short name for reports ("procedural:0", the run folder's name).
      train_c2w: float32 [N, 4, 4] training poses (OpenGL camera-to-world).
      intrinsics: the camera of every render of the search (its width/height set the image size).
      render: c2w [P, 4, 4] -> rgb float32 [P, H, W, 3] in [0, 1] (a `jax.tree_util.Partial`).
      train_images: float32 [N, H, W, 3] the real training images at `intrinsics`' size, or None
        when they cannot be read (then `train_images_note` says why).
      train_names: the N training images' file names.
      room: the procedural `WaldoRoom`, or None.
      truth_render: for a NeRF of the procedural room, the analytic renderer (same signature as
        `render`); None otherwise.
      info: facts for results files (seed, run directory, held-out PSNR of the run, ...).
      train_images_note: why `train_images` is None ("" otherwise).
      render_rgba: as `render` but returning rgba [P, H, W, 4] with the accumulated opacity as alpha,
        for criteria that guard against empty views; None when the source cannot give opacity.
      renderer_report: c2w [V, 4, 4] of every view a run rendered -> facts for results.json (what
        the renderer dropped, ...), or None.
      gradient: how a `+refine` method differentiates a render: "forward" (`jax.jvp`, six tangents:
        the marched NeRF renderer's loops allow no reverse mode) or "reverse" (`jax.vjp`).
      gradient_cost: renders one gradient evaluation through this source's renderer counts as (None:
        the criterion's default, `pipeline.GRADIENT_COSTS`).
      splats, splat_config: a splat source's splats and renderer settings (None otherwise).
    """

    spec: str
    kind: str
    name: str
    train_c2w: np.ndarray
    intrinsics: Intrinsics
    render: jax.tree_util.Partial
    train_images: Optional[np.ndarray]
    train_names: Tuple[str, ...]
    room: Any = None
    truth_render: Optional[jax.tree_util.Partial] = None
    info: Dict[str, Any] = dataclasses.field(default_factory=dict)
    train_images_note: str = ""
    render_rgba: Optional[jax.tree_util.Partial] = None
    renderer_report: Optional[Any] = None
    gradient: str = "forward"
    gradient_cost: Optional[int] = None
    splats: Any = None
    splat_config: Any = None

    @property
    def n_train(self) -> int:
        return int(self.train_c2w.shape[0])


def resize_images(images: np.ndarray, width: int, height: int) -> np.ndarray:
    """Antialiased resize of float images [N, h, w, 3] to [N, height, width, 3] (identity when equal)."""
    images = np.asarray(images, np.float32)
    if images.shape[1:3] == (height, width):
        return images
    out = jax.image.resize(jnp.asarray(images), (images.shape[0], height, width, images.shape[3]), "linear",
                           antialias=True)
    return np.clip(np.asarray(out), 0.0, 1.0)


# ---------------------------------------------------------------------------------------------
# Renderers (module-level functions: the Partials built from them compile once per shape).


def _output(out, rgba: bool) -> Array:
    """rgb [P, H, W, 3], or rgba [P, H, W, 4] with the accumulated opacity as alpha."""
    return jnp.concatenate([out.rgb, out.acc[..., None]], axis=-1) if rgba else out.rgb


def _render_room(room, intrinsics: Intrinsics, render_config, c2w: Array, *, rgba: bool = False) -> Array:
    return _output(render_views(room_field, room, c2w, intrinsics, render_config), rgba)


_render_room_rgba = functools.partial(_render_room, rgba=True)


def _render_field(params, grid, intrinsics: Intrinsics, render_config, march, c2w: Array, *, field,
                  rgba: bool = False) -> Array:
    return _output(render_marched(field, params, grid, c2w, intrinsics, render_config, march).output, rgba)


def room_renderer(room, intrinsics: Intrinsics, rgba: bool = False) -> jax.tree_util.Partial:
    """The procedural room's analytic renderer as a Partial c2w [P, 4, 4] -> rgb [P, H, W, 3] (rgba: [..., 4])."""
    return jax.tree_util.Partial(_render_room_rgba if rgba else _render_room, room, intrinsics,
                                 room_render_config(room, num_samples=_ROOM_SAMPLES))


@functools.lru_cache(maxsize=None)
def _field_fn(field_config, rgba: bool = False):
    """One function object per field config, so that Partials of equal configs share compilations."""
    return functools.partial(_render_field, field=make_field(field_config), rgba=rgba)


def field_renderer(params, occupancy, config, intrinsics: Intrinsics, near: float, far: float, aabb,
                   background, rgba: bool = False) -> jax.tree_util.Partial:
    """The renderer of a trained field (`waldo_jax.render.marched`, as `waldo render`) as a Partial c2w -> rgb.

    With `rgba`, the Partial returns [P, H, W, 4]: the colour and the accumulated opacity.
    """
    params = jax.tree.map(jnp.asarray, params)
    occupancy = None if occupancy is None else jax.tree.map(jnp.asarray, occupancy)
    grid, render_config, march = render_setup(config, occupancy, near, far, np.asarray(aabb, np.float32), background)
    return jax.tree_util.Partial(_field_fn(config.field, rgba), params, grid, intrinsics, render_config, march)


# ---------------------------------------------------------------------------------------------
# Sources.


def parse_procedural(source: str, seed: Optional[int] = None) -> Optional[int]:
    """Seed of a `procedural` / `procedural:SEED` source (None if `source` is not procedural).

    `seed` (a `--seed` flag) may repeat the source's own seed, or give it for plain `procedural`.
    """
    if source != "procedural" and not source.startswith("procedural:"):
        return None
    spec = source.partition(":")[2]
    if spec:
        try:
            spec_seed = int(spec)
        except ValueError:
            raise SourceError(f"bad source {source!r}: expected procedural or procedural:SEED with an integer SEED")
        check_seed(spec_seed, f"the seed of source {source!r}")
        if seed is not None and seed != spec_seed:
            raise SourceError(f"source {source!r} and --seed {seed} disagree")
        return spec_seed
    return 0 if seed is None else seed


def procedural_source(seed: int = 0, resolution: Optional[int] = None, views: int = DEFAULT_PROCEDURAL_VIEWS,
                      scene: Optional[Scene] = None, room=None) -> Source:
    """The procedural room `seed` with `views` training views at resolution x resolution.

    `scene` and `room` (from `waldo_jax.procedural.room_scene`) skip building them again.
    """
    resolution = DEFAULT_PROCEDURAL_RESOLUTION if resolution is None else int(resolution)
    check_resolution(resolution)
    check_views(views)
    if scene is None or room is None:
        try:
            scene, room = room_scene(seed, num_views=views, resolution=resolution, num_samples=_ROOM_SAMPLES)
        except ValueError as e:
            raise SourceError(str(e)) from None
    intrinsics = scene.intrinsics
    images = scene.images
    if (scene.width, scene.height) != (resolution, resolution):
        intrinsics = scene.intrinsics.with_max_side(resolution)
        images = resize_images(images, intrinsics.width, intrinsics.height)
    return Source(spec=f"procedural:{seed}", kind="procedural", name=f"procedural:{seed}",
                  train_c2w=np.asarray(scene.c2w, np.float32), intrinsics=intrinsics,
                  render=room_renderer(room, intrinsics), render_rgba=room_renderer(room, intrinsics, rgba=True),
                  train_images=np.asarray(images, np.float32),
                  train_names=tuple(scene.file_names), room=room,
                  info={"procedural_seed": int(seed), "views": int(views)})


def _run_train_images(record, intrinsics: Intrinsics) -> Tuple[Optional[np.ndarray], str]:
    """The run's training images from its scene folder at `intrinsics`' size, or (None, why)."""
    if not record.path or not Path(record.path).exists():
        return None, f"the training scene {record.path or '(unnamed)'} is not on this machine"
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", UserWarning)  # skipped frames were reported at training time
            scene = load_scene(record.path, downscale=record.metadata.get("downscale"), split=record.split or None)
    except WaldoError as e:
        return None, f"cannot read the training scene again ({e})"
    by_name = {name: i for i, name in enumerate(scene.file_names)}
    missing = [name for name in record.file_names if name not in by_name]
    if missing:
        return None, f"{record.path} no longer has the training image {missing[0]!r}"
    images = scene.images[[by_name[name] for name in record.file_names]]
    return resize_images(images, intrinsics.width, intrinsics.height), ""


def run_source(run_dir: str, resolution: Optional[int] = None) -> Source:
    """A trained run directory (`waldo train` / `waldo demo` output) as a Source.

    Args:
      run_dir: the folder holding `checkpoint.ckpt`.
      resolution: longer side of the renders in pixels (default: the training images' size).
    """
    run = Path(run_dir)
    if not run.is_dir():
        raise SourceError(f"SOURCE {run_dir!r} is neither procedural[:SEED], an existing run directory nor a splat "
                          "scene (a .ply or a 3DGS model folder)")
    checkpoint = load_checkpoint(run)
    record = checkpoint.scene
    intrinsics = record.intrinsics
    if resolution is not None:
        check_resolution(resolution)
        intrinsics = intrinsics.with_max_side(int(resolution))
    background = record.background if record.background is not None else np.zeros(3, np.float32)
    renderer_args = (checkpoint.params, checkpoint.occupancy, checkpoint.config, intrinsics, record.near, record.far,
                     record.aabb, background)
    render, render_rgba = field_renderer(*renderer_args), field_renderer(*renderer_args, rgba=True)
    info = {"run_dir": str(run.resolve()), "scene_path": record.path, "scene_format": record.format,
            "psnr_test": checkpoint.info.get("psnr_test"), "train_steps": checkpoint.info.get("steps")}
    if "scale" in record.metadata and "offset" in record.metadata:  # instant-ngp's frame, for its camera paths
        info["ngp_scale"], info["ngp_offset"] = record.metadata["scale"], record.metadata["offset"]
    room, truth = None, None
    if record.format == "procedural":
        seed = int(record.metadata.get("seed", 0))
        room = make_room(seed)
        truth = room_renderer(room, intrinsics)
        info["procedural_seed"] = seed
        # The room's training images are its analytic renders: make them again at this size.
        images = np.asarray(truth(jnp.asarray(record.c2w)), np.float32)
        note = ""
    else:
        images, note = _run_train_images(record, intrinsics)
    return Source(spec=str(run_dir), kind="run", name=run.resolve().name, train_c2w=np.asarray(record.c2w, np.float32),
                  intrinsics=intrinsics, render=render, render_rgba=render_rgba, train_images=images,
                  train_names=tuple(record.file_names),
                  room=room, truth_render=truth, info=info, train_images_note=note)


def check_views(views) -> int:
    """`views` if it is a number of procedural training views in [1, MAX_PROCEDURAL_VIEWS], else a `SourceError`."""
    if isinstance(views, bool) or not isinstance(views, int) or not 1 <= views <= MAX_PROCEDURAL_VIEWS:
        raise SourceError(f"--views must be an integer between 1 and {MAX_PROCEDURAL_VIEWS}, got {views!r}")
    return views
