"""The exploration loop of "Finding Waldo" (MMSys'24), Algorithm 1, for any search method.

`explore(key, score_fn, Initial(c2w, scores), method, ExploreConfig(...)) -> Result`: from the scored
training views, every epoch the method is asked for `children_per_epoch` poses, `score_fn` scores them
(c2w [children_per_epoch, 4, 4] -> scores; render + criterion, composed by the caller) and they are
written into the population; the top-k views come back with CVIR / mCVIR and per-epoch curves. The
epochs are one `jax.lax.scan` inside one `jax.jit`, the finish (top-k, metrics, archive) a second
program that searches of other methods share; `explore_loop` runs the same epochs as a
Python loop, `explore_seeds` vmaps it over a batch of keys. `score_fn` is part of the compilation
cache key: define it once, or pass arrays through a `jax.tree_util.Partial`. `budget_children` turns
the paper's "low" / "high" budgets into children per epoch. Randomness, fixed shapes, `Partial`
and the budgets: see docs/design.md, section "Search > The exploration loop".
"""

from __future__ import annotations

import dataclasses
import functools
import math
from typing import Any, Callable, Dict, Mapping, Optional, Tuple, Union

import flax.struct
import jax
import jax.numpy as jnp
import numpy as np

from waldo_jax.cameras import camera_focus, pose_to_c2w
from waldo_jax.errors import MAX_INT32
from waldo_jax.search.archive import Archive, ViewGrid, archive_of, coverage, qd_score
from waldo_jax.search.method import SearchMethod, split_for_state
from waldo_jax.search.metrics import EpochMetrics, epoch_metrics, population_cvir, population_mcvir, shot_gains
from waldo_jax.search.population import (
    DIRECTIONS,
    Population,
    direction_sign,
    gather_poses,
    init_population,
    top_k_indices,
    training_poses,
    write_children,
)
from waldo_jax.search.refine import REFINE_SUFFIX, RefineConfig
from waldo_jax.search.registry import get_method
from waldo_jax.search.views import DEFAULT_MIN_SEPARATION, SceneFrame, distinct_count, distinct_top_k, scene_frame
from waldo_jax.types import Array, Pose, PRNGKey

__all__ = [
    "BUDGETS",
    "ExploreConfig",
    "Initial",
    "Result",
    "SeedsResult",
    "budget_children",
    "explore",
    "explore_loop",
    "explore_seeds",
    "search_memory",
    "result_bytes",
]

# Total images (training + generated) of the paper's budgets, inclusive bounds.
BUDGETS = {"low": (250, 300), "high": (900, 1000)}

Budget = Union[str, Tuple[int, int]]


def _budget_bounds(budget: Budget) -> Tuple[int, int]:
    if isinstance(budget, str):
        if budget not in BUDGETS:
            raise ValueError(f"budget must be one of {tuple(BUDGETS)} or a (min, max) pair, got {budget!r}")
        return BUDGETS[budget]
    low, high = (int(b) for b in budget)
    if not 0 < low <= high:
        raise ValueError(f"a budget (min, max) needs 0 < min <= max, got {budget!r}")
    return low, high


def budget_children(n_train: int, budget: Budget = "low", epochs: int = 5) -> int:
    """children_per_epoch so that n_train + epochs * children_per_epoch falls within the budget.

    The total aims at the middle of the budget's range (275 for "low", 950 for "high") and is then
    kept inside it; at least one child per epoch.

    Args:
      n_train: number of training views.
      budget: "low" (250 to 300 images in total), "high" (900 to 1000) or a (min, max) pair.
      epochs: number of epochs.

    Returns:
      children_per_epoch.

    Raises:
      ValueError: when n_train alone (plus one child per epoch) exceeds the budget, or no whole
        number of children per epoch lands in the range.
    """
    low, high = _budget_bounds(budget)
    n_train, epochs = int(n_train), int(epochs)
    if epochs < 1:
        raise ValueError(f"epochs must be >= 1, got {epochs}")
    if n_train < 1:
        raise ValueError(f"n_train must be >= 1, got {n_train}")
    if n_train + epochs > high:
        raise ValueError(
            f"{n_train} training views already exceed the {budget!r} budget of at most {high} images "
            f"with one child per epoch over {epochs} epochs; choose a larger budget or fewer views"
        )
    fewest = max(1, math.ceil((low - n_train) / epochs))
    most = (high - n_train) // epochs
    if fewest > most:
        raise ValueError(
            f"no whole number of children per epoch puts {n_train} + {epochs} x children in [{low}, {high}]; "
            f"set children_per_epoch explicitly"
        )
    goal = round(((low + high) / 2 - n_train) / epochs)
    return int(min(max(goal, fewest), most))


@dataclasses.dataclass(frozen=True)
class ExploreConfig:
    """Static settings of an exploration run (hashable: it is a static argument of the jit).

    Attributes:
      method: "grs", "pibs", "egps", "grs+refine", "egps+refine", "pibs+refine" or "evosax:NAME"
        (`waldo_jax.search.get_method`).
      epochs: number of epochs E (paper: 5).
      children_per_epoch: poses generated per epoch; None derives it from the budget.
      budget: "low", "high" or a (min, max) total image count; used when children_per_epoch is None.
      top_k: views returned (paper: 10).
      top_n: N of mCVIR and of the mean-top-N curve (paper: 10).
      min_separation: degrees; the top-k returned are the best views pairwise at least this far
        apart (`views.distinct_top_k`: different shots); 0 returns the paper's top-k. CVIR and mCVIR
        are the paper's whatever it is.
      grid: the cells of view descriptors (`archive.ViewGrid`): every run reports its archive's
        coverage and QD-score over them, and MAP-Elites searches them.
      direction: "max" when higher criterion scores are better, "min" when lower ones are.
      focus_min_fraction: training look-at points lie at least this fraction of the distance to the
        scene focus in front of their camera (`population.training_look_at`).
      options: the method's own options, given as a mapping and kept as sorted (name, value) pairs
        (hashable); they build its config (`method_config`), which refuses an option the method does
        not have. PIBS: `top_c` (views paired) and `fallback` ("none" masks the slots it cannot fill,
        "grs" fills them with GRS poses); the `+refine` methods: their base method's and `refine`, a
        `RefineConfig`, whose gradient steps count as `refine.renders()` renders, which come out of
        the children: a budget gives them fewer children per epoch, so every method costs the same
        (`cost`).
    """

    method: str = "egps"
    epochs: int = 5
    children_per_epoch: Optional[int] = None
    budget: Budget = "low"
    top_k: int = 10
    top_n: int = 10
    min_separation: float = DEFAULT_MIN_SEPARATION
    grid: ViewGrid = ViewGrid()
    direction: str = "max"
    focus_min_fraction: float = 0.1
    options: Union[Mapping[str, Any], Tuple[Tuple[str, Any], ...]] = ()

    def __post_init__(self):
        if self.epochs < 1:
            raise ValueError(f"epochs must be >= 1, got {self.epochs}")
        if self.children_per_epoch is not None and self.children_per_epoch < 1:
            raise ValueError(f"children_per_epoch must be >= 1, got {self.children_per_epoch}")
        if self.top_k < 1 or self.top_n < 1:
            raise ValueError(f"top_k and top_n must be >= 1, got {self.top_k} and {self.top_n}")
        if self.direction not in DIRECTIONS:
            raise ValueError(f"direction must be one of {DIRECTIONS}, got {self.direction!r}")
        separation = float(self.min_separation)
        if not 0.0 <= separation <= 180.0:
            raise ValueError(f"min_separation must be in [0, 180] degrees, got {self.min_separation!r}")
        object.__setattr__(self, "min_separation", separation)
        if not isinstance(self.grid, ViewGrid):
            raise ValueError(f"grid must be a ViewGrid, got {type(self.grid).__name__}")
        if not isinstance(self.budget, str):  # a list would make the config unhashable
            object.__setattr__(self, "budget", tuple(int(b) for b in self.budget))
        _budget_bounds(self.budget)
        options = dict(self.options)  # a dict would make the config unhashable
        if not all(isinstance(name, str) for name in options):
            raise ValueError(f"options must be named by strings, got {sorted(map(repr, options))}")
        if "grid" in options:
            raise ValueError("the view grid is ExploreConfig.grid, not a method option")
        object.__setattr__(self, "options", tuple(sorted(options.items())))

    @property
    def method_options(self) -> Dict[str, Any]:
        """The method's options as a dict."""
        return dict(self.options)

    def with_options(self, **options: Any) -> "ExploreConfig":
        """This config with the given method options set (the others kept)."""
        return dataclasses.replace(self, options={**self.method_options, **options})

    def method_config(self, method: Optional[SearchMethod] = None) -> Any:
        """The method's static config for this (resolved) config: `SearchMethod.make_config` with
        children_per_epoch, epochs and `options`.

        Args:
          method: the method (default: `get_method(self.method)`).

        Raises:
          ConfigError (a ValueError): an option the method does not have (the message names it and the method).
          ValueError: children_per_epoch is None (call `resolve` first) or an option's value is refused.
        """
        if self.children_per_epoch is None:
            raise ValueError("children_per_epoch is None: resolve the config first (ExploreConfig.resolve)")
        method = get_method(self.method) if method is None else method
        grid = {"grid": self.grid} if "grid" in method.options else {}  # MAP-Elites searches the run's grid
        return method.make_config(self.children_per_epoch, self.epochs, **self.method_options, **grid)

    def resolve(self, n_train: int) -> "ExploreConfig":
        """This config with children_per_epoch fixed (from the budget when it is None).

        Raises:
          ValueError: top_k exceeds the capacity n_train + epochs * children_per_epoch.
        """
        resolved = self
        if self.children_per_epoch is None:
            children = budget_children(n_train, self.budget, self.epochs)
            # Gradient steps are paid for with children, so a refining method costs at most what the
            # others cost (fewer than `epochs` renders less when its gradient renders do not divide evenly).
            children -= -(-self.gradient_renders() // self.epochs)
            if children < 1:
                raise ValueError(
                    f"refinement costs {self.gradient_renders()} renders, more than the {self.budget!r} "
                    f"budget leaves for children after {n_train} training views; refine fewer poses "
                    "or take fewer steps"
                )
            resolved = dataclasses.replace(self, children_per_epoch=children)
        capacity = int(n_train) + resolved.epochs * resolved.children_per_epoch
        renders = capacity + resolved.gradient_renders()
        if renders > MAX_INT32:  # slots and render counts are int32 under jit; each flag alone may fit
            refined = (
                f" and {resolved.gradient_renders():,} for its gradient steps (--refine-poses x --refine-steps x "
                "--gradient-cost)"
                if resolved.gradient_renders()
                else ""
            )
            raise ValueError(
                f"the run would render {renders:,} views, {capacity:,} held ({n_train} training + {resolved.epochs} "
                f"epochs (--epochs) x {resolved.children_per_epoch} children (--children-per-epoch)){refined}: "
                f"past the {MAX_INT32:,} that int32 counts"
            )
        if resolved.top_k > capacity:
            raise ValueError(
                f"top_k (--top-k) {resolved.top_k} exceeds the {capacity} views of the run ({n_train} training "
                f"+ {resolved.epochs} epochs x {resolved.children_per_epoch} children)"
            )
        return resolved

    def capacity(self, n_train: int) -> int:
        """C = n_train + epochs * children_per_epoch."""
        resolved = self.resolve(n_train)
        return int(n_train) + resolved.epochs * resolved.children_per_epoch

    def refine_config(self) -> RefineConfig:
        """The `+refine` methods' `RefineConfig`: the `refine` option, or the default one."""
        return self.method_options.get("refine", RefineConfig())

    def gradient_renders(self) -> int:
        """Renders the method's gradient steps count as (0 unless it refines; `RefineConfig.renders`)."""
        return self.refine_config().renders() if self.method.endswith(REFINE_SUFFIX) else 0

    def cost(self, n_train: int) -> dict:
        """The run's cost in renders, training views included: what the budget bounds.

        Returns:
          {"renders": total, "training_views": n_train, "children": epochs * children_per_epoch,
            "gradient_evaluations": poses refined x steps (0 unless the method refines),
            "renders_per_gradient_evaluation": `RefineConfig.gradient_cost` (0 unless it refines)}.
          A child counts whether or not its method masked it (a fixed-shape epoch renders it).
        """
        resolved = self.resolve(n_train)
        gradients = resolved.gradient_renders()
        children = resolved.epochs * resolved.children_per_epoch
        per_gradient = resolved.refine_config().gradient_cost if gradients else 0
        return {
            "renders": int(n_train) + children + gradients,
            "training_views": int(n_train),
            "children": children,
            "gradient_evaluations": gradients // per_gradient if gradients else 0,
            "renders_per_gradient_evaluation": per_gradient,
        }


@flax.struct.dataclass
class Initial:
    """The scored training views a search starts from.

    Attributes:
      c2w: float32 [N, 4, 4] (or [N, 3, 4]) training camera-to-world matrices.
      scores: float32 [N] their raw criterion scores (from the real images or from renders: the
        caller decides). NaN marks a failed score.
      focus: optional [3] scene focus point for the training look-at points and the scene frame
        (default: `waldo_jax.cameras.camera_focus` of c2w).
      up: optional [3] the scene's up for the scene frame (default: `waldo_jax.cameras.scene_up` of c2w).
    """

    c2w: Array
    scores: Array
    focus: Optional[Array] = None
    up: Optional[Array] = None


@flax.struct.dataclass
class Result:
    """What a search returns.

    Attributes:
      population: the final `Population` (training views and every child, with scores).
      top_indices: int32 [k], slots of the k best views pairwise at least `config.min_separation`
        degrees apart (different shots, `views.distinct_top_k`), best first; the paper's top-k
        when min_separation is 0.
      top_valid: bool [k], False for entries beyond the number of usable (distinct) views.
      top_poses: `Pose` with [k, 3] fields.
      top_c2w: float32 [k, 4, 4].
      top_scores: float32 [k] raw scores (NaN where top_valid is False).
      paper_top_indices: int32 [k], the paper's top-k: the k best views whatever their separation.
      paper_top_valid: bool [k].
      paper_top_shots: int32 [], how many different shots (at `config.min_separation`) the paper's
        top-k holds (`views.distinct_count`).
      metrics: `EpochMetrics`, [E + 1] curves (index 0: the training views).
      cvir: float32 [] CVIR in percent.
      mcvir: float32 [] mCVIR in percent (N = config.top_n), on the paper's top views.
      dcvir: float32 [] dCVIR in percent: the mean of the returned top-k over the best training view
        (`metrics.shot_gains`).
      shots_beating_train: int32 [], entries of the returned top-k better than the best training view.
      archive: `archive.Archive` [M] of every view of the run over `config.grid`.
      coverage: float32 [], the share of the archive's cells filled.
      qd_score: float32 [], the archive's QD-score over `qd_floor` (`archive.qd_score`).
      qd_floor: float32 [], the raw score of the worst usable training view (the QD-score's floor).
    """

    population: Population
    top_indices: Array
    top_valid: Array
    top_poses: Pose
    top_c2w: Array
    top_scores: Array
    paper_top_indices: Array
    paper_top_valid: Array
    paper_top_shots: Array
    metrics: EpochMetrics
    cvir: Array
    mcvir: Array
    dcvir: Array
    shots_beating_train: Array
    archive: Archive
    coverage: Array
    qd_score: Array
    qd_floor: Array


@flax.struct.dataclass
class SeedsResult:
    """`explore_seeds` output: per-seed results (leading axis K) and CVIR / mCVIR statistics.

    Attributes:
      results: `Result` whose every leaf has a leading [K] axis.
      cvir_mean, cvir_std, mcvir_mean, mcvir_std, dcvir_mean, dcvir_std: float32 [] over the K seeds
        (population std, ddof = 0; NaN if any seed's value is NaN).
    """

    results: Result
    cvir_mean: Array
    cvir_std: Array
    mcvir_mean: Array
    mcvir_std: Array
    dcvir_mean: Array
    dcvir_std: Array


# ---------------------------------------------------------------------------------------------
# Setup (host side, raises clear errors).


def _resolve_method(method: Union[str, SearchMethod, None], config: ExploreConfig) -> SearchMethod:
    if isinstance(method, SearchMethod):
        return method
    return get_method(config.method if method is None else method)


def _as_partial(score_fn: Callable) -> jax.tree_util.Partial:
    if not callable(score_fn):
        raise TypeError(f"score_fn must be callable, got {type(score_fn).__name__}")
    return score_fn if isinstance(score_fn, jax.tree_util.Partial) else jax.tree_util.Partial(score_fn)


def _prepare(initial: Initial, method, config: Optional[ExploreConfig], params, objective_fn=None):
    """Validates the inputs and returns everything the jitted search needs."""
    config = ExploreConfig() if config is None else config
    search_method = _resolve_method(method, config)
    if search_method.differentiable != search_method.name.endswith(REFINE_SUFFIX):
        raise ValueError(
            f"method {search_method.name!r}: a method takes gradient steps exactly when its name "
            f"ends with {REFINE_SUFFIX!r} (its budget is counted that way)"
        )
    if search_method.differentiable and objective_fn is None:
        raise ValueError(
            f"method {search_method.name!r} takes gradient steps: pass a differentiable objective_fn "
            "(e.g. the criterion's smooth() composed with the render)"
        )
    config = dataclasses.replace(config, method=search_method.name)
    c2w = np.asarray(initial.c2w, np.float32)
    scores = np.asarray(initial.scores, np.float32)
    if c2w.ndim != 3 or c2w.shape[1:] not in ((4, 4), (3, 4)) or c2w.shape[0] < 1:
        raise ValueError(f"initial.c2w must be [N, 4, 4] or [N, 3, 4] with N >= 1, got shape {c2w.shape}")
    if scores.shape != (c2w.shape[0],):
        raise ValueError(f"initial.scores must have shape ({c2w.shape[0]},), got {scores.shape}")
    if c2w.shape[1] == 3:
        c2w = np.concatenate([c2w, np.broadcast_to(np.array([[[0, 0, 0, 1]]], np.float32), (len(c2w), 1, 4))], 1)
    n_train = c2w.shape[0]
    config = config.resolve(n_train)  # raises when top_k exceeds the capacity
    method_config = config.method_config(search_method)  # raises for an option the method does not have
    params = search_method.default_params() if params is None else params
    focus = camera_focus(c2w) if initial.focus is None else np.asarray(initial.focus, np.float64)
    start = _Start(
        poses=training_poses(c2w, focus, config.focus_min_fraction),
        c2w=jnp.asarray(c2w),
        scores=jnp.asarray(scores),
        frame=scene_frame(c2w, focus, None if initial.up is None else np.asarray(initial.up, np.float64)),
    )
    objective = None if objective_fn is None else _as_partial(objective_fn)
    return search_method, method_config, config, params, start, objective


# ---------------------------------------------------------------------------------------------
# The search (pure, jitted with method / method_config / config static).


@flax.struct.dataclass
class _Start:
    """What the search starts from: the training poses, matrices [N, 4, 4], scores [N] and the scene frame."""

    poses: Pose
    c2w: Array
    scores: Array
    frame: SceneFrame


def _init(start: _Start, config: ExploreConfig) -> Population:
    n_train = int(start.c2w.shape[0])
    return init_population(
        start.poses, start.scores, config.capacity(n_train), config.direction, train_c2w=start.c2w, frame=start.frame
    )


def _report(method_name: str, epochs: int, top_n: int, runs: int, run, epoch, best, mean_top, scored, failed) -> None:
    """Host-side progress line (one per epoch and run; under vmap the callback runs once per run)."""
    for r, e, b, m, s, f in zip(*(np.atleast_1d(np.asarray(v)) for v in (run, epoch, best, mean_top, scored, failed))):
        label = f" run {int(r) + 1}/{runs}" if runs > 1 else ""
        print(
            f"[explore {method_name}{label}] epoch {int(e)}/{epochs}: best {float(b):.6g}, "
            f"mean top-{top_n} {float(m):.6g}, scored {int(s)}, failed {int(f)}",
            flush=True,
        )


def _init_state(key: PRNGKey, population: Population, params, method: SearchMethod, method_config):
    """The method's state before epoch 1, from key fold_in(key, 0) (epochs use fold_in(key, e), e >= 1)."""
    return method.init(jax.random.fold_in(key, 0), population, params, method_config)


def _epoch_step(
    key: PRNGKey,
    score_fn: jax.tree_util.Partial,
    objective,
    carry,
    epoch: Array,
    params,
    method: SearchMethod,
    method_config,
    config: ExploreConfig,
    progress: bool = False,
    run: Array = 0,
    runs: int = 1,
):
    """One epoch of Algorithm 1: ask, score, write, tell. epoch is 1-based (int32, may be traced).

    carry is (population, method state); with `progress` (static) it prints a line, where run / runs
    label the run (run r of a vmapped batch of `runs` seeds).
    """
    population, state = carry
    n = config.children_per_epoch
    ask_key, tell_key = split_for_state(jax.random.fold_in(key, epoch), method)
    children, mask, population, state = method.ask(ask_key, population, state, params, method_config, epoch, objective)
    c2w = jax.vmap(pose_to_c2w)(children)  # [n, 4, 4]
    scores = jnp.asarray(score_fn(c2w), jnp.float32).reshape(n)
    offset = population.num_train + (epoch - 1) * n
    population = write_children(population, children, c2w, scores, mask, epoch, offset)
    if method.stateful:
        fitness = jax.lax.dynamic_slice(population.fitness, (offset,), (n,))  # -inf where masked or failed
        state = method.tell(tell_key, state, fitness, params, method_config)
    if progress:
        curves = epoch_metrics(population, config.epochs, config.top_n)
        jax.debug.callback(
            lambda *a: _report(method.name, config.epochs, config.top_n, runs, *a),
            run,
            epoch,
            curves.best[epoch],
            curves.mean_top_n[epoch],
            curves.num_scored[epoch],
            curves.num_failed[epoch],
        )
    return population, state


def _finish(population: Population, config: ExploreConfig) -> Result:
    fitness, frame = population.fitness, population.frame
    paper, paper_ok = top_k_indices(population, config.top_k)
    indices, ok = distinct_top_k(fitness, population.c2w, frame, config.top_k, config.min_separation)
    dcvir, beating = shot_gains(population, indices, ok)
    slots = jnp.arange(population.capacity, dtype=jnp.int32)
    archive = archive_of(fitness, population.c2w, slots, frame, config.grid)
    floor = jnp.min(jnp.where(population.is_train & jnp.isfinite(fitness), fitness, jnp.inf))
    floor = jnp.where(jnp.isfinite(floor), floor, jnp.nan)  # no usable training view: no floor
    return Result(
        population=population,
        top_indices=indices,
        top_valid=ok,
        top_poses=gather_poses(population, indices),
        top_c2w=population.c2w[indices],
        top_scores=jnp.where(ok, population.score[indices], jnp.nan),
        paper_top_indices=paper,
        paper_top_valid=paper_ok,
        paper_top_shots=distinct_count(population.c2w[paper], paper_ok, frame, config.min_separation),
        metrics=epoch_metrics(population, config.epochs, config.top_n),
        cvir=population_cvir(population),
        mcvir=population_mcvir(population, config.top_n),
        dcvir=dcvir,
        shots_beating_train=beating,
        archive=archive,
        coverage=coverage(archive),
        qd_score=qd_score(archive, floor),
        qd_floor=direction_sign(population.direction) * floor,
    )


def _scan(
    key: PRNGKey,
    score_fn,
    objective,
    start: _Start,
    params,
    method: SearchMethod,
    method_config,
    config: ExploreConfig,
    progress: bool = False,
    run: Array = 0,
    runs: int = 1,
) -> Population:
    """Algorithm 1's epochs as one `lax.scan`: the final population (`_finish` makes the `Result`)."""
    population = _init(start, config)
    carry = (population, _init_state(key, population, params, method, method_config))

    def body(carry, epoch):
        return _epoch_step(
            key, score_fn, objective, carry, epoch, params, method, method_config, config, progress, run, runs
        ), None

    (population, _), _ = jax.lax.scan(body, carry, jnp.arange(1, config.epochs + 1, dtype=jnp.int32))
    return population


def _scan_seeds(
    keys: PRNGKey,
    score_fn,
    objective,
    start: _Start,
    params,
    method: SearchMethod,
    method_config,
    config: ExploreConfig,
    progress: bool = False,
) -> Population:
    """`_scan` vmapped over keys [K]: the K final populations (leading axis K)."""
    runs = keys.shape[0]
    return jax.vmap(
        lambda key, run: _scan(
            key, score_fn, objective, start, params, method, method_config, config, progress, run, runs
        )
    )(keys, jnp.arange(runs, dtype=jnp.int32))


def _finish_seeds(populations: Population, config: ExploreConfig) -> SeedsResult:
    """`_finish` vmapped over K populations, with the mean / std of CVIR, mCVIR and dCVIR over them."""
    results = jax.vmap(lambda population: _finish(population, config))(populations)
    return SeedsResult(
        results=results,
        cvir_mean=jnp.mean(results.cvir),
        cvir_std=jnp.std(results.cvir),
        mcvir_mean=jnp.mean(results.mcvir),
        mcvir_std=jnp.std(results.mcvir),
        dcvir_mean=jnp.mean(results.dcvir),
        dcvir_std=jnp.std(results.dcvir),
    )


def _finish_static(config: ExploreConfig) -> ExploreConfig:
    """The part of `config` that `_finish` reads (epochs, children, top-k, top-n, separation, grid), the rest
    at its defaults: the finishing program's static argument, so that searches that differ only in their
    method or its options share one compiled finish (the direction is the population's own, static)."""
    return ExploreConfig(
        epochs=config.epochs,
        children_per_epoch=config.children_per_epoch,
        top_k=config.top_k,
        top_n=config.top_n,
        min_separation=config.min_separation,
        grid=config.grid,
    )


_STATIC = ("method", "method_config", "config", "progress")
# A search runs as two compiled programs: the epochs (`_scan`: the method, the criterion and the render
# inside) and the finish (`_finish`: top-k, metrics, archive), whose static config holds only what it reads
# (`_finish_static`). Searches that differ in their method or criterion but not in their shapes and
# top-k settings (the paper's three methods on one scene) then compile the finish once, not per method.
_scan_jit = jax.jit(_scan, static_argnames=_STATIC)
_scan_seeds_jit = jax.jit(_scan_seeds, static_argnames=_STATIC)
_init_jit = jax.jit(_init, static_argnames=("config",))
_init_state_jit = jax.jit(_init_state, static_argnames=("method", "method_config"))
_epoch_step_jit = jax.jit(_epoch_step, static_argnames=_STATIC)
_finish_jit = jax.jit(_finish, static_argnames=("config",))
_finish_seeds_jit = jax.jit(_finish_seeds, static_argnames=("config",))


def _programs(key: PRNGKey):
    """(the epochs' program, the finishing program) of a search with one key [] or keys [K]."""
    return (_scan_jit, _finish_jit) if jnp.ndim(key) == 0 else (_scan_seeds_jit, _finish_seeds_jit)


def _run_search(key, score_fn, objective, start: _Start, params, method, method_config, config, progress: bool):
    """The search with key [] (a `Result`) or keys [K] (a `SeedsResult`): its two programs in turn."""
    scan, finish = _programs(key)
    populations = scan(
        key,
        score_fn,
        objective,
        start,
        params,
        method=method,
        method_config=method_config,
        config=config,
        progress=progress,
    )
    return finish(populations, config=_finish_static(config))


# ---------------------------------------------------------------------------------------------
# Public entry points.


def explore(
    key: PRNGKey,
    score_fn: Callable[[Array], Array],
    initial: Initial,
    method: Union[str, SearchMethod, None] = None,
    config: Optional[ExploreConfig] = None,
    params=None,
    objective_fn: Optional[Callable[[Array], Array]] = None,
    progress: bool = False,
) -> Result:
    """Runs one search (Algorithm 1) as a compiled `lax.scan` over epochs, then its compiled finish.

    Args:
      key: PRNG key (`jax.random.key(seed)`); epoch e uses `fold_in(key, e)`, a method's initial
        state `fold_in(key, 0)`.
      score_fn: jit-able c2w [P, 4, 4] -> raw scores [P] (P = children_per_epoch); NaN allowed
        (such a view is kept, counted as failed and never selected). Static (by identity), or a
        `jax.tree_util.Partial` whose bound arrays are traced.
      initial: `Initial` with the training c2w [N, 4, 4] and their scores [N].
      method: a name (`get_method`) or a `SearchMethod`; overrides `config.method` when given.
      config: `ExploreConfig` (default: EGPS, 5 epochs, low budget).
      params: the method's `Params` pytree (default: the paper's values).
      objective_fn: the `+refine` methods' differentiable c2w [P, 4, 4] -> scores [P] (same
        direction as score_fn; e.g. a render composed with `Criterion.smooth()`); unused otherwise.
      progress: print one line per epoch (through `jax.debug.callback`; a static argument of the jit,
        outside `config`).

    Returns:
      `Result`.
    """
    search_method, method_config, config, params, start, objective = _prepare(
        initial, method, config, params, objective_fn
    )
    return _run_search(
        key,
        _as_partial(score_fn),
        objective,
        start,
        params,
        search_method,
        method_config,
        config,
        bool(progress),
    )


def search_memory(
    key: PRNGKey,
    score_fn: Callable[[Array], Array],
    initial: Initial,
    method: Union[str, SearchMethod, None] = None,
    config: Optional[ExploreConfig] = None,
    params=None,
    objective_fn: Optional[Callable[[Array], Array]] = None,
    progress: bool = False,
) -> Optional[int]:
    """Bytes the compiled search needs: its arguments, outputs and temporaries by XLA's own analysis of
    the programs `explore` (one key) or `explore_seeds` (keys [K]) would run, with the same arguments: the
    epochs' program, or the finishing one with the epochs' arguments still held, whichever needs more.

    It compiles those programs without running them; the compiles are cached, so the run that follows
    with the same arguments does not compile again. None where the backend gives no analysis
    (`program_memory`).
    """
    search_method, method_config, config, params, start, objective = _prepare(
        initial, method, config, params, objective_fn
    )
    scan, finish = _programs(key)
    statics = dict(method=search_method, method_config=method_config, config=config, progress=bool(progress))
    arguments = (key, _as_partial(score_fn), objective, start, params)
    epochs = scan.lower(*arguments, **statics).compile()
    populations = jax.eval_shape(functools.partial(scan, **statics), *arguments)
    finishing = finish.lower(populations, config=_finish_static(config)).compile()
    need, held = program_memory(epochs), program_memory(epochs, ("argument_size_in_bytes",))
    finish_need = program_memory(finishing)
    if need is None or held is None or finish_need is None:
        return None
    return max(need, finish_need + held)


def result_bytes(
    score_fn: Callable[[Array], Array],
    initial: Initial,
    method: Union[str, SearchMethod, None] = None,
    config: Optional[ExploreConfig] = None,
    params=None,
    objective_fn: Optional[Callable[[Array], Array]] = None,
) -> int:
    """Bytes of one seed's `Result` (its population, scores and metrics), from the search's shapes alone
    (`jax.eval_shape`: traced, not compiled): what every seed of `explore_seeds` keeps, at least."""
    search_method, method_config, config, params, start, objective = _prepare(
        initial, method, config, params, objective_fn
    )

    def search(*arguments):  # the two programs' shapes, traced together (nothing compiles)
        population = _scan(*arguments, method=search_method, method_config=method_config, config=config)
        return _finish(population, config)

    shapes = jax.eval_shape(
        search,
        jax.random.key(0),
        _as_partial(score_fn),
        objective,
        start,
        params,
    )
    return int(sum(leaf.size * leaf.dtype.itemsize for leaf in jax.tree.leaves(shapes)))


def program_memory(
    compiled, parts: Tuple[str, ...] = ("argument_size_in_bytes", "output_size_in_bytes", "temp_size_in_bytes")
) -> Optional[int]:
    """Bytes a compiled program (`jax.jit(f).lower(...).compile()`) needs by XLA's analysis: arguments,
    outputs and temporaries (or the `parts` of the analysis named), or None where the backend gives none.
    XLA's figure is one device's: a program split over a CPU's host devices counts every device's part,
    since they all take from the host's memory; on accelerators, each with its own, it is the one device's."""
    try:
        analysis = compiled.memory_analysis()
    except (NotImplementedError, RuntimeError):  # pragma: no cover - backends without the analysis
        return None
    if analysis is None:
        return None
    per_device = int(sum(max(int(getattr(analysis, name, 0) or 0), 0) for name in parts))
    devices = {d for s in jax.tree.leaves(compiled.output_shardings) for d in s.device_set}
    on_host = devices and all(d.platform == "cpu" for d in devices)
    return per_device * len(devices) if on_host else per_device


def explore_loop(
    key: PRNGKey,
    score_fn: Callable[[Array], Array],
    initial: Initial,
    method: Union[str, SearchMethod, None] = None,
    config: Optional[ExploreConfig] = None,
    params=None,
    objective_fn: Optional[Callable[[Array], Array]] = None,
    progress: bool = False,
) -> Result:
    """`explore` as a Python loop over a jitted per-epoch step (same arguments, same result).

    Useful to inspect or checkpoint between epochs, and as the reference the scan is tested against.
    """
    search_method, method_config, config, params, start, objective = _prepare(
        initial, method, config, params, objective_fn
    )
    score_fn = _as_partial(score_fn)
    population = _init_jit(start, config=config)
    carry = (population, _init_state_jit(key, population, params, method=search_method, method_config=method_config))
    for epoch in range(1, config.epochs + 1):
        carry = _epoch_step_jit(
            key,
            score_fn,
            objective,
            carry,
            jnp.int32(epoch),
            params,
            method=search_method,
            method_config=method_config,
            config=config,
            progress=bool(progress),
        )
    return _finish_jit(carry[0], config=_finish_static(config))


def explore_seeds(
    keys: PRNGKey,
    score_fn: Callable[[Array], Array],
    initial: Initial,
    method: Union[str, SearchMethod, None] = None,
    config: Optional[ExploreConfig] = None,
    params=None,
    objective_fn: Optional[Callable[[Array], Array]] = None,
    progress: bool = False,
) -> SeedsResult:
    """`explore` for a batch of keys [K], vmapped: one compiled call for the epochs, one for the finish.

    Args:
      keys: [K] PRNG keys (e.g. `jax.random.split(jax.random.key(seed), K)`).
      score_fn, initial, method, config, params, objective_fn, progress: as `explore`; score_fn (and
        objective_fn) are vmapped over the seeds, so they must be vmap-able (any jnp function is).

    Returns:
      `SeedsResult`: per-seed `Result`s (leading axis K) and the mean / std of CVIR, mCVIR and dCVIR.
    """
    search_method, method_config, config, params, start, objective = _prepare(
        initial, method, config, params, objective_fn
    )
    return _run_search(
        keys,
        _as_partial(score_fn),
        objective,
        start,
        params,
        search_method,
        method_config,
        config,
        bool(progress),
    )
