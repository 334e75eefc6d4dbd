"""Fitting 3D Gaussian splats to a scene's training images, with the renderer that explores them.

After the reference 3DGS optimisation (Kerbl et al. 2023), in a fixed capacity:

  init       from the scene's sparse points where it has them (nerfstudio's `sparse_pc.ply`: positions
             and colours), else `FitConfig.init_count` points uniform in the scene box; scales from the
             mean distance to the 3 nearest points, identity rotations, opacity 0.1, SH DC from the colour.
  step       a random training view per step (`views_per_step` of them, vmapped), rendered with
             `waldo_jax.splats.render.render_view` on a random background for RGBA scenes; loss
             (1 - ssim_weight) L1 + ssim_weight (1 - SSIM); Adam with the reference's per-parameter
             learning rates (means' decaying exponentially, in units of the scene extent); the SH degree
             grows by one every `sh_every` steps up to `sh_degree`.
  densify    every `densify_every` steps within [densify_from, densify_until]: splats whose mean
             view-space positional gradient (pixels) exceeds `grad_threshold` are cloned (small ones) or
             split in two (large ones, scales / 1.6, positions drawn from the Gaussian), into the free
             rows of the capacity; transparent (opacity < prune_opacity) and huge splats are pruned (masked).
             New rows start with zero Adam moments. Candidates that do not fit are counted, never silently lost.
  reset      opacities are clamped to 0.01 every `opacity_reset_every` steps (while densifying).

Everything between densifications is one `lax.scan` (one compiled program); `max_pairs` of the
renderer is re-measured after each densification on a sample of training views, rounded up to a power
of two, so the program recompiles only when the scene outgrows it.
"""

from __future__ import annotations

import dataclasses
import math
import time
import warnings
from typing import Any, Callable, Dict, List, Optional, Tuple

import flax.struct
import jax
import jax.numpy as jnp
import numpy as np
import optax

from waldo_jax.errors import MemoryBudgetError, check_memory, host_memory_bytes
from waldo_jax.metrics import image_psnr, psnr_from_mse
from waldo_jax.search.explore import program_memory
from waldo_jax.splats.model import Splats, make_splats, sh_coefficients
from waldo_jax.splats.render import SplatRenderConfig, count_pairs, quat_to_rotmat, render_view
from waldo_jax.splats.sh import SH_C0
from waldo_jax.types import Array, PRNGKey, Scene

__all__ = ["FitConfig", "FitResult", "fit_splats", "init_splats", "ssim", "psnr", "evaluate_splats"]


@dataclasses.dataclass(frozen=True)
class FitConfig:
    """Static settings of a fit (hashable).

    Attributes:
      steps: optimisation steps. The defaults are the reference's with its learning rates x3, a
        densification threshold of half its and no opacity resets: tuned for fits of a few thousand
        steps (the reference runs 30,000) on lego_tiny (1,000 steps: 30.0 dB held out against 24.5 dB
        with the reference's own rates; docs/splats.md).
      capacity: rows of the fixed-size splat arrays (the most splats the fit may hold).
      init_count: random initial splats when the scene has no sparse points (at most capacity / 2).
      sh_degree: the final SH degree; it starts at 0 and grows by one every `sh_every` steps.
      views_per_step: training views rendered per step (vmapped).
      lr_means, lr_means_final: the means' learning rate at the start and end (x the scene extent).
      lr_sh_dc, lr_sh_rest, lr_opacity, lr_scales, lr_quats: the other parameters' learning rates.
      ssim_weight: weight of (1 - SSIM) in the loss.
      densify_from, densify_until, densify_every: the densification window and period (steps;
        densify_until None: 4/5 of the steps).
      grad_threshold: mean view-space positional gradient (of the loss, per unit of normalised device
        coordinates, as the reference measures it) above which a splat is densified.
      percent_dense: splats larger than this fraction of the scene extent are split, smaller cloned.
      prune_opacity: splats below this opacity are pruned at each densification.
      max_scale: splats larger than this fraction of the scene extent are pruned.
      opacity_reset_every: opacities are reset to at most 0.01 this often (0: never).
      render: the renderer's settings (`max_pairs` is re-measured during the fit).
    """

    steps: int = 2000
    capacity: int = 2**15
    init_count: int = 4096
    sh_degree: int = 3
    sh_every: int = 250
    views_per_step: int = 1
    lr_means: float = 4.8e-4
    lr_means_final: float = 4.8e-6
    lr_sh_dc: float = 7.5e-3
    lr_sh_rest: float = 3.75e-4
    lr_opacity: float = 7.5e-2
    lr_scales: float = 1.5e-2
    lr_quats: float = 3e-3
    ssim_weight: float = 0.2
    densify_from: int = 100
    densify_until: Optional[int] = None
    densify_every: int = 100
    grad_threshold: float = 1e-4
    percent_dense: float = 0.01
    prune_opacity: float = 0.005
    max_scale: float = 0.1
    opacity_reset_every: int = 0
    render: SplatRenderConfig = SplatRenderConfig(max_pairs=2**14)

    def __post_init__(self):
        for name in ("steps", "capacity", "init_count", "sh_every", "views_per_step", "densify_every"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ValueError(f"FitConfig.{name} must be an int >= 1, got {value!r}")
        if not 0 <= self.sh_degree <= 3:
            raise ValueError(f"FitConfig.sh_degree must be 0..3, got {self.sh_degree!r}")

    @property
    def last_densify(self) -> int:
        return (4 * self.steps) // 5 if self.densify_until is None else self.densify_until


@flax.struct.dataclass
class FitResult:
    """A finished fit: the splats (valid rows only), their quality and cost, and its history."""

    splats: Splats
    psnr_test: Optional[float] = flax.struct.field(pytree_node=False, default=None)
    psnr_train: Optional[float] = flax.struct.field(pytree_node=False, default=None)
    seconds: float = flax.struct.field(pytree_node=False, default=0.0)
    steps: int = flax.struct.field(pytree_node=False, default=0)
    history: Tuple[Dict[str, Any], ...] = flax.struct.field(pytree_node=False, default=())
    max_pairs: int = flax.struct.field(pytree_node=False, default=0)
    overflow_views: int = flax.struct.field(pytree_node=False, default=0)
    densify_dropped: int = flax.struct.field(pytree_node=False, default=0)
    max_pairs_capped: int = flax.struct.field(pytree_node=False, default=0)
    step_memory: Optional[int] = flax.struct.field(pytree_node=False, default=None)


# ---------------------------------------------------------------------------------------------
# Image metrics.


def _gaussian_window(size: int = 11, sigma: float = 1.5) -> np.ndarray:
    x = np.arange(size) - size // 2
    g = np.exp(-(x**2) / (2 * sigma**2))
    return (g / g.sum()).astype(np.float32)


def ssim(a: Array, b: Array) -> Array:
    """Mean SSIM of images a, b [H, W, C] in [0, 1] (11x11 Gaussian window, sigma 1.5, zero padding
    as the reference's `F.conv2d`, C1 = 0.01^2, C2 = 0.03^2)."""
    window = jnp.asarray(_gaussian_window())

    def blur(x):  # [H, W, C], separable, zero padding
        x = jnp.moveaxis(x, -1, 0)[:, None]  # [C, 1, H, W]
        x = jax.lax.conv_general_dilated(x, window[None, None, :, None], (1, 1), "SAME")
        x = jax.lax.conv_general_dilated(x, window[None, None, None, :], (1, 1), "SAME")
        return jnp.moveaxis(x[:, 0], 0, -1)

    mu_a, mu_b = blur(a), blur(b)
    var_a = blur(a * a) - mu_a**2
    var_b = blur(b * b) - mu_b**2
    cov = blur(a * b) - mu_a * mu_b
    c1, c2 = 0.01**2, 0.03**2
    value = ((2 * mu_a * mu_b + c1) * (2 * cov + c2)) / ((mu_a**2 + mu_b**2 + c1) * (var_a + var_b + c2))
    return jnp.mean(value)


def psnr(a, b) -> float:
    """Mean PSNR (dB) over images a, b [N, H, W, 3] (host arrays)."""
    return float(np.mean(image_psnr(a, b)))


# ---------------------------------------------------------------------------------------------
# Initialisation.


def _knn_scale(points: np.ndarray) -> np.ndarray:
    """Log of the mean distance of each point to its 3 nearest others, [P] (the reference's init scale)."""
    from scipy.spatial import cKDTree

    k = min(4, len(points))
    distances, _ = cKDTree(points).query(points, k=k)
    mean = np.mean(distances[:, 1:], axis=1) if k > 1 else np.ones(len(points))
    return np.log(np.maximum(mean, 1e-7))


def init_splats(
    key: PRNGKey,
    scene: Scene,
    config: FitConfig,
    points: Optional[np.ndarray] = None,
    colors: Optional[np.ndarray] = None,
) -> Tuple[Splats, str]:
    """The initial splats in `config.capacity` rows (the rest invalid) and how they were made.

    Args:
      key: for the random points (when `points` is None) and the subsampling of too many points.
      scene: the training scene (its box bounds random points).
      config: the fit's settings.
      points: float32 [P, 3] sparse points, or None; colors: float32 [P, 3] in [0, 1], or None.
    """
    key_points, key_colors, key_pick = jax.random.split(key, 3)
    budget = max(1, config.capacity // 2)
    if points is None:
        count = min(config.init_count, budget)
        low, high = np.asarray(scene.aabb, np.float32)
        points = np.asarray(jax.random.uniform(key_points, (count, 3), minval=low, maxval=high))
        colors = np.asarray(jax.random.uniform(key_colors, (count, 3)))
        how = f"{count} random points in the scene box"
    else:
        points = np.asarray(points, np.float32)
        if len(points) > budget:
            pick = np.asarray(jax.random.choice(key_pick, len(points), (budget,), replace=False))
            points = points[pick]
            colors = None if colors is None else np.asarray(colors)[pick]
        how = f"{len(points)} sparse points of the scene"
        if colors is None:
            colors = np.full((len(points), 3), 0.5, np.float32)
    count = len(points)
    k = sh_coefficients(config.sh_degree)
    sh = np.zeros((config.capacity, k, 3), np.float32)
    sh[:count, 0] = (np.asarray(colors, np.float32) - 0.5) / SH_C0
    means = np.zeros((config.capacity, 3), np.float32)
    means[:count] = points
    log_scales = np.full((config.capacity, 3), -10.0, np.float32)
    log_scales[:count] = _knn_scale(points)[:, None]
    quats = np.zeros((config.capacity, 4), np.float32)
    quats[:, 0] = 1.0
    logits = np.full(config.capacity, -10.0, np.float32)
    logits[:count] = math.log(0.1 / 0.9)
    valid = np.arange(config.capacity) < count
    return make_splats(means, log_scales, quats, logits, sh, valid), how


# ---------------------------------------------------------------------------------------------
# The step.


@flax.struct.dataclass
class _Data:
    """Training images on the device: premultiplied colour [N, H, W, 3], alpha [N, H, W] or None, c2w [N, 4, 4]."""

    images: Array
    alphas: Optional[Array]
    c2w: Array


_FIELDS = ("means", "log_scales", "quats", "logits", "sh")


@flax.struct.dataclass
class _State:
    params: Dict[str, Array]  # the Splats' float fields (what Adam moves)
    valid: Array  # bool [N]
    opt: Any
    grad_sum: Array  # [N] summed view-space positional gradient norms (pixels)
    grad_count: Array  # [N] views in which the splat was visible

    @property
    def splats(self) -> Splats:
        return Splats(**self.params, valid=self.valid)


def _params(splats: Splats) -> Dict[str, Array]:
    return {name: getattr(splats, name) for name in _FIELDS}


def _sh_adam(lr_dc: float, lr_rest: float) -> optax.GradientTransformation:
    """Adam on the SH coefficients [N, K, 3]: the DC term at lr_dc, the rest at lr_rest (the reference's
    two parameter groups, as one array)."""

    def scale(updates, params=None):
        del params
        k = updates.shape[1]
        lr = jnp.concatenate([jnp.full((1,), lr_dc), jnp.full((k - 1,), lr_rest)])[None, :, None]
        return -lr * updates

    return optax.chain(optax.scale_by_adam(eps=1e-15), optax.stateless_with_tree_map(scale))


def _optimizer(config: FitConfig, extent: float) -> optax.GradientTransformation:
    """Adam with the reference's per-parameter learning rates (the means' decaying, x the scene extent)."""
    means_lr = optax.exponential_decay(config.lr_means * extent, config.steps, config.lr_means_final / config.lr_means)
    transforms = {
        "means": optax.adam(means_lr, eps=1e-15),
        "log_scales": optax.adam(config.lr_scales, eps=1e-15),
        "quats": optax.adam(config.lr_quats, eps=1e-15),
        "logits": optax.adam(config.lr_opacity, eps=1e-15),
        "sh": _sh_adam(config.lr_sh_dc, config.lr_sh_rest),
    }
    return optax.multi_transform(transforms, {name: name for name in _FIELDS})


def _sh_mask(degree_now: Array, k: int) -> Array:
    """float32 [K, 1]: 1 for the coefficients of degree <= degree_now (the reference's growing degree)."""
    degree_of = np.floor(np.sqrt(np.arange(k))).astype(np.int32)
    return (jnp.asarray(degree_of)[:, None] <= degree_now).astype(jnp.float32)


def _loss(
    params: Dict[str, Array],
    offset: Array,
    valid: Array,
    c2w: Array,
    target: Array,
    background: Array,
    degree_now: Array,
    intrinsics,
    config: FitConfig,
):
    splats = Splats(**{**params, "sh": params["sh"] * _sh_mask(degree_now, params["sh"].shape[1])}, valid=valid)
    rgb, _, _, stats = render_view(splats, c2w, intrinsics, config.render, background, mean2d_offset=offset)
    l1 = jnp.mean(jnp.abs(rgb - target))
    loss = (1.0 - config.ssim_weight) * l1 + config.ssim_weight * (1.0 - ssim(rgb, target))
    return loss, (rgb, stats)


def _step(state: _State, key: PRNGKey, step: Array, data: _Data, intrinsics, optimizer, config: FitConfig):
    key_view, key_bg = jax.random.split(key)
    views = jax.random.randint(key_view, (config.views_per_step,), 0, data.images.shape[0])
    c2w = data.c2w[views]
    if data.alphas is None:
        background = jnp.zeros((config.views_per_step, 3), jnp.float32)
        target = data.images[views]
    else:
        background = jax.random.uniform(key_bg, (config.views_per_step, 3))
        target = data.images[views] + (1.0 - data.alphas[views][..., None]) * background[:, None, None, :]
    degree_now = jnp.minimum(step // config.sh_every, config.sh_degree)
    offset = jnp.zeros((config.views_per_step, state.valid.shape[0], 2), jnp.float32)

    def total(params, offset):
        losses, (rgb, stats) = jax.vmap(
            lambda o, c, t, b: _loss(params, o, state.valid, c, t, b, degree_now, intrinsics, config)
        )(offset, c2w, target, background)
        return jnp.mean(losses), (rgb, stats)

    (loss, (rgb, stats)), (grads, grad_offset) = jax.value_and_grad(total, argnums=(0, 1), has_aux=True)(
        state.params, offset
    )
    updates, opt = optimizer.update(grads, state.opt, state.params)
    params = optax.apply_updates(state.params, updates)
    # The view-space positional gradient of each view in the reference's units (normalised device
    # coordinates: x W / 2, y H / 2 per pixel); the loss is a mean over views, undone.
    ndc = jnp.array([0.5 * intrinsics.width, 0.5 * intrinsics.height], jnp.float32)
    norm = jnp.linalg.norm(grad_offset * ndc, axis=-1) * config.views_per_step  # [V, N]
    mse = jnp.mean((rgb - target) ** 2)
    new = state.replace(
        params=params,
        opt=opt,
        grad_sum=state.grad_sum + jnp.sum(norm, 0),
        grad_count=state.grad_count + jnp.sum(norm > 0, 0),
    )
    return new, {
        "loss": loss,
        "psnr": psnr_from_mse(mse),
        "pair_overflow": jnp.sum(stats.pair_overflow > 0),
    }


def _run_steps(
    state: _State, key: PRNGKey, first: Array, data: _Data, intrinsics, optimizer, config: FitConfig, count: int
):
    def body(state, index):
        step = first + index
        return _step(state, jax.random.fold_in(key, step), step, data, intrinsics, optimizer, config)

    return jax.lax.scan(body, state, jnp.arange(count, dtype=jnp.int32))


_run_steps_jit = jax.jit(_run_steps, static_argnames=("optimizer", "config", "count"))


# ---------------------------------------------------------------------------------------------
# Densification.


def _reset_moments(opt, rows: Array, field: Optional[str] = None):
    """Adam moments zeroed on `rows` (bool [N]) of every per-splat leaf (of `field`'s only, if given)."""

    def zero(path, leaf):
        if field is not None and not any(getattr(k, "key", None) == field for k in path):
            return leaf
        if hasattr(leaf, "shape") and leaf.ndim >= 1 and leaf.shape[0] == rows.shape[0]:
            return jnp.where(rows.reshape((-1,) + (1,) * (leaf.ndim - 1)), jnp.zeros_like(leaf), leaf)
        return leaf

    return jax.tree_util.tree_map_with_path(zero, opt)


def _densify(state: _State, key: PRNGKey, extent: Array, reset_opacity: Array, config: FitConfig):
    """Clone / split / prune into the fixed capacity (see the module docstring). Returns (state, dropped)."""
    splats = state.splats
    n = splats.count
    grad = state.grad_sum / jnp.maximum(state.grad_count, 1)
    scale_max = jnp.max(splats.scales(), axis=-1)
    large = scale_max > config.percent_dense * extent
    candidate = splats.valid & (grad >= config.grad_threshold) & (state.grad_count > 0)
    split = candidate & large
    prune = (
        splats.valid
        & ~candidate
        & ((splats.opacities() < config.prune_opacity) | (scale_max > config.max_scale * extent))
    )
    valid = splats.valid & ~prune
    # One new row per candidate, largest gradients first, into the free rows; the rest are counted.
    source = jnp.argsort(jnp.where(candidate, -grad, jnp.inf))  # [N] candidates first
    free_rows = jnp.argsort(valid, stable=True)  # [N] free rows first
    wanted, available = jnp.sum(candidate), jnp.sum(~valid)
    placed = jnp.minimum(wanted, available)
    target = jnp.where(jnp.arange(n) < placed, free_rows, n)  # n: not placed (dropped by mode="drop")
    split = split & jnp.zeros(n, bool).at[source].set(jnp.arange(n) < placed)  # an unplaced split stays whole
    # A split's two halves are drawn from the Gaussian and shrink by 1.6; a clone is a copy.
    rotation = quat_to_rotmat(splats.rotations())  # [N, 3, 3]
    key_a, key_b = jax.random.split(key)

    def draw(k):
        return splats.means + jnp.einsum("nij,nj->ni", rotation, jax.random.normal(k, (n, 3)) * splats.scales())

    shrink = jnp.where(split, jnp.log(1.6), 0.0)[:, None]
    moved = jnp.where(split[:, None], draw(key_a), splats.means)
    params = dict(state.params)
    params["means"] = moved.at[target].set(jnp.where(split[:, None], draw(key_b), splats.means)[source], mode="drop")
    params["log_scales"] = (
        (splats.log_scales - shrink).at[target].set((splats.log_scales - shrink)[source], mode="drop")
    )
    for name in ("quats", "logits", "sh"):
        params[name] = params[name].at[target].set(params[name][source], mode="drop")
    added = jnp.zeros(n, bool).at[target].set(True, mode="drop")
    valid = valid | added
    params["logits"] = jnp.where(
        reset_opacity & valid, jnp.minimum(params["logits"], math.log(0.01 / 0.99)), params["logits"]
    )
    opt = _reset_moments(state.opt, added | split | prune)
    opt = _reset_moments(opt, jnp.broadcast_to(reset_opacity, (n,)), field="logits")
    return state.replace(
        params=params, valid=valid, opt=opt, grad_sum=jnp.zeros(n, jnp.float32), grad_count=jnp.zeros(n, jnp.int32)
    ), wanted - placed


_densify_jit = jax.jit(_densify, static_argnames=("config",))


# ---------------------------------------------------------------------------------------------
# The fit.


def _data(scene: Scene) -> _Data:
    images = np.asarray(scene.images, np.float32)
    alphas = None
    if scene.alphas is not None:
        alphas = np.asarray(scene.alphas, np.float32)
        background = np.zeros(3, np.float32) if scene.background is None else np.asarray(scene.background, np.float32)
        images = images - (1.0 - alphas[..., None]) * background  # premultiplied
    return _Data(
        images=jnp.asarray(images),
        alphas=None if alphas is None else jnp.asarray(alphas),
        c2w=jnp.asarray(np.asarray(scene.c2w, np.float32)[:, :3, :4]),
    )


def _scene_extent(scene: Scene) -> float:
    """The reference's `cameras_extent`: 1.1 x the largest distance of a camera from their mean."""
    origins = np.asarray(scene.c2w, np.float64)[:, :3, 3]
    return float(1.1 * np.max(np.linalg.norm(origins - origins.mean(0), axis=1)))


def _max_pairs(splats: Splats, c2w: Array, intrinsics, config: SplatRenderConfig) -> int:
    needed = int(np.max(np.asarray(_count_pairs(splats, c2w, intrinsics, config=config))))
    return max(2**12, 1 << int(math.ceil(math.log2(max(1.5 * needed, 1)))))


_count_pairs = jax.jit(count_pairs, static_argnames=("config",))


def evaluate_splats(splats: Splats, scene: Scene, config: SplatRenderConfig) -> float:
    """Mean PSNR of the splats' renders of `scene`'s views against its images (on its background)."""
    from waldo_jax.splats.render import render_splats

    background = np.zeros(3, np.float32) if scene.background is None else np.asarray(scene.background, np.float32)
    c2w = jnp.asarray(np.asarray(scene.c2w, np.float32))
    config = dataclasses.replace(config, max_pairs=_max_pairs(splats, c2w, scene.intrinsics, config))
    rendered = jax.jit(render_splats, static_argnames=("config",))(
        splats, c2w, scene.intrinsics, config=config, background=jnp.asarray(background)
    )
    return psnr(np.asarray(rendered.rgb), scene.images)


# A fit whose step renders at least this many pixels times a step before the first block and says how
# long the fit will take (a block is `densify_every` steps: minutes of silence on large images).
TIMED_STEP_PIXELS = 2**18


class _Programs:
    """The fit's compiled step programs, one per (max_pairs, steps in the block), each checked against
    the host's free memory before it runs (XLA's analysis of its temporaries and outputs: the state and
    the images it takes are in memory already)."""

    def __init__(self, state, key, data, intrinsics, optimizer, config: FitConfig):
        # The state's shapes only (the fit replaces it every block: holding it would keep a third copy).
        shapes = jax.tree.map(lambda a: jax.ShapeDtypeStruct(a.shape, a.dtype, sharding=a.sharding), state)
        self.args = (shapes, key, jnp.int32(0), data, intrinsics)
        self.optimizer, self.config = optimizer, config
        self.compiled: Dict[Tuple[int, int], Any] = {}
        self.need: Dict[int, Optional[int]] = {}

    def get(self, render_config: SplatRenderConfig, count: int):
        key = (render_config.max_pairs, count)
        if key not in self.compiled:
            cfg = dataclasses.replace(self.config, render=render_config)
            lowered = _run_steps_jit.lower(*self.args, self.optimizer, cfg, count)
            self.compiled[key] = lowered.compile()
            analysis = _new_memory(self.compiled[key])
            self.need[render_config.max_pairs] = max(analysis or 0, self.need.get(render_config.max_pairs) or 0) or None
        return self.compiled[key]

    def fits(self, render_config: SplatRenderConfig, count: int) -> Tuple[bool, Optional[int], int]:
        """(whether the block's program fits the host's free memory, bytes it needs, bytes free)."""
        self.get(render_config, count)
        need, available = self.need[render_config.max_pairs], host_memory_bytes()
        return not (need and available and need > available), need, available


def _new_memory(compiled) -> Optional[int]:
    """Bytes a compiled step program takes beyond its arguments (its temporaries and outputs)."""
    total = program_memory(compiled)
    if total is None:
        return None
    analysis = compiled.memory_analysis()
    return max(total - int(getattr(analysis, "argument_size_in_bytes", 0) or 0), 0)


def _fit_size(scene: Scene, config: FitConfig) -> str:
    return (
        f"{config.views_per_step} view{'s' * (config.views_per_step > 1)} of {scene.width}x{scene.height} a step, "
        f"{config.capacity} splats"
    )


def fit_splats(
    key: PRNGKey,
    scene: Scene,
    config: FitConfig = FitConfig(),
    test_scene: Optional[Scene] = None,
    points: Optional[np.ndarray] = None,
    colors: Optional[np.ndarray] = None,
    log: Optional[Callable[[str], None]] = print,
    ready: Optional[Callable[[], None]] = None,
) -> FitResult:
    """Fits splats to `scene`'s images; the held-out PSNR on `test_scene` when given.

    The work of a step is set by the images' size: before any step runs, the first block's compiled
    program is checked against the host's free memory (refused with `MemoryBudgetError`, naming the
    image size, the memory and `--downscale` / `--capacity`), and a step rendering at least `TIMED_STEP_PIXELS`
    pixels is timed and the fit's time estimated (logged). A later block whose `max_pairs` would
    not fit the memory keeps the largest that does (a warning); the pairs beyond are dropped and counted
    (`overflow_views`, `max_pairs_capped`).

    Args:
      key: the fit's PRNG key (initialisation, views, backgrounds, splits).
      scene: the training scene.
      config: `FitConfig`.
      test_scene: held-out views, or None.
      points, colors: sparse points [P, 3] (and colours [P, 3] in [0, 1]) to start from, or None.
      log: where progress lines go (one per densification, and the time estimate), or None for none.
      ready: called once the memory check has passed, before the first step (a run folder is made there).

    Returns:
      `FitResult` (its splats hold the valid rows only).

    Raises:
      MemoryBudgetError: the first block's program needs more memory than the host has free.
    """
    start = time.perf_counter()
    check_memory(
        capacity_bytes(config),
        f"a splat fit of --capacity {config.capacity} (SH degree {config.sh_degree}: the splats, their Adam "
        "moments, a step's new copy and its work per splat)",
        "pass a lower --capacity",
    )
    key_init, key_steps, key_densify = jax.random.split(key, 3)
    splats, how = init_splats(key_init, scene, config, points, colors)
    extent = max(_scene_extent(scene), 1e-6)
    optimizer = _optimizer(config, extent)
    data = _data(scene)
    n = config.capacity
    params = _params(splats)
    state = _State(
        params=params,
        valid=splats.valid,
        opt=optimizer.init(params),
        grad_sum=jnp.zeros(n, jnp.float32),
        grad_count=jnp.zeros(n, jnp.int32),
    )
    sample = data.c2w[:: max(1, data.c2w.shape[0] // 16)]
    render_config = dataclasses.replace(
        config.render, max_pairs=_max_pairs(splats, sample, scene.intrinsics, config.render)
    )
    programs = _Programs(state, key_steps, data, scene.intrinsics, optimizer, config)
    need = _check_first_block(programs, render_config, scene, config)
    if ready is not None:
        ready()
    history: List[Dict[str, Any]] = [{"step": 0, "splats": int(np.sum(np.asarray(splats.valid))), "init": how}]
    history[0]["step_memory_bytes"] = need
    state, step, overflow_views = _timed_first_step(programs, render_config, state, scene, config, history[0], log)
    dropped_total, capped = 0, 0
    while step < config.steps:
        # Blocks end on multiples of densify_every (a timed first step makes the first block one shorter).
        count = min(config.densify_every - step % config.densify_every, config.steps - step)
        state, metrics = programs.get(render_config, count)(state, key_steps, jnp.int32(step), data, scene.intrinsics)
        step += count
        metrics = jax.device_get(metrics)
        overflow_views += int(np.sum(metrics["pair_overflow"]))
        row = {
            "step": step,
            "loss": float(np.mean(metrics["loss"])),
            "psnr": float(np.mean(metrics["psnr"])),
            "max_pairs": render_config.max_pairs,
        }
        if config.densify_from <= step <= config.last_densify and step < config.steps:
            reset = config.opacity_reset_every > 0 and step % config.opacity_reset_every == 0
            state, dropped = _densify_jit(
                state,
                jax.random.fold_in(key_densify, step),
                jnp.float32(extent),
                jnp.bool_(reset),
                config=dataclasses.replace(config, render=render_config),
            )
            dropped_total += int(dropped)
            render_config, wanted = _next_render_config(programs, render_config, state, sample, scene, config, step)
            capped = max(capped, wanted)
            row.update(
                {
                    "splats": int(np.sum(np.asarray(state.splats.valid))),
                    "densify_dropped": int(dropped),
                    "opacity_reset": bool(reset),
                }
            )
            if wanted:
                row["max_pairs_capped"] = wanted
        history.append(row)
        if log is not None:
            log(
                f"[fit] step {step}/{config.steps}: loss {row['loss']:.4f}, train PSNR {row['psnr']:.2f} dB, "
                f"{int(np.sum(np.asarray(state.splats.valid)))} splats, max_pairs {render_config.max_pairs}"
            )
    seconds = time.perf_counter() - start
    degree_now = min(step // config.sh_every, config.sh_degree)
    final = _compact(state.splats)
    final = final.replace(sh=final.sh * _sh_mask(jnp.int32(degree_now), final.sh.shape[1]))
    psnr_test = None if test_scene is None else evaluate_splats(final, test_scene, config.render)
    return FitResult(
        splats=final,
        psnr_test=psnr_test,
        seconds=seconds,
        steps=step,
        history=tuple(history),
        max_pairs=render_config.max_pairs,
        overflow_views=overflow_views,
        densify_dropped=dropped_total,
        max_pairs_capped=capped,
        step_memory=max((b for b in programs.need.values() if b), default=None),
    )


# Temporaries of a fit step per splat row and view, whatever the image: XLA's analysis of lego_tiny's step
# (100x100, SH degree 3) at 2^24 rows was 21.9 GiB (projection, sort, SH and their gradients).
STEP_BYTES_PER_SPLAT = 1400


def capacity_bytes(config: FitConfig) -> int:
    """Bytes a fit takes by its capacity alone, checked before anything is allocated: the state twice (a
    step's input and its output: each splat's parameters, means 3, log-scales 3, quaternion 4, logit 1,
    SH 3 x (degree + 1)^2, with their two Adam moments, and its gradient statistics) and a step's
    temporaries per splat (`STEP_BYTES_PER_SPLAT` per view). The step's pixel part comes on top (its
    compiled program is checked too)."""
    floats = 11 + 3 * (config.sh_degree + 1) ** 2
    state = 2 * config.capacity * (4 * 3 * floats + 8 + 1)
    return state + config.capacity * config.views_per_step * STEP_BYTES_PER_SPLAT


def _check_first_block(programs: _Programs, render_config: SplatRenderConfig, scene: Scene, config: FitConfig):
    """The first block's program's memory (bytes or None), refused when it exceeds the free memory."""
    fits, need, available = programs.fits(render_config, min(config.densify_every, config.steps))
    if not fits:
        raise MemoryBudgetError(
            f"fitting splats to {_fit_size(scene, config)}: a step needs {need / 2**30:,.1f} GiB (XLA's analysis of "
            f"the compiled step, {render_config.max_pairs} splat-tile pairs a view), more than the "
            f"{available / 2**30:.1f} GiB this machine has free; pass --downscale K (a step's pixels and pairs "
            f"fall about K^2 times) or a lower --capacity (now {config.capacity})"
        )
    return need


def _timed_first_step(programs, render_config, state, scene: Scene, config: FitConfig, first: dict, log):
    """(state, steps run, views with pair overflow): two steps run one by one when a step renders at
    least `TIMED_STEP_PIXELS` pixels, the second timed (the first run of a program also takes its memory
    from the system: 2.5 x as long on the fox), the estimate logged and kept in `first`; none otherwise."""
    if config.views_per_step * scene.width * scene.height < TIMED_STEP_PIXELS or config.steps < 3:
        return state, 0, 0
    data, key = programs.args[3], programs.args[1]
    overflow = 0
    for step in range(2):
        timer = time.perf_counter()
        state, metrics = programs.get(render_config, 1)(state, key, jnp.int32(step), data, scene.intrinsics)
        overflow += int(np.sum(jax.device_get(metrics)["pair_overflow"]))  # waits for the step
        seconds = time.perf_counter() - timer
    first["step_seconds"] = round(seconds, 3)
    if log is not None:
        log(
            f"[fit] one step ({_fit_size(scene, config)}) took {seconds:.2f} s: about "
            f"{_duration(seconds * config.steps)} for {config.steps} steps on this machine "
            "(--downscale K: about K^2 x less)"
        )
    return state, 2, overflow


def _next_render_config(programs, render_config, state, sample, scene: Scene, config: FitConfig, step: int):
    """(the renderer's settings for the next block, the max_pairs wanted and not taken or 0): the pairs
    re-measured after a densification, kept at the current `max_pairs` when more would not fit."""
    wanted = dataclasses.replace(
        render_config, max_pairs=_max_pairs(state.splats, sample, scene.intrinsics, config.render)
    )
    next_count = min(config.densify_every, config.steps - step)
    if wanted.max_pairs <= render_config.max_pairs or programs.fits(wanted, next_count)[0]:
        return wanted, 0
    warnings.warn(
        f"splat fit, step {step}: {wanted.max_pairs} splat-tile pairs a view would not fit this machine's "
        f"memory; keeping {render_config.max_pairs} (the pairs beyond are dropped and counted in train.json)",
        stacklevel=3,
    )
    return render_config, wanted.max_pairs


def _duration(seconds: float) -> str:
    if seconds < 120:
        return f"{seconds:.0f} s"
    if seconds < 7200:
        return f"{seconds / 60:.0f} min"
    return f"{seconds / 3600:.1f} h"


def _compact(splats: Splats) -> Splats:
    """The valid rows only (host-side)."""
    keep = np.asarray(splats.valid)
    return jax.tree.map(lambda a: jnp.asarray(np.asarray(a)[keep]), splats)
