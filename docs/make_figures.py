"""Regenerates the README's pictures of the procedural Waldo room (CPU, about a minute).

python docs/make_figures.py
"""

from pathlib import Path

import waldo_jax  # noqa: F401  (XLA flags first)
import jax
import jax.numpy as jnp
import numpy as np

from waldo_jax.cameras import look_at
from waldo_jax.io import contact_sheet, save_png
from waldo_jax.procedural import room_field, room_render_config, room_scene, waldo_visibility_batch
from waldo_jax.render import render_views

OUT = Path(__file__).resolve().parent / "images"


def main():
    OUT.mkdir(exist_ok=True)
    scene, room = room_scene(0, num_views=12, resolution=96)
    train_vis = np.asarray(waldo_visibility_batch(room, jnp.asarray(scene.c2w), scene.intrinsics))
    save_png(
        OUT / "procedural_room_training_views.png",
        contact_sheet(list(scene.images), columns=6, labels=[f"train {v:.0%}" for v in train_vis]),
    )
    # 2000 random poses within the training cameras' bounds, looking near Waldo; the four best.
    k_o, k_t = jax.random.split(jax.random.key(0))
    origins = scene.c2w[:, :3, 3]
    o = jax.random.uniform(k_o, (2000, 3), minval=origins.min(0), maxval=origins.max(0))
    t = room.waldo_center + 0.3 * jax.random.normal(k_t, (2000, 3))
    c2w = jax.vmap(look_at, in_axes=(0, 0, None))(o, t, jnp.array([0.0, 1.0, 0.0]))
    vis = np.asarray(waldo_visibility_batch(room, c2w, scene.intrinsics))
    best = np.argsort(-vis)[:6]
    images = np.asarray(render_views(room_field, room, c2w[best], scene.intrinsics, room_render_config(room)).rgb)
    order = np.argsort(-train_vis)[:6]
    save_png(
        OUT / "procedural_room_best_vs_train.png",
        contact_sheet(
            list(scene.images[order]) + list(images),
            columns=6,
            labels=[f"train {v:.0%}" for v in train_vis[order]] + [f"random {v:.0%}" for v in vis[best]],
        ),
    )
    print(f"best training visibility {train_vis.max():.3f}; best of 2000 random poses {vis.max():.3f}")


if __name__ == "__main__":
    main()
