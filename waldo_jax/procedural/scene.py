"""The room as a scene: its render config, its training views and held-out test views rendered as `Scene`s."""

from __future__ import annotations

import dataclasses
from typing import Optional, Tuple

import jax
import jax.numpy as jnp
import numpy as np

from waldo_jax.procedural.cameras import RoomCameraConfig, training_cameras
from waldo_jax.procedural.room import BACKGROUND, WaldoRoom, make_room, room_field, waldo_field
from waldo_jax.render import RenderConfig, render_views
from waldo_jax.types import Intrinsics, Scene

__all__ = ["room_render_config", "room_scene", "held_out_scene", "waldo_mask"]


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
        },
    )
    return scene, room


def held_out_scene(
    room: WaldoRoom, seed: int, count: int, train_scene: Scene, camera_config: RoomCameraConfig = RoomCameraConfig()
) -> Scene:
    """`count` views of the room from cameras its NeRF has not seen (another key, the training views'
    `camera_config`), rendered analytically at `train_scene`'s intrinsics: the NeRF's held-out test split."""
    c2w = training_cameras(
        jax.random.fold_in(jax.random.key(seed), 2), room, count, train_scene.intrinsics, camera_config
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
