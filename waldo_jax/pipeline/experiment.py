"""An experiment: a `Source` (what renders) + a `Criterion` (what scores) + a search method -> `ExploreRun`.

`run_explore` composes the source and the criterion into the search's score function, scores the
initial population, runs `waldo_jax.search.explore` (one seed) or `explore_seeds` (several seeds,
one vmapped call) and re-renders the top-k views; `waldo_jax.pipeline.outputs` writes its files.

Initial scores (`initial`): "images" scores the real training images, as the paper does;
"renders" scores renders at the training poses instead (a comparison free of the renderer's own
artefacts). A criterion that scores poses (the room's oracle) ignores images: it is recorded as
"poses".
"""

from __future__ import annotations

import dataclasses
import math
import os
import time
from typing import Callable, Dict, List, NamedTuple, Optional, Tuple

import jax
import jax.numpy as jnp
import numpy as np

from waldo_jax.criteria import Criterion, Views
from waldo_jax.errors import MIN_RESOLUTION, WaldoError, host_memory_bytes
from waldo_jax.search import (
    ExploreConfig,
    Initial,
    RefineConfig,
    Result,
    explore,
    explore_seeds,
    get_method,
    result_bytes,
    search_memory,
)
from waldo_jax.pipeline.sources import Source

__all__ = [
    "ExploreRun",
    "INITIAL_MODES",
    "GRADIENT_COSTS",
    "gradient_cost_for",
    "refine_for_source",
    "score_function",
    "objective_function",
    "initial_scores",
    "PreparedSearch",
    "prepare_explore",
    "run_explore",
    "run_prepared",
    "seed_keys",
    "generated_slots",
    "check_epoch_memory",
    "check_epoch_pixels",
    "epoch_check",
    "check_search_memory",
    "memory_bytes",
    "EPOCH_BYTES_PER_PIXEL",
]

INITIAL_MODES = ("images", "renders")
# Working memory of one epoch per rendered pixel (renders, criterion activations, the search's own
# arrays), an upper estimate: `waldo explore procedural --criterion saliency --resolution 128` grew by
# 134 MB per extra seed (50 children of 128x128 each: 164 bytes per pixel) on the 2-core CPU, when the
# seeds rendered at once. They now render one after another (`score_function`): one seed's epoch is
# what is rendered at once; what every seed keeps is counted by `check_search_memory`.
EPOCH_BYTES_PER_PIXEL = 256


def memory_bytes() -> int:
    """Memory the first device can use: its allocator's limit on an accelerator, half the RAM on a CPU."""
    stats = None
    try:
        stats = jax.devices()[0].memory_stats()
    except Exception:  # backends without memory statistics
        pass
    if stats and stats.get("bytes_limit"):
        return int(stats["bytes_limit"])
    try:
        return int(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")) // 2
    except (AttributeError, ValueError, OSError):
        return 8 << 30


def check_epoch_memory(source: Source, config: ExploreConfig, seeds: int) -> None:
    """Refuses a run whose epoch (children_per_epoch renders of one seed at once: seeds render one after
    another) would not fit in memory, with the resolution or children that would (`EPOCH_BYTES_PER_PIXEL`)."""
    check_epoch_pixels(source.intrinsics.width, source.intrinsics.height, config, seeds)


def epoch_check(config: ExploreConfig, seeds: int) -> Callable[[int, int, int], None]:
    """`check_epoch_pixels` for a source not loaded yet: `load_source(..., check=)` calls it with the
    renders' width, height and the training views' count before it renders or reads any image, so a
    size the epoch cannot hold is refused before the source's own work (its training views' renders)."""

    def check(width: int, height: int, n_train: int) -> None:
        try:
            resolved = config.resolve(n_train)
        except ValueError:
            return  # a budget these views exceed: the caller's own check says so, with the source's name
        check_epoch_pixels(width, height, resolved, seeds)

    return check


def check_epoch_pixels(width: int, height: int, config: ExploreConfig, seeds: int) -> None:
    """`check_epoch_memory` for renders of width x height (a resolved `config`). `seeds` does not count:
    each seed's epoch renders on its own (`score_function`); `check_search_memory` counts what they keep."""
    del seeds
    pixels = width * height
    per_seed = config.children_per_epoch * pixels * EPOCH_BYTES_PER_PIXEL
    available = memory_bytes()
    if per_seed <= available:
        return
    views = (
        f"one epoch renders {config.children_per_epoch} views of {width}x{height} at once, about "
        f"{per_seed / 2**30:.1f} GiB, more than the {available / 2**30:.1f} GiB at hand"
    )
    side = max(width, height)
    fits = int(side * math.sqrt(available / per_seed))
    children = available // (pixels * EPOCH_BYTES_PER_PIXEL)
    if fits >= MIN_RESOLUTION:
        raise WaldoError(
            f"--resolution {side}: {views}; pass --resolution {fits} or less (or at most --children-per-epoch "
            f"{children} at this resolution)"
        )
    raise WaldoError(
        f"--children-per-epoch {config.children_per_epoch}: {views}; at most --children-per-epoch {children} "
        "at this resolution"
    )


def check_search_memory(seed: int, seeds: int, score_fn, initial: Initial, config: ExploreConfig, objective, progress):
    """Refuses a search whose compiled program needs more memory than the device has (XLA's analysis of
    the whole scan: the population of every epoch, the renders and the criterion's activations), before
    it runs; the compile is the one the run reuses."""
    # XLA's figure is what the program may take at once: set against the memory free now (the host's
    # on a CPU, not `memory_bytes`' half of it, a rule of thumb for the epoch's working set).
    available = memory_bytes() if jax.devices()[0].platform != "cpu" else host_memory_bytes()
    if seeds > 1 and available:
        # What every seed keeps, from the search's shapes before anything compiles: a count of seeds
        # past it is refused before XLA is asked to compile it (past 2**31 slots XLA cannot index).
        kept = result_bytes(score_fn, initial, config=config, objective_fn=objective)
        if seeds * kept > available:
            raise WaldoError(
                f"--seeds {seeds}: each seed keeps {kept / 2**10:,.0f} KiB of results ({config.epochs} epochs x "
                f"{config.children_per_epoch} children and the training views), {seeds * kept / 2**30:,.1f} "
                f"GiB for all, more than the {available / 2**30:.1f} GiB at hand; at most --seeds "
                f"{available // kept} here"
            )
    keys = jax.random.key(seed) if seeds == 1 else seed_keys(seed, seeds)
    need = search_memory(keys, score_fn, initial, config=config, objective_fn=objective, progress=progress)
    if need is not None and available and need > available:
        # Most of a many-seed search's need is what its seeds keep, in proportion to their number.
        fits = seeds * available // need
        seeds_hint = f"about --seeds {fits} at most here, or " if fits >= 1 and seeds > 1 else ""
        raise WaldoError(
            f"--epochs {config.epochs} x --children-per-epoch {config.children_per_epoch} x --seeds {seeds}: "
            f"the compiled search needs {need / 2**30:,.1f} GiB (XLA's own analysis), more than the "
            f"{available / 2**30:.1f} GiB at hand; {seeds_hint}fewer epochs, children or seeds, or a lower "
            "--resolution"
        )


# Renders one refinement gradient evaluation counts as, by what the criterion scores (>= 2): the
# ratio of a forward-mode gradient's time to an exact score's, rounded up, measured on the 2-core CPU
# with benchmarks/gradient_cost.py: 1.7 for the room's oracle on poses; 4.9 for saliency on the
# room's renders and 11.5 on a trained fox NeRF's (64 px), the costlier taken for every render (and
# for "posed" combinations, which render). Sources that differentiate in reverse mode carry their own
# measured cost (`Source.gradient_cost`): a NeRF run 3 (`sources.NERF_GRADIENT_COST`, 2.4 to 2.6
# measured; 3.76 against 10.57 in forward mode before its rules), splats `splat_sources.SPLAT_GRADIENT_COST`.
GRADIENT_COSTS = {"poses": 2, "images": 12, "renders": 12, "posed": 12}


def gradient_cost_for(criterion: Criterion, source: Optional[Source] = None) -> int:
    """The default `RefineConfig.gradient_cost` for a criterion (`GRADIENT_COSTS` by its inputs), or the
    source's own measured cost (`Source.gradient_cost`) for a criterion of its renders."""
    if source is not None and source.gradient_cost is not None and criterion.needs.render:
        return int(source.gradient_cost)
    return GRADIENT_COSTS[criterion.inputs]


def refine_for_source(
    refine: RefineConfig, source: Source, criterion: Criterion, default_cost: bool = True
) -> RefineConfig:
    """`refine` with the source's way of differentiating (`Source.gradient`) and, when `default_cost`,
    the gradient cost for this source and criterion (`gradient_cost_for`)."""
    mode = source.gradient if criterion.needs.render else refine.gradient
    cost = gradient_cost_for(criterion, source) if default_cost else refine.gradient_cost
    return dataclasses.replace(refine, gradient=mode, gradient_cost=cost)


def scene_views(renderer: Optional[jax.tree_util.Partial], intrinsics, c2w) -> Views:
    """The `Views` of cameras c2w [P, 4, 4]: rendered by a scene's `renderer` (None: the poses alone)."""
    return Views(None, c2w, intrinsics) if renderer is None else renderer(c2w, intrinsics)


def _score_views(render, criterion: Criterion, intrinsics, c2w):
    return criterion.evaluate(scene_views(render, intrinsics, c2w))


# A search of several seeds (`explore_seeds`) vmaps its scoring over them. Views that are rendered are
# rendered and scored one seed's population at a time instead: a renderer's blocks are sized for one
# call, and vmapped they grew by the number of seeds (`waldo demo --search-renders`, 8 seeds of GRS on the
# room NeRF's renders: 12.9 GiB by XLA's analysis, 17.5 GB at its peak on the 2-core CPU; 4.9 GB now).
# Each seed scores as it would alone (tests/test_seeds_render_one_by_one.py); against the seeds as one
# batch, the same on the room's renders and to float rounding on the demo's NeRF (its CVIR mean over 8
# seeds 28.57216 against 28.57215). Not the refinement's objective: reverse mode does not pass through a
# sequential vmap.
_score_views_per_seed = jax.custom_batching.sequential_vmap(_score_views)


def score_function(source: Source, criterion: Criterion) -> jax.tree_util.Partial:
    """c2w [P, 4, 4] -> scores [P]: the criterion of the source's views (rendered where it scores
    pixels: `scoring_renderer`). Vmapped over seeds, rendered views are scored one seed at a time."""
    render = scoring_renderer(source, criterion)
    score = _score_views if render is None else _score_views_per_seed
    return jax.tree_util.Partial(score, render, criterion, source.intrinsics)


def objective_function(source: Source, criterion: Criterion) -> jax.tree_util.Partial:
    """The `+refine` methods' objective: the criterion's smooth stand-in of the source's views, as
    `score_function` but vmapped over seeds as one batch (it is differentiated).

    Raises:
      CriterionError: the criterion has no smooth stand-in (`Criterion.smooth`).
    """
    smooth = criterion.smooth()
    return jax.tree_util.Partial(_score_views, scoring_renderer(source, smooth), smooth, source.intrinsics)


def scoring_renderer(source: Source, criterion: Criterion) -> Optional[jax.tree_util.Partial]:
    """The source's renderer where the criterion scores pixels, None where it scores poses alone."""
    return source.renderer if criterion.needs.render else None


# Compiled once per criterion function and shape: scoring eagerly is ~10x slower for a network
# (CSNet on 16 images: 22 s eager vs 2.6 s jitted on the 2-core CPU).
_jit_score_views = jax.jit(lambda criterion, views: criterion.evaluate(views))


def initial_scores(source: Source, criterion: Criterion, initial: str = "images") -> Tuple[np.ndarray, str]:
    """Scores [N] of the training views and what was scored ("images", "renders" or "poses")."""
    if initial not in INITIAL_MODES:
        raise WaldoError(f"initial scores must come from one of {INITIAL_MODES}, got {initial!r}")
    train_c2w = jnp.asarray(source.train_c2w)
    if not criterion.needs.render:
        return np.asarray(_jit_score_views(criterion, Views(None, train_c2w, source.intrinsics)), np.float32), "poses"
    if initial == "images":
        if source.train_images is None:
            raise WaldoError(
                f"cannot score the real training images of {source.spec}: {source.train_images_note}; "
                "use --initial renders to score renders at the training poses instead"
            )
        images = jnp.asarray(source.train_images)
    else:
        rgba = source.views(train_c2w).rgba
        # Colour alone where the criterion takes no opacity, sliced here rather than in the compiled
        # criterion, so that its program (and its float rounding) is the one that scores photographs.
        images = rgba if criterion.needs.opacity else rgba[..., :3]
    return np.asarray(_jit_score_views(criterion, Views(images, train_c2w, source.intrinsics)), np.float32), initial


def seed_keys(seed: int, count: int):
    """[count] keys for seeds seed, seed + 1, ...: seed s of a multi-seed run is `jax.random.key(s)`."""
    return jax.vmap(jax.random.key)(jnp.arange(seed, seed + count, dtype=jnp.uint32))


@dataclasses.dataclass
class ExploreRun:
    """A finished exploration (host-side record).

    Attributes:
      source, criterion, config: what ran (config resolved: children_per_epoch set).
      seeds: the seeds (one per vmapped run).
      results: `Result` of each seed (NumPy leaves, no seed axis), in the order of `seeds`.
      scores_train: float32 [N] initial scores; initial: what they were computed on.
      top_images: float32 [k, H, W, 3] renders of the first seed's top-k views (its different shots,
        `ExploreConfig.min_separation`; the paper's top-k at 0).
      top_truth: the same views rendered by the analytic room (a NeRF of the room), or None.
      seconds: {"setup", "search", "render_topk", "total"} wall-clock.
      stats: mean / std of CVIR, mCVIR and dCVIR over the seeds.
    """

    source: Source
    criterion: Criterion
    config: ExploreConfig
    seeds: List[int]
    results: List[Result]
    scores_train: np.ndarray
    initial: str
    top_images: np.ndarray
    top_truth: Optional[np.ndarray]
    seconds: Dict[str, float]
    stats: Dict[str, float]

    @property
    def result(self) -> Result:
        """The first seed's result (the one the images and poses files show)."""
        return self.results[0]


class PreparedSearch(NamedTuple):
    """A search ready to run (`prepare_explore`): its checks passed and its program compiled.

    Attributes:
      source, criterion, config: what runs (config resolved).
      seed, seeds: the first seed and how many.
      scores: float32 [N] the training views' scores; initial: what they were computed on.
      start: the search's `Initial`; score_fn, objective: what it calls (objective None unless `+refine`).
      progress: the per-epoch lines.
      seconds: wall-clock of the preparation (checks, initial scores, the compile).
    """

    source: Source
    criterion: Criterion
    config: ExploreConfig
    seed: int
    seeds: int
    scores: np.ndarray
    initial: str
    start: Initial
    score_fn: Callable
    objective: Optional[Callable]
    progress: bool
    seconds: float


def prepare_explore(
    source: Source,
    criterion: Criterion,
    config: ExploreConfig,
    seed: int = 0,
    seeds: int = 1,
    initial: str = "images",
    progress: bool = False,
) -> PreparedSearch:
    """Everything `run_explore` does before its search runs: the settings resolved and checked, the
    training views scored, and the search's program compiled (XLA's memory analysis checked against the
    memory at hand). Arguments as `run_explore`. Pure of side effects but the compile cache, so several
    can be prepared on threads at once (their compiles then overlap: `waldo demo` does)."""
    if seeds < 1:
        raise WaldoError(f"--seeds must be >= 1, got {seeds}")
    start = time.perf_counter()
    if get_method(config.method).differentiable:  # the source's renderer sets the gradient mode it allows
        config = config.with_options(
            refine=refine_for_source(config.refine_config(), source, criterion, default_cost=False)
        )
    config = dataclasses.replace(config, direction=criterion.direction).resolve(source.n_train)
    check_epoch_memory(source, config, seeds)
    objective = objective_function(source, criterion) if get_method(config.method).differentiable else None
    scores, initial_used = initial_scores(source, criterion, initial)
    start_init = Initial(c2w=source.train_c2w, scores=scores)
    score_fn = score_function(source, criterion)
    check_search_memory(seed, seeds, score_fn, start_init, config, objective, progress)
    return PreparedSearch(
        source,
        criterion,
        config,
        seed,
        seeds,
        scores,
        initial_used,
        start_init,
        score_fn,
        objective,
        progress,
        time.perf_counter() - start,
    )


def run_explore(
    source: Source,
    criterion: Criterion,
    config: ExploreConfig,
    seed: int = 0,
    seeds: int = 1,
    initial: str = "images",
    setup_seconds: float = 0.0,
    progress: bool = False,
) -> ExploreRun:
    """Runs one search (or `seeds` searches in one vmapped call) and renders the top-k views.

    Args:
      source: what renders.
      criterion: what scores; its direction overrides `config.direction`.
      config: the search's static settings (method, budget, epochs, top_k, ...); a `+refine` method
        differentiates as the source allows (`refine_for_source`: its gradient mode, the cost as given).
      seed: the first seed; `seeds` > 1 runs seeds seed, seed + 1, ... (`seed_keys`).
      seeds: number of seeds.
      initial: "images" or "renders" (see the module docstring).
      setup_seconds: time already spent loading the source (reported under seconds.setup).
      progress: print one line per epoch (`explore`'s `progress`).
    """
    return run_prepared(prepare_explore(source, criterion, config, seed, seeds, initial, progress), setup_seconds)


def run_prepared(prepared: PreparedSearch, setup_seconds: float = 0.0) -> ExploreRun:
    """Runs a prepared search (`prepare_explore`) and renders the top-k views: `run_explore`'s second half.
    Its seconds.search counts the preparation's time and the search's."""
    source, config, seed, seeds = prepared.source, prepared.config, prepared.seed, prepared.seeds
    score_fn, start_init, objective, progress = prepared.score_fn, prepared.start, prepared.objective, prepared.progress
    start = time.perf_counter() - prepared.seconds
    if seeds == 1:
        results = [
            jax.device_get(
                explore(
                    jax.random.key(seed), score_fn, start_init, config=config, objective_fn=objective, progress=progress
                )
            )
        ]
        stats = {
            "cvir_mean": float(results[0].cvir),
            "cvir_std": 0.0,
            "mcvir_mean": float(results[0].mcvir),
            "mcvir_std": 0.0,
            "dcvir_mean": float(results[0].dcvir),
            "dcvir_std": 0.0,
        }
    else:
        out = jax.device_get(
            explore_seeds(
                seed_keys(seed, seeds), score_fn, start_init, config=config, objective_fn=objective, progress=progress
            )
        )
        results = [jax.tree.map(lambda a, i=i: a[i], out.results) for i in range(seeds)]
        stats = {
            "cvir_mean": float(out.cvir_mean),
            "cvir_std": float(out.cvir_std),
            "mcvir_mean": float(out.mcvir_mean),
            "mcvir_std": float(out.mcvir_std),
            "dcvir_mean": float(out.dcvir_mean),
            "dcvir_std": float(out.dcvir_std),
        }
    searched = time.perf_counter()

    top = results[0]
    valid = np.asarray(top.top_valid)
    top_c2w = jnp.asarray(np.asarray(top.top_c2w)[valid])
    top_images = np.asarray(source.render(top_c2w), np.float32)
    top_truth = None if source.truth is None else np.asarray(source.render_truth(top_c2w), np.float32)
    done = time.perf_counter()
    seconds = {
        "setup": round(setup_seconds, 3),
        "search": round(searched - start, 3),
        "render_topk": round(done - searched, 3),
        "total": round(setup_seconds + done - start, 3),
    }
    return ExploreRun(
        source=source,
        criterion=prepared.criterion,
        config=config,
        seeds=list(range(seed, seed + seeds)),
        results=results,
        scores_train=prepared.scores,
        initial=prepared.initial,
        top_images=top_images,
        top_truth=top_truth,
        seconds=seconds,
        stats=stats,
    )


def generated_slots(result: Result, n_train: int) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The rendered children of one seed in generation order (masked slots left out).

    Returns:
      (scores float [G], epochs int [G], slots int [G]): their scores, epochs of birth and slots in
      `result.population`.
    """
    population = result.population
    slots = np.arange(n_train, np.asarray(population.score).shape[0])
    valid = np.asarray(population.valid)[slots]
    slots = slots[valid]
    return np.asarray(population.score)[slots], np.asarray(population.epoch)[slots], slots
