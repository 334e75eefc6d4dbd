"""`waldo view` on output folders a user has edited or damaged, through the real entry point: every value the
viewer reads from results.json (an explore's or a path's), summary.json (a demo's) and poses.json, the top-k
images and the --export target. Each case ends in one line `waldo: error: ...` naming the file and the key,
exit status 1, no traceback and no page written (or, for legal but degenerate input, one `waldo: warning:`
line), instead of the TypeError, KeyError, ZeroDivisionError, hang or NaN-drawn frustum it had been.

The folders are written here by hand (no search runs): their SOURCE does not exist, so the scene's geometry is
left out with a note and each case takes a fraction of a second.
"""

import json
import os

import numpy as np
import pytest
from PIL import Image

from conftest import within
from waldo_jax.cli import main

pytest.importorskip("viser", reason="the viewer needs viser (pip install 'waldo_jax[view]')")

NAN = float("nan")


def _pose(x: float = 0.0) -> list:
    return [[1.0, 0.0, 0.0, x], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 1.0, 3.0], [0.0, 0.0, 0.0, 1.0]]


def _results() -> dict:
    """results.json of a small explore: 3 training views, 4 generated ones, 2 top-k shots, 2 archive elites."""
    return {
        "method": "egps",
        "criterion": "colorfulness",
        "direction": "max",
        "source": "no_such_source_here",
        "source_info": {"ngp_scale": 0.33, "ngp_offset": [0.5, 0.5, 0.5], "ngp_from_mitsuba": False},
        "resolution": [16, 16],
        "train_c2w": [_pose(i) for i in range(3)],
        "scores_train": [0.1, None, 0.3],
        "generated_c2w": [_pose(3 + i) for i in range(4)],
        "scores_generated": [0.4, 0.5, None, 0.7],
        "generated_epochs": [1, 1, 2, 2],
        "generated_slots": [3, 4, 5, 6],
        "archive": {
            "elites": [
                {"cell": 0, "slot": 6, "azimuth": 10.0, "elevation": 5.0, "distance_band": 0, "score": 0.7},
                {"cell": 1, "slot": 2, "score": 0.3},
            ]
        },
        "topk": [
            {"rank": 0, "score": 0.7, "c2w": _pose(6), "image": "topk/00.png", "epoch": 2},
            {"rank": 1, "score": 0.3, "c2w": _pose(2), "image": "topk/01.png", "training_view": True},
        ],
    }


def _poses_json() -> dict:
    return {
        "w": 16,
        "h": 16,
        "fl_x": 14.0,
        "fl_y": 14.0,
        "cx": 8.0,
        "cy": 8.0,
        "frames": [{"file_path": "topk/00.png", "transform_matrix": _pose(6)}],
    }


def _explore_folder(folder, results=None, poses=None):
    """An explore output folder in `folder`: results.json, poses.json and two 16x16 top-k images."""
    (folder / "topk").mkdir(parents=True)
    for i in range(2):
        Image.fromarray(np.full((16, 16, 3), 60 * i + 40, np.uint8)).save(folder / "topk" / f"{i:02d}.png")
    (folder / "results.json").write_text(json.dumps(_results() if results is None else results))
    (folder / "poses.json").write_text(json.dumps(_poses_json() if poses is None else poses))
    return folder


def _refused(capsys, tmp_path, folder, *says, extra=()):
    """Runs `waldo view FOLDER --export`; checks one error line holding each of `says` and no page."""
    page = tmp_path / "page.html"
    status = main(["view", str(folder), "--quiet", "--export", str(page), *extra])
    captured = capsys.readouterr()
    err = captured.err.strip().splitlines()
    assert status == 1 and len(err) == 1 and err[0].startswith("waldo: error: "), (status, captured)
    for text in says:
        assert text in err[0], err[0]
    assert not page.exists()
    return err[0]


def _set(key_path, value):
    def edit(results):
        where = results
        for key in key_path[:-1]:
            where = where[key]
        if value is KeyError:
            del where[key_path[-1]]
        else:
            where[key_path[-1]] = value

    return edit


# (id, edit of results.json, the key the message names): one case per kind of value the viewer reads.
RESULTS_CASES = [
    ("topk-not-a-list", _set(["topk"], "abc"), "topk: expected a list"),
    ("topk-entry-not-an-object", _set(["topk"], [3]), "topk[0]: expected a JSON object"),
    ("topk-rank-missing", _set(["topk", 0, "rank"], KeyError), "topk[0].rank: missing"),
    ("topk-rank-text", _set(["topk", 0, "rank"], "a"), "topk[0].rank"),
    ("topk-rank-fraction", _set(["topk", 0, "rank"], 0.5), "topk[0].rank"),
    ("topk-rank-past-64-bits", _set(["topk", 0, "rank"], 10**30), "topk[0].rank"),
    ("topk-rank-twice", _set(["topk", 1, "rank"], 0), "topk[1].rank: rank 0 is given to two shots"),
    ("topk-score-text", _set(["topk", 0, "score"], "x"), "topk[0].score"),
    ("topk-score-nan", _set(["topk", 0, "score"], NAN), "topk[0].score: expected a finite number"),
    ("topk-c2w-missing", _set(["topk", 0, "c2w"], KeyError), "topk[0].c2w: missing"),
    ("topk-c2w-3x3", _set(["topk", 0, "c2w"], [[1, 0, 0], [0, 1, 0], [0, 0, 1]]), "topk[0].c2w: expected a 4x4"),
    ("topk-c2w-nan", _set(["topk", 0, "c2w"], [[NAN] * 4] * 4), "topk[0].c2w: pose has non-finite values"),
    ("topk-score-past-float64", _set(["topk", 0, "score"], 10**400), "topk[0].score: expected a finite number"),
    ("topk-c2w-past-float64", _set(["topk", 0, "c2w", 0, 3], 10**400), "topk[0].c2w: pose has non-finite values"),
    ("train-c2w-row-past-float64", _set(["train_c2w", 2, 3, 3], -(10**400)), "train_c2w[2]: pose has non-finite"),
    ("topk-c2w-zero", _set(["topk", 0, "c2w"], [[0] * 4] * 4), "topk[0].c2w: pose is not rigid"),
    ("topk-c2w-far", _set(["topk", 0, "c2w"], _pose(1e300)), "topk[0].c2w: camera origin has a coordinate of 1e+300"),
    ("topk-image-number", _set(["topk", 0, "image"], 5), "topk[0].image: expected text"),
    ("topk-image-absolute", _set(["topk", 0, "image"], "/etc/hostname"), "topk[0].image: expected a file name inside"),
    ("topk-image-outside", _set(["topk", 0, "image"], "../../x.png"), "topk[0].image: expected a file name inside"),
    ("topk-image-a-folder", _set(["topk", 0, "image"], "topk"), "topk[0].image"),
    ("train-c2w-text", _set(["train_c2w"], "abc"), "train_c2w: expected a list"),
    ("train-c2w-flat", _set(["train_c2w"], [[1, 2, 3]]), "train_c2w[0]: expected a 4x4"),
    ("train-c2w-nan", _set(["train_c2w", 1], [[NAN] * 4] * 4), "train_c2w[1]: pose has non-finite values"),
    ("generated-c2w-booleans", _set(["generated_c2w", 0], [[True] * 4] * 4), "generated_c2w[0]: expected a 4x4"),
    ("scores-train-text", _set(["scores_train"], "abc"), "scores_train: expected a list"),
    ("scores-train-short", _set(["scores_train"], [0.1]), "scores_train: 1 scores for 3 views"),
    ("scores-generated-nan", _set(["scores_generated", 1], NAN), "scores_generated[1]: expected a finite number"),
    ("scores-generated-boolean", _set(["scores_generated", 0], True), "scores_generated[0]"),
    ("scores-generated-long", _set(["scores_generated"], [0.1] * 9), "scores_generated: 9 scores for 4 views"),
    ("generated-epochs-text", _set(["generated_epochs"], "ab"), "generated_epochs: expected a list"),
    ("generated-slots-fraction", _set(["generated_slots", 0], 1.5), "generated_slots[0]"),
    ("generated-slots-short", _set(["generated_slots"], [3]), "generated_slots: 1 entries for 4 views"),
    ("direction-unknown", _set(["direction"], "sideways"), "direction: expected one of 'max', 'min'"),
    ("criterion-list", _set(["criterion"], [1]), "criterion: expected text"),
    ("source-number", _set(["source"], 5), "source: expected text"),
    ("resolution-zero", _set(["resolution"], [0, 0]), "resolution: expected [width, height]"),
    ("resolution-nan", _set(["resolution"], [NAN, 16]), "resolution: expected [width, height]"),
    ("resolution-number", _set(["resolution"], 16), "resolution: expected a list"),
    ("source-info-list", _set(["source_info"], [1]), "source_info: expected a JSON object"),
    ("ngp-scale-text", _set(["source_info", "ngp_scale"], "x"), "source_info.ngp_scale"),
    ("ngp-offset-two", _set(["source_info", "ngp_offset"], [1, 2]), "source_info.ngp_offset"),
    ("ngp-offset-null-axis", _set(["source_info", "ngp_offset"], [0.5, None, 0.5]), "ngp_offset: expected 3 numbers"),
    ("ngp-offset-text", _set(["source_info", "ngp_offset"], "x"), "ngp_offset: expected a finite number"),
    ("archive-list", _set(["archive"], [1]), "archive: expected a JSON object"),
    ("archive-elites-text", _set(["archive", "elites"], "abc"), "archive.elites: expected a list"),
    ("archive-elite-number", _set(["archive", "elites"], [5]), "archive.elites[0]: expected a JSON object"),
    ("archive-cell-missing", _set(["archive", "elites", 0, "cell"], KeyError), "archive.elites[0].cell: missing"),
    ("archive-cell-twice", _set(["archive", "elites", 1, "cell"], 0), "archive.elites[1].cell: cell 0 holds two"),
    ("archive-azimuth-text", _set(["archive", "elites", 0, "azimuth"], "x"), "archive.elites[0].azimuth"),
    ("archive-score-text", _set(["archive", "elites", 0, "score"], "x"), "archive.elites[0].score"),
]


@pytest.mark.parametrize("edit,says", [c[1:] for c in RESULTS_CASES], ids=[c[0] for c in RESULTS_CASES])
def test_every_results_field_the_viewer_reads_is_refused_by_its_key(tmp_path, capsys, edit, says):
    results = _results()
    edit(results)
    folder = _explore_folder(tmp_path / "run", results)
    _refused(capsys, tmp_path, folder, str(folder / "results.json"), says)


def test_an_older_output_s_paper_topk_is_checked_by_its_key(tmp_path, capsys):
    results = _results()
    del results["generated_c2w"]
    results["paper_topk"] = [{"rank": "x", "c2w": 5}]
    _refused(capsys, tmp_path, _explore_folder(tmp_path / "run", results), "paper_topk[0].rank")


def test_the_undamaged_folder_is_drawn(tmp_path, capsys):
    """The folder the cases edit is itself drawn: every camera, no warning."""
    folder = _explore_folder(tmp_path / "run")
    page = tmp_path / "page.html"
    assert main(["view", str(folder), "--quiet", "--export", str(page)]) == 0
    captured = capsys.readouterr()
    assert "warning" not in captured.err and "11 cameras)" in captured.out  # 3 + 4 views, 2 elites, 2 shots
    assert page.stat().st_size > 0


def _image(kind):
    def put(path):
        path.unlink()
        if kind == "folder":
            path.mkdir()
        elif kind == "fifo":
            os.mkfifo(path)
        elif kind == "loop":
            path.symlink_to(path.name)
        elif kind == "empty":
            path.write_bytes(b"")
        elif kind == "5000x8":
            Image.fromarray(np.zeros((8, 5000, 3), np.uint8)).save(path)
        elif kind == "20000x1":
            Image.fromarray(np.zeros((1, 20000, 3), np.uint8)).save(path, format="PNG")
        elif kind == "truncated":
            Image.fromarray(np.random.default_rng(0).integers(0, 255, (64, 64, 3), np.uint8)).save(path, format="PNG")
            path.write_bytes(path.read_bytes()[:400])
        elif kind == "hdr":
            Image.fromarray(np.full((16, 16), 300.0, np.float32)).save(path, format="TIFF")

    return put


@pytest.mark.parametrize(
    "kind,says",
    [
        ("folder", "a directory, where an image file was expected"),
        ("fifo", "a FIFO, socket or device"),
        ("loop", "a symbolic link loop"),
        ("empty", "not a readable image"),
        ("5000x8", "the image is 5000x8"),
        ("20000x1", "the image is 20000x1"),
        ("truncated", "not a readable image"),
        ("hdr", "outside the [0, 1] waldo reads"),
    ],
)
def test_a_top_k_image_that_cannot_be_shown_is_named(tmp_path, capsys, kind, says):
    folder = _explore_folder(tmp_path / "run")
    _image(kind)(folder / "topk" / "00.png")
    _refused(capsys, tmp_path, folder, str(folder / "topk" / "00.png"), says)


def test_a_missing_top_k_image_is_a_warning(tmp_path, capsys):
    folder = _explore_folder(tmp_path / "run")
    (folder / "topk" / "01.png").unlink()
    assert main(["view", str(folder), "--quiet", "--export", str(tmp_path / "page.html")]) == 0
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("waldo: warning: ") and "topk[1].image" in err[0], err


@pytest.mark.parametrize(
    "edit,says",
    [
        (lambda p: p.update(fl_y=0), "fl_y: expected a positive number, got 0"),
        (lambda p: p.update(fl_y=NAN), "fl_y: expected a finite number, got nan"),
        (lambda p: p.update(h="x"), "h: expected a finite number, got 'x'"),
        (lambda p: (p.pop("fl_y"), p.pop("fl_x"), p.update(camera_angle_x=4.0)), "camera_angle_x: expected an angle"),
    ],
    ids=["fl_y-zero", "fl_y-nan", "h-text", "angle-past-pi"],
)
def test_a_damaged_poses_json_is_refused_by_its_key(tmp_path, capsys, edit, says):
    """poses.json gives the frustums' field of view: a focal length of 0 had been a ZeroDivisionError, a NaN
    one a page of frustums with a NaN field of view."""
    poses = _poses_json()
    edit(poses)
    folder = _explore_folder(tmp_path / "run", poses=poses)
    _refused(capsys, tmp_path, folder, str(folder / "poses.json"), says)


def test_waldos_own_edge_outputs_are_shown(tmp_path, capsys):
    """Two folders `waldo explore` itself writes: one whose every view failed its guard (`topk: []`, a
    poses.json of `frames: []` by `io.write_transforms`), and a 4:3 scene's run at `--resolution 8`, whose
    views and shots are 8x6 (`with_max_side` keeps the aspect). Both are drawn, not refused."""
    from waldo_jax.io import write_transforms
    from waldo_jax.types import Intrinsics

    empty = _explore_folder(tmp_path / "empty", results={**_results(), "topk": []})
    write_transforms(empty / "poses.json", np.zeros((0, 4, 4)), Intrinsics.create(16, 16, 14.0), [])
    small = _results()
    small["resolution"] = [8, 6]
    small_folder = _explore_folder(tmp_path / "small", results=small, poses={**_poses_json(), "w": 8, "h": 6})
    for i in range(2):
        Image.fromarray(np.full((6, 8, 3), 90, np.uint8)).save(small_folder / "topk" / f"{i:02d}.png")
    for folder in (empty, small_folder):
        page = tmp_path / f"{folder.name}.html"
        assert main(["view", str(folder), "--quiet", "--export", str(page)]) == 0, capsys.readouterr()
        assert page.stat().st_size > 0


def test_views_past_the_page_s_bound_are_left_out_with_a_warning(tmp_path, capsys, monkeypatch):
    """A results.json of 10^6 views had taken 20 minutes to draw; past MAX_FRUSTUMS the worst views are left
    out (here with the bound lowered to 10: 3 training views, 2 elites and 2 shots leave room for 3 of the 4
    generated views, the unscored one left out), and more cameras than that that are not views are refused."""
    import waldo_jax.viewer.scene as scene

    monkeypatch.setattr(scene, "MAX_FRUSTUMS", 10)
    folder = _explore_folder(tmp_path / "run")
    page = tmp_path / "page.html"
    assert main(["view", str(folder), "--quiet", "--export", str(page)]) == 0
    captured = capsys.readouterr()
    err = captured.err.strip().splitlines()
    assert len(err) == 1 and "4 searched views; waldo view draws the best 3" in err[0], err
    data = json.loads(
        page.read_text().split('<script id="waldo-frustums" type="application/json">')[1].split("</script>")[0]
    )
    assert len(data["frustums"]) == 10 and "/views/0002" not in {f["name"] for f in data["frustums"]}
    page.unlink()
    monkeypatch.setattr(scene, "MAX_FRUSTUMS", 5)
    _refused(capsys, tmp_path, folder, "7 cameras to draw", "at most 5")


def _path_folder(folder, edit=None):
    """A `waldo path` output: results.json (limits, found, video) and poses.json of 4 frames."""
    folder.mkdir()
    results = {
        "source": "no_such_source_here",
        "criterion": "colorfulness",
        "direction": "max",
        "method": "egps",
        "limits": {},
        "found": {"frame_scores": [0.1, 0.2, 0.3, 0.4]},
        "video": {"frame_size": [16, 16], "fps": 12.0},
    }
    if edit is not None:
        edit(results)
    (folder / "results.json").write_text(json.dumps(results))
    poses = dict(_poses_json(), frames=[{"transform_matrix": _pose(i)} for i in range(4)])
    (folder / "poses.json").write_text(json.dumps(poses))
    return folder


@pytest.mark.parametrize(
    "edit,says",
    [
        (_set(["video", "fps"], "x"), "video.fps"),
        (_set(["video", "fps"], NAN), "video.fps"),
        (_set(["video", "fps"], 0), "video.fps: expected a positive number"),
        (_set(["video", "frame_size"], ["a", 1]), "video.frame_size"),
        (_set(["video"], [1]), "video: expected a JSON object"),
        (_set(["found"], "x"), "found: expected a JSON object"),
        (_set(["found", "frame_scores"], ["x"] * 4), "found.frame_scores[0]"),
        (_set(["found", "frame_scores"], [0.5]), "found.frame_scores: 1 scores for 4 frames"),
        (_set(["direction"], 3), "direction: expected text"),
    ],
    ids=[
        "fps-text",
        "fps-nan",
        "fps-zero",
        "frame-size-text",
        "video-list",
        "found-text",
        "scores-text",
        "scores-short",
        "direction-number",
    ],
)
def test_a_path_output_s_results_are_refused_by_their_key(tmp_path, capsys, edit, says):
    folder = _path_folder(tmp_path / "path", edit)
    _refused(capsys, tmp_path, folder, str(folder / "results.json"), says)


@pytest.mark.parametrize(
    "summary,says",
    [
        ({"room_seed": "abc"}, "room_seed"),
        ({"room_seed": 1.5}, "room_seed"),
        ({"room_seed": 0, "settings": [1]}, "settings: expected a JSON object"),
        ({"room_seed": 0, "settings": {"waldo_scale": "x"}}, "settings.waldo_scale"),
        ({"room_seed": 0, "settings": {"waldo_scale": NAN}}, "settings.waldo_scale"),
        ({"room_seed": 0, "settings": {"stripe_width": -1}}, "settings.stripe_width: expected a positive number"),
        ({"room_seed": 0, "methods": [1]}, "methods: expected a JSON object"),
    ],
    ids=["seed-text", "seed-fraction", "settings-list", "scale-text", "scale-nan", "stripe-negative", "methods-list"],
)
def test_a_demo_summary_is_refused_by_its_key(tmp_path, capsys, summary, says):
    folder = tmp_path / "demo"
    _explore_folder(folder / "egps")
    (folder / "summary.json").write_text(json.dumps(summary))
    _refused(capsys, tmp_path, folder, str(folder / "summary.json"), says)


def test_export_never_writes_through_a_link_nor_into_a_fifo(tmp_path, capsys):
    """A dangling link at --export had the page written wherever it pointed, without --force; a FIFO with
    --force waited for a reader for ever; a folder is refused with --force too."""
    folder = _explore_folder(tmp_path / "run")
    elsewhere = tmp_path / "elsewhere.html"
    link = tmp_path / "link.html"
    link.symlink_to(elsewhere)
    for argv in ([], ["--force"]):
        status = main(["view", str(folder), "--quiet", "--export", str(link), *argv])
        err = capsys.readouterr().err
        assert not elsewhere.exists(), (argv, status, err)
    assert "exists (--force overwrites it)" in err or status == 0
    fifo = tmp_path / "fifo.html"
    os.mkfifo(fifo)
    (tmp_path / "dir.html").mkdir()
    for target, says in ((fifo, "a FIFO, socket or device"), (tmp_path / "dir.html", "a folder")):
        with within(120):  # a hang ends the test; a loaded CI worker is well inside it
            status = main(["view", str(folder), "--quiet", "--export", str(target), "--force"])
        err = capsys.readouterr().err.strip().splitlines()
        assert status == 1 and len(err) == 1 and f"--export {target}: {says}" in err[0], err


def test_a_selected_shot_s_grey_or_16_bit_image_is_shown_as_rgb(tmp_path, monkeypatch):
    """A click on a shot showed its image as `imread(...)[..., :3]`: a grey image's first three columns, a
    16-bit one's raw values. It is read as every image is (RGB, 8-bit), its whole width."""
    from waldo_jax.viewer import load_view_scene
    from waldo_jax.viewer.server import serve

    folder = _explore_folder(tmp_path / "run")
    grey = np.tile(np.linspace(0, 65535, 16, dtype=np.uint16), (16, 1))
    Image.fromarray(grey).save(folder / "topk" / "00.png")
    viewer = serve(load_view_scene(str(folder)), port=0)
    try:
        shown = []
        monkeypatch.setattr(viewer.server.gui, "add_image", lambda image, **kw: shown.append(np.asarray(image)))
        viewer.select("/topk/00")
        assert len(shown) == 1 and shown[0].shape == (16, 16, 3) and shown[0].dtype == np.uint8
        assert shown[0][0, -1, 0] == 255 and shown[0][0, 0, 0] == 0
    finally:
        viewer.stop()


def test_an_export_the_disk_refuses_is_said_in_the_panel(tmp_path, monkeypatch):
    """ "Export this path" on a full disk (or a folder made read-only since) raised an OSError in viser's
    callback thread: a traceback in the terminal and nothing in the browser. The panel says it."""
    import waldo_jax.viewer.server as server
    from waldo_jax.viewer import load_view_scene

    def full(*args, **kwargs):
        raise OSError(28, "No space left on device", str(tmp_path / "run" / "viewer_path_01"))

    monkeypatch.setattr(server, "export_camera_path", full)
    viewer = server.serve(load_view_scene(str(_explore_folder(tmp_path / "run"))), port=0)
    try:
        viewer._on_export("")
        assert "viewer_path_01: No space left on device" in viewer.export_panel.content
    finally:
        viewer.stop()


def test_a_fifo_where_a_json_file_is_read_is_said_or_passed_by(tmp_path, capsys):
    """A FIFO named summary.json beside an explore output (the viewer asks its parent whether it is a demo)
    blocked the read for ever; one named results.json was taken for a folder without results."""
    folder = _explore_folder(tmp_path / "demo" / "egps")
    os.mkfifo(tmp_path / "demo" / "summary.json")
    with within(120):  # a hang ends the test; a loaded CI worker is well inside it
        assert main(["view", str(folder), "--quiet", "--export", str(tmp_path / "page.html")]) == 0
        capsys.readouterr()
        (folder / "results.json").unlink()
        os.mkfifo(folder / "results.json")
        _refused(capsys, tmp_path / "demo", folder, "results.json: a FIFO, socket or device")


@pytest.mark.parametrize("kind", ["folder", "fifo"])
def test_score_says_a_poses_file_that_is_no_file_before_loading_the_source(tmp_path, capsys, monkeypatch, kind):
    """`waldo score --source S --poses P`: a folder or a FIFO at P was found only after S had loaded (a NeRF
    run or a large splat scene: seconds to minutes)."""
    import waldo_jax.pipeline as pipeline

    def loaded(*args, **kwargs):
        raise AssertionError("the source was loaded before --poses was checked")

    monkeypatch.setattr(pipeline, "load_source", loaded)
    poses = tmp_path / "poses.json"
    poses.mkdir() if kind == "folder" else os.mkfifo(poses)
    status = main(["score", "--criterion", "colorfulness", "--source", "procedural:0", "--poses", str(poses)])
    err = capsys.readouterr().err.strip().splitlines()
    assert status == 1 and len(err) == 1 and str(poses) in err[0] and "where a poses file was expected" in err[0]
