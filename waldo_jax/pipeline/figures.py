"""Figures of an experiment: contact sheets of the best views and the pose cloud coloured by score.

`contact_sheet` (one run) and `methods_sheet` (several methods side by side, the paper's qualitative
figure) are uint8 arrays; `pose_cloud` writes the paper's pose-cloud figure with host-side
Matplotlib (no display needed).
"""

from __future__ import annotations

import os
from typing import List, Mapping, Optional, Sequence, Tuple

import jax.numpy as jnp
import numpy as np

from waldo_jax import io
from waldo_jax.io import atomic_file
from waldo_jax.pipeline.experiment import ExploreRun
from waldo_jax.pipeline.sources import resize_images

__all__ = ["pose_cloud", "STAGES", "contact_sheet", "methods_sheet", "training_tiles"]

STAGES = ("start", "epoch 1", "final")


def _camera_axes(c2w: np.ndarray):
    """Camera centres [N, 3] and viewing directions [N, 3] (OpenGL: the camera looks down -z)."""
    return c2w[:, :3, 3], -c2w[:, :3, 2]


def pose_cloud(path: str | os.PathLike, c2w: np.ndarray, scores: np.ndarray, epoch: np.ndarray, direction: str,
               title: str = "", threshold: Optional[float] = None, marker: Optional[np.ndarray] = None,
               stages: Sequence[int] = (0, 1, -1), arrow_length: Optional[float] = None) -> None:
    """Writes a figure with one 3D panel per stage: the poses that exist at that stage, coloured by score.

    Stage e shows the training views (epoch 0) and every child born in epochs 1..e (-1: all epochs).
    Training views are drawn as triangles, children as dots; a short line shows each view direction.
    With `threshold`, views better than it are green and the others red (the paper's colouring);
    otherwise a colour map of the score (brighter = better in the criterion's direction).

    Args:
      path: PNG to write.
      c2w: float [C, 4, 4] poses of the population (valid slots only).
      scores: float [C] their raw scores (NaN: failed, drawn grey).
      epoch: int [C] epoch of birth (0: training view).
      direction: "max" or "min".
      title: figure title.
      threshold: optional score threshold for green/red colouring.
      marker: optional [3] point to mark (e.g. Waldo's position), drawn as a black star.
      stages: epochs to show, one panel each (-1: the final epoch).
      arrow_length: length of the view-direction lines (default: 4 % of the cloud's extent).
    """
    # A bare Figure (no pyplot): draws off-screen without switching a notebook's backend.
    import matplotlib
    from matplotlib.figure import Figure

    c2w = np.asarray(c2w, np.float64)
    scores = np.asarray(scores, np.float64)
    epoch = np.asarray(epoch)
    centres, views = _camera_axes(c2w)
    last = int(epoch.max()) if epoch.size else 0
    finite = np.isfinite(scores)
    lo, hi = (np.min(scores[finite]), np.max(scores[finite])) if finite.any() else (0.0, 1.0)
    extent = float(np.max(np.ptp(centres, axis=0))) if len(centres) > 1 else 1.0
    arrow = arrow_length if arrow_length is not None else 0.04 * max(extent, 1e-6)
    cmap = matplotlib.colormaps["viridis" if direction == "max" else "viridis_r"]

    fig = Figure(figsize=(4.2 * len(stages), 4.4))
    points = centres if marker is None else np.concatenate([centres, np.asarray(marker, np.float64).reshape(1, 3)])
    bounds = (points.min(0), points.max(0)) if len(points) else (np.zeros(3), np.ones(3))
    for panel, stage in enumerate(stages):
        upto = last if stage < 0 else min(stage, last)
        ax = fig.add_subplot(1, len(stages), panel + 1, projection="3d")
        shown = epoch <= upto
        if threshold is not None:
            good = (scores > threshold) if direction == "max" else (scores < threshold)
            colours = np.where(good[:, None], np.array([[0.1, 0.65, 0.2, 1.0]]), np.array([[0.85, 0.15, 0.15, 1.0]]))
        else:
            colours = cmap((scores - lo) / max(hi - lo, 1e-12))
        colours[~finite] = (0.6, 0.6, 0.6, 1.0)
        for is_train, mark, size in ((True, "^", 34), (False, "o", 12)):
            sel = shown & ((epoch == 0) == is_train)
            if not sel.any():
                continue
            # Plot y (up) as the vertical axis: (x, z, y).
            ax.scatter(centres[sel, 0], centres[sel, 2], centres[sel, 1], c=colours[sel], marker=mark, s=size,
                       depthshade=False, edgecolors="k" if is_train else "none", linewidths=0.4)
            tips = centres[sel] + arrow * views[sel]
            for a, b, col in zip(centres[sel], tips, colours[sel]):
                ax.plot([a[0], b[0]], [a[2], b[2]], [a[1], b[1]], color=col, linewidth=0.6)
        if marker is not None:
            m = np.asarray(marker, np.float64)
            ax.scatter([m[0]], [m[2]], [m[1]], c="k", marker="*", s=120, depthshade=False)
        name = "start (training views)" if upto == 0 else (f"epoch {upto}" if stage >= 0 else f"final (epoch {upto})")
        ax.set_title(f"{name}: {int(shown.sum())} views", fontsize=9)
        ax.set_xlim(bounds[0][0], bounds[1][0])
        ax.set_ylim(bounds[0][2], bounds[1][2])
        ax.set_zlim(bounds[0][1], bounds[1][1])
        ax.set_xlabel("x", fontsize=8)
        ax.set_ylabel("z", fontsize=8)
        ax.set_zlabel("y (up)", fontsize=8)
        ax.tick_params(labelsize=6)
        ax.view_init(elev=28, azim=-60)
    if threshold is None and finite.any():
        mappable = matplotlib.cm.ScalarMappable(cmap=cmap, norm=matplotlib.colors.Normalize(lo, hi))
        fig.colorbar(mappable, ax=fig.axes, shrink=0.6, label="score")
    if title:
        fig.suptitle(title, fontsize=10)
    with atomic_file(path) as f:
        fig.savefig(f, format="png", dpi=90, bbox_inches="tight")


# ---------------------------------------------------------------------------------------------
# Contact sheets.


def _format_score(value: float) -> str:
    """A score for a label: three significant digits, \"n/a\" when it is not finite."""
    return "n/a" if not np.isfinite(value) else f"{value:.3g}"


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
