"""The figures' training rows show what was scored; the methods sheet labels ranks, scores and training poses."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from waldo_jax.pipeline import figures

PHOTO = 1.0  # every training image is this grey; a render of training pose i is 0.1 * (i + 1)


def _render(c2w):
    return np.broadcast_to((0.1 * (np.asarray(c2w)[:, 0, 3] + 1.0))[:, None, None, None], (len(c2w), 4, 4, 3))


def _run(initial="renders", photos=True, top_indices=(1, 5), truth=False):
    c2w = np.tile(np.eye(4, dtype=np.float32), (3, 1, 1))
    c2w[:, 0, 3] = np.arange(3)
    source = SimpleNamespace(train_images=np.full((3, 4, 4, 3), PHOTO, np.float32) if photos else None,
                             train_c2w=c2w, render=_render, n_train=3)
    result = SimpleNamespace(top_valid=np.array([True, True, False]), top_scores=np.array([0.9, 0.5, np.nan]),
                             top_indices=np.array(list(top_indices) + [0]))
    top = np.full((2, 4, 4, 3), 0.5, np.float32)
    return SimpleNamespace(source=source, initial=initial, scores_train=np.array([0.2, 0.9, 0.4]),
                           criterion=SimpleNamespace(direction="max"), result=result, top_images=top,
                           top_truth=top + 0.25 if truth else None)


@pytest.mark.parametrize("initial, photos, expected, title", [
    ("images", True, [PHOTO, PHOTO], "training"),
    ("poses", True, [PHOTO, PHOTO], "training"),  # the room's training images are its analytic views
    ("renders", True, [0.2, 0.3], "training (renders)"),
    ("images", False, [0.2, 0.3], "training (renders)"),  # the photographs are not on this machine
])
def test_training_tiles_show_what_was_scored(initial, photos, expected, title):
    tiles, got_title = figures.training_tiles(_run(initial, photos), [1, 2])
    assert got_title == title and [float(t[0, 0, 0]) for t in tiles] == pytest.approx(expected)


def test_methods_sheet_rows_labels_and_training_marks(monkeypatch):
    captured = {}
    monkeypatch.setattr(figures.io, "contact_sheet",
                        lambda images, columns, labels, row_titles: captured.update(
                            images=images, labels=labels, titles=row_titles) or np.zeros((1, 1, 3), np.uint8))
    runs = {"grs": _run(top_indices=(1, 5)), "egps": _run(top_indices=(7, 2), truth=True)}
    figures.methods_sheet(runs, columns=3)
    assert captured["titles"] == ["training (renders)", "GRS", "EGPS (NeRF)", "EGPS (truth)"]
    labels, images = captured["labels"], captured["images"]
    assert labels[:3] == ["0.9", "0.4", "0.2"]  # the best training views, best first
    assert [float(t[0, 0, 0]) for t in images[:3]] == pytest.approx([0.2, 0.3, 0.1])
    assert labels[3:6] == ["#1 0.9 train", "#2 0.5", None]  # slot 1 < n_train: a training pose
    assert labels[6:9] == ["#1 0.9", "#2 0.5 train", None]
    assert images[5] is None and float(images[9][0, 0, 0]) == pytest.approx(0.75)  # padding, then the truth row
