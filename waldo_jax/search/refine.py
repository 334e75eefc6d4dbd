"""Gradient refinement of camera poses through a differentiable objective, and the `+refine` methods.

`refine_poses(objective, poses, box, direction, config)` takes `config.steps` bounded gradient steps
on each pose's (origin, look-at point), its up vector fixed, to raise a differentiable objective
(c2w [P, 4, 4] -> scores [P]: a render and a smooth criterion, or a smooth pose oracle), all poses in
one batched call per step, and returns for each pose the best point it reached. `refine` adds the exact
score of those points and keeps, per pose, the better of start and refined pose, so it never lowers
a score. `refined_method(base)` is a search method (`egps+refine`, `grs+refine`, `pibs+refine`) that
runs its base method and, in its last `config.refine.epochs` epochs, replaces the last
`config.refine.poses` children by refined copies of the population's best poses.

The solver is optimistix's `OptaxMinimiser` around Adam (`optax.adam`, each update clipped to
`step_size`), stepped in a `lax.scan` of fixed length rather than `optimistix.minimise`'s while loop:
the cost is known before the run, every iterate can be checked, and an iterate whose objective is
not finite or whose origin leaves the scene box is never kept (the step that led there is undone).
Gradients are forward-mode by default (`jax.jvp`, six tangents: origin and look-at point), which any
renderer allows, or reverse-mode (`RefineConfig.gradient`: one `jax.vjp`, cheaper) where the source's
renderer supports it (the splat renderer; the marched NeRF renderer through its own backward pass,
`render.marched_vjp`); optimistix receives them through its reverse-mode API either way (see
`_loss`). Each gradient evaluation of one pose counts as `config.gradient_cost` renders in the budget.
Why Adam, the units, the box and the measured cost: docs/design.md, section "Search > Gradient refinement".
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Any, Callable, Optional, Tuple

import flax.struct
import jax
import jax.numpy as jnp
import optax
import optimistix as optx

from waldo_jax import autodiff
from waldo_jax.cameras import pose_to_c2w
from waldo_jax.errors import ConfigError
from waldo_jax.search import grs
from waldo_jax.search.method import SearchMethod, check_options
from waldo_jax.search.population import Population, direction_sign, gather_poses, top_k_indices
from waldo_jax.types import Array, Pose, PRNGKey

__all__ = [
    "REFINE_SUFFIX",
    "GRADIENT_COST",
    "GRADIENT_MODES",
    "RefineConfig",
    "RefinedConfig",
    "RefineResult",
    "SceneBox",
    "scene_box",
    "values_and_gradients",
    "refine_poses",
    "refine",
    "refined_method",
]

REFINE_SUFFIX = "+refine"

# Renders one gradient evaluation of one pose counts as, by default: the time of a forward-mode
# gradient (value and six tangents) over that of a render and exact score, rounded up, measured on
# the 2-core CPU for the costliest case, a trained fox NeRF with the saliency network at 64 px (11.5;
# benchmarks/gradient_cost.py). Pose oracles cost less (`waldo_jax.pipeline.gradient_cost_for`).
GRADIENT_COST = 12
GRADIENT_MODES = ("forward", "reverse")


@dataclasses.dataclass(frozen=True)
class RefineConfig:
    """Static settings of gradient refinement (hashable: part of the jit's static configuration).

    Attributes:
      poses: poses refined per refining epoch (the population's best, one batch).
      steps: gradient evaluations per pose (a fixed number: the cost is known before the run).
      step_size: Adam's learning rate, and the most one update moves a coordinate, in units of the
        scene extent (the largest side of the training origins' bounding box).
      gradient_cost: renders one gradient evaluation of one pose counts as in the budget (>= 2).
      epochs: a `+refine` method refines in its last `epochs` epochs.
      box_margin: the scene box is the training origins' bounding box grown by this fraction of the
        extent on every side; an origin outside it is never kept.
      gradient: "forward" (six `jax.jvp` tangents: any renderer, including the marched NeRF renderer's
        forward-mode variant) or "reverse" (one `jax.vjp`, cheaper: the splat renderer, the marched
        NeRF renderer with `gradient="reverse"`; `Source.gradient` says which a source allows).
    """

    poses: int = 4
    steps: int = 4
    step_size: float = 0.02
    gradient_cost: int = GRADIENT_COST
    epochs: int = 1
    box_margin: float = 0.1
    gradient: str = "forward"

    def __post_init__(self):
        for name in ("poses", "steps", "epochs"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ValueError(f"RefineConfig.{name} must be an int >= 1, got {value!r}")
        if isinstance(self.gradient_cost, bool) or not isinstance(self.gradient_cost, int) or self.gradient_cost < 2:
            raise ValueError(
                f"RefineConfig.gradient_cost must be an int >= 2 (a gradient costs more than a render), "
                f"got {self.gradient_cost!r}"
            )
        if not 0.0 < self.step_size <= 1.0:
            raise ValueError(
                f"RefineConfig.step_size must be in (0, 1] (a fraction of the scene extent), got {self.step_size!r}"
            )
        if not 0.0 <= self.box_margin <= 10.0:
            raise ValueError(f"RefineConfig.box_margin must be in [0, 10], got {self.box_margin!r}")
        if self.gradient not in GRADIENT_MODES:
            raise ValueError(f"RefineConfig.gradient must be one of {GRADIENT_MODES}, got {self.gradient!r}")

    def renders_per_epoch(self) -> int:
        """Renders one refining epoch's gradient steps count as: poses * steps * gradient_cost."""
        return self.poses * self.steps * self.gradient_cost

    def renders(self) -> int:
        """Renders all refining epochs' gradient steps count as."""
        return self.epochs * self.renders_per_epoch()


@flax.struct.dataclass
class SceneBox:
    """Where a refined camera may go: origins within [low, high]; `extent` sets the step units.

    Attributes:
      low, high: float32 [3] corners of the box.
      extent: float32 [], the largest side of the training origins' bounding box (before the margin).
    """

    low: Array
    high: Array
    extent: Array

    def contains(self, origin: Array) -> Array:
        """bool [...]: origin [..., 3] is finite and inside the box."""
        return jnp.all(jnp.isfinite(origin) & (origin >= self.low) & (origin <= self.high), axis=-1)


def scene_box(population: Population, margin: float = 0.1) -> SceneBox:
    """The training origins' bounding box grown by `margin` times its largest side on every side."""
    low, high = grs.origin_bounds(population)
    extent = jnp.maximum(jnp.max(high - low), 1e-6)
    return SceneBox(low=low - margin * extent, high=high + margin * extent, extent=extent)


@flax.struct.dataclass
class RefineResult:
    """What `refine_poses` (and `refine`) return for P poses.

    Attributes:
      poses: `Pose` [P, 3] fields: the best point each pose reached (the start when none was better).
      start_values, values: float32 [P], the objective at the start and at `poses` (NaN when never
        finite).
      accepted: int32 [P], steps that stayed finite and in the box.
      scores: float32 [P], `refine` only: the exact score of the returned pose (the start's when the
        refined pose did not score better); NaN from `refine_poses`.
      improved: bool [P], `refine` only: the refined pose scored better than the start.
    """

    poses: Pose
    start_values: Array
    values: Array
    accepted: Array
    scores: Array
    improved: Array


def values_and_gradients(
    objective: Callable[[Array], Array], start: Pose, extent: Array, offsets: Array, mode: str = "forward"
) -> Tuple[Array, Array]:
    """The objective and its gradient at poses moved by `offsets`.

    Pose p sits at origin start.origin[p] + extent * offsets[p, :3] and look-at point
    start.target[p] + extent * offsets[p, 3:], with its up vector. Each view's score depends on its
    own pose only (true of every criterion), so one derivative of all poses at once gives every
    pose's gradient: in forward mode one `jax.jvp` per coordinate (six, vmapped), each moving every
    pose along it; in reverse mode one `jax.vjp` of the sum of the values.

    Args:
      objective: c2w [P, 4, 4] -> scores [P].
      start: `Pose` with [P, 3] fields.
      extent: [] the unit of the offsets.
      offsets: float32 [P, 6].
      mode: "forward" or "reverse" (static).

    Returns:
      (values [P], gradients [P, 6]) with respect to the offsets.
    """

    def values(offsets):
        poses = Pose(
            origin=start.origin + extent * offsets[:, :3], target=start.target + extent * offsets[:, 3:], up=start.up
        )
        return jnp.asarray(objective(jax.vmap(pose_to_c2w)(poses)), jnp.float32).reshape(offsets.shape[0])

    if mode == "reverse":
        value, pullback = jax.vjp(values, offsets)
        return value, pullback(jnp.ones_like(value))[0]

    def along(direction):
        return jax.jvp(values, (offsets,), (jnp.broadcast_to(direction, offsets.shape),))

    with autodiff.tangents("forward"):  # rules whose fast form is the forward one (CSNet's) take it
        value, tangents = jax.vmap(along, out_axes=(None, 0))(jnp.eye(6, dtype=offsets.dtype))
    return value, tangents.T


def _loss(offsets: Array, args, mode: str = "forward") -> Tuple[Array, Array]:
    """optimistix's objective: the signed loss summed over poses, with the forward-mode gradient.

    Its value is sum_p -sign * objective_p and its reverse-mode gradient is the forward-mode one:
    the loss is written as value + <g, offsets - stop_gradient(offsets)> with value and g computed
    on stop_gradient(offsets), so reverse mode never enters the renderer. A pose whose value or
    gradient is not finite contributes 0 and a zero gradient (it does not move). Adam works per
    coordinate, so the sum over poses is P independent problems. Aux: the values [P].
    """
    objective, start, extent, sign = args
    fixed = jax.lax.stop_gradient(offsets)
    values, gradients = values_and_gradients(objective, start, extent, fixed, mode)
    ok = jnp.isfinite(values) & jnp.all(jnp.isfinite(gradients), axis=-1)
    loss = jnp.where(ok, -sign * values, 0.0)
    grad = jax.lax.stop_gradient(jnp.where(ok[:, None], -sign * gradients, 0.0))
    return jnp.sum(loss) + jnp.sum(grad * (offsets - fixed)), values


_loss_fns = {mode: functools.partial(_loss, mode=mode) for mode in GRADIENT_MODES}  # one object per mode


def _solver(config: RefineConfig) -> optx.OptaxMinimiser:
    update = optax.chain(optax.adam(config.step_size), optax.clip(config.step_size))
    return optx.OptaxMinimiser(update, rtol=0.0, atol=0.0)


def refine_poses(
    objective: Callable[[Array], Array],
    poses: Pose,
    box: SceneBox,
    direction: str = "max",
    config: RefineConfig = RefineConfig(),
) -> RefineResult:
    """`config.steps` bounded gradient steps from each pose; the best point of each path (jit-able).

    Args:
      objective: differentiable c2w [P, 4, 4] -> scores [P] in the criterion's direction; NaN
        allowed (that point is never kept).
      poses: `Pose` with [P, 3] fields, the starting points.
      box: where origins may go, and the unit of the steps (`scene_box`).
      direction: "max" or "min" (static).
      config: `RefineConfig` (static).

    Returns:
      `RefineResult` (scores NaN, improved False: see `refine` for the exact scores).
    """
    sign = direction_sign(direction)
    count = poses.origin.shape[0]
    args = (objective, poses, box.extent, jnp.float32(sign))
    loss = _loss_fns[config.gradient]
    offsets = jnp.zeros((count, 6), jnp.float32)
    solver = _solver(config)
    aux_struct = jax.ShapeDtypeStruct((count,), jnp.float32)
    state = solver.init(loss, offsets, args, {}, jax.ShapeDtypeStruct((), jnp.float32), aux_struct, frozenset())

    def inside(offsets):
        return box.contains(poses.origin + box.extent * offsets[:, :3]) & jnp.all(jnp.isfinite(offsets), axis=-1)

    def step(carry, index):
        offsets, state, best, best_fitness, start_values, accepted = carry
        proposed, state, values = solver.step(loss, offsets, args, {}, state, frozenset())
        # `values` are those of `offsets`, the point this step evaluated.
        fitness = jnp.where(jnp.isfinite(values) & inside(offsets), sign * values, -jnp.inf)
        better = fitness > best_fitness
        best = jnp.where(better[:, None], offsets, best)
        best_fitness = jnp.where(better, fitness, best_fitness)
        start_values = jnp.where(index == 0, values, start_values)
        keep = inside(proposed)  # a step that leaves the box or is not finite is undone
        accepted = accepted + (keep & jnp.isfinite(values)).astype(jnp.int32)
        return (jnp.where(keep[:, None], proposed, offsets), state, best, best_fitness, start_values, accepted), None

    nan = jnp.full((count,), jnp.nan, jnp.float32)
    init = (offsets, state, offsets, jnp.full((count,), -jnp.inf, jnp.float32), nan, jnp.zeros((count,), jnp.int32))
    (_, _, best, best_fitness, start_values, accepted), _ = jax.lax.scan(
        step, init, jnp.arange(config.steps, dtype=jnp.int32)
    )
    refined = Pose(
        origin=poses.origin + box.extent * best[:, :3], target=poses.target + box.extent * best[:, 3:], up=poses.up
    )
    values = jnp.where(jnp.isfinite(best_fitness), sign * best_fitness, jnp.nan)
    return RefineResult(
        poses=refined,
        start_values=start_values,
        values=values,
        accepted=accepted,
        scores=nan,
        improved=jnp.zeros((count,), bool),
    )


def _refine(
    objective, score_fn, poses: Pose, scores: Array, box: SceneBox, direction: str, config: RefineConfig
) -> RefineResult:
    sign = direction_sign(direction)
    result = refine_poses(objective, poses, box, direction, config)
    new_scores = jnp.asarray(score_fn(jax.vmap(pose_to_c2w)(result.poses)), jnp.float32).reshape(scores.shape)
    start_fitness = jnp.where(jnp.isfinite(scores), sign * scores, -jnp.inf)
    moved = jnp.any(result.poses.origin != poses.origin, axis=-1) | jnp.any(
        result.poses.target != poses.target, axis=-1
    )
    # A pose that did not move keeps its given score (its re-render could differ by rounding alone).
    improved = moved & jnp.isfinite(new_scores) & (sign * new_scores > start_fitness)
    pick = lambda new, old: jnp.where(improved.reshape((-1,) + (1,) * (new.ndim - 1)), new, old)  # noqa: E731
    return result.replace(
        poses=jax.tree.map(pick, result.poses, poses), scores=pick(new_scores, scores), improved=improved
    )


_refine_jit = jax.jit(_refine, static_argnames=("direction", "config"))


def refine(
    objective: Callable[[Array], Array],
    score_fn: Callable[[Array], Array],
    poses: Pose,
    scores: Array,
    box: SceneBox,
    direction: str = "max",
    config: RefineConfig = RefineConfig(),
) -> RefineResult:
    """Refines poses and keeps, per pose, the better of start and refined pose by the exact score.

    Args:
      objective: differentiable c2w [P, 4, 4] -> scores [P] the steps follow (a smooth stand-in for
        the criterion, e.g. `Criterion.smooth()` composed with a render).
      score_fn: the exact c2w [P, 4, 4] -> scores [P]; scores the refined poses once.
      poses: `Pose` with [P, 3] fields (e.g. `Result.top_poses` of a search).
      scores: float32 [P] their exact scores (e.g. `Result.top_scores`).
      box: `scene_box` of the search's population (or any `SceneBox`).
      direction: "max" or "min".
      config: `RefineConfig`.

    Returns:
      `RefineResult`: `scores` is never worse than the start's (NaN start scores can only improve).
    """
    return _refine_jit(
        jax.tree_util.Partial(objective),
        jax.tree_util.Partial(score_fn),
        poses,
        jnp.asarray(scores, jnp.float32),
        box,
        direction=direction,
        config=config,
    )


# ---------------------------------------------------------------------------------------------
# The `+refine` methods.


@dataclasses.dataclass(frozen=True)
class RefinedConfig:
    """Static settings of a `+refine` method.

    Attributes:
      base: the base method's `Config`.
      refine: `RefineConfig`.
      epochs: the search's epochs (the last `refine.epochs` of them refine).
    """

    base: Any
    refine: RefineConfig
    epochs: int

    @property
    def children_per_epoch(self) -> int:
        """The base method's children per epoch (the refined poses take the last slots of a refining epoch)."""
        return self.base.children_per_epoch

    def __post_init__(self):
        if self.refine.poses > self.children_per_epoch:
            raise ValueError(
                f"refining {self.refine.poses} poses needs at least as many children per epoch, "
                f"got {self.children_per_epoch}"
            )
        if self.refine.epochs > self.epochs:
            raise ValueError(f"refine epochs ({self.refine.epochs}) exceed the search's {self.epochs} epochs")


def _refined_children(
    population: Population, children: Pose, mask: Array, objective, config: RefinedConfig
) -> Tuple[Pose, Array]:
    """The epoch's children with the last `refine.poses` replaced by refined copies of the best poses."""
    count = config.refine.poses
    indices, ok = top_k_indices(population, count)
    box = scene_box(population, config.refine.box_margin)
    refined = refine_poses(objective, gather_poses(population, indices), box, population.direction, config.refine)
    n = config.children_per_epoch
    slot_ok = jnp.concatenate([jnp.zeros((n - count,), bool), ok])

    def put(child, new):
        new = jnp.concatenate([child[: n - count], new], axis=0)
        return jnp.where(slot_ok.reshape((-1,) + (1,) * (child.ndim - 1)), new, child)

    return jax.tree.map(put, children, refined.poses), mask | slot_ok


def refined_method(base: SearchMethod) -> SearchMethod:
    """`base` + gradient refinement in its last epochs, as a method named "<base>+refine".

    Its options are the base method's and `refine` (a `RefineConfig`); it needs the search's `epochs`.
    """
    if base.differentiable:
        raise ValueError(f"method {base.name!r} already refines")
    name = base.name + REFINE_SUFFIX

    def init(key: PRNGKey, population: Population, params, config: RefinedConfig):
        return base.init(key, population, params, config.base)

    def ask(
        key: PRNGKey, population: Population, state, params, config: RefinedConfig, epoch: Array, objective
    ) -> Tuple[Pose, Array, Population, Any]:
        children, mask, population, state = base.ask(key, population, state, params, config.base, epoch, objective)
        refining = epoch > config.epochs - config.refine.epochs
        children, mask = jax.lax.cond(
            refining,
            lambda c, m: _refined_children(population, c, m, objective, config),
            lambda c, m: (c, m),
            children,
            mask,
        )
        return children, mask, population, state

    def tell(key: PRNGKey, state, fitness: Array, params, config: RefinedConfig):
        return base.tell(key, state, fitness, params, config.base)

    options = base.options + ("refine",)

    def create(
        children_per_epoch: int,
        epochs: Optional[int] = None,
        method: str = name,
        refine: RefineConfig = RefineConfig(),
        **base_options,
    ):
        check_options(method, base_options, options)
        if epochs is None:
            raise ConfigError(f"search method {method!r} needs the search's epochs (its last refine.epochs refine)")
        return RefinedConfig(
            base=base.config_type.create(children_per_epoch, epochs, method=method, **base_options),
            refine=refine,
            epochs=int(epochs),
        )

    return SearchMethod(
        name=name,
        params_type=base.params_type,
        config_type=_Factory(create, options),
        ask_fn=ask,
        init_fn=init,
        tell_fn=tell,
        differentiable=True,
    )


@dataclasses.dataclass(frozen=True)
class _Factory:
    """A `config_type` whose `create` is a given function (hashable by identity) and whose options are `OPTIONS`."""

    create: Callable[..., Any]
    OPTIONS: Tuple[str, ...] = ()
