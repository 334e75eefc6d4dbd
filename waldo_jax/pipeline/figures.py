"""Figures of an experiment: contact sheets of the best views and the pose cloud coloured by score.

`contact_sheet` (one run) and `methods_sheet` (several methods side by side, the paper's qualitative
figure) are uint8 arrays; `pose_cloud` writes the paper's pose-cloud figure with host-side
Matplotlib (no display needed). Every figure names what its scores are (`criterion_label`,
`criterion_caption`: the criterion, its direction and range), and 3D figures stand the scene's own up
axis vertical (`scene_up`, `plot_frame`: the mean of the training cameras' up vectors, as nerfstudio's
and multinerf's orientation does).
"""

from __future__ import annotations

import dataclasses
import os
from typing import List, Mapping, Optional, Sequence, Tuple

import jax.numpy as jnp
import numpy as np

from waldo_jax import io
from waldo_jax.cameras import scene_up
from waldo_jax.io import atomic_file
from waldo_jax.pipeline.experiment import ExploreRun
from waldo_jax.pipeline.sources import resize_images

__all__ = [
    "pose_cloud",
    "PoseCloudStyle",
    "STAGES",
    "contact_sheet",
    "methods_sheet",
    "training_tiles",
    "criterion_label",
    "criterion_caption",
    "scene_up",
    "plot_frame",
    "PlotFrame",
    "UP_SNAP_DEGREES",
]

STAGES = ("start", "epoch 1", "final")
# A mean of a few cameras' up vectors leans a few degrees off the scene's up (lego_tiny's: 5.6 degrees
# off +z); scenes are nearly always made with a world axis up, so an axis this close is taken as up.
UP_SNAP_DEGREES = 15.0


# ---------------------------------------------------------------------------------------------
# What the scores are.


def _range_text(value_range: Tuple[float, float]) -> str:
    """A criterion's value range in words: 'in [0, 1]', '>= 0', '<= 5', or '' when unbounded."""
    low, high = (float(v) for v in value_range)
    if np.isfinite(low) and np.isfinite(high):
        return f"in [{low:g}, {high:g}]"
    if np.isfinite(low):
        return f">= {low:g}"
    return f"<= {high:g}" if np.isfinite(high) else ""


def _direction_text(criterion) -> str:
    """'higher is better' or 'lower is better', then the range when it is bounded."""
    words = "higher is better" if criterion.direction == "max" else "lower is better"
    bounds = _range_text(getattr(criterion, "value_range", (-np.inf, np.inf)))
    return f"{words}, {bounds}" if bounds else words


def criterion_label(criterion) -> str:
    """Short axis / colour-bar label of a criterion's scores: name, direction and range.

    E.g. "waldo_oracle (higher is better, in [0, 1])".
    """
    return f"{criterion.name} ({_direction_text(criterion)})"


def criterion_caption(criterion) -> str:
    """One sentence on what a criterion's scores are, for captions and reports: name, description,
    direction and range. E.g. "brisque: BRISQUE (Mittal et al. 2012) ...; lower is better, in [0, 100]"."""
    description = getattr(criterion, "description", "")
    return (
        f"{criterion.name}: {description}; {_direction_text(criterion)}" if description else criterion_label(criterion)
    )


# ---------------------------------------------------------------------------------------------
# The scene's up axis.


@dataclasses.dataclass(frozen=True)
class PlotFrame:
    """World -> plot coordinates that stand the scene's up vertical (the plot's third axis).

    Attributes:
      rotation: float64 [3, 3], a rotation; row i is the world direction of the plot's axis i.
      labels: the plot's three axis labels (world axes, e.g. ("x", "y", "z (up)"), or directions).
      up: float64 [3] the world direction plotted vertical (unit).
      up_text: the up direction in words, e.g. "+z" or "(0.27, 0.00, 0.96)".
    """

    rotation: np.ndarray
    labels: Tuple[str, str, str]
    up: np.ndarray
    up_text: str

    def __call__(self, points: np.ndarray) -> np.ndarray:
        """Plot coordinates [..., 3] of world points or directions [..., 3]."""
        return np.asarray(points, np.float64) @ self.rotation.T


def _vector_text(v: np.ndarray) -> str:
    return "(" + ", ".join(f"{x:.2f}" for x in v) + ")"


def plot_frame(up: np.ndarray, snap_degrees: float = UP_SNAP_DEGREES) -> PlotFrame:
    """The right-handed frame whose vertical axis is `up`, snapped to a world axis within `snap_degrees`.

    Snapped (the usual case: +z for Blender scenes, +y for the procedural room, -y for LLFF), the
    plot's axes are world axes and keep their names, e.g. up +y plots (z, x, y). Otherwise the plot's
    vertical is `up` itself and its horizontal axes are named by their world directions.

    Args:
      up: float [3] the scene's up (`scene_up`); need not be unit.
      snap_degrees: largest angle between `up` and a world axis taken as that axis.
    """
    up = np.asarray(up, np.float64)
    up = up / max(float(np.linalg.norm(up)), 1e-12)
    k = int(np.argmax(np.abs(up)))
    sign = 1.0 if up[k] > 0 else -1.0
    eye = np.eye(3)
    if np.degrees(np.arccos(min(abs(float(up[k])), 1.0))) <= snap_degrees:
        # The cyclic order (k+1, k+2, k) is right-handed; a downward world axis swaps the horizontals.
        first, second = ((k + 1) % 3, (k + 2) % 3) if sign > 0 else ((k + 2) % 3, (k + 1) % 3)
        name = "-" if sign < 0 else ""
        axis_up = f"{name}{'xyz'[k]}"
        return PlotFrame(
            rotation=np.stack([eye[first], eye[second], sign * eye[k]]),
            labels=("xyz"[first], "xyz"[second], f"{axis_up} (up)"),
            up=sign * eye[k],
            up_text=axis_up if sign < 0 else f"+{axis_up}",
        )
    across = eye[int(np.argmin(np.abs(up)))]  # the world axis least aligned with up
    first = across - np.dot(across, up) * up
    first /= np.linalg.norm(first)
    second = np.cross(up, first)
    return PlotFrame(
        rotation=np.stack([first, second, up]),
        labels=(f"along {_vector_text(first)}", f"along {_vector_text(second)}", f"up {_vector_text(up)}"),
        up=up,
        up_text=_vector_text(up),
    )


def _camera_axes(c2w: np.ndarray):
    """Camera centres [N, 3] and viewing directions [N, 3] (OpenGL: the camera looks down -z)."""
    return c2w[:, :3, 3], -c2w[:, :3, 2]


# Pose-cloud colours of a score better than the threshold, of any other score, and of a failed view.
_GOOD, _BAD, _FAILED = (0.1, 0.65, 0.2, 1.0), (0.85, 0.15, 0.15, 1.0), (0.6, 0.6, 0.6, 1.0)


def _legend_handles(
    epoch: np.ndarray, threshold: Optional[float], direction: str, failed: bool, marker_label: Optional[str]
):
    """Proxy artists naming every kind of mark `pose_cloud` draws (training and generated views where present)."""
    from matplotlib.lines import Line2D

    def point(mark, label, face="0.75", edge="k", size=7):
        return Line2D(
            [], [], ls="none", marker=mark, markersize=size, markerfacecolor=face, markeredgecolor=edge, label=label
        )

    handles = [point("^", "training view")] if np.any(epoch == 0) else []
    if np.any(epoch > 0):
        handles.append(point("o", "generated view", edge="none", size=5))
    handles.append(Line2D([], [], color="0.4", lw=0.8, label="view direction"))
    if threshold is not None:
        better = ">" if direction == "max" else "<"
        handles += [
            point("s", f"score {better} {threshold:g}", face=_GOOD, edge="none"),
            point("s", "other scores", face=_BAD, edge="none"),
        ]
    if failed:
        handles.append(point("s", "failed (no score)", face=_FAILED, edge="none"))
    if marker_label:
        handles.append(point("*", marker_label, face="k", size=11))
    return handles


@dataclasses.dataclass(frozen=True)
class PoseCloudStyle:
    """How `pose_cloud` draws its figure: title, colouring, the marked point, the panels and the frame.

    Attributes:
      title: figure title ("" for none).
      threshold: optional score threshold: views better than it are green, the others red (the paper's
        colouring); None: a colour map of the score (brighter = better in the criterion's direction).
      marker: optional float [3] point to mark (e.g. Waldo's position), drawn as a black star.
      marker_label: the legend's name of `marker`.
      stages: epochs to show, one panel each (-1: the final epoch).
      arrow_length: length of the view-direction lines (default: 4 % of the cloud's extent).
      score_label: what the scores are, for the colour bar (`criterion_label`; default: the direction).
      up: float [3] the world direction drawn vertical (default: `scene_up` of the epoch-0 poses).
    """

    title: str = ""
    threshold: Optional[float] = None
    marker: Optional[np.ndarray] = None
    marker_label: str = "target"
    stages: Sequence[int] = (0, 1, -1)
    arrow_length: Optional[float] = None
    score_label: Optional[str] = None
    up: Optional[np.ndarray] = None


@dataclasses.dataclass(frozen=True)
class _Cloud:
    """The poses in plot coordinates and their colours: what every panel of `pose_cloud` draws."""

    frame: PlotFrame
    centres: np.ndarray  # float64 [C, 3] camera centres
    views: np.ndarray  # float64 [C, 3] viewing directions
    colours: np.ndarray  # float64 [C, 4] RGBA
    epoch: np.ndarray  # int [C] epoch of birth
    star: Optional[np.ndarray]  # float64 [3] the marker, or None
    bounds: Tuple[np.ndarray, np.ndarray]  # the axes' limits: lowest and highest corner [3] of poses and marker
    arrow: float  # length of the view-direction lines


def _score_colours(
    scores: np.ndarray, direction: str, threshold: Optional[float], cmap, lo: float, hi: float
) -> np.ndarray:
    """RGBA [C, 4] of each score: green / red about `threshold`, else `cmap` over [lo, hi]; failed ones grey."""
    if threshold is not None:
        good = (scores > threshold) if direction == "max" else (scores < threshold)
        colours = np.where(good[:, None], np.array([_GOOD]), np.array([_BAD]))
    else:
        colours = cmap((scores - lo) / max(hi - lo, 1e-12))
    colours[~np.isfinite(scores)] = _FAILED
    return colours


def _plot_cloud(c2w: np.ndarray, epoch: np.ndarray, colours: np.ndarray, style: PoseCloudStyle) -> _Cloud:
    """The poses in the frame that stands the scene's up vertical, with the marker, the limits and the arrow."""
    training = c2w[epoch == 0] if np.any(epoch == 0) else c2w
    frame = plot_frame(scene_up(training) if style.up is None else style.up)
    centres, views = (frame(a) for a in _camera_axes(c2w))  # plot coordinates: the scene's up is the third
    extent = float(np.max(np.ptp(centres, axis=0))) if len(centres) > 1 else 1.0
    arrow = style.arrow_length if style.arrow_length is not None else 0.04 * max(extent, 1e-6)
    star = None if style.marker is None else frame(np.asarray(style.marker, np.float64).reshape(3))
    points = centres if star is None else np.concatenate([centres, star[None]])
    bounds = (points.min(0), points.max(0)) if len(points) else (np.zeros(3), np.ones(3))
    return _Cloud(
        frame=frame, centres=centres, views=views, colours=colours, epoch=epoch, star=star, bounds=bounds, arrow=arrow
    )


def _widened(low: float, high: float, arrow: float) -> Tuple[float, float]:
    """Axis limits (low, high) as they are, or, for a range of no extent, widened on each side by the
    view-direction lines' length `arrow` (at least 5 % of the range's magnitude, and 0.05), so that the
    lines stay inside the box."""
    low, high = float(low), float(high)
    if high - low > 1e-9 * max(1.0, abs(low), abs(high)):
        return low, high
    pad = max(0.05 * max(abs(low), abs(high), 1.0), float(arrow))
    return low - pad, high + pad


def _draw_stage(ax, cloud: _Cloud, stage: int, last: int) -> None:
    """One 3D panel: the poses that exist at `stage` (-1: the final epoch `last`), the marker, axes and title."""
    from mpl_toolkits.mplot3d.art3d import Line3DCollection

    upto = last if stage < 0 else min(stage, last)
    shown = cloud.epoch <= upto
    for is_train, mark, size in ((True, "^", 34), (False, "o", 12)):
        sel = shown & ((cloud.epoch == 0) == is_train)
        if not sel.any():
            continue
        centres, colours = cloud.centres[sel], cloud.colours[sel]
        ax.scatter(
            centres[:, 0],
            centres[:, 1],
            centres[:, 2],
            c=colours,
            marker=mark,
            s=size,
            depthshade=False,
            edgecolors="k" if is_train else "none",
            linewidths=0.4,
        )
        # One collection of every view's direction line: an artist per line cost a second a figure.
        tips = centres + cloud.arrow * cloud.views[sel]
        ax.add_collection3d(Line3DCollection(np.stack([centres, tips], 1), colors=colours, linewidths=0.6))
    if cloud.star is not None:
        star = cloud.star
        ax.scatter([star[0]], [star[1]], [star[2]], c="k", marker="*", s=120, depthshade=False)
    name = "start (training views)" if upto == 0 else (f"epoch {upto}" if stage >= 0 else f"final (epoch {upto})")
    ax.set_title(f"{name}: {int(shown.sum())} views", fontsize=9)
    # Cameras all at one height (or one place) give an axis of no extent: widened here, as Matplotlib
    # would do with a warning of its own ("identical low and high zlims").
    (x0, x1), (y0, y1), (z0, z1) = (_widened(a, b, cloud.arrow) for a, b in zip(*cloud.bounds))
    ax.set_xlim(x0, x1)
    ax.set_ylim(y0, y1)
    ax.set_zlim(z0, z1)
    ax.set_xlabel(cloud.frame.labels[0], fontsize=8)
    ax.set_ylabel(cloud.frame.labels[1], fontsize=8)
    ax.set_zlabel(cloud.frame.labels[2], fontsize=8)
    ax.tick_params(labelsize=6)
    ax.view_init(elev=28, azim=-60)


def _legend_and_caption(
    fig, cloud: _Cloud, direction: str, failed: bool, score_label: str, style: PoseCloudStyle
) -> None:
    """The legend naming every mark below the panels, and the caption: the vertical and what the colours are."""
    handles = _legend_handles(
        cloud.epoch, style.threshold, direction, failed, None if cloud.star is None else style.marker_label
    )
    fig.legend(
        handles=handles, loc="upper center", bbox_to_anchor=(0.45, 0.06), ncol=len(handles), fontsize=8, frameon=False
    )
    colour = f"Colour: {score_label}." if style.threshold is None else f"Scores: {score_label}."
    fig.text(
        0.45,
        -0.02,
        f"Vertical: the scene's up, {cloud.frame.up_text} (the mean of the training cameras' up vectors). {colour}",
        ha="center",
        va="top",
        fontsize=8,
    )


def pose_cloud(
    path: Optional[str | os.PathLike],
    c2w: np.ndarray,
    scores: np.ndarray,
    epoch: np.ndarray,
    direction: str,
    style: PoseCloudStyle = PoseCloudStyle(),
):
    """Writes a figure with one 3D panel per stage: the poses that exist at that stage, coloured by score.

    Stage e shows the training views (epoch 0) and every child born in epochs 1..e (-1: all epochs).
    Training views are drawn as triangles, children as dots; a short line shows each view direction.
    With `style.threshold`, views better than it are green and the others red (the paper's colouring);
    otherwise a colour map of the score (brighter = better in the criterion's direction). The scene's
    up (`style.up`, default `scene_up` of the training views) is vertical (`plot_frame`); a legend names
    every mark, and a caption the up direction.

    Args:
      path: PNG to write (None: write nothing, only return the figure).
      c2w: float [C, 4, 4] poses of the population (valid slots only).
      scores: float [C] their raw scores (NaN: failed, drawn grey).
      epoch: int [C] epoch of birth (0: training view).
      direction: "max" or "min".
      style: a `PoseCloudStyle`: title, threshold, marker and its label, stages, arrow length, score
        label and up direction.

    Returns:
      The Matplotlib `Figure`.
    """
    # A bare Figure (no pyplot): draws off-screen without switching a notebook's backend.
    import matplotlib
    from matplotlib.figure import Figure

    c2w = np.asarray(c2w, np.float64)
    scores = np.asarray(scores, np.float64)
    epoch = np.asarray(epoch)
    last = int(epoch.max()) if epoch.size else 0
    finite = np.isfinite(scores)
    lo, hi = (np.min(scores[finite]), np.max(scores[finite])) if finite.any() else (0.0, 1.0)
    cmap = matplotlib.colormaps["viridis" if direction == "max" else "viridis_r"]
    score_label = style.score_label or f"score ({'higher' if direction == 'max' else 'lower'} is better)"
    cloud = _plot_cloud(c2w, epoch, _score_colours(scores, direction, style.threshold, cmap, lo, hi), style)

    fig = Figure(figsize=(4.2 * len(style.stages), 4.4))
    for panel, stage in enumerate(style.stages):
        _draw_stage(fig.add_subplot(1, len(style.stages), panel + 1, projection="3d"), cloud, stage, last)
    if style.threshold is None and finite.any():
        mappable = matplotlib.cm.ScalarMappable(cmap=cmap, norm=matplotlib.colors.Normalize(lo, hi))
        fig.colorbar(mappable, ax=fig.axes, shrink=0.6, label=score_label)
    _legend_and_caption(fig, cloud, direction, bool((~finite).any()), score_label, style)
    if style.title:
        fig.suptitle(style.title, fontsize=10)
    if path is not None:
        with atomic_file(path) as f:
            fig.savefig(f, format="png", dpi=90, bbox_inches="tight")
    return fig


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
    """uint8 sheet: best training views (first row), best found views (second), analytic truth (third, if any),
    under a caption naming the criterion, its direction and range (`criterion_caption`)."""
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
    titles = [f"{train_title}", f"{run.config.method.upper()} found{_apart(run)}"]
    if run.top_truth is not None:
        images += list(run.top_truth) + [None] * (columns - k)
        labels += [None] * columns
        titles.append("analytic truth")
    return io.contact_sheet(
        images, columns=columns, labels=labels, row_titles=titles, caption=_sheet_caption(run.criterion)
    )


def _apart(run: ExploreRun) -> str:
    """ ", >= 20 deg apart" when the top-k are different shots (`ExploreConfig.min_separation`), else ""."""
    separation = run.config.min_separation
    return f", >= {separation:g} deg apart" if separation > 0 else ""


def _sheet_caption(criterion) -> str:
    return f"Scores on the tiles: {criterion_caption(criterion)}"


def methods_sheet(runs: Mapping[str, ExploreRun], columns: int) -> np.ndarray:
    """uint8 sheet comparing methods on one source and criterion: best training views, then each method's best.

    Row 1: the best training views (`training_tiles`) with their scores. Then per method (in the
    order of `runs`) its top views of the first seed as the source renders them, labelled with rank
    and score; a top view that is a training pose is marked "train" (its score is the training
    view's, the tile the render). For a NeRF of the procedural room each method's row is followed
    by the same views rendered by the analytic room (the truth). A caption names the criterion.
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
        found = row(
            run.top_images,
            [f"#{r + 1} {_format_score(s)}" + (" train" if t else "") for r, (s, t) in enumerate(zip(scores, trained))],
        )
        images, labels = images + found[0], labels + found[1]
        if run.top_truth is None:
            titles.append(method.upper() + _apart(run))
        else:
            truth = row(run.top_truth, [])
            images, labels = images + truth[0], labels + truth[1]
            titles += [f"{method.upper()} (NeRF{_apart(run)})", f"{method.upper()} (truth)"]
    return io.contact_sheet(
        images, columns=columns, labels=labels, row_titles=titles, caption=_sheet_caption(first.criterion)
    )
