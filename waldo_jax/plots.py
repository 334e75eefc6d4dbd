"""Figures of a search: the pose cloud coloured by score, per epoch stage (the paper's pose-cloud figure).

Host-side Matplotlib (Agg backend, no display needed).
"""

from __future__ import annotations

import os
from typing import Optional, Sequence

import numpy as np

from waldo_jax.io import atomic_file

__all__ = ["pose_cloud", "STAGES"]

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
