"""A complete exploration run: SOURCE + criterion + method -> search -> files (`waldo explore`).

`run_explore` composes a `waldo_jax.sources.Source` (what renders) with a
`waldo_jax.criteria.Criterion` (what scores) into the search's score function, scores the initial
population, runs `waldo_jax.search.explore` (one seed) or `explore_seeds` (several seeds, one
vmapped call), and re-renders the top-k views. `write_outputs` writes what `waldo explore` promises:

  results.json      the run: method, criterion, direction, seed(s), budget, n_train, n_generated,
                    scores_train, scores_generated (generation order), cvir, mcvir, topk
                    [{score, c2w, image, ...}], epochs (per-epoch best and mean-top-N), seconds;
                    with several seeds also per_seed and the mean / std of CVIR and mCVIR
  topk/NN.png       the top-k views, best first (the first seed's)
  contact_sheet.png best training views in the first row, best found views below, scores on them
  poses.json        the top-k poses in transforms.json form (instant-ngp / nerfstudio can render them)
  pose_cloud.png    every pose coloured by score at the start, after epoch 1 and at the end

Initial scores (`initial`): "images" scores the real training images, as the paper does;
"renders" scores renders at the training poses instead (a comparison free of the renderer's own
artefacts). A criterion that scores poses (the room's oracle) ignores images: it is recorded as
"poses".
"""

from __future__ import annotations

import dataclasses
import os
import time
from pathlib import Path
from typing import Any, Dict, List, Mapping, Optional, Sequence, Tuple

import jax
import jax.numpy as jnp
import numpy as np

from waldo_jax import io
from waldo_jax.criteria import Criterion
from waldo_jax.errors import WaldoError
from waldo_jax.search import ExploreConfig, Initial, Result, explore, explore_seeds
from waldo_jax.sources import Source

__all__ = ["ExploreRun", "INITIAL_MODES", "score_function", "initial_scores", "run_explore", "write_outputs",
           "seed_keys", "contact_sheet", "methods_sheet", "training_tiles", "check_epoch_memory", "memory_bytes",
           "EPOCH_BYTES_PER_PIXEL"]

INITIAL_MODES = ("images", "renders")
RESULTS_JSON = "results.json"
# Working memory of one epoch per rendered pixel (renders, criterion activations, the search's own
# arrays), an upper estimate: `waldo explore procedural --criterion saliency --resolution 128` grew by
# 134 MB per extra seed (50 children of 128x128 each: 164 bytes per pixel) on the 2-core CPU.
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
    """Refuses a run whose batched epoch (seeds x children_per_epoch renders) would not fit in memory,
    with the largest --seeds that would (see `EPOCH_BYTES_PER_PIXEL`)."""
    pixels = source.intrinsics.width * source.intrinsics.height
    per_seed = config.children_per_epoch * pixels * EPOCH_BYTES_PER_PIXEL
    available = memory_bytes()
    if seeds * per_seed > available:
        raise WaldoError(
            f"--seeds {seeds}: one epoch renders {seeds} x {config.children_per_epoch} views of "
            f"{source.intrinsics.width}x{source.intrinsics.height} at once, about {seeds * per_seed / 2**30:.1f} GiB, "
            f"more than the {available / 2**30:.1f} GiB at hand; at most --seeds {max(available // per_seed, 0)} "
            "here (or a lower --resolution)")


def _score_rendered(render, criterion: Criterion, c2w):
    return criterion.apply(criterion.params, render(c2w))


def _score_posed(criterion: Criterion, intrinsics, c2w):
    return criterion.apply(criterion.params, c2w, intrinsics)


def score_function(source: Source, criterion: Criterion) -> jax.tree_util.Partial:
    """c2w [P, 4, 4] -> scores [P]: render with the source and score, or score the poses directly."""
    if criterion.inputs == "poses":
        return jax.tree_util.Partial(_score_posed, criterion, source.intrinsics)
    return jax.tree_util.Partial(_score_rendered, _renderer(source, criterion), criterion)


def _renderer(source: Source, criterion: Criterion) -> jax.tree_util.Partial:
    """The source's renderer for the criterion: colour, or colour + opacity for a "renders" criterion."""
    if criterion.inputs != "renders":
        return source.render
    if source.render_rgba is None:
        raise WaldoError(f"criterion {criterion.name!r} needs the renderer's opacity, which {source.spec} does not give")
    return source.render_rgba


# Compiled once per criterion function and shape: scoring eagerly is ~10x slower for a network
# (CSNet on 16 images: 22 s eager vs 2.6 s jitted on the 2-core CPU).
_jit_score_images = jax.jit(lambda criterion, images: criterion.score_images(images))
_jit_score_poses = jax.jit(lambda criterion, c2w, intrinsics: criterion.score_poses(c2w, intrinsics))


def initial_scores(source: Source, criterion: Criterion, initial: str = "images") -> tuple[np.ndarray, str]:
    """Scores [N] of the training views and what was scored ("images", "renders" or "poses")."""
    if initial not in INITIAL_MODES:
        raise WaldoError(f"initial scores must come from one of {INITIAL_MODES}, got {initial!r}")
    train_c2w = jnp.asarray(source.train_c2w)
    if criterion.inputs == "poses":
        return np.asarray(_jit_score_poses(criterion, train_c2w, source.intrinsics), np.float32), "poses"
    if initial == "images":
        if source.train_images is None:
            raise WaldoError(f"cannot score the real training images of {source.spec}: {source.train_images_note}; "
                             "use --initial renders to score renders at the training poses instead")
        return np.asarray(_jit_score_images(criterion, jnp.asarray(source.train_images)), np.float32), "images"
    return np.asarray(_jit_score_images(criterion, _renderer(source, criterion)(train_c2w)), np.float32), "renders"


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
      top_images: float32 [k, H, W, 3] renders of the first seed's top-k views.
      top_truth: the same views rendered by the analytic room (a NeRF of the room), or None.
      seconds: {"setup", "search", "render_topk", "total"} wall-clock.
      stats: mean / std of CVIR and mCVIR over the seeds.
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


def run_explore(source: Source, criterion: Criterion, config: ExploreConfig, seed: int = 0, seeds: int = 1,
                initial: str = "images", setup_seconds: float = 0.0) -> ExploreRun:
    """Runs one search (or `seeds` searches in one vmapped call) and renders the top-k views.

    Args:
      source: what renders.
      criterion: what scores; its direction overrides `config.direction`.
      config: the search's static settings (method, budget, epochs, top_k, ...).
      seed: the first seed; `seeds` > 1 runs seeds seed, seed + 1, ... (`seed_keys`).
      seeds: number of seeds.
      initial: "images" or "renders" (see the module docstring).
      setup_seconds: time already spent loading the source (reported under seconds.setup).
    """
    if seeds < 1:
        raise WaldoError(f"--seeds must be >= 1, got {seeds}")
    start = time.perf_counter()
    config = dataclasses.replace(config, direction=criterion.direction).resolve(source.n_train)
    check_epoch_memory(source, config, seeds)
    scores, initial_used = initial_scores(source, criterion, initial)
    start_init = Initial(c2w=source.train_c2w, scores=scores)
    score_fn = score_function(source, criterion)
    if seeds == 1:
        results = [jax.device_get(explore(jax.random.key(seed), score_fn, start_init, config=config))]
        stats = {"cvir_mean": float(results[0].cvir), "cvir_std": 0.0,
                 "mcvir_mean": float(results[0].mcvir), "mcvir_std": 0.0}
    else:
        out = jax.device_get(explore_seeds(seed_keys(seed, seeds), score_fn, start_init, config=config))
        results = [jax.tree.map(lambda a, i=i: a[i], out.results) for i in range(seeds)]
        stats = {"cvir_mean": float(out.cvir_mean), "cvir_std": float(out.cvir_std),
                 "mcvir_mean": float(out.mcvir_mean), "mcvir_std": float(out.mcvir_std)}
    searched = time.perf_counter()

    top = results[0]
    valid = np.asarray(top.top_valid)
    top_c2w = jnp.asarray(np.asarray(top.top_c2w)[valid])
    top_images = np.asarray(source.render(top_c2w), np.float32)
    top_truth = None if source.truth_render is None else np.asarray(source.truth_render(top_c2w), np.float32)
    done = time.perf_counter()
    seconds = {"setup": round(setup_seconds, 3), "search": round(searched - start, 3),
               "render_topk": round(done - searched, 3), "total": round(setup_seconds + done - start, 3)}
    return ExploreRun(source=source, criterion=criterion, config=config, seeds=list(range(seed, seed + seeds)),
                      results=results, scores_train=scores, initial=initial_used, top_images=top_images,
                      top_truth=top_truth, seconds=seconds, stats=stats)


# ---------------------------------------------------------------------------------------------
# Files.


def _floats(values) -> List[Optional[float]]:
    """JSON-safe floats (NaN / inf -> None)."""
    return [float(v) if np.isfinite(v) else None for v in np.asarray(values, np.float64).ravel()]


def _float(value) -> Optional[float]:
    return _floats([value])[0]


def _generated(result: Result, n_train: int):
    """(scores, epochs, slots) of the rendered children in generation order (masked slots left out)."""
    population = result.population
    slots = np.arange(n_train, np.asarray(population.score).shape[0])
    valid = np.asarray(population.valid)[slots]
    slots = slots[valid]
    return np.asarray(population.score)[slots], np.asarray(population.epoch)[slots], slots


def _epoch_rows(result: Result) -> List[Dict[str, Any]]:
    m = result.metrics
    return [{"epoch": e, "best": _float(m.best[e]), "mean_top_n": _float(m.mean_top_n[e]),
             "scored": int(m.num_scored[e]), "failed": int(m.num_failed[e])} for e in range(len(m.best))]


def _format_score(value: float) -> str:
    return "n/a" if not np.isfinite(value) else f"{value:.3g}"


def results_dict(run: ExploreRun, image_names: Sequence[str]) -> Dict[str, Any]:
    """The contents of results.json (see the module docstring)."""
    config, result, source = run.config, run.result, run.source
    scores_generated, epochs_generated, slots = _generated(result, source.n_train)
    population = result.population
    valid = np.asarray(result.top_valid)
    indices = np.asarray(result.top_indices)[valid]
    topk = []
    for rank, (slot, name) in enumerate(zip(indices, image_names)):
        entry = {"rank": rank, "score": _float(population.score[slot]),
                 "c2w": np.round(np.asarray(population.c2w[slot], np.float64), 8).tolist(), "image": name,
                 "epoch": int(population.epoch[slot]), "training_view": bool(slot < source.n_train),
                 "origin": _floats(population.origin[slot]), "look_at": _floats(population.target[slot]),
                 "up": _floats(population.up[slot])}
        if slot < source.n_train:
            entry["training_image"] = source.train_names[slot]
        topk.append(entry)
    out: Dict[str, Any] = {
        "method": config.method,
        "criterion": run.criterion.name,
        "criterion_description": run.criterion.description,
        "direction": run.criterion.direction,
        "source": source.spec,
        "source_info": source.info,
        "seed": run.seeds[0],
        "budget": config.budget if isinstance(config.budget, str) else list(config.budget),
        "epochs_count": config.epochs,
        "children_per_epoch": config.children_per_epoch,
        "top_k": config.top_k,
        "top_n": config.top_n,
        "resolution": [source.intrinsics.width, source.intrinsics.height],
        "initial_scores": run.initial,
        "n_train": source.n_train,
        "n_generated": int(len(slots)),
        "n_failed_generated": int(np.sum(~np.isfinite(scores_generated))),
        "scores_train": _floats(run.scores_train),
        "scores_generated": _floats(scores_generated),
        "generated_epochs": [int(e) for e in epochs_generated],
        "cvir": _float(result.cvir),
        "mcvir": _float(result.mcvir),
        "topk": topk,
        "epochs": _epoch_rows(result),
        "seconds": run.seconds,
        "device": jax.devices()[0].platform + (f":{jax.devices()[0].device_kind}"
                                               if getattr(jax.devices()[0], "device_kind", "") else ""),
    }
    if config.method == "pibs":
        out["pibs"] = {"top_c": config.top_c, "fallback": config.pibs_fallback}
    if len(run.seeds) > 1:
        out["seeds"] = run.seeds
        out["per_seed"] = [{"seed": s, "cvir": _float(r.cvir), "mcvir": _float(r.mcvir),
                            "best": _float(r.metrics.best[-1]), "mean_top_n": _float(r.metrics.mean_top_n[-1])}
                           for s, r in zip(run.seeds, run.results)]
        out.update({k: _float(v) for k, v in run.stats.items()})
    return out


def _best_training(run: ExploreRun, k: int) -> List[int]:
    scores = np.asarray(run.scores_train, np.float64)
    sign = 1.0 if run.criterion.direction == "max" else -1.0
    order = np.argsort(np.where(np.isfinite(scores), -sign * scores, np.inf), kind="stable")
    return [int(i) for i in order[:k]]


def training_tiles(run: ExploreRun, indices: Sequence[int]) -> Tuple[List[np.ndarray], str]:
    """Tiles float32 [H, W, 3] of the training views `indices`, as they were scored, and their row title.

    The training images when the initial scores are theirs (or the poses'); renders at the
    training poses when the scores are of renders (`initial="renders"`) or the images are not on
    this machine: a tile always shows what its score was computed on.
    """
    source = run.source
    if source.train_images is not None and run.initial != "renders":
        return [source.train_images[i] for i in indices], "training"
    c2w = jnp.asarray(source.train_c2w[np.asarray(indices, dtype=int)])
    return list(np.asarray(source.render(c2w), np.float32)), "training (renders)"


def contact_sheet(run: ExploreRun, columns: Optional[int] = None) -> np.ndarray:
    """uint8 sheet: best training views (first row), best found views (second), analytic truth (third, if any)."""
    from waldo_jax.sources import resize_images

    k = len(run.top_images)
    columns = columns or max(k, 1)
    shape = run.top_images.shape[1:3] if k else (run.source.intrinsics.height, run.source.intrinsics.width)
    best_train = _best_training(run, columns)
    tiles, train_title = training_tiles(run, best_train)
    train_row = [resize_images(tile[None], shape[1], shape[0])[0] for tile in tiles]
    images = train_row + [None] * (columns - len(train_row))
    labels = [_format_score(run.scores_train[i]) for i in best_train] + [None] * (columns - len(best_train))
    found = list(run.top_images) + [None] * (columns - k)
    scores = np.asarray(run.result.top_scores)[np.asarray(run.result.top_valid)]
    images += found
    labels += [f"#{r + 1} {_format_score(s)}" for r, s in enumerate(scores)] + [None] * (columns - k)
    titles = [f"{train_title}", f"{run.config.method.upper()} found"]
    if run.top_truth is not None:
        images += list(run.top_truth) + [None] * (columns - k)
        labels += [None] * columns
        titles.append("analytic truth")
    return io.contact_sheet(images, columns=columns, labels=labels, row_titles=titles)


def methods_sheet(runs: Mapping[str, ExploreRun], columns: int) -> np.ndarray:
    """uint8 sheet comparing methods on one source and criterion: best training views, then each method's best.

    Row 1: the best training views (`training_tiles`) with their scores. Then per method (in the
    order of `runs`) its top views of the first seed as the source renders them, labelled with rank
    and score; a top view that is a training pose is marked "train" (its score is the training
    view's, the tile the render). For a NeRF of the procedural room each method's row is followed
    by the same views rendered by the analytic room (the truth).
    """
    first = next(iter(runs.values()))
    best_train = _best_training(first, columns)

    def row(images, labels):
        images, labels = list(images)[:columns], list(labels)[:columns]
        return images + [None] * (columns - len(images)), labels + [None] * (columns - len(labels))

    tiles, title = training_tiles(first, best_train)
    images, labels = row(tiles, [_format_score(first.scores_train[i]) for i in best_train])
    titles = [title]
    for method, run in runs.items():
        valid = np.asarray(run.result.top_valid)
        scores = np.asarray(run.result.top_scores)[valid]
        trained = np.asarray(run.result.top_indices)[valid] < run.source.n_train
        found = row(run.top_images, [f"#{r + 1} {_format_score(s)}" + (" train" if t else "")
                                     for r, (s, t) in enumerate(zip(scores, trained))])
        images, labels = images + found[0], labels + found[1]
        if run.top_truth is None:
            titles.append(method.upper())
        else:
            truth = row(run.top_truth, [])
            images, labels = images + truth[0], labels + truth[1]
            titles += [f"{method.upper()} (NeRF)", f"{method.upper()} (truth)"]
    return io.contact_sheet(images, columns=columns, labels=labels, row_titles=titles)


def write_outputs(run: ExploreRun, out: Path, title: str = "") -> Dict[str, Any]:
    """Writes results.json, topk/*.png, contact_sheet.png, poses.json and pose_cloud.png into `out`.

    `out` must exist (see `waldo_jax.io.prepare_output_dir`). Returns the results dictionary.
    """
    from waldo_jax.plots import pose_cloud

    out = Path(out)
    (out / "topk").mkdir(exist_ok=True)
    names = [f"topk/{i:02d}.png" for i in range(len(run.top_images))]
    written = [Path(n).name for n in names]
    for name, image in zip(names, run.top_images):
        io.save_png(out / name, image)
    if run.top_truth is not None:
        for i, image in enumerate(run.top_truth):
            io.save_png(out / "topk" / f"{i:02d}_truth.png", image)
            written.append(f"{i:02d}_truth.png")
    for path in io.stale_files(out / "topk", r"\d{2,}(_truth)?\.png", written):  # an earlier run's (--force)
        path.unlink()
    io.save_png(out / "contact_sheet.png", contact_sheet(run))

    result = run.result
    valid_top = np.asarray(result.top_valid)
    top_scores = np.asarray(result.top_scores)[valid_top]
    io.write_transforms(out / "poses.json", np.asarray(result.top_c2w)[valid_top], run.source.intrinsics, names,
                        extra={"waldo_explore": {"criterion": run.criterion.name, "method": run.config.method,
                                                 "scores": _floats(top_scores), "source": run.source.spec}})

    population = result.population
    filled = np.asarray(population.valid)
    marker = None if run.source.room is None else np.asarray(run.source.room.waldo_center)
    pose_cloud(out / "pose_cloud.png", np.asarray(population.c2w)[filled], np.asarray(population.score)[filled],
               np.asarray(population.epoch)[filled], run.criterion.direction,
               title=title or f"{run.config.method.upper()} on {run.source.name}, {run.criterion.name}",
               marker=marker)
    results = results_dict(run, names)
    io.write_json(out / RESULTS_JSON, results)
    return results
