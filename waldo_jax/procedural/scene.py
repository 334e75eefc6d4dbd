"""The room as a scene: its render config, its training views and held-out test views rendered as `Scene`s."""

from __future__ import annotations

import dataclasses
from typing import Optional, Tuple

import jax
import jax.numpy as jnp
import numpy as np

from waldo_jax.cameras import look_at, project_points
from waldo_jax.procedural.cameras import RoomCameraConfig, training_cameras
from waldo_jax.procedural.visibility import waldo_visibility_batch
from waldo_jax.procedural.room import BACKGROUND, WaldoRoom, make_room, room_field, waldo_field
from waldo_jax.render import RenderConfig, render_views
from waldo_jax.types import Intrinsics, Scene

__all__ = ["room_render_config", "room_scene", "held_out_scene", "waldo_mask", "waldo_reference"]


def room_render_config(room: WaldoRoom, num_samples: int = 128, **kwargs):
    """A `RenderConfig` suited to the room: its box, near 0.05, far 12 and the sky background."""
    return RenderConfig.create(
        near=0.05, far=12.0, aabb=room.aabb, background=BACKGROUND, num_samples=num_samples, **kwargs
    )


def room_scene(
    seed: int = 0,
    num_views: int = 24,
    resolution: int = 64,
    num_samples: int = 128,
    camera_config: RoomCameraConfig = RoomCameraConfig(),
    room: Optional[WaldoRoom] = None,
) -> Tuple[Scene, WaldoRoom]:
    """The room's training views as a `Scene`, rendered with `waldo_jax.render.render_views`.

    Args:
      seed: seeds the room (unless `room` is given) and the cameras.
      num_views: number of training views.
      resolution: the views are resolution x resolution pixels.
      num_samples: samples per ray for the renders.
      camera_config: where the training cameras go.
      room: an already built room (else `make_room(seed)`).

    Returns:
      (scene, room).
    """
    room = make_room(seed) if room is None else room
    intrinsics = Intrinsics.from_fov(resolution, resolution, camera_config.fov_x)
    key = jax.random.fold_in(jax.random.key(seed), 1)
    c2w = training_cameras(key, room, num_views, intrinsics, camera_config)
    config = room_render_config(room, num_samples=num_samples)
    images = np.asarray(render_views(room_field, room, jnp.asarray(c2w), intrinsics, config).rgb, np.float32)
    scene = Scene(
        images=images,
        c2w=np.asarray(c2w, np.float32),
        intrinsics=intrinsics,
        aabb=room.aabb,
        near=0.05,
        far=12.0,
        file_names=tuple(f"view_{i:03d}.png" for i in range(num_views)),
        format="procedural",
        name=f"procedural:{seed}",
        split="train",
        path="",
        background=np.asarray(BACKGROUND, np.float32),
        metadata={
            "seed": int(seed),
            "num_samples": int(num_samples),
            "max_visibility": float(camera_config.max_visibility),
            "waldo_scale": float(room.waldo_scale),
            "stripe_width": float(room.stripe_width),
        },
    )
    return scene, room


def room_from_metadata(metadata: dict) -> WaldoRoom:
    """The room a procedural scene's `metadata` (as `room_scene` writes it, and a checkpoint keeps it)
    was rendered from: its seed, Waldo's size and his stripes' width (a run written before the last two
    were recorded has the default room's)."""
    waldo_scale = float(metadata.get("waldo_scale", 1.0))
    stripe_width = metadata.get("stripe_width")
    return make_room(
        int(metadata.get("seed", 0)),
        waldo_scale=waldo_scale,
        stripe_width=None if stripe_width is None else float(stripe_width),
    )


def held_out_scene(
    room: WaldoRoom, seed: int, count: int, train_scene: Scene, camera_config: RoomCameraConfig = RoomCameraConfig()
) -> Scene:
    """`count` views of the room from cameras its NeRF has not seen (another key, the training views'
    `camera_config`), rendered analytically at `train_scene`'s intrinsics: the NeRF's held-out test split.

    Of the `count` views, the covering share (`RoomCameraConfig.cover_views`) is the training views':
    `cover_views * count / train_scene.n_images`, rounded."""
    cover = min(count, round(camera_config.cover_views * count / max(train_scene.n_images, 1)))
    c2w = training_cameras(
        jax.random.fold_in(jax.random.key(seed), 2),
        room,
        count,
        train_scene.intrinsics,
        dataclasses.replace(camera_config, cover_views=cover),
    )
    images = np.asarray(
        render_views(room_field, room, jnp.asarray(c2w), train_scene.intrinsics, room_render_config(room)).rgb,
        np.float32,
    )
    return dataclasses.replace(
        train_scene,
        images=images,
        c2w=c2w,
        split="test",
        file_names=tuple(f"test_{i:03d}.png" for i in range(len(c2w))),
    )


def waldo_mask(room: WaldoRoom, c2w, intrinsics: Intrinsics, num_samples: int = 128) -> np.ndarray:
    """Waldo's pixels in views c2w [P, 4, 4]: float32 [P, H, W] in [0, 1], the share of each pixel's ray
    weight that lands on Waldo (`room.waldo_field` rendered on black, as the room's views are rendered);
    > 0.5 where the pixel shows him."""
    config = room_render_config(room, num_samples=num_samples).replace(background=jnp.zeros(3, jnp.float32))
    rendered = render_views(waldo_field, room, jnp.asarray(c2w, jnp.float32), intrinsics, config).rgb
    return np.asarray(rendered[..., 0], np.float32)


def waldo_reference(room: WaldoRoom, distance: float = 1.6, height: float = 0.5, resolution: int = 128) -> np.ndarray:
    """A reference image of Waldo (as a user would hold one): a crop of him from a close render where he is
    fully visible, float32 [h, w, 3].

    Of 120 cameras on a ring of `distance` x his size around him at `height` x his size, looking at his
    centre, the one the oracle says sees most of him renders the room at `resolution`^2 (60 degrees); the
    crop is the bounding box of his surface samples in that view.

    Raises:
      ValueError: no camera of the ring sees more than 95 % of him.
    """
    scale = float(room.waldo_scale)
    angle = jnp.linspace(0.0, 2 * jnp.pi, 120, endpoint=False)
    centre = room.waldo_center
    ring = distance * scale
    origins = jnp.stack(
        [centre[0] + ring * jnp.cos(angle), jnp.full_like(angle, height * scale), centre[2] + ring * jnp.sin(angle)], -1
    )
    c2w = jax.vmap(look_at, in_axes=(0, None, None))(origins, centre, jnp.array([0.0, 1.0, 0.0]))
    intrinsics = Intrinsics.from_fov(resolution, resolution, np.radians(60.0))
    visible = np.asarray(waldo_visibility_batch(room, c2w, intrinsics))
    best = int(np.argmax(visible))
    if visible[best] <= 0.95:
        raise ValueError(f"no camera of the ring around Waldo sees all of him (at most {visible[best]:.0%})")
    config = room_render_config(room, num_samples=128)
    image = np.asarray(render_views(room_field, room, c2w[best : best + 1], intrinsics, config).rgb[0])
    uv, _ = project_points(c2w[best], intrinsics, room.waldo_points)
    (x0, y0), (x1, y1) = np.floor(np.min(uv, 0)).astype(int), np.ceil(np.max(uv, 0)).astype(int)
    return image[max(y0, 0) : y1, max(x0, 0) : x1].astype(np.float32)
