"""Path search: the keyframes of the camera path whose frames best satisfy a criterion, as one
`lax.scan` over epochs with explicit keys (the exploration loop of "Finding Waldo", lifted from poses
to paths).

A candidate is K keyframe poses; its F frames (`path.sample_path`) are all scored in one batched
call per epoch (`frame_fn`: c2w [B, 4, 4] -> (scores [B], opacity [B])), and the path's score is an
aggregate of its frames' scores: their mean, or a soft minimum (-t log mean exp(-s / t) on the
direction-signed scores, `temperature` t in score units) so that no frame is bad. A path that
breaks a limit (`PathLimits`: speed, turn, scene box, opacity) is never a result; for breeding it
ranks below every path that keeps them, by how far it breaks them, so the search can walk back
into the limits.

Start: `initial_paths` candidates (epoch 0) built from anchor poses (the top poses of an `explore`
run, or the training views) and the training cameras: the training trajectory (K training cameras
evenly spaced in their order), the straight path between the two best anchors, and chains of
nearest anchors (from rank-biased random starts, jittered by `jitter` scene extents). Then each of
`epochs` epochs adds `paths_per_epoch` children:
  * "egps": EGPS on keyframes (two rank-biased parents from the better half; per keyframe, the
    crossover and mutation of `waldo_jax.search.egps`: uniform per axis, mean up, delta in
    {-nabla, 0, +nabla} with nabla = 0.1 x the parents' gap);
  * "evosax:NAME": any evosax strategy on the keyframe vector [K x 9], normalised by the training
    poses as `waldo_jax.search.strategy` does for one pose.
Each is a `PathMethod` (init / ask / tell), resolved from its name once by `path_method` and passed to
the jitted search as a static argument, as `explore` takes a `SearchMethod`.
The budget counts rendered (scored) frames: F x (initial_paths + epochs x paths_per_epoch).
"""

from __future__ import annotations

import dataclasses
import functools
import math
from typing import Any, Callable, Optional, Tuple, Union

import flax.struct
import jax
import jax.numpy as jnp
import numpy as np

from waldo_jax.search.path import PathLimits, path_c2w, straight_path
from waldo_jax.cameras import camera_focus
from waldo_jax.search import egps
from waldo_jax.search import strategy as evosax_strategy
from waldo_jax.search.population import DIRECTIONS, direction_sign, draw_index, training_poses, uniform_rows
from waldo_jax.types import Array, Pose, PRNGKey

__all__ = [
    "PATH_BUDGETS",
    "AGGREGATES",
    "PathConfig",
    "PathPopulation",
    "PathResult",
    "path_limits",
    "aggregate_scores",
    "initial_paths",
    "search_path",
    "search_path_loop",
    "search_path_seeds",
    "search_path_memory",
    "check_method",
    "PathMethod",
    "path_method",
    "default_params",
    "EVOSAX_STD_INIT",
]

# Rendered frames in all (initial paths included). A path of F frames is F images, so these are ten
# times the paper's image budgets: about 100 paths of 24 frames at "low".
PATH_BUDGETS = {"low": (2500, 3000), "high": (9000, 10000)}
AGGREGATES = ("mean", "softmin")
Budget = Union[str, Tuple[int, int]]


def check_method(method: str) -> str:
    """`method` if the path search knows it ("egps" or "evosax:NAME"), else a ValueError naming the choices."""
    path_method(method)
    return method


@dataclasses.dataclass(frozen=True)
class PathConfig:
    """Static settings of a path search (hashable: a static argument of the jit).

    Attributes:
      keyframes: K, keyframe poses per path (>= 2).
      frames: F, frames sampled along a path (>= 4: jerk needs four).
      method: "egps" or "evosax:NAME".
      epochs: E.
      paths_per_epoch: children per epoch; None derives it from the budget.
      budget: "low" / "high" (`PATH_BUDGETS`, in frames) or a (min, max) number of frames.
      initial_paths: M, the starting candidates (>= 3: trajectory, straight path, a chain).
      aggregate: "mean" or "softmin" over a path's frames.
      temperature: softmin's t, in score units.
      direction: "max" or "min" (the criterion's).
      top_k: paths returned, best first.
      jitter: std of the initial chains' keyframe jitter, in scene extents.
      paths_per_call: paths scored per vectorised call (None: all of an epoch); bounds memory.
    """

    keyframes: int = 4
    frames: int = 24
    method: str = "egps"
    epochs: int = 5
    paths_per_epoch: Optional[int] = None
    budget: Budget = "low"
    initial_paths: int = 16
    aggregate: str = "mean"
    temperature: float = 0.05
    direction: str = "max"
    top_k: int = 5
    jitter: float = 0.02
    paths_per_call: Optional[int] = None

    def __post_init__(self):
        for name, value, least in (
            ("keyframes", self.keyframes, 2),
            ("frames", self.frames, 4),
            ("epochs", self.epochs, 1),
            ("initial_paths", self.initial_paths, 3),
            ("top_k", self.top_k, 1),
        ):
            if int(value) < least:
                raise ValueError(f"PathConfig.{name} must be >= {least}, got {value}")
        if self.paths_per_epoch is not None and self.paths_per_epoch < 2:
            raise ValueError(f"PathConfig.paths_per_epoch must be >= 2, got {self.paths_per_epoch}")
        if self.paths_per_call is not None and self.paths_per_call < 1:
            raise ValueError(f"PathConfig.paths_per_call must be >= 1, got {self.paths_per_call}")
        if self.aggregate not in AGGREGATES:
            raise ValueError(f"PathConfig.aggregate must be one of {AGGREGATES}, got {self.aggregate!r}")
        if not (self.temperature > 0 and math.isfinite(self.temperature)) or self.temperature > MAX_TEMPERATURE:
            raise ValueError(
                f"PathConfig.temperature must be a positive number of at most {MAX_TEMPERATURE:g} (past it, scores "
                f"over the temperature underflow float32), got {self.temperature}"
            )
        if self.direction not in DIRECTIONS:
            raise ValueError(f"PathConfig.direction must be one of {DIRECTIONS}, got {self.direction!r}")
        if not (0 <= self.jitter < 1):
            raise ValueError(f"PathConfig.jitter must lie in [0, 1), got {self.jitter}")
        check_method(self.method)
        if not isinstance(self.budget, str):
            object.__setattr__(self, "budget", tuple(int(b) for b in self.budget))
        self.budget_bounds()

    def budget_bounds(self) -> Tuple[int, int]:
        if isinstance(self.budget, str):
            if self.budget not in PATH_BUDGETS:
                raise ValueError(
                    f"path budget must be one of {tuple(PATH_BUDGETS)} or a (min, max) number of "
                    f"frames, got {self.budget!r}"
                )
            return PATH_BUDGETS[self.budget]
        low, high = self.budget
        if not 0 < low <= high:
            raise ValueError(f"a path budget (min, max) needs 0 < min <= max frames, got {self.budget!r}")
        return low, high

    def resolve(self) -> "PathConfig":
        """This config with paths_per_epoch fixed: F x (M + E x P) frames inside the budget, near its middle."""
        if self.paths_per_epoch is not None:
            return self
        low, high = self.budget_bounds()
        f, m, e = self.frames, self.initial_paths, self.epochs
        fewest = max(2, math.ceil((low / f - m) / e))
        most = math.floor((high / f - m) / e)
        if fewest > most:
            raise ValueError(
                f"no number of paths per epoch (>= 2) puts {f} frames x ({m} initial + {e} epochs x "
                f"paths) inside the budget of {low}-{high} frames; use fewer frames or initial paths, "
                "or a larger budget"
            )
        goal = round(((low + high) / 2 / f - m) / e)
        return dataclasses.replace(self, paths_per_epoch=int(min(max(goal, fewest), most)))

    def capacity(self) -> int:
        """C = M + E x P candidates."""
        resolved = self.resolve()
        return resolved.initial_paths + resolved.epochs * resolved.paths_per_epoch

    def cost(self) -> dict:
        """{"frames": rendered frames in all, "paths": candidates, "frames_per_path": F}."""
        return {"frames": self.capacity() * self.frames, "paths": self.capacity(), "frames_per_path": self.frames}


def path_limits(
    train_c2w: np.ndarray,
    max_speed: float = 0.05,
    max_turn: float = 5.0,
    min_opacity: float = 0.0,
    min_travel: float = 0.0,
    margin: float = 0.1,
) -> PathLimits:
    """`PathLimits` of a scene from its training cameras: the box is their origins' bounding box grown by
    `margin` x its largest side (the extent), speed in extents per frame, turn in degrees per frame,
    travel (the whole path's length) in extents."""
    origins = np.asarray(train_c2w, np.float64)[:, :3, 3]
    low, high = origins.min(0), origins.max(0)
    extent = max(float(np.max(high - low)), 1e-6)
    for name, value in (("max_speed", max_speed), ("max_turn", max_turn)):
        if not (value > 0 and math.isfinite(value)):
            raise ValueError(f"{name} must be a positive number, got {value}")
    if not (0 <= min_opacity <= 1):
        raise ValueError(f"min_opacity must lie in [0, 1], got {min_opacity}")
    if not (0 <= min_travel < math.inf):
        raise ValueError(f"min_travel must be a number >= 0, got {min_travel}")
    f32 = lambda v: jnp.asarray(v, jnp.float32)  # noqa: E731
    return PathLimits(
        max_speed=f32(max_speed),
        max_turn=f32(max_turn),
        min_opacity=f32(min_opacity),
        min_travel=f32(min_travel),
        low=f32(low - margin * extent),
        high=f32(high + margin * extent),
        extent=f32(extent),
    )


# The largest softmin temperature: (least score - score) / t must stay a normal float32 (> 1.2e-38) for
# score gaps down to 1e-7; the softmin is the mean long before.
MAX_TEMPERATURE = 1e30


def aggregate_scores(frame_scores: Array, config: PathConfig) -> Array:
    """A path's score from its frames' raw scores [..., F] (NaN if any frame's is NaN)."""
    sign = direction_sign(config.direction)
    signed = sign * frame_scores
    if config.aggregate == "mean":
        value = jnp.mean(signed, axis=-1)
    else:
        # softmin_t(s) = -t log mean exp(-s / t), written from the least score: min(s) - t log1p(mean(expm1(
        # (min(s) - s) / t))). The plain form cancelled in float32 for a temperature far above the scores
        # (1e10: log mean exp of numbers near 0 is exactly 0, every path scored 0); this one tends to the mean.
        t = config.temperature
        low = jnp.min(signed, axis=-1)  # NaN if a frame's is NaN
        spread = jnp.mean(jnp.expm1((low[..., None] - signed) / t), axis=-1)  # in (-1, 0]
        value = jnp.where(jnp.isinf(low), low, low - t * jnp.log1p(spread))  # -inf frame: -inf; all +inf: +inf
    return sign * value


@flax.struct.dataclass
class PathPopulation:
    """Every candidate path of one search: the M initial ones in slots 0..M-1, then each epoch's.

    Attributes:
      keyframes: `Pose` with [C, K, 3] fields.
      score: float32 [C] aggregate raw score (NaN: not yet filled, or a frame failed).
      frame_scores: float32 [C, F].
      violation: float32 [C], `PathLimits.violation` (0: keeps every limit).
      valid: bool [C], the slot holds a scored path.
      epoch: int32 [C], 0 for initial paths, e for a child of epoch e, -1 for unfilled slots.
      direction: "max" or "min" (static).
    """

    keyframes: Pose
    score: Array
    frame_scores: Array
    violation: Array
    valid: Array
    epoch: Array
    direction: str = flax.struct.field(pytree_node=False, default="max")

    @property
    def feasible(self) -> Array:
        """bool [C]: a scored path with a finite score that keeps every limit."""
        return self.valid & jnp.isfinite(self.score) & (self.violation == 0.0)

    @property
    def fitness(self) -> Array:
        """[C] signed score of feasible paths, -inf elsewhere: what results are ranked by."""
        return jnp.where(self.feasible, direction_sign(self.direction) * self.score, -jnp.inf)

    @property
    def selection(self) -> Array:
        """[C] what breeding ranks by: `fitness` for feasible paths; below them, by how far they break
        the limits, the others with a finite score and violation; -inf for failures and empty slots."""
        usable = self.valid & jnp.isfinite(self.score) & jnp.isfinite(self.violation)
        broken = -evosax_strategy.WORST * (1.0 + self.violation)
        return jnp.where(self.feasible, self.fitness, jnp.where(usable, broken, -jnp.inf))


@flax.struct.dataclass
class PathResult:
    """What a path search returns.

    Attributes:
      population: the final `PathPopulation`.
      top_indices: int32 [k] best feasible slots, best first; top_valid: bool [k].
      best_keyframes: `Pose` [K, 3] of the best feasible path (when none is feasible, of the one that
        breaks the limits least: check `found`).
      best_c2w: float32 [F, 4, 4] its frames; best_frame_scores: float32 [F]; best_score: [].
      found: bool [], some path kept every limit.
      curve: float32 [E + 1], best feasible aggregate after the initial paths and after each epoch.
    """

    population: PathPopulation
    top_indices: Array
    top_valid: Array
    best_keyframes: Pose
    best_c2w: Array
    best_frame_scores: Array
    best_score: Array
    found: Array
    curve: Array


# ---------------------------------------------------------------------------------------------
# Initial paths.


def _chain(start: Array, origins: Array, count: int) -> Array:
    """Indices [count] of a nearest-neighbour chain through `origins` [A, 3] from anchor `start`."""

    def step(carry, _):
        current, visited = carry
        distance = jnp.linalg.norm(origins - origins[current], axis=-1)
        nearest = jnp.argmin(jnp.where(visited, jnp.inf, distance)).astype(jnp.int32)
        return (nearest, visited.at[nearest].set(True)), nearest

    visited = jnp.zeros(origins.shape[0], bool).at[start].set(True)
    _, rest = jax.lax.scan(step, (start, visited), None, length=count - 1)
    return jnp.concatenate([start[None], rest])


def initial_paths(
    key: PRNGKey, anchors: Pose, anchor_fitness: Array, train: Pose, limits: PathLimits, config: PathConfig
) -> Pose:
    """The M starting paths ([M, K, 3] fields); see the module docstring.

    Args:
      key: PRNG key (consumed).
      anchors: `Pose` [A, 3] (A >= K), e.g. an explore run's top poses; anchor_fitness: [A] signed
        scores (higher is better, -inf unusable).
      train: `Pose` [N, 3] of the training cameras, in their order.
      limits: the scene's `PathLimits` (its extent scales the jitter).
      config: `PathConfig`.
    """
    k, m = config.keyframes, config.initial_paths
    n = train.origin.shape[0]
    trajectory = jax.tree.map(lambda x: x[np.round(np.linspace(0, n - 1, k)).astype(np.int32)], train)
    best_two = jax.lax.top_k(anchor_fitness, 2)[1]
    pick = lambda i: jax.tree.map(lambda x: x[i], anchors)  # noqa: E731
    straight = straight_path(pick(best_two[0]), pick(best_two[1]), k)
    start_key, jitter_key = jax.random.split(key)
    weights, _ = egps.parent_weights(anchor_fitness, jnp.float32(1.0))
    starts = jax.vmap(draw_index, in_axes=(0, None))(jax.random.uniform(start_key, (m - 2,)), weights)
    order = jax.vmap(lambda s: _chain(s, anchors.origin, k))(starts)  # [M - 2, K]
    chains = jax.tree.map(lambda x: x[order], anchors)
    noise = jax.random.normal(jitter_key, (2, m - 2, k, 3)) * config.jitter * limits.extent
    chains = chains.replace(origin=chains.origin + noise[0], target=chains.target + noise[1])
    return jax.tree.map(
        lambda *xs: jnp.concatenate([x[None] if x.ndim == 2 else x for x in xs]), trajectory, straight, chains
    )


# ---------------------------------------------------------------------------------------------
# Scoring candidates.


def _evaluate(frame_fn, keyframes: Pose, limits: PathLimits, config: PathConfig):
    """(score [P], frame_scores [P, F], violation [P]) of candidate keyframes [P, K, 3]."""

    def one(path: Pose):
        c2w = path_c2w(path, config.frames)
        scores, opacity = frame_fn(c2w)
        scores = jnp.asarray(scores, jnp.float32).reshape(config.frames)
        opacity = jnp.asarray(opacity, jnp.float32).reshape(config.frames)
        violation, _ = limits.violation(c2w, opacity)
        return scores, violation

    size = keyframes.origin.shape[0]
    batch = size if config.paths_per_call is None else min(config.paths_per_call, size)
    frame_scores, violation = jax.lax.map(one, keyframes, batch_size=batch)
    return aggregate_scores(frame_scores, config), frame_scores, violation


def _write(population: PathPopulation, keyframes: Pose, score, frame_scores, violation, mask, epoch, offset):
    def put(buffer, value):
        return jax.lax.dynamic_update_slice_in_dim(buffer, value.astype(buffer.dtype), offset, axis=0)

    n = mask.shape[0]
    return population.replace(
        keyframes=jax.tree.map(put, population.keyframes, keyframes),
        score=put(population.score, jnp.where(mask, score, jnp.nan)),
        frame_scores=put(population.frame_scores, jnp.where(mask[:, None], frame_scores, jnp.nan)),
        violation=put(population.violation, jnp.where(mask, violation, jnp.nan)),
        valid=put(population.valid, mask),
        epoch=put(population.epoch, jnp.where(mask, jnp.broadcast_to(epoch, (n,)), -1)),
    )


# ---------------------------------------------------------------------------------------------
# The methods: EGPS on keyframes, evosax on keyframe vectors, each a `PathMethod`.


@dataclasses.dataclass(frozen=True)
class PathMethod:
    """One path-search method, resolved from its name once at the edge (`path_method`) and passed to the
    jitted search as a static argument (hashable), as `waldo_jax.search.SearchMethod` is to `explore`.

    A method draws each epoch's children from the population and may carry a state across epochs (an
    evosax strategy's search distribution); a stateless one (EGPS) has no `init_fn` / `tell_fn`, its
    state is `()`, and `init` does not use its key.

    Attributes:
      name: "egps" or "evosax:NAME".
      params_fn: () -> the method's default numeric parameters (a pytree).
      ask_fn: stateless: (key, population, params, config) -> (children, child_mask); with a state:
        (key, population, state, params, config) -> (children, child_mask, state').
      init_fn: (key, population, train, limits, params, config) -> state, after the initial paths.
      tell_fn: (key, state, selection, params, config) -> state', `selection` [P] of the epoch's children.
    """

    name: str
    params_fn: Callable[[], Any]
    ask_fn: Callable[..., Any]
    init_fn: Optional[Callable[..., Any]] = None
    tell_fn: Optional[Callable[..., Any]] = None

    def default_params(self) -> Any:
        """The method's default numeric parameters."""
        return self.params_fn()

    def init(self, key, population, train, limits, params, config) -> Any:
        """The state before epoch 1 (`()` for a stateless method)."""
        return () if self.init_fn is None else self.init_fn(key, population, train, limits, params, config)

    def ask(self, key, population, state, params, config) -> Tuple[Pose, Array, Any]:
        """One epoch's (children: `Pose` [P, K, 3], child_mask: bool [P], state')."""
        if self.init_fn is None:
            children, mask = self.ask_fn(key, population, params, config)
            return children, mask, state
        return self.ask_fn(key, population, state, params, config)

    def tell(self, key, state, selection, params, config) -> Any:
        """The state after the children's `selection` [P] is known (unchanged for a stateless method)."""
        return state if self.tell_fn is None else self.tell_fn(key, state, selection, params, config)


def _egps_child(u: Array, keyframes: Pose, selection: Array, weights: Array, params: egps.Params, k: int) -> Pose:
    parent1, parent2 = egps.select_parents(u[:2], weights, selection)
    pick = lambda i: jax.tree.map(lambda x: x[i], keyframes)  # noqa: E731
    return jax.vmap(egps.breed, in_axes=(0, 0, 0, None))(u[2:].reshape(k, 12), pick(parent1), pick(parent2), params)


def _egps_ask(key, population: PathPopulation, params: egps.Params, config: PathConfig) -> Tuple[Pose, Array]:
    """EGPS children [P, K, 3]: every keyframe bred from the same two rank-biased parent paths."""
    n, k = config.paths_per_epoch, config.keyframes
    selection = population.selection
    weights, can_breed = egps.parent_weights(selection, params.rank_bias)
    u = uniform_rows(key, n, 2 + 12 * k)
    children = jax.vmap(_egps_child, in_axes=(0, None, None, None, None, None))(
        u, population.keyframes, selection, weights, params, k
    )
    return children, jnp.broadcast_to(can_breed, (n,))


_EGPS = PathMethod(name="egps", params_fn=egps.Params, ask_fn=_egps_ask)


@flax.struct.dataclass
class _EvosaxState:
    strategy: Any
    asked: Array
    shift: Array
    scale: Array


def _scaling(train: Pose, limits: PathLimits, k: int) -> Tuple[Array, Array]:
    """(shift, scale) [K x 9] of the keyframe vector: the training poses' mean and spread, per coordinate."""
    vectors = evosax_strategy.to_vector(train)
    shift = jnp.mean(vectors, axis=0)
    spread = jnp.std(vectors, axis=0)
    floor = 0.05 * jnp.concatenate([jnp.full((6,), limits.extent), jnp.ones((3,))])
    return jnp.tile(shift, k), jnp.tile(jnp.maximum(spread, floor), k)


def _strategy(name: str, config: PathConfig):
    return evosax_strategy.make_strategy(name, config.paths_per_epoch, config.keyframes * evosax_strategy.POSE_DIM)


def _flat(keyframes: Pose) -> Array:
    return evosax_strategy.to_vector(keyframes).reshape(*keyframes.origin.shape[:-2], -1)


def _evosax_init(name: str, key, population: PathPopulation, train: Pose, limits: PathLimits, params, config):
    """The strategy `name`'s state, started from the best initial paths (repeated to P)."""
    strategy = _strategy(name, config)
    shift, scale = _scaling(train, limits, config.keyframes)
    n, m = config.paths_per_epoch, config.initial_paths
    order = jax.lax.top_k(population.selection[:m], min(n, m))[1]
    order = jnp.tile(order, -(-n // order.shape[0]))[:n]
    start = (_flat(population.keyframes)[order] - shift) / scale
    es_params = evosax_strategy.strategy_params(strategy, params)
    if evosax_strategy.is_distribution_based(strategy):
        es_state = strategy.init(key, start[0], es_params)
    else:
        loss = jnp.where(jnp.isfinite(population.selection[order]), -population.selection[order], evosax_strategy.WORST)
        es_state = strategy.init(key, start, loss, es_params)
    return _EvosaxState(strategy=es_state, asked=jnp.zeros_like(start), shift=shift, scale=scale)


def _evosax_ask(name: str, key, population: PathPopulation, state: _EvosaxState, params, config: PathConfig):
    """The strategy's P asked keyframe vectors as paths (all real)."""
    del population
    n, k = config.paths_per_epoch, config.keyframes
    strategy = _strategy(name, config)
    asked, es_state = strategy.ask(key, state.strategy, evosax_strategy.strategy_params(strategy, params))
    asked = jnp.asarray(asked, jnp.float32)
    vectors = (state.shift + state.scale * asked).reshape(n, k, evosax_strategy.POSE_DIM)
    return evosax_strategy.to_pose(vectors), jnp.ones(n, bool), state.replace(strategy=es_state, asked=asked)


def _evosax_tell(name: str, key, state: _EvosaxState, selection: Array, params, config: PathConfig):
    """The state after the asked paths' selection is told back (negated: evosax minimises)."""
    strategy = _strategy(name, config)
    loss = jnp.where(jnp.isfinite(selection), -selection, evosax_strategy.WORST)
    es_state, _ = strategy.tell(
        key, state.asked, loss, state.strategy, evosax_strategy.strategy_params(strategy, params)
    )
    return state.replace(strategy=es_state)


# evosax's initial std on the keyframe vector, in training spreads: of 0.05, 0.1 and 0.3, 0.3 found the
# best paths on the room (waldo_oracle, 4 seeds, CMA-ES and SNES) while 1.0 (one pose's default)
# scattered the keyframes so that most paths broke the speed limits.
EVOSAX_STD_INIT = 0.3


def _evosax_params() -> evosax_strategy.Params:
    return evosax_strategy.Params(std_init=jnp.asarray(EVOSAX_STD_INIT, jnp.float32))


@functools.lru_cache(maxsize=None)
def _evosax_method(name: str) -> PathMethod:
    """The path method "evosax:<name>" (one object per name: equal and hashed by identity of its bound
    functions, so its compilations are reused)."""
    return PathMethod(
        name=evosax_strategy.PREFIX + name,
        params_fn=_evosax_params,
        ask_fn=functools.partial(_evosax_ask, name),
        init_fn=functools.partial(_evosax_init, name),
        tell_fn=functools.partial(_evosax_tell, name),
    )


def path_method(method: str) -> PathMethod:
    """The `PathMethod` called `method` ("egps" or "evosax:NAME"): where the name is read, once.

    Raises:
      ValueError: an unknown method or evosax strategy (the message names the choices).
    """
    if method == "egps":
        return _EGPS
    if isinstance(method, str) and method.startswith(evosax_strategy.PREFIX):
        name = method[len(evosax_strategy.PREFIX) :]
        if name not in evosax_strategy.strategy_names():
            raise ValueError(
                f"unknown evosax strategy {name!r}; choose one of {', '.join(evosax_strategy.strategy_names())}"
            )
        return _evosax_method(name)
    raise ValueError(f"path search method must be egps or evosax:NAME, got {method!r}")


def default_params(config: PathConfig):
    """The method's default numeric parameters: `egps.Params()`, or `strategy.Params` with
    `EVOSAX_STD_INIT`."""
    return path_method(config.method).default_params()


# ---------------------------------------------------------------------------------------------
# The search.


def _init(key, frame_fn, anchors, anchor_fitness, train: Pose, limits: PathLimits, params, method, config: PathConfig):
    c, f, k, m = config.capacity(), config.frames, config.keyframes, config.initial_paths
    empty = PathPopulation(
        keyframes=Pose(*(jnp.zeros((c, k, 3), jnp.float32) for _ in range(3))),
        score=jnp.full((c,), jnp.nan, jnp.float32),
        frame_scores=jnp.full((c, f), jnp.nan, jnp.float32),
        violation=jnp.full((c,), jnp.nan, jnp.float32),
        valid=jnp.zeros((c,), bool),
        epoch=jnp.full((c,), -1, jnp.int32),
        direction=config.direction,
    )
    start_key, state_key = jax.random.split(jax.random.fold_in(key, 0))
    paths = initial_paths(start_key, anchors, anchor_fitness, train, limits, config)
    score, frame_scores, violation = _evaluate(frame_fn, paths, limits, config)
    population = _write(empty, paths, score, frame_scores, violation, jnp.ones(m, bool), 0, 0)
    return population, method.init(state_key, population, train, limits, params, config)


def _epoch(key, frame_fn, carry, epoch, train: Pose, limits: PathLimits, params, method, config: PathConfig):
    population, state = carry
    ask_key, tell_key = jax.random.split(jax.random.fold_in(key, epoch))
    children, mask, state = method.ask(ask_key, population, state, params, config)
    score, frame_scores, violation = _evaluate(frame_fn, children, limits, config)
    n = config.paths_per_epoch
    offset = config.initial_paths + (epoch - 1) * n
    population = _write(population, children, score, frame_scores, violation, mask, epoch, offset)
    state = method.tell(tell_key, state, jax.lax.dynamic_slice_in_dim(population.selection, offset, n), params, config)
    return population, state


def _best_so_far(population: PathPopulation) -> Array:
    best = jnp.max(population.fitness)
    return jnp.where(jnp.isfinite(best), direction_sign(population.direction) * best, jnp.nan)


def _finish(population: PathPopulation, curve: Array, config: PathConfig) -> PathResult:
    values, indices = jax.lax.top_k(population.fitness, config.top_k)
    # No path kept the limits: the one that broke them least (still `found` False).
    best = jnp.where(jnp.isfinite(values[0]), indices[0], jnp.argmax(population.selection))
    keyframes = jax.tree.map(lambda x: x[best], population.keyframes)
    return PathResult(
        population=population,
        top_indices=indices.astype(jnp.int32),
        top_valid=jnp.isfinite(values),
        best_keyframes=keyframes,
        best_c2w=path_c2w(keyframes, config.frames),
        best_frame_scores=population.frame_scores[best],
        best_score=population.score[best],
        found=jnp.isfinite(values[0]),
        curve=curve,
    )


def _search(key, frame_fn, anchors, anchor_fitness, train, limits, params, method, config: PathConfig) -> PathResult:
    carry = _init(key, frame_fn, anchors, anchor_fitness, train, limits, params, method, config)
    first = _best_so_far(carry[0])

    def body(carry, epoch):
        carry = _epoch(key, frame_fn, carry, epoch, train, limits, params, method, config)
        return carry, _best_so_far(carry[0])

    (population, _), curve = jax.lax.scan(body, carry, jnp.arange(1, config.epochs + 1, dtype=jnp.int32))
    return _finish(population, jnp.concatenate([first[None], curve]), config)


# The method and the config are static: the jitted code calls the method, never reads its name.
_search_jit = jax.jit(_search, static_argnames=("method", "config"))


def _search_seeds(keys, frame_fn, anchors, anchor_fitness, train, limits, params, method, config) -> PathResult:
    search = lambda key: _search(key, frame_fn, anchors, anchor_fitness, train, limits, params, method, config)  # noqa: E731
    return jax.vmap(search)(keys)


_search_seeds_jit = jax.jit(_search_seeds, static_argnames=("method", "config"))
_init_jit = jax.jit(_init, static_argnames=("method", "config"))
_epoch_jit = jax.jit(_epoch, static_argnames=("method", "config"))
_finish_jit = jax.jit(_finish, static_argnames=("config",))


def _prepare(frame_fn, anchor_c2w, anchor_scores, train_c2w, limits, config, params):
    if not callable(frame_fn):
        raise TypeError(f"frame_fn must be callable, got {type(frame_fn).__name__}")
    frame_fn = frame_fn if isinstance(frame_fn, jax.tree_util.Partial) else jax.tree_util.Partial(frame_fn)
    config = config.resolve()
    anchor_c2w = np.asarray(anchor_c2w, np.float32)
    train_c2w = np.asarray(train_c2w, np.float32)
    anchor_scores = np.asarray(anchor_scores, np.float32)
    if anchor_c2w.ndim != 3 or anchor_c2w.shape[1:] not in ((4, 4), (3, 4)):
        raise ValueError(f"anchor poses must be [A, 4, 4], got shape {anchor_c2w.shape}")
    if anchor_scores.shape != (anchor_c2w.shape[0],):
        raise ValueError(f"anchor scores must have shape ({anchor_c2w.shape[0]},), got {anchor_scores.shape}")
    usable = int(np.sum(np.isfinite(anchor_scores)))
    if usable < max(2, config.keyframes) or anchor_c2w.shape[0] < config.keyframes:
        raise ValueError(
            f"a path of {config.keyframes} keyframes needs at least {max(2, config.keyframes)} anchor "
            f"poses with a finite score, got {usable} of {anchor_c2w.shape[0]}"
        )
    if train_c2w.ndim != 3 or train_c2w.shape[0] < 2:
        raise ValueError(f"the training trajectory needs at least 2 training poses, got shape {train_c2w.shape}")
    focus = camera_focus(train_c2w)
    train = training_poses(train_c2w, focus)
    anchors = training_poses(anchor_c2w, focus)
    sign = direction_sign(config.direction)
    fitness = jnp.asarray(np.where(np.isfinite(anchor_scores), sign * anchor_scores, -np.inf), jnp.float32)
    method = path_method(config.method)
    params = method.default_params() if params is None else params
    return frame_fn, anchors, fitness, train, limits, params, method, config


def search_path(
    key: PRNGKey,
    frame_fn: Callable,
    anchor_c2w,
    anchor_scores,
    train_c2w,
    limits: PathLimits,
    config: PathConfig = PathConfig(),
    params=None,
) -> PathResult:
    """Runs one path search as a single compiled `lax.scan` over epochs.

    Args:
      key: PRNG key; the initial paths use fold_in(key, 0), epoch e fold_in(key, e).
      frame_fn: jit-able c2w [B, 4, 4] -> (raw scores [B], mean opacity [B]); NaN scores allowed (such a
        path fails and is never selected). Static by identity, or a `jax.tree_util.Partial`.
      anchor_c2w, anchor_scores: [A, 4, 4] poses and their raw scores the initial paths are built from.
      train_c2w: [N, 4, 4] the training cameras in their order (the training trajectory).
      limits: `PathLimits` (`path_limits`).
      config: `PathConfig`.
      params: the method's numeric parameters (default `default_params`).
    """
    frame_fn, anchors, fitness, train, limits, params, method, config = _prepare(
        frame_fn, anchor_c2w, anchor_scores, train_c2w, limits, config, params
    )
    return _search_jit(key, frame_fn, anchors, fitness, train, limits, params, method=method, config=config)


def search_path_seeds(
    keys: PRNGKey,
    frame_fn: Callable,
    anchor_c2w,
    anchor_scores,
    train_c2w,
    limits: PathLimits,
    config: PathConfig = PathConfig(),
    params=None,
) -> PathResult:
    """`search_path` for a batch of keys [S], vmapped in one compiled call (leaves gain a leading [S])."""
    frame_fn, anchors, fitness, train, limits, params, method, config = _prepare(
        frame_fn, anchor_c2w, anchor_scores, train_c2w, limits, config, params
    )
    return _search_seeds_jit(keys, frame_fn, anchors, fitness, train, limits, params, method=method, config=config)


def search_path_memory(
    keys: PRNGKey,
    frame_fn: Callable,
    anchor_c2w,
    anchor_scores,
    train_c2w,
    limits: PathLimits,
    config: PathConfig = PathConfig(),
    params=None,
) -> Optional[int]:
    """Bytes the compiled search of `search_path` (one key) or `search_path_seeds` (keys [S]) needs with
    these arguments, by XLA's own analysis (arguments, outputs and temporaries: every candidate's
    keyframes and frame scores, an epoch's frames and renders), or None where the backend gives none.

    It compiles the program without running it, so work and memory set by the flags (`--epochs` x
    `--paths-per-epoch` x `--frames` x `--seeds`) can be refused before they fill the machine. Only the
    shapes of `anchor_scores` matter. The run that follows may compile again (`waldo path` builds its
    `frame_fn` anew: 11 s -> 28 s for 2 seeds of 16 px on the 2-core CPU), so callers ask only where the
    candidates are large (`waldo_jax.cli.path.SEARCH_CHECK_SHARE`).
    """
    from waldo_jax.search.explore import program_memory  # the one reading of XLA's memory analysis

    frame_fn, anchors, fitness, train, limits, params, method, config = _prepare(
        frame_fn, anchor_c2w, anchor_scores, train_c2w, limits, config, params
    )
    search = _search_jit if jnp.ndim(keys) == 0 else _search_seeds_jit
    lowered = search.lower(keys, frame_fn, anchors, fitness, train, limits, params, method=method, config=config)
    return program_memory(lowered.compile())


def search_path_loop(
    key: PRNGKey,
    frame_fn: Callable,
    anchor_c2w,
    anchor_scores,
    train_c2w,
    limits: PathLimits,
    config: PathConfig = PathConfig(),
    params=None,
) -> PathResult:
    """`search_path` as a Python loop over jitted epochs (same result): to inspect between epochs, and
    the reference the scan is tested against."""
    frame_fn, anchors, fitness, train, limits, params, method, config = _prepare(
        frame_fn, anchor_c2w, anchor_scores, train_c2w, limits, config, params
    )
    carry = _init_jit(key, frame_fn, anchors, fitness, train, limits, params, method=method, config=config)
    curve = [_best_so_far(carry[0])]
    for epoch in range(1, config.epochs + 1):
        carry = _epoch_jit(key, frame_fn, carry, jnp.int32(epoch), train, limits, params, method=method, config=config)
        curve.append(_best_so_far(carry[0]))
    return _finish_jit(carry[0], jnp.stack(curve), config=config)
