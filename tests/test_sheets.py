"""The figures: training rows show what was scored; the methods sheet labels ranks, scores and training
poses; every sheet and plot names the criterion, its direction and range; pose clouds stand the scene's
up vertical and have legends; path plots mark start and end; the GIF keeps the stated fps."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from PIL import Image

from waldo_jax import io
from waldo_jax.pipeline import figures, path_run

PHOTO = 1.0  # every training image is this grey; a render of training pose i is 0.1 * (i + 1)
CRITERION = SimpleNamespace(
    name="saliency", direction="max", value_range=(0.0, 1.0), description="share of salient pixels"
)


def _render(c2w):
    return np.broadcast_to((0.1 * (np.asarray(c2w)[:, 0, 3] + 1.0))[:, None, None, None], (len(c2w), 4, 4, 3))


def _run(initial="renders", photos=True, top_indices=(1, 5), truth=False, separation=0.0):
    c2w = np.tile(np.eye(4, dtype=np.float32), (3, 1, 1))
    c2w[:, 0, 3] = np.arange(3)
    source = SimpleNamespace(
        train_images=np.full((3, 4, 4, 3), PHOTO, np.float32) if photos else None,
        train_c2w=c2w,
        render=_render,
        n_train=3,
    )
    result = SimpleNamespace(
        top_valid=np.array([True, True, False]),
        top_scores=np.array([0.9, 0.5, np.nan]),
        top_indices=np.array(list(top_indices) + [0]),
    )
    top = np.full((2, 4, 4, 3), 0.5, np.float32)
    return SimpleNamespace(
        source=source,
        initial=initial,
        scores_train=np.array([0.2, 0.9, 0.4]),
        criterion=CRITERION,
        result=result,
        top_images=top,
        top_truth=top + 0.25 if truth else None,
        config=SimpleNamespace(method="egps", min_separation=separation),
    )


@pytest.mark.parametrize(
    "initial, photos, expected, title",
    [
        ("images", True, [PHOTO, PHOTO], "training"),
        ("poses", True, [PHOTO, PHOTO], "training"),  # the room's training images are its analytic views
        ("renders", True, [0.2, 0.3], "training (renders)"),
        ("images", False, [0.2, 0.3], "training (renders)"),  # the photographs are not on this machine
    ],
)
def test_training_tiles_show_what_was_scored(initial, photos, expected, title):
    tiles, got_title = figures.training_tiles(_run(initial, photos), [1, 2])
    assert got_title == title and [float(t[0, 0, 0]) for t in tiles] == pytest.approx(expected)


def test_methods_sheet_rows_labels_and_training_marks(monkeypatch):
    captured = {}
    monkeypatch.setattr(
        figures.io,
        "contact_sheet",
        lambda images, columns, labels, row_titles, caption: (
            captured.update(images=images, labels=labels, titles=row_titles) or np.zeros((1, 1, 3), np.uint8)
        ),
    )
    runs = {"grs": _run(top_indices=(1, 5), separation=20.0), "egps": _run(top_indices=(7, 2), truth=True)}
    figures.methods_sheet(runs, columns=3)
    # GRS's top views are different shots (>= 20 degrees apart); EGPS's are the paper's top-k.
    assert captured["titles"] == ["training (renders)", "GRS, >= 20 deg apart", "EGPS (NeRF)", "EGPS (truth)"]
    labels, images = captured["labels"], captured["images"]
    assert labels[:3] == ["0.9", "0.4", "0.2"]  # the best training views, best first
    assert [float(t[0, 0, 0]) for t in images[:3]] == pytest.approx([0.2, 0.3, 0.1])
    assert labels[3:6] == ["#1 0.9 train", "#2 0.5", None]  # slot 1 < n_train: a training pose
    assert labels[6:9] == ["#1 0.9", "#2 0.5 train", None]
    assert images[5] is None and float(images[9][0, 0, 0]) == pytest.approx(0.75)  # padding, then the truth row


# ---------------------------------------------------------------------------------------------
# What the scores are, on every sheet, plot and results file.


@pytest.mark.parametrize(
    "criterion, label, caption",
    [
        (
            CRITERION,
            "saliency (higher is better, in [0, 1])",
            "saliency: share of salient pixels; higher is better, in [0, 1]",
        ),
        (
            SimpleNamespace(name="brisque", direction="min", value_range=(0.0, 100.0), description="BRISQUE"),
            "brisque (lower is better, in [0, 100])",
            "brisque: BRISQUE; lower is better, in [0, 100]",
        ),
        (
            SimpleNamespace(name="colorfulness", direction="max", value_range=(0.0, np.inf), description=""),
            "colorfulness (higher is better, >= 0)",
            "colorfulness (higher is better, >= 0)",
        ),
        (
            SimpleNamespace(name="score", direction="min", value_range=(-np.inf, np.inf), description="d"),
            "score (lower is better)",
            "score: d; lower is better",
        ),
    ],
)
def test_criterion_label_and_caption_name_direction_and_range(criterion, label, caption):
    assert figures.criterion_label(criterion) == label and figures.criterion_caption(criterion) == caption


def test_sheets_are_captioned_with_the_criterion(monkeypatch):
    captions = []
    monkeypatch.setattr(
        figures.io,
        "contact_sheet",
        lambda *a, caption=None, **k: captions.append(caption) or np.zeros((1, 1, 3), np.uint8),
    )
    figures.contact_sheet(_run())
    figures.methods_sheet({"egps": _run()}, columns=2)
    assert captions == ["Scores on the tiles: saliency: share of salient pixels; higher is better, in [0, 1]"] * 2


def test_contact_sheet_caption_is_a_band_above_the_tiles():
    tiles = [np.full((8, 8, 3), 0.5, np.float32)] * 2
    plain = io.contact_sheet(tiles, columns=2)
    captioned = io.contact_sheet(tiles, columns=2, caption="saliency: share of salient pixels; " * 4)
    band = captioned.shape[0] - plain.shape[0]
    assert captioned.shape[1] == plain.shape[1] and band > 30  # a long caption wraps onto several lines
    assert captioned[:band].min() < 100 and plain[:band].min() >= 100  # text where plain has grey tiles
    np.testing.assert_array_equal(captioned[band:], plain)  # the tiles, moved down


# ---------------------------------------------------------------------------------------------
# The scene's up axis.


def _ring(up_axis: int, sign: float = 1.0, count: int = 6) -> np.ndarray:
    """c2w [count, 4, 4]: OpenGL cameras on a ring around the origin at rising heights along the world axis
    `up_axis` (times `sign`), looking at the origin, upright in that world."""
    up = sign * np.eye(3)[up_axis]
    across = np.eye(3)[(up_axis + 1) % 3], np.eye(3)[(up_axis + 2) % 3]
    c2w = np.tile(np.eye(4), (count, 1, 1))
    for i, angle in enumerate(np.linspace(0.0, 2 * np.pi, count, endpoint=False)):
        origin = 3.0 * (np.cos(angle) * across[0] + np.sin(angle) * across[1]) + (0.5 + 0.2 * i) * up
        back = origin / np.linalg.norm(origin)  # the camera looks down -z: its z axis points away from the target
        right = np.cross(up, back)
        right /= np.linalg.norm(right)
        c2w[i, :3, :3] = np.stack([right, np.cross(back, right), back], axis=1)
        c2w[i, :3, 3] = origin
    return c2w


@pytest.mark.parametrize("axis, sign, name", [(2, 1.0, "+z"), (1, 1.0, "+y"), (1, -1.0, "-y"), (0, -1.0, "-x")])
def test_scene_up_is_the_cameras_up_and_the_plot_stands_it_vertical(axis, sign, name):
    c2w = _ring(axis, sign)
    up = figures.scene_up(c2w)
    assert up[axis] * sign > 0.9  # the cameras look down at the origin: their up leans, their mean does not
    frame = figures.plot_frame(up)
    np.testing.assert_allclose(frame.up, sign * np.eye(3)[axis], atol=1e-12)  # snapped to the world axis
    np.testing.assert_allclose(frame(frame.up), [0.0, 0.0, 1.0], atol=1e-12)
    assert frame.up_text == name and frame.labels[2] == f"{name.lstrip('+')} (up)"
    np.testing.assert_allclose(frame.rotation @ frame.rotation.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(frame.rotation) == pytest.approx(1.0)  # a rotation, never a mirror
    if (axis, sign) == (2, 1.0):
        np.testing.assert_array_equal(frame.rotation, np.eye(3))  # a Blender scene's axes as they are


@settings(max_examples=40, deadline=None)
@given(st.lists(st.floats(-1.0, 1.0), min_size=3, max_size=3).filter(lambda v: np.linalg.norm(v) > 0.1))
def test_plot_frame_of_any_up_is_a_rotation_taking_it_vertical(up):
    up = np.asarray(up) / np.linalg.norm(up)
    for snap in (0.0, figures.UP_SNAP_DEGREES):
        frame = figures.plot_frame(up, snap_degrees=snap)
        np.testing.assert_allclose(frame.rotation @ frame.rotation.T, np.eye(3), atol=1e-9)
        assert np.linalg.det(frame.rotation) == pytest.approx(1.0)
        vertical = frame(up)[2]
        assert vertical == pytest.approx(1.0) if snap == 0.0 else vertical >= np.cos(np.radians(snap)) - 1e-9


def _cloud(c2w, marker=None, threshold=None):
    epoch = np.array([0] * len(c2w) + [1, 2])
    poses = np.concatenate([c2w, c2w[:2]])
    poses[len(c2w) :, :3, 3] += 0.3
    scores = np.array([0.1 * i for i in range(len(c2w))] + [0.9, np.nan])
    style = figures.PoseCloudStyle(
        threshold=threshold, marker=marker, marker_label="Waldo", score_label="saliency (higher is better, in [0, 1])"
    )
    return figures.pose_cloud(None, poses, scores, epoch, "max", style=style)


@pytest.mark.slow
@pytest.mark.parametrize("axis", [2, 1])
def test_pose_cloud_plots_the_scene_up_vertical(axis):
    c2w = _ring(axis)
    fig = _cloud(c2w)
    heights = np.concatenate([c2w[:, axis, 3], c2w[:2, axis, 3] + 0.3])
    panels = [ax for ax in fig.axes if ax.name == "3d"]
    assert len(panels) == 3
    for ax in panels:
        assert ax.get_zlabel() == f"{'xyz'[axis]} (up)"
        assert ax.get_zlim() == pytest.approx((heights.min(), heights.max()))  # the vertical axis is the up axis
    assert any(f"up, +{'xyz'[axis]}" in t.get_text() for t in fig.texts)


def test_pose_cloud_draws_one_direction_line_per_view_in_its_score_colour():
    from mpl_toolkits.mplot3d.art3d import Line3DCollection

    c2w = _ring(2)
    fig = _cloud(c2w, threshold=0.25)  # scores 0.0, 0.1, ... for the ring, then 0.9 (epoch 1) and NaN (epoch 2)
    panels = [ax for ax in fig.axes if ax.name == "3d"]
    shown = [len(c2w), len(c2w) + 1, len(c2w) + 2]  # start, epoch 1, final
    for ax, count in zip(panels, shown, strict=True):
        lines = [c for c in ax.collections if isinstance(c, Line3DCollection)]
        colours = np.concatenate([c.get_colors() for c in lines])
        assert len(colours) == count  # a line for every view of the panel, one artist per kind of view
        good = [0.1 * i > 0.25 for i in range(len(c2w))] + [True, None][: count - len(c2w)]
        for colour, is_good in zip(colours, good):
            expected = figures._FAILED if is_good is None else (figures._GOOD if is_good else figures._BAD)
            np.testing.assert_allclose(colour, expected)


@pytest.mark.slow
def test_pose_cloud_legend_names_every_mark():
    fig = _cloud(_ring(2), marker=np.zeros(3))
    texts = [t.get_text() for legend in fig.legends for t in legend.get_texts()]
    assert texts == ["training view", "generated view", "view direction", "failed (no score)", "Waldo"]
    assert "saliency (higher is better, in [0, 1])" in [ax.get_ylabel() for ax in fig.axes]  # the colour bar
    fig = _cloud(_ring(2), threshold=0.5)
    texts = [t.get_text() for legend in fig.legends for t in legend.get_texts()]
    assert texts == [
        "training view",
        "generated view",
        "view direction",
        "score > 0.5",
        "other scores",
        "failed (no score)",
    ]
    c2w = _ring(2)  # the training views alone: no legend entry for marks the figure does not draw
    fig = figures.pose_cloud(None, c2w, np.arange(len(c2w), dtype=float), np.zeros(len(c2w), int), "min")
    assert [t.get_text() for t in fig.legends[0].get_texts()] == ["training view", "view direction"]
    assert "Colour: score (lower is better)." in fig.texts[-1].get_text()


# ---------------------------------------------------------------------------------------------
# `waldo path`'s figures and GIF.


def _path_run(up_axis=1):
    train = _ring(up_axis, count=5)
    best = _ring(up_axis, count=8)
    return SimpleNamespace(
        source=SimpleNamespace(train_c2w=train, room=SimpleNamespace(waldo_center=np.zeros(3)), name="room"),
        criterion=CRITERION,
        config=SimpleNamespace(method="egps", frames=8),
        results=[SimpleNamespace(best_c2w=best)],
        found=[{"frame_scores": np.linspace(0, 1, 8)}],
        references={
            "straight": {"c2w": best[::-1], "frame_scores": np.zeros(8)},
            "training": {"c2w": best[1:], "frame_scores": np.ones(8)},
        },
    )


def test_path_plot_marks_start_and_end_from_above():
    run = _path_run(up_axis=1)  # the room: +y up
    fig = path_run._path_figure(run)
    ax = fig.axes[0]
    assert (ax.get_xlabel(), ax.get_ylabel()) == ("z", "x") and "+y" in ax.get_title()  # looking down +y
    starts = [c.get_offsets()[0] for c in ax.collections if c.get_gid() == "start"]
    ends = [c.get_offsets()[0] for c in ax.collections if c.get_gid() == "end"]
    best = run.results[0].best_c2w[:, :3, 3]
    np.testing.assert_allclose(starts[0], best[0, [2, 0]])
    np.testing.assert_allclose(ends[0], best[-1, [2, 0]])
    assert len(starts) == len(ends) == 3  # the found path and both references
    texts = [t.get_text() for t in ax.get_legend().get_texts()]
    assert texts == [
        "training cameras",
        "found (egps)",
        "straight",
        "training trajectory",
        "view direction (found)",
        "Waldo (the target)",
        "start (frame 0)",
        "end (frame 7)",
    ]


def test_score_plot_names_the_criterion():
    ax = path_run._score_figure(_path_run()).axes[0]
    assert ax.get_ylabel() == "saliency (higher is better, in [0, 1])"
    assert "share of salient pixels" in ax.get_title() and "frame" in ax.get_xlabel()


@pytest.mark.parametrize("fps", [12.0, 15.0, 7.0])
def test_gif_frames_last_one_over_fps_to_the_centisecond(tmp_path, fps):
    frames = np.linspace(0.0, 1.0, 4, dtype=np.float32)[:, None, None, None] * np.ones((4, 6, 6, 3), np.float32)
    path_run._video(tmp_path / "path.gif", frames, fps)
    with Image.open(tmp_path / "path.gif") as gif:
        durations = []
        for i in range(gif.n_frames):
            gif.seek(i)
            durations.append(gif.info["duration"])
    assert durations == [round(100 / fps) * 10] * 4 == [path_run.gif_frame_ms(fps)] * 4


def test_pose_cloud_of_cameras_at_one_height_warns_nothing():
    """Cameras on a ring at one height (a COLMAP rig, or copies of one pose) gave Matplotlib's own warning,
    "Attempting to set identical low and high zlims", which the CLI showed as waldo's."""
    import warnings

    c2w = _ring(2)
    c2w[:, 2, 3] = 1.5  # every centre at one height
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        fig = figures.pose_cloud(None, c2w, np.arange(len(c2w), dtype=float), np.zeros(len(c2w), int), "max")
        same = figures.pose_cloud(None, np.repeat(c2w[:1], 4, 0), np.ones(4), np.zeros(4, int), "max")
    for panel in [ax for ax in fig.axes if ax.name == "3d"]:
        low, high = panel.get_zlim()
        assert low < 1.5 < high
    assert all(np.ptp(ax.get_xlim()) > 0 for ax in same.axes if ax.name == "3d")
