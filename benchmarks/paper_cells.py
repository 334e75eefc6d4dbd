"""The cells of `paper_tables.py`: one search over K seeds per (scene, criterion, method, budget),
summarised as JSON; its figures; and, on the Waldo room, the visibility of the views it generated
against the best visibility any pose can reach.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any, Dict, List, Optional

import jax
import jax.numpy as jnp
import numpy as np


def _float(value) -> Optional[float]:
    value = float(value)
    return value if math.isfinite(value) else None


def summarise(run) -> Dict[str, Any]:
    """Every number of one cell (one criterion, scene, method, budget; K seeds)."""
    from waldo_jax.pipeline import generated_slots

    n_train = run.source.n_train
    per_seed = []
    for seed, result in zip(run.seeds, run.results):
        m = result.metrics
        _, _, slots = generated_slots(result, n_train)
        per_seed.append(
            {
                "seed": seed,
                "cvir": _float(result.cvir),
                "mcvir": _float(result.mcvir),
                "best": _float(m.best[-1]),
                "mean_top_n": _float(m.mean_top_n[-1]),
                "best_train": _float(m.best[0]),
                "mean_top_n_train": _float(m.mean_top_n[0]),
                "best_per_epoch": [_float(v) for v in m.best],
                "mean_top_n_per_epoch": [_float(v) for v in m.mean_top_n],
                "n_generated": int(len(slots)),
                "n_failed": int(np.sum(np.asarray(m.num_failed)[1:])),
            }
        )
    config = run.config
    return {
        "cvir_mean": _float(run.stats["cvir_mean"]),
        "cvir_std": _float(run.stats["cvir_std"]),
        "mcvir_mean": _float(run.stats["mcvir_mean"]),
        "mcvir_std": _float(run.stats["mcvir_std"]),
        "n_train": n_train,
        "children_per_epoch": config.children_per_epoch,
        "epochs": config.epochs,
        "top_k": config.top_k,
        "top_n": config.top_n,
        "n_total": n_train + config.epochs * config.children_per_epoch,
        "initial_scores": run.initial,
        "seeds": run.seeds,
        "seconds": run.seconds,
        "per_seed": per_seed,
    }


def explore_cell(source, criterion, method: str, budget: str, args, children: Dict[str, float]):
    from waldo_jax.pipeline import run_explore
    from waldo_jax.search import ExploreConfig

    config = ExploreConfig(
        method=method,
        budget=budget,
        epochs=args.epochs,
        top_k=args.top_k,
        children_per_epoch=int(children[budget]) if budget in children else None,
    )
    return run_explore(source, criterion, config, seed=args.seed, seeds=args.seeds, initial=args.initial)


def explore_cells(source, criterion, budgets, methods, args, children: Dict[str, float], record) -> Dict[str, Any]:
    """Runs every (budget, method) cell of one scene and criterion, calling `record(budget, method, run)`
    after each; returns the runs of the last budget by method (the ones the figures show)."""
    figure_runs = {}
    for budget in budgets:
        for method in methods:
            run = explore_cell(source, criterion, method, budget, args, children)
            record(budget, method, run)
            if budget == budgets[-1]:
                figure_runs[method] = run
    return figure_runs


# ---------------------------------------------------------------------------------------------
# Figures.


def write_figures(folder: Path, scene: str, criterion_name: str, runs: Dict[str, Any], args, budget: str) -> List[str]:
    """The views sheet and the pose clouds (threshold: the best training score) of one scene and criterion."""
    from waldo_jax import io
    from waldo_jax.pipeline import PoseCloudStyle, criterion_label, methods_sheet, pose_cloud

    written = []
    path = folder / f"{scene}_{criterion_name}_views.png"
    io.save_png(path, methods_sheet(runs, args.figure_columns))
    written.append(str(path))
    for method, run in runs.items():
        if method not in args.cloud_methods:
            continue
        population = run.result.population
        filled = np.asarray(population.valid)
        threshold = float(run.result.metrics.best[0])  # the best training score
        marker = None if run.source.room is None else np.asarray(run.source.room.waldo_center)
        path = folder / f"{scene}_{criterion_name}_{method}_cloud.png"
        style = PoseCloudStyle(
            title=(
                f"{method.upper()} on {scene}, {criterion_name}, {budget} budget, seed "
                f"{run.seeds[0]}: green = better than the best training view ({threshold:.3g})"
            ),
            threshold=threshold,
            marker=marker,
            marker_label="Waldo (the target)",
            score_label=criterion_label(run.criterion),
        )
        pose_cloud(
            path,
            np.asarray(population.c2w)[filled],
            np.asarray(population.score)[filled],
            np.asarray(population.epoch)[filled],
            run.criterion.direction,
            style=style,
        )
        written.append(str(path))
    return written


# ---------------------------------------------------------------------------------------------
# The Waldo room: visibility of the generated poses.


def waldo_row(run, goal: float) -> Dict[str, Any]:
    """Per seed: best visibility generated, visibility of the best-scored view, renders to reach `goal`."""
    from waldo_jax.pipeline import generated_slots
    from waldo_jax.procedural import waldo_visibility_batch

    room, intrinsics = run.source.room, run.source.intrinsics
    train_visibility = np.asarray(waldo_visibility_batch(room, jnp.asarray(run.source.train_c2w), intrinsics))
    per_seed = []
    for seed, result in zip(run.seeds, run.results):
        _, _, slots = generated_slots(result, run.source.n_train)
        c2w = np.asarray(result.population.c2w)[slots]  # generation order
        visibility = np.asarray(waldo_visibility_batch(room, jnp.asarray(c2w), intrinsics)) if len(slots) else []
        visibility = np.asarray(visibility, np.float64)
        reached = np.flatnonzero(visibility >= goal)
        top = np.asarray(result.top_c2w)[np.asarray(result.top_valid)][:1]
        top_visibility = (
            float(np.asarray(waldo_visibility_batch(room, jnp.asarray(top), intrinsics))[0]) if len(top) else None
        )
        per_seed.append(
            {
                "seed": seed,
                "best_visibility": float(visibility.max()) if len(visibility) else None,
                "best_scored_visibility": top_visibility,
                "renders_to_goal": int(reached[0]) + 1 if len(reached) else None,
                "n_generated": int(len(slots)),
                "cvir": _float(result.cvir),
                "mcvir": _float(result.mcvir),
            }
        )
    found = [s for s in per_seed if s["renders_to_goal"] is not None]
    best = [s["best_visibility"] for s in per_seed if s["best_visibility"] is not None]
    scored = [s["best_scored_visibility"] for s in per_seed if s["best_scored_visibility"] is not None]
    return {
        "goal": goal,
        "seeds": len(per_seed),
        "found_share": len(found) / len(per_seed),
        "best_visibility_mean": float(np.mean(best)) if best else None,
        "best_visibility_max": float(np.max(best)) if best else None,
        "best_scored_visibility_mean": float(np.mean(scored)) if scored else None,
        "renders_to_goal_mean": float(np.mean([s["renders_to_goal"] for s in found])) if found else None,
        "best_training_visibility": float(train_visibility.max()),
        "children_per_epoch": run.config.children_per_epoch,
        "n_train": run.source.n_train,
        "cvir_mean": _float(run.stats["cvir_mean"]),
        "mcvir_mean": _float(run.stats["mcvir_mean"]),
        "seconds": run.seconds,
        "per_seed": per_seed,
    }


def reachable_visibility(source, samples: int, goal: float, seed: int = 0) -> Dict[str, Any]:
    """The known answer: the best visibility of Waldo that the searches' origin region allows.

    `samples` origins are drawn uniformly within the per-axis bounds of the training camera origins
    (where GRS draws its origins: `waldo_jax.search.grs.origin_bounds`), each camera aimed at Waldo's
    centre with GRS's mean up vector and the run's intrinsics. Aiming at Waldo only moves him into
    the frame (occlusion depends on the origin alone), so the best of these is a sample estimate of
    the highest visibility any search pose with an origin in that box can reach; a goal above it is
    out of the searches' reach in this room, whatever the method or budget.

    Returns:
      best (max visibility), goal_share (fraction of the samples at or above `goal`), samples,
      the best pose's origin, and the box.
    """
    from waldo_jax.cameras import look_at
    from waldo_jax.procedural import waldo_visibility_batch
    from waldo_jax.search import grs
    from waldo_jax.search.population import init_population, training_poses

    train = training_poses(source.train_c2w)
    population = init_population(train, jnp.zeros(source.n_train), source.n_train)
    low, high = grs.origin_bounds(population)
    up = grs.mean_up(population)
    room = source.room
    origins = jax.random.uniform(jax.random.key(seed), (samples, 3), minval=low, maxval=high)
    aim = jax.jit(jax.vmap(lambda o: look_at(o, room.waldo_center, up)))
    chunk = 4096
    visibility = np.concatenate(
        [
            np.asarray(waldo_visibility_batch(room, aim(origins[i : i + chunk]), source.intrinsics))
            for i in range(0, samples, chunk)
        ]
    ).astype(np.float64)
    best = int(np.argmax(visibility))
    return {
        "best": float(visibility[best]),
        "goal": goal,
        "goal_share": float(np.mean(visibility >= goal)),
        "samples": samples,
        "seed": seed,
        "best_origin": np.asarray(origins[best], np.float64).round(4).tolist(),
        "origin_low": np.asarray(low, np.float64).round(4).tolist(),
        "origin_high": np.asarray(high, np.float64).round(4).tolist(),
        "aim": "Waldo's centre, GRS's mean up vector",
    }
