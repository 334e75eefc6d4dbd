"""What a search explores: a `Source` = training views + a batched renderer, from a SOURCE string.

SOURCE is what `waldo explore` and `waldo render` accept:
  * `procedural` or `procedural:SEED`: the procedural Waldo room (`waldo_jax.procedural`), rendered
    by its analytic field; its training views are the room's training cameras rendered by that
    same field (they are the "real images" of this scene);
  * a run directory of `waldo train` (or of `waldo demo`): the trained hash-grid field renders, and
    the training images are read again from the scene folder the checkpoint names (their file
    names are in the checkpoint). A run trained on the procedural room keeps the room, so its
    oracles (`waldo_oracle`) still apply and renders can be compared with the analytic truth.

Every scene gives one renderer, `renderer(c2w [P, 4, 4], intrinsics) -> Views` (colour and
accumulated opacity as rgba [P, H, W, 4], with the poses and the camera): the `Views` every criterion
takes (`waldo_jax.criteria.Views`). It is a `jax.tree_util.Partial` whose arrays (the room, the
field's parameters, the occupancy grid, the splats) are traced arguments, so it can be called inside
the search's jit and compiles once per image size.
"""

from __future__ import annotations

import dataclasses
import functools
import os
import re
import warnings
from pathlib import Path
from typing import Any, Callable, Dict, Optional, Tuple

import jax
import jax.numpy as jnp
import numpy as np

from waldo_jax.criteria.base import Views, rendered_views
from waldo_jax.errors import WaldoError, check_memory, check_resolution, check_seed
from waldo_jax.nerf.checkpoint import load_checkpoint
from waldo_jax.nerf.field import make_field
from waldo_jax.nerf.trained import TrainedField, render_setup
from waldo_jax.procedural import room_field, room_from_metadata, room_render_config, room_scene
from waldo_jax.render import render_views
from waldo_jax.render.marched import render_marched
from waldo_jax.scenes import load_scene
from waldo_jax.scenes.tool_frames import NgpFrame, nerfstudio_applied, ngp_frame
from waldo_jax.scenes.common import read_json
from waldo_jax.types import Array, Intrinsics, Scene

__all__ = [
    "Source",
    "SourceError",
    "procedural_source",
    "run_source",
    "resize_images",
    "render_in",
    "parse_procedural",
    "room_renderer",
    "field_renderer",
    "DEFAULT_PROCEDURAL_RESOLUTION",
    "DEFAULT_PROCEDURAL_VIEWS",
    "MAX_PROCEDURAL_VIEWS",
    "NERF_GRADIENT",
    "NERF_GRADIENT_COST",
    "check_views",
    "export_info",
    "source_world",
    "warn_other_world",
]

DEFAULT_PROCEDURAL_RESOLUTION = 64
DEFAULT_PROCEDURAL_VIEWS = 24
MAX_PROCEDURAL_VIEWS = 1000  # the paper's high budget in images: more training views than that are surely a typo
_ROOM_SAMPLES = 128


class SourceError(WaldoError, ValueError):
    """A SOURCE that cannot be opened (the message names it and says why)."""


def source_world(source: "Source") -> Optional[str]:
    """The world a SOURCE's poses are in, as waldo's path and poses files record it (`source_world`, read
    back by `scenes.camera_paths.recorded_world`).

    "procedural:N" for the room of seed N and for a NeRF trained on it. For another NeRF run, and for
    splats waldo fitted (their train.json), the scene they were trained on: its folder as an absolute path
    with links followed, so that the runs and fits of one scene share it. For other splats, their file.
    None where it is not known: no recorded scene, a relative one (recorded by an older waldo: relative to
    a folder no longer known), or one that cannot be resolved (a link loop).

    Args:
      source: a loaded `Source` (its `kind` and `info` are read).

    Returns:
      The world's name, or None.
    """
    seed = source.info.get("procedural_seed")
    if seed is not None:
        return f"procedural:{int(seed)}"
    scene = source.info.get("scene_path") or source.info.get("fit_scene_path")
    where = scene or (source.info.get("splat_file") if source.kind == "splats" else None)
    if not isinstance(where, str) or not os.path.isabs(where):
        return None
    try:
        path = Path(where).resolve()
        # A scene given by its file (transforms.json, poses_bounds.npy) is its folder, here or not.
        scene_file = path.is_file() or (not path.exists() and path.suffix.lower() in (".json", ".npy"))
        return str(path.parent if scene and scene_file else path)
    except (OSError, RuntimeError, ValueError):  # a link loop, a NUL in the name
        return None


def warn_other_world(what: str, recorded: Optional[str], world: Optional[str], name: str) -> None:
    """One warning line when the poses `what` names (a flag and its file) were found in the world `recorded`
    and are used in `world` (the SOURCE `name`'s, `source_world`): the same numbers place the cameras
    elsewhere. Nothing where either world is not known, or where the recorded one is a folder or file that
    is not on this machine (a file from another machine, a scene moved since: no telling)."""
    if recorded is None or world is None or recorded == world:
        return
    if not recorded.startswith("procedural:") and not os.path.exists(recorded):
        return
    used = world if world == name else f"{world} ({name})"
    warnings.warn(
        f"{what} was written for {recorded}, not for {used}: its poses place the cameras in another scene's world",
        stacklevel=3,
    )


@dataclasses.dataclass(frozen=True, eq=False)
class Source:
    """A scene to explore.

    Attributes:
      spec: the SOURCE string it came from.
      kind: "procedural", "run" (a NeRF of `waldo train`) or "splats" (`pipeline.splat_sources`).
      name: a short name for reports ("procedural:0", the run folder's name).
      train_c2w: float32 [N, 4, 4] training poses (OpenGL camera-to-world).
      intrinsics: the camera of every render of the search (its width/height set the image size).
      renderer: the scene's one renderer, (c2w [P, 4, 4], intrinsics) -> `Views` whose rgba float32
        [P, H, W, 4] in [0, 1] holds the colour and the accumulated opacity (a `jax.tree_util.Partial`).
      train_images: float32 [N, H, W, 3] the real training images at `intrinsics`' size, or None
        when they cannot be read (then `train_images_note` says why).
      train_names: the N training images' file names.
      room: the procedural `WaldoRoom`, or None.
      truth: for a NeRF of the procedural room, the analytic room's renderer (same signature as
        `renderer`); None otherwise.
      info: facts for results files (seed, run directory, held-out PSNR of the run, ...).
      train_images_note: why `train_images` is None ("" otherwise).
      renderer_report: c2w [V, 4, 4] of every view a run rendered -> facts for results.json (what
        the renderer dropped, ...), or None.
      gradient: how a `+refine` method differentiates a render: "forward" (`jax.jvp`, six tangents) or
        "reverse" (`jax.vjp`: the splat renderer, and the marched NeRF renderer's own backward pass).
      gradient_cost: renders one gradient evaluation through this source's renderer counts as (None:
        the criterion's default, `pipeline.GRADIENT_COSTS`).
      sized_renderer: (c2w [P, 4, 4], intrinsics) -> (a renderer whose capacities are sized to those
        very poses, a line saying what was sized): a splat scene's pairs, so that no view drops a
        splat (`waldo render`); None where `renderer` has no capacity to size.
    """

    spec: str
    kind: str
    name: str
    train_c2w: np.ndarray
    intrinsics: Intrinsics
    renderer: jax.tree_util.Partial
    train_images: Optional[np.ndarray]
    train_names: Tuple[str, ...]
    room: Any = None
    truth: Optional[jax.tree_util.Partial] = None
    info: Dict[str, Any] = dataclasses.field(default_factory=dict)
    train_images_note: str = ""
    renderer_report: Optional[Any] = None
    gradient: str = "forward"
    gradient_cost: Optional[int] = None
    sized_renderer: Optional[Callable[[np.ndarray, Intrinsics], Tuple[jax.tree_util.Partial, str]]] = None

    @property
    def n_train(self) -> int:
        return int(self.train_c2w.shape[0])

    def views(self, c2w, intrinsics: Optional[Intrinsics] = None) -> Views:
        """The `Views` of cameras c2w [P, 4, 4] (at `intrinsics`, default the source's own)."""
        return self.renderer(jnp.asarray(c2w, jnp.float32), self.intrinsics if intrinsics is None else intrinsics)

    def render(self, c2w, intrinsics: Optional[Intrinsics] = None) -> Array:
        """rgb float32 [P, H, W, 3] of cameras c2w [P, 4, 4] (at `intrinsics`, default the source's own)."""
        return _rgb(self.views(c2w, intrinsics))

    def render_truth(self, c2w, intrinsics: Optional[Intrinsics] = None) -> Array:
        """rgb [P, H, W, 3] of the analytic truth (`truth`) at cameras c2w [P, 4, 4].

        Raises:
          WaldoError: the source has no truth (only a NeRF of the procedural room has one).
        """
        if self.truth is None:
            raise WaldoError(f"{self.spec} has no analytic truth to render (a NeRF of the procedural room has)")
        intrinsics = self.intrinsics if intrinsics is None else intrinsics
        return _rgb(self.truth(jnp.asarray(c2w, jnp.float32), intrinsics))


def _rgb(views: Views) -> Array:
    return views.rgba[..., :3]


def render_in(render: Callable, c2w, count: int) -> np.ndarray:
    """`render(c2w)` [P, H, W, 3] (e.g. `Source.render`) in calls of `count` poses (the last padded by
    repeating a pose), so that any number of views renders with the program already compiled for `count`."""
    c2w = np.asarray(c2w, np.float32)
    total = c2w.shape[0]
    if total == 0:
        raise ValueError("render_in needs at least one pose")
    padded = np.concatenate([c2w, np.repeat(c2w[-1:], (-total) % count, axis=0)])
    parts = [np.asarray(render(jnp.asarray(padded[i : i + count]))) for i in range(0, len(padded), count)]
    return np.concatenate(parts)[:total]


def resize_images(images: np.ndarray, width: int, height: int) -> np.ndarray:
    """Antialiased resize of float images [N, h, w, 3] to [N, height, width, 3] (identity when equal)."""
    images = np.asarray(images, np.float32)
    if images.shape[1:3] == (height, width):
        return images
    out = jax.image.resize(
        jnp.asarray(images), (images.shape[0], height, width, images.shape[3]), "linear", antialias=True
    )
    return np.clip(np.asarray(out), 0.0, 1.0)


# ---------------------------------------------------------------------------------------------
# Renderers (module-level functions: the Partials built from them compile once per shape).


def _room_views(room, render_config, c2w: Array, intrinsics: Intrinsics) -> Views:
    out = render_views(room_field, room, c2w, intrinsics, render_config)
    return rendered_views(out.rgb, out.acc, c2w, intrinsics)


def _field_views(params, setup, c2w: Array, intrinsics: Intrinsics, *, field, gradient: str = "forward") -> Views:
    out = render_marched(field, params, setup, c2w, intrinsics, gradient=gradient).output
    return rendered_views(out.rgb, out.acc, c2w, intrinsics)


def room_renderer(room, num_samples: int = _ROOM_SAMPLES) -> jax.tree_util.Partial:
    """The procedural room's analytic renderer, (c2w [P, 4, 4], intrinsics) -> `Views` (a Partial)."""
    return jax.tree_util.Partial(_room_views, room, room_render_config(room, num_samples=num_samples))


@functools.lru_cache(maxsize=None)
def _field_fn(field_config, gradient: str = "forward"):
    """One function object per field config, so that Partials of equal configs share compilations."""
    return functools.partial(_field_views, field=make_field(field_config), gradient=gradient)


# How a `+refine` method differentiates a trained field's renders (`Source.gradient`): reverse mode through
# the marched renderer's own backward pass (`render.marched_vjp`), one pass over the composited samples.
NERF_GRADIENT = "reverse"
# Renders one refinement gradient of a NeRF source counts as (`Source.gradient_cost`): the ratio of a
# reverse-mode gradient's time to a render and exact score's, rounded up: 2.36-2.55 for saliency on the
# fox NeRF at 64 px (4 poses) on the 2-core CPU, against 3.12-3.76 for the code before, alternately in one session
# (benchmarks/gradient_cost.py; benchmarks/results/gradient_cost_fox_ab_cpu.json). What made it cheaper:
# the hash grid's derivative with respect to the point by a rule (`nerf.hashgrid.encode`) and CSNet's
# reverse mode through the same taps as its forward (`criteria.csnet.model`); the render's gradient is
# now about 2 renders (the render, then a pass that evaluates the field again and pulls back through it)
# and CSNet's about 0.7.
NERF_GRADIENT_COST = 3


def field_renderer(field: TrainedField, gradient: str = "forward") -> jax.tree_util.Partial:
    """The renderer of a trained field (`waldo_jax.render.marched`), (c2w [P, 4, 4], intrinsics) ->
    `Views` (a Partial).

    `field`: the trained field and its near, far, background and box (`nerf.trained.TrainedField`).
    `gradient`: how its images differentiate with respect to c2w, "forward" (`jax.jvp`) or "reverse"
    (`jax.vjp`) (`render.marched.render_marched`); the images are the same.
    """
    params = jax.tree.map(jnp.asarray, field.params)
    occupancy = None if field.occupancy is None else jax.tree.map(jnp.asarray, field.occupancy)
    setup = render_setup(field.replace(params=params, occupancy=occupancy))
    return jax.tree_util.Partial(_field_fn(field.config.field, gradient), params, setup)


def with_gradient(source: "Source", gradient: str) -> "Source":
    """`source` with its trained-field renderer differentiating in `gradient` mode ("forward" or
    "reverse"; the images are the same), e.g. to compare the two, with the gradient cost of that mode.
    Other sources are returned as they are."""
    renderer = source.renderer
    if getattr(renderer.func, "func", None) is not _field_views:
        return source
    cost = NERF_GRADIENT_COST if gradient == NERF_GRADIENT else None  # None: the default, `GRADIENT_COSTS`
    rebuilt = jax.tree_util.Partial(functools.partial(renderer.func, gradient=gradient), *renderer.args)
    return dataclasses.replace(source, renderer=rebuilt, gradient=gradient, gradient_cost=cost)


# ---------------------------------------------------------------------------------------------
# Sources.


def parse_procedural(source: str, seed: Optional[int] = None) -> Optional[int]:
    """Seed of a `procedural` / `procedural:SEED` source (None if `source` is not procedural).

    `seed` (a `--seed` flag) may repeat the source's own seed, or give it for plain `procedural`.
    """
    if source != "procedural" and not source.startswith("procedural:"):
        return None
    colon, spec = source.partition(":")[1:]
    if colon:
        # ASCII digits only: int() also took "", " 1", "+1", "1_0" and Arabic-Indic digits as seeds.
        if not re.fullmatch(r"[0-9]+", spec):
            raise SourceError(
                f"bad source {source!r}: expected procedural or procedural:SEED with SEED a whole number in digits"
            )
        spec_seed = int(spec)
        check_seed(spec_seed, f"the seed of source {source!r}")
        if seed is not None and seed != spec_seed:
            raise SourceError(f"source {source!r} and --seed {seed} disagree")
        return spec_seed
    return 0 if seed is None else seed


# The default longer side of a NeRF run's renders (its training images' size when smaller), as a splat
# scene's (`splat_sources.SPLAT_RESOLUTION`): a search renders hundreds of views, and at the fox's
# 1080x1920 one view costs 2M rays (about 9 minutes at the training step on the 2-core CPU, at the
# 3,900 rays/s measured there; half that at x2), and its epoch would not fit in 24 GiB; `--resolution`
# sets another.
RUN_RESOLUTION = 256


# Bytes a training view of the room holds per pixel while it is made: float32 rgb, depth and opacity
# rendered, and the rgb image kept.
_ROOM_VIEW_BYTES_PER_PIXEL = 32


def procedural_source(
    seed: int = 0,
    resolution: Optional[int] = None,
    views: int = DEFAULT_PROCEDURAL_VIEWS,
    scene: Optional[Scene] = None,
    room=None,
    check: Optional[Callable[[int, int, int], None]] = None,
) -> Source:
    """The procedural room `seed` with `views` training views at resolution x resolution.

    `scene` and `room` (from `waldo_jax.procedural.room_scene`) skip building them again; `check` is
    `load_source`'s, called before the training views are rendered.
    """
    resolution = DEFAULT_PROCEDURAL_RESOLUTION if resolution is None else int(resolution)
    check_resolution(resolution)
    check_views(views)
    if check is not None:
        check(resolution, resolution, views)
    # Then the training views' render (rgb, depth and opacity) and their images, before the room renders them.
    check_memory(
        views * resolution * resolution * _ROOM_VIEW_BYTES_PER_PIXEL,
        f"--views {views} at --resolution {resolution} (the room's training views)",
        "use fewer --views or a smaller --resolution",
    )

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
    return Source(
        spec=f"procedural:{seed}",
        kind="procedural",
        name=f"procedural:{seed}",
        train_c2w=np.asarray(scene.c2w, np.float32),
        intrinsics=intrinsics,
        renderer=room_renderer(room),
        train_images=np.asarray(images, np.float32),
        train_names=tuple(scene.file_names),
        room=room,
        info={"procedural_seed": int(seed), "views": int(views), **export_info("procedural", {}, scene.aabb, "")},
    )


def export_info(fmt: str, metadata: Dict[str, Any], aabb, folder: str) -> Dict[str, Any]:
    """What `waldo path`'s exports need of a training scene, as `Source.info` keys.

    `ngp_scale`, `ngp_offset`, `ngp_from_mitsuba`: the frame NGP's loader makes of the scene's
    transforms.json (the room's, as `waldo render procedural` writes it, has the room's `aabb`).
    `nerfstudio_applied_transform` / `_scale` / `_source`: what a nerfstudio model folds into its
    dataparser_transforms.json; source "unknown" for a checkpoint saved before waldo recorded it
    whose scene file is gone. Older instant-ngp checkpoints re-read their scene file when it is there.
    """
    scene_file = Path(folder) / str(metadata.get("scene_file", "transforms.json")) if folder else None
    meta = None
    needs_file = fmt in ("instant-ngp", "nerfstudio") and (
        "nerfstudio_applied" not in metadata or (fmt == "instant-ngp" and "from_mitsuba" not in metadata)
    )
    if needs_file and scene_file is not None and scene_file.is_file():
        try:
            meta = read_json(scene_file)
        except WaldoError:
            meta = None
    ngp = NgpFrame()
    if fmt == "procedural":
        ngp = ngp_frame({"aabb": np.asarray(aabb, np.float64).tolist()})
    elif fmt == "instant-ngp" and meta is not None and "from_mitsuba" not in metadata:
        try:
            ngp = ngp_frame(meta)
        except ValueError:
            pass
    elif fmt == "instant-ngp" and "scale" in metadata and "offset" in metadata:
        ngp = NgpFrame.create(float(metadata["scale"]), metadata["offset"], bool(metadata.get("from_mitsuba", False)))
    info: Dict[str, Any] = {
        "ngp_scale": ngp.scale,
        "ngp_offset": list(ngp.offset),
        "ngp_from_mitsuba": ngp.from_mitsuba,
    }
    applied, scale, source = None, 1.0, "none"
    if "nerfstudio_applied" in metadata:
        recorded = metadata["nerfstudio_applied"]
        applied, scale, source = recorded.get("transform"), float(recorded.get("scale", 1.0)), recorded.get("source")
    elif fmt in ("instant-ngp", "nerfstudio"):
        source = "unknown"
        if meta is not None:
            try:
                found, scale, source = nerfstudio_applied(meta, scene_file.parent)
                applied = None if found is None else found.tolist()
            except ValueError:
                source = "unknown"
    info.update(nerfstudio_applied_transform=applied, nerfstudio_applied_scale=scale, nerfstudio_applied_source=source)
    return info


def _run_train_images(record, intrinsics: Intrinsics) -> Tuple[Optional[np.ndarray], str]:
    """The run's training images from its scene folder at `intrinsics`' size, or (None, why)."""
    if not record.path or not Path(record.path).exists():
        return None, f"the training scene {record.path or '(unnamed)'} is not on this machine"
    if not Path(record.path).is_absolute():  # a run saved before the path was recorded whole
        warnings.warn(
            f"the run records its training scene by the relative path {record.path!r}; reading it from the "
            f"current folder, as {Path(record.path).absolute()}",
            stacklevel=2,
        )
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


def run_source(
    run_dir: str,
    resolution: Optional[int] = None,
    images: bool = True,
    check: Optional[Callable[[int, int, int], None]] = None,
) -> Source:
    """A trained run directory (`waldo train` / `waldo demo` output) as a Source.

    Args:
      run_dir: the folder holding `checkpoint.ckpt`.
      resolution: longer side of the renders in pixels (default: the training images' size, at most
        `RUN_RESOLUTION`).
      images: read (or, for the procedural room, render) the training images; False leaves them None.
      check: `load_source`'s, called with the renders' size before any image is read or rendered.
    """
    run = Path(run_dir)
    if not run.is_dir():
        raise SourceError(
            f"SOURCE {run_dir!r} is neither procedural[:SEED], an existing run directory nor a splat "
            "scene (a .ply or a 3DGS model folder)"
        )
    checkpoint = load_checkpoint(run)
    record = checkpoint.scene
    intrinsics = record.intrinsics
    if resolution is not None:
        check_resolution(resolution)
        intrinsics = intrinsics.with_max_side(int(resolution))
    elif max(intrinsics.width, intrinsics.height) > RUN_RESOLUTION:
        intrinsics = intrinsics.with_max_side(RUN_RESOLUTION)
    if check is not None:
        check(intrinsics.width, intrinsics.height, len(record.c2w))
    field = TrainedField.from_checkpoint(checkpoint)
    info = {
        "run_dir": str(run.resolve()),
        "scene_path": record.path,
        "scene_format": record.format,
        "psnr_test": checkpoint.info.get("psnr_test"),
        "train_steps": checkpoint.info.get("steps"),
    }
    info.update(export_info(record.format, record.metadata, record.aabb, record.path))
    if field.occupancy is not None and not bool(np.any(np.asarray(field.occupancy.bitfield))):
        info["degenerate"] = "the occupancy grid is empty: every render is the background alone"
        warnings.warn(
            f"{run_dir}: the run's occupancy grid marks no cell occupied, so every render is the background "
            "alone (the field learned no density above the grid's threshold); train it again",
            stacklevel=2,
        )
    room, truth = None, None
    if record.format == "procedural":
        seed = int(record.metadata.get("seed", 0))
        room = room_from_metadata(record.metadata)  # the demo's room has a larger Waldo than make_room(seed)
        truth = room_renderer(room)
        info["procedural_seed"] = seed
    if not images:
        images, note = None, "not loaded (images=False)"
    elif truth is not None:  # the room's training images are its analytic renders: made again at this size
        images, note = np.asarray(_rgb(truth(jnp.asarray(record.c2w, jnp.float32), intrinsics)), np.float32), ""
    else:
        images, note = _run_train_images(record, intrinsics)
    return Source(
        spec=str(run_dir),
        kind="run",
        name=run.resolve().name,
        train_c2w=np.asarray(record.c2w, np.float32),
        intrinsics=intrinsics,
        renderer=field_renderer(field, gradient=NERF_GRADIENT),
        train_images=images,
        train_names=tuple(record.file_names),
        room=room,
        truth=truth,
        info=info,
        train_images_note=note,
        gradient=NERF_GRADIENT,
        gradient_cost=NERF_GRADIENT_COST,
    )


def check_views(views) -> int:
    """`views` if it is a number of procedural training views in [1, MAX_PROCEDURAL_VIEWS], else a `SourceError`."""
    if isinstance(views, bool) or not isinstance(views, int) or not 1 <= views <= MAX_PROCEDURAL_VIEWS:
        raise SourceError(f"--views must be an integer between 1 and {MAX_PROCEDURAL_VIEWS}, got {views!r}")
    return views
