"""A NeRF run (`waldo train` / `waldo demo` output) as a point cloud of its density, for `waldo view`.

Candidates are the centres of a G x G x G grid over the occupancy grid's base box (cascade 0, where the
training cameras look), jittered inside their cells by a fixed key; those in occupied cells are evaluated by
the trained field. A point is kept where one cell's length of its density is opaque enough,
alpha = 1 - exp(-sigma * cell) >= `min_alpha`; if more than `count` are kept, an evenly spaced subset of them
(deterministic). Colours are the field's RGB seen from the training cameras' centre. Names: sigma (density,
per world unit), alpha (opacity of one cell).

Why these numbers (docs/viewer.md has the pictures): on the CPU-trained fox, cells of a 96^3 grid over the
field's whole box at alpha >= 0.5 keep about 3,000 points, a sparse lattice of floaters around the fox; this
grid over the occupied box at 0.2 keeps about 30,000 that draw its shape, in a third of the time.
"""

from __future__ import annotations

import math
from typing import Tuple

import numpy as np

__all__ = ["DENSITY_GRID", "MAX_POINTS", "MIN_ALPHA", "density_note", "nerf_points"]

DENSITY_GRID = 64  # cells per axis of the candidate grid (262k candidates before the occupancy test)
# A kept point's cell is at least 20 % opaque: the CPU-trained fox (runs/fox_nerf) keeps 30k of its 182k
# occupied cells at 0.2, 180 at 0.5 (its field is a thin fog around the fox).
MIN_ALPHA = 0.2
MAX_POINTS = 60_000
_CHUNK = 65_536  # points per field call


def _candidates(grid, resolution: int, seed: int) -> np.ndarray:
    """Jittered cell centres [G**3, 3] of a G-grid over the occupancy grid's base box, in occupied cells only."""
    import jax
    import jax.numpy as jnp

    from waldo_jax.render.occupancy import is_occupied

    low, high = (np.asarray(b, np.float64) for b in grid.base_aabb)
    ticks = (np.arange(resolution) + 0.5) / resolution
    u = np.stack(np.meshgrid(ticks, ticks, ticks, indexing="ij"), -1).reshape(-1, 3)  # [G**3, 3] in (0, 1)
    jitter = np.asarray(jax.random.uniform(jax.random.key(seed), u.shape, minval=-0.5, maxval=0.5))
    xyz = (low + (u + jitter / resolution) * (high - low)).astype(np.float32)
    grid = jax.tree_util.tree_map(jnp.asarray, grid)  # a checkpoint's arrays are NumPy
    occupied = np.asarray(jax.jit(jax.vmap(lambda x: is_occupied(grid, x)))(jnp.asarray(xyz)))
    return xyz[occupied]


def nerf_points(
    checkpoint, count: int = MAX_POINTS, resolution: int = DENSITY_GRID, min_alpha=None, seed: int = 0
) -> Tuple[np.ndarray, np.ndarray]:
    """The dense parts of a trained field as points: (xyz float32 [P, 3], rgb float32 [P, 3] in [0, 1]), P <= count.

    Args:
      checkpoint: a loaded `waldo_jax.nerf.checkpoint.Checkpoint` (params, occupancy, config, scene).
      count: the most points returned (an evenly spaced subset of the kept ones beyond it).
      resolution: G, cells per axis of the candidate grid over the occupancy grid's base box.
      min_alpha: the opacity of one cell's length a point's density must reach (None: `MIN_ALPHA`, read at call
        time).
      seed: the key of the jitter inside the cells (same seed, same points).
    """
    import jax
    import jax.numpy as jnp

    from waldo_jax.nerf.field import make_field_batch
    from waldo_jax.nerf.samplers import make_sampler

    min_alpha = MIN_ALPHA if min_alpha is None else float(min_alpha)
    config = checkpoint.config
    grid = make_sampler(config).view_grid(checkpoint.occupancy)
    xyz = _candidates(grid, int(resolution), seed)
    if len(xyz) == 0:
        return np.zeros((0, 3), np.float32), np.zeros((0, 3), np.float32)
    eye = np.mean(np.asarray(checkpoint.scene.c2w, np.float64)[:, :3, 3], axis=0).astype(np.float32)
    field = jax.jit(make_field_batch(config.field))
    params = jax.tree_util.tree_map(jnp.asarray, checkpoint.params)
    sigma, rgb = [], []
    padded = np.concatenate([xyz, np.repeat(xyz[-1:], (-len(xyz)) % _CHUNK, axis=0)])
    for start in range(0, len(padded), _CHUNK):
        part = padded[start : start + _CHUNK]
        s, c = field(params, jnp.asarray(part), jnp.asarray(part - eye))
        sigma.append(np.asarray(s))
        rgb.append(np.asarray(c))
    sigma_all = np.concatenate(sigma)[: len(xyz)]
    rgb_all = np.concatenate(rgb)[: len(xyz)]
    cell = float(np.max(np.asarray(grid.base_aabb[1]) - np.asarray(grid.base_aabb[0]))) / resolution
    alpha = 1.0 - np.exp(-np.nan_to_num(sigma_all, nan=0.0) * cell)
    keep = np.flatnonzero(alpha >= min_alpha)
    if len(keep) > count:
        keep = keep[np.linspace(0, len(keep) - 1, count).round().astype(np.int64)]
    return xyz[keep], np.clip(rgb_all[keep], 0.0, 1.0).astype(np.float32)


def density_note(points: np.ndarray) -> str:
    """One line on what a NeRF's point cloud is."""
    share = math.floor(MIN_ALPHA * 100)
    if not len(points):
        return f"the NeRF is not drawn: no cell of its occupied box is >= {share} % opaque"
    return (
        f"the NeRF is drawn as {len(points):,} points of its density: where a 1/{DENSITY_GRID} cell of its "
        f"occupied box is >= {share} % opaque"
    )
