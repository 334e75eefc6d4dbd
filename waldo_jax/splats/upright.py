"""Which way is up in a splat scene that comes without cameras, and whether to orbit it or stand inside it.

A camera-less splat file holds no gravity. Its up is read from the scene itself, in this order:

1. **A support plane** (a table, a floor, the ground): the largest plane of splat means (RANSAC over
   triples of means, weighted by opacity) with nearly all the rest of the scene on one side of it
   (`one_side_share`), that rest standing tall enough over it (`min_height_ratio`: the height of the
   mass over the plane against the plane's own extent, so an object's flat face -- a guitar's top --
   is not taken for the floor it stands on), touched by the mass just above it on only a part of its
   extent (an object's flat top or bottom has its body all along it; a table or floor carries its load
   on feet, bases and walls), as wide as the mass it carries (`max_overhang`: a small flat patch on an
   object's side has all of the object on one side of it and overhanging it, as every tangent plane of
   a convex body does; a floor or table reaches under what stands on it), and, where the plane's splats
   are flat, their own normals agreeing with it. Up is its normal, toward the mass.
2. **The format's axis convention**, when it agrees with a well-defined principal axis of the means
   (within `axis_prior_deg`): the reference 3DGS / COLMAP frames usually have y down, so a tall object
   standing along -y keeps -y as its up.
3. **The flattest direction** of the means (least variance): a lying object's axis, a ground-hugging
   scene's vertical. Its sign is the weakest decision: toward the side holding more opacity (a capture
   sees tops more than bottoms).

Names: means [N, 3] the splats' centres, w [N] their opacities, D the robust bounds' diagonal.

The layout: an **object** (most of the mass near the centre: orbit it on a ring) or a **surround**
(little mass near the centre and far splats all around the horizon, as in a room or an unbounded
capture: stand inside and look out). `--up` and `--orbit` override both decisions.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from typing import Optional, Tuple

import jax
import jax.numpy as jnp
import numpy as np

from waldo_jax.splats.render import quat_to_rotmat

__all__ = [
    "UprightConfig",
    "Upright",
    "estimate_upright",
    "FORMAT_UP",
    "LAYOUTS",
    "parse_up",
    "ring_origins",
    "visible_share",
    "robust_bounds",
    "extent_problem",
]

# Robust bounds: a splat further from the median than this many median absolute deviations (per axis) is a
# stray (25 % of splats at 1e30 would otherwise set a quantile, and the ring, 1e30 away); the quantiles
# of every usual scene lie well within it, so its bounds are the plain quantiles'.
_STRAY_MADS = 1000.0
# A scene whose robust diagonal is below this is one point: no camera distance frames it in float32.
MIN_EXTENT = 1e-6

LAYOUTS = ("object", "surround")
# The usual up of each file family's frame (a prior, used only when it agrees with the splats' shape).
FORMAT_UP = {
    "3dgs-ply": ((0.0, -1.0, 0.0), "3DGS/COLMAP frames usually have y down"),
}


@dataclasses.dataclass(frozen=True)
class UprightConfig:
    """Static settings of `estimate_upright` (plain Python: they set shapes and thresholds)."""

    max_splats: int = 2**21  # a larger scene is decided on this many of its splats (a uniform thinning)
    sample: int = 16384  # means drawn (without replacement) for the plane search
    trials: int = 512  # RANSAC triples
    plane_tolerance: float = 0.01  # inlier band: this fraction of D either side of the plane
    min_plane_share: float = 0.05  # the plane holds at least this share of the opacity
    one_side_share: float = 0.9  # of the off-plane opacity, on the mass side
    min_height_ratio: float = 0.2  # mass height over the plane / the plane's extent
    flat_ratio: float = 0.3  # a splat is flat when its smallest scale / its middle one is below this
    min_normal_agreement: float = 0.7  # median |cos| of flat inliers' normals with the plane's
    max_contact_share: float = 0.6  # of the plane's cells, at most this share under the mass just above it
    max_overhang: float = 1.5  # the mass's extent along the plane / the plane's own extent, at most
    contact_grid: int = 24
    axis_prior_deg: float = 20.0
    distinct_axis_ratio: float = 1.5  # an axis is well defined when its variance differs this much from its neighbour's
    layout_views: int = 12  # cameras per ring in the object/surround test
    layout_grid: int = 48  # voxels per side of its occlusion grid
    inside_radius: float = 0.3  # of the robust radius: the inside ring
    surround_margin: float = 0.02  # stand inside when that sees more of the opacity by this much


@dataclasses.dataclass(frozen=True)
class Upright:
    """The decision of `estimate_upright`.

    Attributes:
      up: unit vector [3] (float64), the scene's up.
      rule: "given", "support plane", "format axis" or "flattest direction".
      reason: the decision in words (printed by `waldo scene info`).
      layout: "object" or "surround" (see the module docstring).
      layout_reason: that decision in words.
      plane: (point [3], normal [3]) of the support plane, or None.
      details: the figures behind both decisions (JSON-ready).
    """

    up: np.ndarray
    rule: str
    reason: str
    layout: str
    layout_reason: str
    plane: Optional[Tuple[np.ndarray, np.ndarray]]
    details: dict

    def as_json(self) -> dict:
        return {
            "up": [round(float(v), 6) for v in self.up],
            "rule": self.rule,
            "reason": self.reason,
            "layout": self.layout,
            "layout_reason": self.layout_reason,
            "plane": None
            if self.plane is None
            else {"point": self.plane[0].tolist(), "normal": self.plane[1].tolist()},
            **self.details,
        }


def parse_up(text: str, what: str = "--up") -> np.ndarray:
    """'X,Y,Z' to a unit vector [3]; a ValueError naming `what` for anything else (a zero or non-finite vector)."""
    parts = [p.strip() for p in str(text).split(",")]
    try:
        values = np.array([float(p) for p in parts], np.float64)
    except ValueError:
        values = None
    if values is None or values.shape != (3,) or not np.all(np.isfinite(values)):
        raise ValueError(f"{what} {text!r}: expected three numbers X,Y,Z (e.g. 0,0,1)")
    norm = float(np.linalg.norm(values))
    if norm < 1e-9:
        raise ValueError(f"{what} {text!r}: the zero vector has no direction")
    return values / norm


def _unit(v: np.ndarray) -> np.ndarray:
    return v / max(float(np.linalg.norm(v)), 1e-300)


def _angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    return math.degrees(math.acos(float(np.clip(np.dot(_unit(a), _unit(b)), -1.0, 1.0))))


@functools.partial(jax.jit, static_argnames=("trials",))
def _plane_trials(key, points, weights, tolerance, trials: int):
    """RANSAC planes through `trials` random triples of `points` [M, 3] (weights [M]).

    Returns (normals [T, 3] unit, offsets [T], inlier weight [T], weight above [T], weight below [T]);
    a degenerate triple has inlier weight -1.
    """
    idx = jax.random.choice(key, points.shape[0], (trials, 3), replace=True)
    a, b, c = points[idx[:, 0]], points[idx[:, 1]], points[idx[:, 2]]  # [T, 3]
    n = jnp.cross(b - a, c - a)  # [T, 3]
    norm = jnp.linalg.norm(n, axis=-1, keepdims=True)  # [T, 1]
    ok = norm[:, 0] > 1e-12
    n = n / jnp.where(ok[:, None], norm, 1.0)
    offsets = jnp.sum(n * a, axis=-1)  # [T]
    d = points @ n.T - offsets  # [M, T]
    inlier = jnp.abs(d) <= tolerance
    w = weights[:, None]
    on = jnp.sum(jnp.where(inlier, w, 0.0), axis=0)
    above = jnp.sum(jnp.where(d > tolerance, w, 0.0), axis=0)
    below = jnp.sum(jnp.where(d < -tolerance, w, 0.0), axis=0)
    return n, offsets, jnp.where(ok, on, -1.0), above, below


def _contact_share(points, n, d, inliers, tolerance: float, diagonal: float, grid: int) -> float:
    """The share of the plane's occupied cells (a `grid`^2 map of its inliers in its own coordinates)
    under which the mass continues in the slab just above it (`tolerance` to 5 % of `diagonal`)."""
    # The map's axes are the inliers' own principal directions in the plane, so that the share does not
    # depend on how the scene is turned in the world.
    q = points[inliers] - points[inliers].mean(0)
    q = q - np.outer(q @ n, n)
    _, vectors = np.linalg.eigh(q.T @ q)
    u = _unit(vectors[:, 2] - n * np.dot(vectors[:, 2], n))
    v = np.cross(n, u)
    plane_uv = np.stack([points[inliers] @ u, points[inliers] @ v], -1)
    low, high = plane_uv.min(0), plane_uv.max(0)
    size = np.maximum(high - low, 1e-30) * (1 + 1e-9)

    def cells(uv):
        ij = np.floor((uv - low) / size * grid).astype(np.int64)
        ok = np.all((ij >= 0) & (ij < grid), axis=-1)
        return set(np.ravel_multi_index(ij[ok].T, (grid, grid)).tolist())

    slab = (d > tolerance) & (d <= tolerance + 0.05 * diagonal)
    occupied = cells(plane_uv)
    above = cells(np.stack([points[slab] @ u, points[slab] @ v], -1)) if slab.any() else set()
    return len(occupied & above) / max(len(occupied), 1)


def _flat_normals(log_scales: np.ndarray, quats: np.ndarray, flat_ratio: float) -> Tuple[np.ndarray, np.ndarray]:
    """(normals [N, 3], flat [N] bool): each splat's axis of smallest scale, and whether it is flat."""
    q = quats / np.maximum(np.linalg.norm(quats, axis=-1, keepdims=True), 1e-12)
    columns = np.swapaxes(np.asarray(quat_to_rotmat(jnp.asarray(q, jnp.float32)), np.float64), 1, 2)  # [N, axis, 3]
    order = np.argsort(log_scales, axis=-1)
    smallest = order[:, 0]
    normals = columns[np.arange(len(q)), smallest]
    sorted_scales = np.take_along_axis(log_scales, order, axis=-1)
    flat = (sorted_scales[:, 0] - sorted_scales[:, 1]) < math.log(flat_ratio)
    return normals, flat


def ring_origins(centre: np.ndarray, up: np.ndarray, distance: float, count: int, elevation_deg: float) -> np.ndarray:
    """[count, 3] points `distance` from `centre`, `elevation_deg` above the plane normal to `up`, evenly
    spaced in azimuth (the first along the side axis: `up` x (1, 0, 0), or x (0, 1, 0) when `up` is near x)."""
    up = _unit(np.asarray(up, np.float64))
    side = _unit(np.cross(up, [1.0, 0.0, 0.0] if abs(up[0]) < 0.9 else [0.0, 1.0, 0.0]))
    forward = np.cross(up, side)
    angles = 2 * np.pi * np.arange(count) / count
    elevation = math.radians(elevation_deg)
    directions = (
        math.cos(elevation) * (np.cos(angles)[:, None] * side + np.sin(angles)[:, None] * forward)
        + math.sin(elevation) * up
    )
    return np.asarray(centre, np.float64) + distance * directions


@functools.partial(jax.jit, static_argnames=("steps",))
def _visible_from(voxel_centres, log_clear, origin, grid_low, voxel, steps: int):
    """[V] transmittance from each voxel centre [V, 3] to `origin` [3] through the grid of
    log(1 - alpha) per voxel `log_clear` [G, G, G] (the voxel itself excluded)."""
    g = log_clear.shape[0]
    t = (jnp.arange(steps) + 0.5) / steps  # [S]
    delta = origin - voxel_centres  # [V, 3]
    length = jnp.linalg.norm(delta, axis=-1)  # [V]
    points = voxel_centres[:, None, :] + t[None, :, None] * delta[:, None, :]  # [V, S, 3]
    cell = jnp.floor((points - grid_low) / voxel).astype(jnp.int32)  # [V, S, 3]
    inside = jnp.all((cell >= 0) & (cell < g), axis=-1)
    own = jnp.floor((voxel_centres - grid_low) / voxel).astype(jnp.int32)  # [V, 3]
    not_own = jnp.any(cell != own[:, None, :], axis=-1)
    cell = jnp.clip(cell, 0, g - 1)
    per_sample = log_clear[cell[..., 0], cell[..., 1], cell[..., 2]]  # [V, S]
    # Each sample stands for length / steps of the segment: a voxel's alpha holds over one voxel size.
    weight = (length / steps / voxel)[:, None]
    return jnp.exp(jnp.sum(jnp.where(inside & not_own, per_sample * weight, 0.0), axis=-1))


def visible_share(
    points: np.ndarray, opacity: np.ndarray, origins: np.ndarray, grid: int = 48, steps: int = 96
) -> float:
    """The share of the opacity in voxels that some camera at `origins` [C, 3] sees with transmittance
    above 1/2 (occlusion only, field of view ignored), on a `grid`^3 voxel grid over `points` [N, 3]
    whose voxel alpha is 1 - prod(1 - opacity) of the splats in it (each at most 0.99)."""
    low, high = points.min(0), points.max(0)
    side = float(np.max(high - low)) * 1.02 + 1e-12
    grid_low = 0.5 * (low + high) - 0.5 * side
    voxel = side / grid
    cell = np.clip(np.floor((points - grid_low) / voxel).astype(np.int64), 0, grid - 1)
    flat = np.ravel_multi_index(cell.T, (grid,) * 3)
    log_clear = np.zeros(grid**3)
    np.add.at(log_clear, flat, np.log1p(-np.minimum(opacity, 0.99)))
    mass = np.bincount(flat, weights=opacity, minlength=grid**3)
    occupied = np.flatnonzero(mass > 0)
    centres = grid_low + (np.stack(np.unravel_index(occupied, (grid,) * 3), -1) + 0.5) * voxel
    seen = np.zeros(len(occupied), bool)
    args = (jnp.asarray(centres, jnp.float32), jnp.asarray(log_clear.reshape((grid,) * 3), jnp.float32))
    for origin in origins:
        transmittance = _visible_from(
            *args, jnp.asarray(origin, jnp.float32), jnp.asarray(grid_low, jnp.float32), voxel, steps
        )
        seen |= np.asarray(transmittance) > 0.5
    return float(mass[occupied][seen].sum() / max(mass.sum(), 1e-30))


def _layout(points, weights, centre, radius, up, config: UprightConfig) -> Tuple[str, str, dict]:
    """Object or surround: which ring of cameras sees more of the scene's opacity, one outside its
    bounds (an orbit) or one inside them (standing in a room or a garden)? A room seen from outside
    shows its walls and hides everything in it; a donut seen from inside its hole shows only that."""
    outside = ring_origins(centre, up, 2.0 * radius, config.layout_views, 30.0)
    inside = ring_origins(centre, up, config.inside_radius * radius, config.layout_views, 0.0)
    seen_outside = visible_share(points, weights, outside, config.layout_grid)
    seen_inside = visible_share(points, weights, inside, config.layout_grid)
    details = {"seen_from_outside": round(seen_outside, 4), "seen_from_inside": round(seen_inside, 4)}
    figures = (
        f"a ring outside the bounds sees {100 * seen_outside:.0f} % of the opacity, one inside them "
        f"({config.inside_radius:g} x the radius from the centre) {100 * seen_inside:.0f} %"
    )
    if seen_inside >= seen_outside + config.surround_margin:
        return "surround", f"{figures}: a surrounding scene, stand inside", details
    return "object", f"{figures}: an object, orbit it", details


def estimate_upright(
    key,
    means: np.ndarray,
    weights: np.ndarray,
    shapes: Optional[Tuple[np.ndarray, np.ndarray]] = None,
    format_up: Optional[Tuple[Tuple[float, float, float], str]] = None,
    up: Optional[np.ndarray] = None,
    layout: Optional[str] = None,
    config: UprightConfig = UprightConfig(),
) -> Upright:
    """The scene's up and layout (see the module docstring for the rules, in order). A scene of more than
    `config.max_splats` splats is decided on a uniform thinning to about that many (its full count in
    `details["thinned_from"]`).

    Args:
      key: a JAX PRNG key (the RANSAC triples and the sample of means).
      means: [N, 3] splat centres (valid rows only).
      weights: [N] opacities (sigmoid of the logits).
      shapes: (log_scales [N, 3], quats [N, 4] w first), for the flat splats' normals; None skips that check.
      format_up: (up [3], why) the file family's usual up (`FORMAT_UP`), or None.
      up: a given up (`--up`): taken as is (rule "given").
      layout: a given layout (`--orbit`), one of `LAYOUTS`, or None to decide.
      config: thresholds.

    Returns:
      An `Upright`.
    """
    if layout is not None and layout not in LAYOUTS:
        raise ValueError(f"layout {layout!r}: expected one of {', '.join(LAYOUTS)}")
    count = len(means)
    thinned = None
    if count > config.max_splats:
        # Every figure below is a share, a quantile or a sample: a uniform thinning to about `max_splats`
        # keeps them, and bounds the work (30M splats took 76 s, most of it a permutation of all of them).
        thin_key, key = jax.random.split(key)
        thinned = np.flatnonzero(np.asarray(jax.random.uniform(thin_key, (count,))) < config.max_splats / count)
        means, weights = np.asarray(means)[thinned], np.asarray(weights)[thinned]
        if shapes is not None:
            shapes = (np.asarray(shapes[0])[thinned], np.asarray(shapes[1])[thinned])
    means = np.asarray(means, np.float64)
    weights = np.asarray(weights, np.float64)
    low, high = np.quantile(means, 0.02, axis=0), np.quantile(means, 0.98, axis=0)
    keep = np.all((means >= low) & (means <= high), axis=1) & (weights > 0)
    points, w = means[keep], weights[keep]
    if len(points) < 3 or float(w.sum()) <= 0:
        return _too_few(len(points), format_up, up, layout)
    centre = 0.5 * (low + high)
    diagonal = max(float(np.linalg.norm(high - low)), 1e-12)
    radius = 0.5 * diagonal
    details: dict = {"splats_used": int(len(points)), "robust_diagonal": diagonal}
    if thinned is not None:
        details["thinned_from"] = int(count)
    plane = None

    if up is not None:
        up = _unit(np.asarray(up, np.float64))
        rule, reason = "given", "given (--up)"
    else:
        up, rule, reason, plane = _decide_up(key, points, w, keep, shapes, format_up, diagonal, config, details)
    if layout is not None:
        layout_name, layout_reason = layout, "given (--orbit)"
    else:
        layout_name, layout_reason, more = _layout(points, w, centre, radius, up, config)
        details.update(more)
    return Upright(up, rule, reason, layout_name, layout_reason, plane, details)


def robust_bounds(means: np.ndarray, valid=None, quantile: float = 0.02) -> Tuple[np.ndarray, np.ndarray]:
    """(low, high) [3]: the `quantile` and 1 - `quantile` quantiles per axis of the valid splats' finite means,
    strays (further than `_STRAY_MADS` median absolute deviations from the median on an axis) left out.

    Where no stray is found these are the plain quantiles. No finite mean gives zeros."""
    points = np.asarray(means, np.float64)
    if valid is not None:
        points = points[np.asarray(valid, bool)]
    points = points[np.all(np.isfinite(points), axis=1)]
    if not len(points):
        return np.zeros(3), np.zeros(3)
    median = np.median(points, axis=0)
    spread = np.median(np.abs(points - median), axis=0)  # [3], robust to up to half the splats
    # An axis on which most splats share one value (a floor: no spread) tells no stray apart.
    kept = np.all((np.abs(points - median) <= _STRAY_MADS * spread) | (spread == 0), axis=1)
    if np.any(spread > 0) and kept.sum() >= 0.5 * len(points) and not kept.all():
        points = points[kept]
    return np.quantile(points, quantile, axis=0), np.quantile(points, 1.0 - quantile, axis=0)


def extent_problem(means: np.ndarray, valid=None, bounds=None) -> Optional[str]:
    """Why a ring of views cannot frame the splats (all at one point: a robust diagonal under `MIN_EXTENT`),
    or None. `bounds`: their `robust_bounds`, where already computed."""
    low, high = robust_bounds(means, valid) if bounds is None else bounds
    diagonal = float(np.linalg.norm(high - low))
    if diagonal >= MIN_EXTENT:
        return None
    points = np.asarray(means, np.float64)[np.asarray(valid, bool)] if valid is not None else np.asarray(means)
    return (
        f"the {len(points)} splats' centres span {diagonal:.3g} (robust bounds {low.round(6).tolist()} to "
        f"{high.round(6).tolist()}): a scene of one point, which no view frames"
    )


def _too_few(count: int, format_up, up, layout: Optional[str]) -> Upright:
    """The decision for a scene of fewer than 3 splats with opacity inside their robust bounds (or none
    opaque at all): the given up, else the file family's axis (else +z), and the object layout."""
    why = f"{count} splats with opacity inside their robust bounds, too few to find an up"
    if up is not None:
        up, rule, reason = _unit(np.asarray(up, np.float64)), "given", "given (--up)"
    elif format_up is not None:
        up, rule, reason = _unit(np.asarray(format_up[0], np.float64)), "format axis", f"{why}: {format_up[1]}"
    else:
        up, rule, reason = np.array([0.0, 0.0, 1.0]), "format axis", f"{why}: +z"
    layout_reason = "given (--orbit)" if layout is not None else f"{why}: orbit them"
    return Upright(up, rule, reason, layout or "object", layout_reason, None, {"splats_used": int(count)})


def _refine_plane(points, w, n, d0, tolerance: float):
    """A plane (normal n, offset d0) refitted twice by weighted least squares to its inliers."""
    for _ in range(2):
        d = points @ n - d0
        inl = np.abs(d) <= tolerance
        if inl.sum() < 3:
            break
        q = points[inl]
        qc = np.average(q, axis=0, weights=w[inl])
        _, vectors = np.linalg.eigh(np.cov((q - qc).T, aweights=w[inl]))
        n = vectors[:, 0] * np.sign(np.dot(vectors[:, 0], n) or 1.0)
        d0 = float(np.dot(n, qc))
    return n, d0


def _plane_figures(points, w, plane, scale, flat_splats, config: UprightConfig) -> Optional[dict]:
    """What a candidate support plane holds: its share of the opacity, the share of the rest on its
    upper side, the mass's height over its extent, its contact share and its flat splats' agreement;
    None when it holds fewer than 3 splats or nothing stands above it."""
    (n, d0), (tolerance, diagonal), (flat, flat_normals) = plane, scale, flat_splats
    d = points @ n - d0
    inl = np.abs(d) <= tolerance
    share = float(w[inl].sum()) / float(w.sum())
    mass = d > tolerance
    below_mass = d < -tolerance
    one_side = float(w[mass].sum()) / max(float(w[mass | below_mass].sum()), 1e-30)
    if inl.sum() < 3 or not mass.any():
        return None
    height = float(np.quantile(d[mass], 0.95))
    q = points[inl] - points[inl].mean(0)
    in_plane = q - np.outer(q @ n, n)
    extent = 2.0 * float(np.quantile(np.linalg.norm(in_plane, axis=-1), 0.95))
    ratio = height / max(extent, 1e-30)
    above = points[mass] - points[inl].mean(0)
    above_in_plane = above - np.outer(above @ n, n)
    overhang = 2.0 * float(np.quantile(np.linalg.norm(above_in_plane, axis=-1), 0.95)) / max(extent, 1e-30)
    contact = _contact_share(points, n, d, inl, tolerance, diagonal, config.contact_grid)
    agreement = None
    if flat is not None and flat[inl].sum() >= max(10, 0.2 * inl.sum()):
        agreement = float(np.median(np.abs(flat_normals[inl & flat] @ n)))
    return {
        "normal": n.round(6).tolist(),
        "share": share,
        "one_side_share": one_side,
        "height_ratio": ratio,
        "flat_normal_agreement": agreement,
        "contact_share": contact,
        "overhang": overhang,
    }


def _rounded(figures: dict) -> dict:
    """`figures` with its shares and ratios rounded to 4 digits, for the details written out."""
    return {k: v if isinstance(v, list) or v is None else round(v, 4) for k, v in figures.items()}


def _plane_rejection(figures: dict, config: UprightConfig) -> Optional[str]:
    """Why a candidate plane is no support (the first rule it fails), or None."""
    share, one_side, ratio = figures["share"], figures["one_side_share"], figures["height_ratio"]
    contact, agreement = figures["contact_share"], figures["flat_normal_agreement"]
    if share < config.min_plane_share:
        return f"holds {100 * share:.1f} % of the opacity"
    if one_side < config.one_side_share:
        return f"only {100 * one_side:.0f} % of the rest on one side"
    if ratio < config.min_height_ratio:
        return f"the mass stands {ratio:.2f} x its extent over it (a face, not a support)"
    if contact > config.max_contact_share:
        return (
            f"the mass rests on {100 * contact:.0f} % of it (an object's own face, which its body "
            "continues under; a support carries its load on a part)"
        )
    if figures["overhang"] > config.max_overhang:
        return (
            f"the mass reaches {figures['overhang']:.1f} x its extent along it (a patch of an object's side, "
            "not a support under it)"
        )
    if agreement is not None and agreement < config.min_normal_agreement:
        return f"its flat splats' normals agree only {agreement:.2f} (median |cos|)"
    return None


def _decide_up(key, points, w, keep, shapes, format_up, diagonal, config: UprightConfig, details: dict):
    sample_key, trial_key = jax.random.split(key)
    m = min(config.sample, len(points))
    chosen = np.asarray(jax.random.choice(sample_key, len(points), (m,), replace=False))
    sp, sw = points[chosen], w[chosen]
    tolerance = config.plane_tolerance * diagonal
    normals, offsets, on, above, below = (
        np.asarray(v, np.float64)
        for v in _plane_trials(
            trial_key, jnp.asarray(sp, jnp.float32), jnp.asarray(sw, jnp.float32), tolerance, config.trials
        )
    )
    total = float(sw.sum())
    off = above + below
    side_share = np.maximum(above, below) / np.maximum(off, 1e-30)
    candidates = np.flatnonzero((on >= config.min_plane_share * total) & (side_share >= config.one_side_share))
    flat_normals = flat = None
    if shapes is not None:
        flat_normals, flat = _flat_normals(
            np.asarray(shapes[0], np.float64)[keep], np.asarray(shapes[1], np.float64)[keep], config.flat_ratio
        )
    rejected = []
    prior = None if format_up is None else (_unit(np.asarray(format_up[0], np.float64)), format_up[1])
    accepted = []
    # The best-supported planes first; each is refined by a least-squares fit to its inliers.
    for t in candidates[np.argsort(-on[candidates])][:16]:
        sign = 1.0 if above[t] >= below[t] else -1.0
        n, d0 = _refine_plane(points, w, normals[t] * sign, offsets[t] * sign, tolerance)
        figures = _plane_figures(points, w, (n, d0), (tolerance, diagonal), (flat, flat_normals), config)
        if figures is None:
            continue
        why = _plane_rejection(figures, config)
        if why:
            rejected.append({**_rounded(figures), "rejected": why})
            continue
        accepted.append((figures["share"], n, d0, _rounded(figures)))
    details["planes_rejected"] = rejected[:4]
    if accepted:
        # The largest accepted plane; where a format prior exists, a plane along it is preferred
        # over a larger one across it (a room's floor over its walls).
        def rank(item):
            share, n = item[0], item[1]
            along = prior is not None and _angle_deg(n, prior[0]) <= config.axis_prior_deg
            return (along, share)

        share, n, d0, figures = max(accepted, key=rank)
        details["plane"] = figures
        reason = (
            f"a support plane holding {100 * share:.0f} % of the opacity, "
            f"{100 * figures['one_side_share']:.0f} % of the rest above it, the mass "
            f"{figures['height_ratio']:.2f} x its extent tall"
            + (
                ""
                if figures["flat_normal_agreement"] is None
                else f", its flat splats' normals agreeing {figures['flat_normal_agreement']:.2f}"
            )
        )
        return n, "support plane", reason, (n * d0, n)

    return _principal_up(points, w, prior, config, details)


def _principal_up(points, w, prior, config: UprightConfig, details: dict):
    """With no support plane: the principal axis the format prior agrees with, else the flattest direction."""
    centred = points - np.average(points, axis=0, weights=w)
    values, vectors = np.linalg.eigh(np.cov(centred.T, aweights=w))  # ascending variances
    details["principal_variances"] = values.round(8).tolist()
    distinct = [
        values[1] >= config.distinct_axis_ratio * max(values[0], 1e-30),
        values[2] >= config.distinct_axis_ratio * max(values[1], 1e-30) and values[1] >= 0,
    ]
    if prior is not None:
        for index, ok in ((0, distinct[0]), (2, distinct[1])):
            axis = vectors[:, index]
            angle = min(_angle_deg(axis, prior[0]), _angle_deg(-axis, prior[0]))
            if ok and angle <= config.axis_prior_deg:
                up = axis * np.sign(np.dot(axis, prior[0]))
                which = "flattest" if index == 0 else "longest"
                reason = (
                    f"no support plane; the format's axis convention ({prior[1]}) agrees within "
                    f"{angle:.0f} deg with the splats' {which} principal axis"
                )
                return up, "format axis", reason, None
    axis = vectors[:, 0]
    coordinate = centred @ axis
    heavier = float(w[coordinate > 0].sum()) - float(w[coordinate < 0].sum())
    up = axis * (1.0 if heavier >= 0 else -1.0)
    ratio = values[1] / max(values[0], 1e-30)
    reason = (
        f"no support plane; the splats' flattest direction (variance {ratio:.1f} x smaller than the next"
        f"{'' if distinct[0] else ': weakly defined'}), signed toward the side holding more opacity "
        "(the sign is a guess: pass --up to fix it)"
    )
    details["sign_margin"] = round(abs(heavier) / float(w.sum()), 4)
    return up, "flattest direction", reason, None
