"""The archive of a run as a picture (`archive.png`) and as JSON: where the search found good views.

Every run files its views into the cells of `ExploreConfig.grid` (`waldo_jax.search.archive`): one
cell per (azimuth, elevation, distance band) of the camera seen from the scene's focus. The picture is
one tile per (elevation band, azimuth sector), the best view over the distance bands, rendered by the
source, its score on it (`#r` when it is also the r-th of the top-k, `train` when it is a training
view), grey where no view was filed; rows from above (top) to below, columns by azimuth. The caption
says the frame (the focus, up and azimuth 0) and the coverage and QD-score.
"""

from __future__ import annotations

from typing import Any, Dict, List

import jax
import numpy as np

from waldo_jax import io
from waldo_jax.pipeline.experiment import ExploreRun
from waldo_jax.pipeline.figures import criterion_caption
from waldo_jax.pipeline.sources import render_in
from waldo_jax.search.archive import sky_map, view_descriptor
from waldo_jax.search.views import frame_axes

__all__ = ["archive_sheet", "archive_summary", "view_descriptors"]

_EMPTY_GREY = 0.55
_descriptors = jax.jit(jax.vmap(view_descriptor, in_axes=(0, None)))
# One program for the frame's axes: eagerly each of their operations compiled on its own, 0.6 s a run against 0.1 s.
_frame_axes = jax.jit(frame_axes)
# Poses are padded to a multiple of this (copies of the last, cropped away): one program for the top-k and
# the archive's elites of every method, not one per count.
_DESCRIPTOR_BUCKET = 64


def view_descriptors(run: ExploreRun, c2w: np.ndarray) -> List[Dict[str, float]]:
    """Azimuth and elevation (degrees) and distance (in training-camera distances) of views c2w [P, 4, 4]
    in the first seed's scene frame."""
    if len(c2w) == 0:
        return []
    c2w = np.asarray(c2w, np.float32)
    padded = np.concatenate([c2w, np.repeat(c2w[-1:], (-len(c2w)) % _DESCRIPTOR_BUCKET, axis=0)])
    values = np.asarray(_descriptors(padded, run.result.population.frame), np.float64)[: len(c2w)]
    return [
        {"azimuth": round(float(a), 2), "elevation": round(float(e), 2), "distance": round(float(d), 4)}
        for a, e, d in values
    ]


def _vector(v) -> List[float]:
    return [round(float(x), 6) for x in np.asarray(v, np.float64)]


def archive_summary(run: ExploreRun) -> Dict[str, Any]:
    """results.json's "archive" of the first seed: the grid, the frame, coverage, QD-score and every elite."""
    result, grid = run.result, run.config.grid
    archive = result.archive
    fitness, slots = np.asarray(archive.fitness), np.asarray(archive.slot)
    filled = np.flatnonzero(np.isfinite(fitness))
    population = result.population
    score = np.asarray(population.score)
    train_fitness = _sign(run) * np.asarray(run.scores_train, np.float64)
    train_best = np.max(train_fitness[np.isfinite(train_fitness)], initial=-np.inf)
    east, north, up = (np.asarray(v) for v in _frame_axes(population.frame))
    descriptors = view_descriptors(run, np.asarray(population.c2w)[slots[filled]])
    elites = []
    for cell, slot, descriptor in zip(filled, slots[filled], descriptors):
        ring, rest = divmod(int(cell), grid.elevation_cells * grid.azimuth_cells)
        band, sector = divmod(rest, grid.azimuth_cells)
        elites.append(
            {
                "cell": int(cell),
                "sector": sector,
                "elevation_band": band,
                "distance_band": ring,
                "slot": int(slot),
                "score": float(score[slot]),
                "training_view": bool(slot < run.source.n_train),
                **descriptor,
            }
        )
    frame = {
        "focus": _vector(population.frame.focus),
        "up": _vector(up),
        "azimuth_0": _vector(east),
        "azimuth_90": _vector(north),
        "radius": float(population.frame.radius),
    }
    return {
        "grid": grid.to_dict(),
        "frame": frame,
        "coverage": float(result.coverage),
        "cells_filled": int(len(filled)),
        "cells_beating_train": int(np.sum(fitness[filled] > train_best)),
        "qd_score": float(result.qd_score),
        "qd_floor": None if not np.isfinite(result.qd_floor) else float(result.qd_floor),
        "elites": elites,
    }


def _sign(run: ExploreRun) -> float:
    return 1.0 if run.criterion.direction == "max" else -1.0


def _labels(run: ExploreRun, slots: np.ndarray) -> List[str]:
    """A tile's label: its score, `#r` if it is the r-th view of the top-k, `train` for a training view."""
    top = np.asarray(run.result.top_indices)[np.asarray(run.result.top_valid)]
    score = np.asarray(run.result.population.score)
    labels = []
    for slot in slots:
        rank = np.flatnonzero(top == slot)
        text = (f"#{int(rank[0]) + 1} " if len(rank) else "") + f"{score[slot]:.3g}"
        labels.append(text + (" train" if slot < run.source.n_train else ""))
    return labels


def archive_sheet(run: ExploreRun) -> np.ndarray:
    """uint8 picture of the first seed's archive (the module docstring); renders its filled cells."""
    grid, result = run.config.grid, run.result
    sky = sky_map(result.archive, grid)
    fitness, slots = np.asarray(sky.fitness)[::-1], np.asarray(sky.slot)[::-1]  # rows: highest band first
    filled = np.isfinite(fitness).ravel()
    width, height = run.source.intrinsics.width, run.source.intrinsics.height
    tiles: List[Any] = [np.full((height, width, 3), _EMPTY_GREY, np.float32)] * fitness.size
    labels: List[Any] = ["empty"] * fitness.size
    if filled.any():
        picked = slots.ravel()[filled]
        chunk = max(int(np.sum(np.asarray(result.top_valid))), 1)  # the top-k renders' program: no new compile
        images = render_in(run.source.render, np.asarray(result.population.c2w)[picked], chunk)
        for i, image, label in zip(np.flatnonzero(filled), images, _labels(run, picked)):
            tiles[i], labels[i] = np.asarray(image, np.float32), label
    rows = [f"el {low:+.0f}..{high:+.0f}" for low, high in grid.elevation_bounds()][::-1]
    columns = [f"az {a:+.0f}" for a in grid.azimuth_centres()]
    east, _, up = (", ".join(f"{x:.2f}" for x in np.asarray(v)) for v in _frame_axes(result.population.frame))
    caption = (
        f"{run.config.method.upper()} archive on {run.source.name}: the best view of each cell, the camera seen from "
        f"the focus with up ({up}), azimuth 0 towards ({east}), best over {grid.distance_bands} distance bands; "
        "grey: empty. "
        f"Coverage {float(result.coverage):.0%} of {grid.cells} cells, QD-score {float(result.qd_score):.3g}. "
        f"Scores: {criterion_caption(run.criterion)}"
    )
    return io.contact_sheet(
        tiles, columns=grid.azimuth_cells, labels=labels, row_titles=rows, caption=caption, column_titles=columns
    )
