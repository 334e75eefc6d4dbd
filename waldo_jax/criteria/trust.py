"""The `trust` criterion: how well the training cameras cover a view, from poses alone (no render).

A radiance field is believable where its training cameras looked from a similar distance and direction;
far from them it may render mush. For one candidate camera, `trust` casts a fixed grid of
`GRID` x `GRID` rays (cell centres of the image) to a fixed depth, the candidate's distance to the
training cameras' focus point (`waldo_jax.cameras.camera_focus`, where their axes meet), and scores the
share of those points p that at least one training camera j sees:

  * in its frame, in front of it (the training cameras are assumed to share the search camera's field
    of view: the frame test uses the intrinsics the candidate is scored with);
  * from a similar distance: |log(|p - o| / |p - o_j|)| <= log(`MAX_RATIO`) (a close-up at a third of
    the training distance asks for detail the training images never held);
  * from a similar direction: the angle between the rays o -> p and o_j -> p at most `MAX_ANGLE`.

Names: o the candidate's centre, o_j the training camera j's, p a grid point. A training camera's own
pose scores 1; a view looking away from every training camera's sight, or from much nearer, 0.
The smooth stand-in (`+refine`) replaces the three steps by sigmoids (`FRAME_SOFTNESS`,
`RATIO_SOFTNESS`, `ANGLE_SOFTNESS`). Scale free: only ratios and angles enter. Meant as a guard for
NeRF sources (`--criterion waldo_found --guard trust:0.5`). The defaults (x1.5, 30 degrees) ranked the
demo NeRF's renders best in a first sweep (`benchmarks/trust_guard.py`), weakly and not confirmed on
more views: in that room the render's PSNR hardly depends on coverage (docs/results.md, "Trust in the
renders").
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np

from waldo_jax.cameras import camera_focus, pixel_directions, project_points
from waldo_jax.criteria.base import Criterion, CriterionContext, CriterionError, CriterionSpec, register
from waldo_jax.types import Array, Intrinsics

__all__ = ["GRID", "MAX_RATIO", "MAX_ANGLE", "trust", "trust_params", "trust_scores"]

GRID = 4  # rays per image side: 16 points per view
MAX_RATIO = 1.5  # a point counts as seen from a similar distance within this ratio (either way)
MAX_ANGLE = math.radians(30.0)  # ... and from a similar direction within this angle
FRAME_SOFTNESS = 0.02  # the smooth stand-in's sigmoid widths: image fraction at the frame's border (probes 0.125 in),
RATIO_SOFTNESS = 0.05  # log distance ratio,
ANGLE_SOFTNESS = math.radians(3.0)  # radians
_MIN_DEPTH = 0.05  # the depth floor, as a fraction of the training cameras' median distance to the focus


def _step(margin: Array, width: float) -> Array:
    """1 where margin >= 0 (width 0), else a sigmoid of that width."""
    if width > 0.0:
        return jax.nn.sigmoid(margin / width)
    return (margin >= 0.0).astype(jnp.float32)


def _view_trust(params, c2w: Array, intrinsics: Intrinsics, smooth: bool) -> Array:
    """Coverage in [0, 1] of one candidate c2w [4, 4] by the training cameras (see the module docstring)."""
    train_c2w, focus, min_depth, log_max_ratio, max_angle = params  # [N, 4, 4], [3], [], [], []
    origin = c2w[:3, 3]  # [3]
    cells = (jnp.arange(GRID, dtype=jnp.float32) + 0.5) / GRID
    u = cells * intrinsics.width
    v = cells * intrinsics.height
    uu, vv = jnp.meshgrid(u, v, indexing="xy")  # [G, G]
    dirs_cam = jax.vmap(lambda a, b: pixel_directions(intrinsics, a, b))(uu.ravel(), vv.ravel())  # [G*G, 3], z = -1
    depth = jnp.maximum(jnp.linalg.norm(focus - origin), min_depth)
    points = origin + depth * (dirs_cam @ c2w[:3, :3].T)  # [G*G, 3]
    to_candidate = jnp.linalg.norm(points - origin, axis=-1)  # [G*G]
    frame_w, ratio_w, angle_w = (FRAME_SOFTNESS, RATIO_SOFTNESS, ANGLE_SOFTNESS) if smooth else (0.0, 0.0, 0.0)

    def seen_by(train: Array) -> Array:  # [G*G]: the points training camera `train` [4, 4] sees alike
        uv, z = project_points(train, intrinsics, points)  # [G*G, 2], [G*G]
        uv_unit = uv / jnp.array([intrinsics.width, intrinsics.height], jnp.float32)  # [G*G, 2]
        inside = jnp.min(jnp.concatenate([uv_unit, 1.0 - uv_unit], axis=-1), axis=-1)  # [G*G], < 0 outside
        in_frame = (z > 0.0) * _step(inside, frame_w)
        offset = points - train[:3, 3]  # [G*G, 3]
        to_train = jnp.linalg.norm(offset, axis=-1)  # [G*G]
        log_ratio = jnp.abs(jnp.log(jnp.maximum(to_candidate, 1e-9) / jnp.maximum(to_train, 1e-9)))
        cosine = jnp.sum((points - origin) * offset, axis=-1) / jnp.maximum(to_candidate * to_train, 1e-18)
        angle = jnp.arccos(jnp.clip(cosine, -1.0 + 1e-6, 1.0 - 1e-6))
        return in_frame * _step(log_max_ratio - log_ratio, ratio_w) * _step(max_angle - angle, angle_w)

    seen = jnp.max(jax.vmap(seen_by)(train_c2w), axis=0)  # [G*G]
    return jnp.mean(seen)


def trust_scores(params, c2w: Array, intrinsics: Intrinsics, smooth: bool = False) -> Array:
    """`trust` of cameras c2w [P, 4, 4]: float32 [P] in [0, 1]; params as `trust(context).params`."""
    scores = jax.vmap(lambda c: _view_trust(params, c, intrinsics, smooth))(c2w)
    return jnp.where(jnp.isfinite(scores), scores, 0.0)


def _exact(params, c2w, intrinsics):
    return trust_scores(params, c2w, intrinsics)


def _smooth(params, c2w, intrinsics):
    return trust_scores(params, c2w, intrinsics, smooth=True)


def trust_params(train_c2w: np.ndarray, max_ratio: float = MAX_RATIO, max_angle: float = MAX_ANGLE):
    """`trust`'s params: (training c2w float32 [N, 4, 4], their focus point [3], the depth floor [],
    log(max_ratio) [], max_angle [] in radians); the last two are leaves, so a sweep may vmap over them."""
    train_c2w = np.asarray(train_c2w, np.float64)
    focus = camera_focus(train_c2w)
    floor = _MIN_DEPTH * float(np.median(np.linalg.norm(train_c2w[:, :3, 3] - focus, axis=-1)))
    return (
        jnp.asarray(train_c2w, jnp.float32),
        jnp.asarray(focus, jnp.float32),
        jnp.float32(max(floor, 1e-6)),
        jnp.float32(math.log(max_ratio)),
        jnp.float32(max_angle),
    )


def trust(context: CriterionContext) -> Criterion:
    """The `trust` criterion (direction max, in [0, 1]): the share of a view's 4 x 4 probe points at the
    focus distance that a training camera saw from within x1.5 the distance and 30 degrees (module docstring)."""
    train_c2w = context.train_c2w
    if train_c2w is None or np.asarray(train_c2w).ndim != 3 or len(train_c2w) == 0:
        where = f" (source: {context.source})" if context.source else ""
        raise CriterionError(
            f"criterion 'trust' needs the source's training camera poses{where}: use a SOURCE "
            "with training cameras (procedural:SEED, a NeRF run, splats)"
        )
    return Criterion(
        params=trust_params(train_c2w),
        name="trust",
        direction="max",
        value_range=(0.0, 1.0),
        inputs="poses",
        apply=_exact,
        description=_TRUST,
        smooth_apply=_smooth,
    )


_TRUST = (
    "share of the view's 4 x 4 probe points a training camera saw from a similar distance (x1.5) and "
    "direction (30 degrees); from poses alone, a guard for NeRF sources"
)
register(CriterionSpec("trust", "max", "poses", _TRUST, trust, smooth=True))
