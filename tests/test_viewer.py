"""`waldo view` and `waldo_jax.view` (issue 44): the viser server and its page, the scene graph of a donut explore
output, the click handler, bad input, the --export snapshot, and (marked `browser`) headless Chromium drawing it."""

import base64
import contextlib
import html.parser
import json
import shutil
import subprocess
import sys
import time
import urllib.request
from collections import Counter

import numpy as np
import pytest

from conftest import built_once
from test_splat_cli import TINY, require_donut
from waldo_jax.cli import main

viser = pytest.importorskip("viser", reason="the viewer needs viser (pip install 'waldo_jax[view]')")

from waldo_jax.viewer import load_view_scene  # noqa: E402
from waldo_jax.viewer.server import serve  # noqa: E402

SERVE_SECONDS = 10.0  # the target on the 2-core CPU


@pytest.fixture(scope="module")
def donut_explore(tmp_path_factory):
    """A tiny EGPS explore of the donut splats (built once per session): (folder, results.json)."""
    donut = require_donut()

    def build(folder):
        argv = ["explore", str(donut), "--criterion", "colorfulness", "--method", "egps", "--out", str(folder / "run")]
        assert main([*argv, *TINY]) == 0

    out = built_once(tmp_path_factory, "viewer_donut_explore", build) / "run"
    return out, json.loads((out / "results.json").read_text())


@pytest.fixture(scope="module")
def donut_viewer(donut_explore):
    out, _ = donut_explore
    start = time.perf_counter()
    viewer = serve(load_view_scene(str(out)), port=0)
    seconds = time.perf_counter() - start
    yield viewer, seconds
    viewer.stop()


def _expected_cameras(results):
    """Training views, generated views, the top-k shots and the archive's elites (one per filled cell)."""
    return results["n_train"] + results["n_generated"] + len(results["topk"]) + results["archive"]["cells_filled"]


def test_import_waldo_jax_does_not_need_viser():
    code = "import sys, waldo_jax, waldo_jax.viewer; assert 'viser' not in sys.modules; print('ok')"
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0 and done.stdout.strip() == "ok", done.stderr


def test_serves_its_page_over_http_in_time(donut_viewer):
    viewer, seconds = donut_viewer
    assert seconds <= SERVE_SECONDS, f"served in {seconds:.1f} s (target {SERVE_SECONDS} s)"
    assert viewer.url.startswith("http://127.0.0.1:") and viewer.server.get_port() > 0
    with urllib.request.urlopen(viewer.url, timeout=20) as response:
        body = response.read().decode("utf-8", "replace")
        assert response.status == 200
    assert "<html" in body.lower() and "</html>" in body.lower()


def test_scene_graph_holds_a_frustum_per_camera(donut_viewer, donut_explore):
    viewer, _ = donut_viewer
    _, results = donut_explore
    handles = viewer.frustum_handles()
    assert len(handles) == _expected_cameras(results) == len(viewer.scene.frustums)
    names = {h.name for h in handles}
    assert sum(n.startswith("/train/") for n in names) == results["n_train"]
    assert sum(n.startswith("/views/") for n in names) == results["n_generated"]
    assert sum(n.startswith("/topk/") for n in names) == len(results["topk"])
    assert sum(n.startswith("/archive/") for n in names) == results["archive"]["cells_filled"]
    assert viewer.scene.splats is not None and len(viewer.scene.splats.centers) > 1000
    # The frustums sit at the poses of results.json (OpenGL c2w -> viser's OpenCV: same position).
    best = viewer.handles["/topk/00"]
    np.testing.assert_allclose(best.position, np.asarray(results["topk"][0]["c2w"])[:3, 3], atol=1e-5)


class _Camera:
    def __init__(self):
        self.position = np.zeros(3)
        self.look_at = np.ones(3)
        self.up_direction = np.array([0.0, 1.0, 0.0])
        self.fov = 1.0


class _Client:
    """What `Viewer.select` uses of a viser client: its camera and `atomic()`."""

    def __init__(self):
        self.camera = _Camera()

    @contextlib.contextmanager
    def atomic(self):
        yield


def test_a_click_moves_the_camera_and_fills_the_panel(donut_viewer, donut_explore):
    viewer, _ = donut_viewer
    _, results = donut_explore
    assert "no camera selected" in viewer.panel.content
    client = _Client()
    viewer.select("/topk/00", [client])
    best = results["topk"][0]
    assert "top-k different shot **#1**" in viewer.panel.content
    assert f"**{best['score']:.6g}**" in viewer.panel.content and "rank **1** of" in viewer.panel.content
    c2w = np.asarray(best["c2w"])
    np.testing.assert_allclose(client.camera.position, c2w[:3, 3], atol=1e-6)
    forward = client.camera.look_at - client.camera.position
    assert float(np.dot(forward / np.linalg.norm(forward), -c2w[:3, 2])) > 0.999  # looks where the view looks
    # A generated view: its own score and rank, no top-k line.
    scores = results["scores_generated"]
    j = int(np.argmin(scores))
    viewer.select(f"/views/{j:04d}", [client])
    assert f"**{scores[j]:.6g}**" in viewer.panel.content and "top-k" not in viewer.panel.content
    np.testing.assert_allclose(client.camera.position, np.asarray(results["generated_c2w"][j])[:3, 3], atol=1e-6)


def test_notebook_view_returns_the_server_and_shows_an_iframe(donut_explore, monkeypatch):
    import IPython
    import IPython.display

    import waldo_jax

    shown = []
    monkeypatch.setattr(IPython, "get_ipython", lambda: object())  # as inside a notebook
    monkeypatch.setattr(IPython.display, "display", shown.append)
    out, results = donut_explore
    viewer = waldo_jax.view(str(out))
    try:
        assert isinstance(viewer.server, viser.ViserServer)
        assert len(viewer.frustum_handles()) == _expected_cameras(results)
        assert len(shown) == 1 and isinstance(shown[0], IPython.display.IFrame) and shown[0].src == viewer.url
    finally:
        viewer.stop()


def _one_error_line(capsys, argv):
    status = main(argv)
    err = capsys.readouterr().err.strip().splitlines()
    assert status == 1 and len(err) == 1 and err[0].startswith("waldo: error: "), (status, err)
    return err[0]


def test_bad_input_is_one_line_and_exit_1(tmp_path, capsys):
    missing = tmp_path / "nowhere"
    assert str(missing) in _one_error_line(capsys, ["view", str(missing), "--quiet"])
    empty = tmp_path / "empty"
    empty.mkdir()
    (empty / "notes.txt").write_text("not a run")
    line = _one_error_line(capsys, ["view", str(empty), "--quiet"])
    assert str(empty) in line and "results.json" in line
    other = tmp_path / "other"
    other.mkdir()
    (other / "results.json").write_text(json.dumps({"psnr": 30}))
    assert "not the results of `waldo explore`" in _one_error_line(capsys, ["view", str(other), "--quiet"])
    line = _one_error_line(capsys, ["view", str(other), "--export", str(tmp_path / "snap.png")])
    assert "--export" in line and not (tmp_path / "snap.png").exists()
    assert "--port" in _one_error_line(capsys, ["view", str(other), "--port", "70000"])


class _Scripts(html.parser.HTMLParser):
    """The text of each <script>, with its attributes."""

    def __init__(self):
        super().__init__()
        self.scripts, self._open = [], None

    def handle_starttag(self, tag, attrs):
        if tag == "script":
            self._open = [dict(attrs), ""]

    def handle_data(self, data):
        if self._open is not None:
            self._open[1] += data

    def handle_endtag(self, tag):
        if tag == "script" and self._open is not None:
            self.scripts.append(tuple(self._open))
            self._open = None


def _embedded_messages(page: str) -> Counter:
    """The message types of the viser scene embedded in an exported page."""
    import msgspec
    import zstandard

    b64 = page.split('window.__VISER_EMBED_DATA__="', 1)[1].split('"', 1)[0]
    raw = base64.b64decode(b64)
    inner = zstandard.ZstdDecompressor().decompress(raw[8:], max_output_size=int.from_bytes(raw[:8], "little"))
    length = int.from_bytes(inner[:8], "little")
    recording = msgspec.msgpack.decode(inner[8 : 8 + length])
    return Counter(message.get("type") for _, message in recording["messages"])


def test_export_writes_a_self_contained_page_with_the_frustums(donut_explore, tmp_path, capsys):
    out, results = donut_explore
    target = tmp_path / "donut.html"
    assert main(["view", str(out), "--export", str(target), "--quiet"]) == 0
    assert "wrote" in capsys.readouterr().out
    page = target.read_text(encoding="utf-8")
    parser = _Scripts()
    parser.feed(page)
    parser.close()
    blocks = [text for attrs, text in parser.scripts if attrs.get("id") == "waldo-frustums"]
    assert len(blocks) == 1
    frustums = json.loads(blocks[0])["frustums"]
    assert len(frustums) == _expected_cameras(results)
    best = next(f for f in frustums if f["topk_rank"] == 1)
    assert best["score"] == results["topk"][0]["score"]
    messages = _embedded_messages(page)
    assert messages["CameraFrustumMessage"] == _expected_cameras(results)
    assert messages["GaussianSplatsMessage"] == 1
    assert not any(attrs.get("src", "").startswith("http") for attrs, _ in parser.scripts)  # nothing fetched
    assert main(["view", str(out), "--export", str(target)]) == 1  # exists: --force overwrites
    assert "--force" in capsys.readouterr().err


def _chromium():
    return shutil.which("chromium") or shutil.which("chromium-browser")


def _screenshot(url: str, path) -> np.ndarray:
    """A headless Chromium screenshot of `url` (software WebGL), as uint8 [H, W, 3]."""
    import imageio.v3 as iio

    command = [
        _chromium(),
        "--headless=new",
        "--no-sandbox",
        "--use-angle=swiftshader",
        "--enable-unsafe-swiftshader",
        "--hide-scrollbars",
        "--window-size=800,600",
        "--virtual-time-budget=15000",
        f"--screenshot={path}",
        url,
    ]
    subprocess.run(command, capture_output=True, timeout=180, check=True)
    return np.asarray(iio.imread(path))[..., :3]


def _drawn_share(image: np.ndarray) -> float:
    """The share of pixels away from the white background, the panel's corner left out."""
    body = image[:, 320:] if image.shape[1] > 400 else image  # the top-left corner holds viser's notices
    return float(np.mean(np.any(np.abs(body.astype(int) - 255) > 24, axis=-1)))


@pytest.mark.browser
@pytest.mark.slow
def test_chromium_draws_the_served_page_and_the_export(donut_viewer, donut_explore, tmp_path):
    if _chromium() is None:
        pytest.skip("no chromium / chromium-browser on PATH (Debian: apt-get install chromium)")
    viewer, _ = donut_viewer
    served = _screenshot(viewer.url, tmp_path / "served.png")
    out, _ = donut_explore
    target = tmp_path / "donut.html"
    assert main(["view", str(out), "--export", str(target), "--quiet"]) == 0
    exported = _screenshot(target.as_uri(), tmp_path / "exported.png")
    for name, image in (("served", served), ("exported", exported)):
        share = _drawn_share(image)
        assert share >= 0.05, f"{name}: only {share:.1%} of the pixels are drawn"
        orange = np.mean(np.all(np.abs(image.astype(int) - (255, 120, 0)) < 60, axis=-1))
        assert orange > 1e-4, f"{name}: no top-k frustum (orange) drawn"


@pytest.mark.browser
@pytest.mark.slow
def test_a_click_through_viser_moves_the_browsers_camera(donut_viewer, tmp_path):
    """A real client (headless Chromium on the served page): `select` (a frustum's click handler) moves the
    camera the browser reports back onto the clicked view."""
    if _chromium() is None:
        pytest.skip("no chromium / chromium-browser on PATH (Debian: apt-get install chromium)")
    viewer, _ = donut_viewer
    known = set(viewer.server.get_clients())
    flags = ["--headless=new", "--no-sandbox", "--use-angle=swiftshader", "--enable-unsafe-swiftshader"]
    flags += [f"--user-data-dir={tmp_path / 'profile'}", "--window-size=800,600", "--remote-debugging-port=0"]
    # --remote-debugging-port keeps headless Chromium running on the page until it is terminated.
    browser = subprocess.Popen([_chromium(), *flags, viewer.url], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        client, deadline = None, time.monotonic() + 120
        while client is None and time.monotonic() < deadline:
            fresh = [c for i, c in viewer.server.get_clients().items() if i not in known]
            client = next((c for c in fresh if c.camera.update_timestamp > 0), None)
            time.sleep(0.2)
        assert client is not None, "the browser never connected and reported its camera"
        target = viewer.frustums["/topk/00"].c2w[:3, 3]
        assert not np.allclose(client.camera.position, target, atol=1e-3)
        clicked = time.time()
        viewer.select("/topk/00", [client])
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:
            if client.camera.update_timestamp > clicked and np.allclose(client.camera.position, target, atol=1e-3):
                break
            time.sleep(0.1)
        np.testing.assert_allclose(client.camera.position, target, atol=1e-3)
        assert client.camera.update_timestamp > clicked  # the browser itself reported the new camera
    finally:
        browser.terminate()
        browser.wait(timeout=30)


def test_a_nerf_run_is_drawn_as_its_opaque_cells_with_its_cameras(tmp_path, monkeypatch):
    """A `waldo train` run: points at the grid cells the field makes at least half opaque (checked against
    the field itself), inside its box, the same on a second load, and its training cameras."""
    import jax
    import jax.numpy as jnp
    from test_bad_input import _write_run, _write_scene

    import waldo_jax.viewer.scene as scene_module
    from waldo_jax.nerf.checkpoint import load_checkpoint
    from waldo_jax.nerf.field import make_field_batch

    _write_scene(tmp_path / "scene")
    _write_run(tmp_path / "run")
    monkeypatch.setattr(scene_module, "NERF_OPACITY", 0.01)  # the untrained field is faint
    view = load_view_scene(str(tmp_path / "run"))
    xyz, rgb = view.points
    assert len(view.frustums) == 8 and all(f.kind == "train" for f in view.frustums)
    assert xyz.shape[1] == 3 and rgb.shape == xyz.shape and 0 < len(xyz) <= scene_module.MAX_ROOM_POINTS
    np.testing.assert_array_equal(xyz, load_view_scene(str(tmp_path / "run")).points[0])  # deterministic
    checkpoint = load_checkpoint(tmp_path / "run")
    low, high = np.asarray(checkpoint.scene.aabb) if checkpoint.scene.aabb is not None else checkpoint.config.field.aabb
    assert np.all(xyz >= low - 1e-5) and np.all(xyz <= high + 1e-5)
    sigma, _ = jax.jit(make_field_batch(checkpoint.config.field))(
        checkpoint.params, jnp.asarray(xyz), jnp.ones_like(jnp.asarray(xyz))
    )
    cell = float(np.min(np.asarray(high) - np.asarray(low))) / scene_module.NERF_GRID
    assert np.all(1.0 - np.exp(-np.asarray(sigma) * cell) >= 0.01 - 1e-6)


def test_a_browser_camera_turns_back_into_the_pose_it_came_from():
    from waldo_jax.viewer.live import opengl_c2w
    from waldo_jax.viewer.server import opencv_pose

    rng = np.random.default_rng(0)
    for _ in range(20):
        q = rng.normal(size=4)
        w, x, y, z = q / np.linalg.norm(q)
        rotation = np.array(
            [
                [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
            ]
        )
        c2w = np.eye(4)
        c2w[:3, :3], c2w[:3, 3] = rotation, rng.normal(size=3)
        np.testing.assert_allclose(opengl_c2w(*opencv_pose(c2w)), c2w, atol=1e-9)


def test_render_this_view_is_the_sources_render(tmp_path):
    """ "Render this view" on a SOURCE: the image in the panel is the source's own render of that pose."""
    import jax.numpy as jnp

    from waldo_jax.pipeline import load_source

    view = load_view_scene("procedural:0")
    viewer = serve(view, port=0)
    try:
        c2w = view.frustums[3].c2w
        image = viewer.render_view(c2w)
        source = load_source("procedural:0", resolution=128)
        expected = np.asarray(source.render(jnp.asarray(c2w[None], jnp.float32)))[0]
        np.testing.assert_allclose(image, np.clip(expected, 0, 1), atol=1e-6)
        assert viewer.live_image is not None and "rendered at" in viewer.live_panel.content
        with pytest.raises(Exception, match="no criterion"):
            viewer.live.score(c2w)  # a SOURCE alone has no criterion: the button is not offered
    finally:
        viewer.stop()


def test_score_this_view_gives_the_searchs_own_score_and_rank(donut_viewer, donut_explore):
    """ "Score this view" at the best shot's pose: the run's criterion gives the score the search gave it,
    ranked first among the search's views."""
    viewer, _ = donut_viewer
    _, results = donut_explore
    best = next(f for f in viewer.scene.frustums if f.topk_rank == 1)
    value, rank = viewer.score_view(best.c2w)
    assert value == pytest.approx(best.score, rel=1e-4, abs=1e-6)
    assert rank is not None and rank <= 2  # ties with itself among the scored views
    assert results["criterion"] in viewer.live_panel.content and "rank" in viewer.live_panel.content


@pytest.mark.filterwarnings("ignore:os.fork:RuntimeWarning")  # imageio-ffmpeg writes the MP4 in a subprocess
def test_a_camera_path_is_drawn_and_its_slider_moves_the_cameras(tmp_path):
    """A `waldo path` output: one frustum per frame (with its frame score), the path's line, and the frame
    slider / play button moving the cameras frame by frame."""
    from test_search_path import CLI_TINY

    out = tmp_path / "path"
    assert main(["path", "procedural:1", "--out", str(out), "--quiet", *CLI_TINY]) == 0
    results = json.loads((out / "results.json").read_text())
    view = load_view_scene(str(out))
    frames = [f for f in view.frustums if f.kind == "path"]
    assert view.camera_path is not None and len(frames) == len(view.camera_path) == 8
    assert [f.score for f in frames] == pytest.approx(results["found"]["frame_scores"])
    viewer = serve(view, port=0)
    try:
        assert viewer.frame_slider is not None and viewer.frame_slider.max == 7
        shown = viewer.show_frame(5, clients=[])
        assert shown.name == "/path/0005" and viewer.selected is shown
        np.testing.assert_allclose(shown.c2w, view.camera_path[5])
        assert "path frame 5" in viewer.panel.content
    finally:
        viewer.stop()


def test_the_archive_elites_are_drawn_at_the_views_they_hold(donut_explore):
    """An explore output's view archive: one purple frustum per filled cell, at the pose of its elite's
    population slot (training views, then generated ones)."""
    out, results = donut_explore
    view = load_view_scene(str(out))
    elites = [f for f in view.frustums if f.kind == "elite"]
    assert len(elites) == results["archive"]["cells_filled"] > 0
    train = np.asarray(results["train_c2w"]).reshape(-1, 4, 4)
    generated = dict(zip(results["generated_slots"], np.asarray(results["generated_c2w"]).reshape(-1, 4, 4)))
    for frustum, elite in zip(elites, results["archive"]["elites"]):
        assert frustum.name == f"/archive/{elite['cell']:03d}"
        slot = elite["slot"]
        np.testing.assert_allclose(frustum.c2w, train[slot] if slot < len(train) else generated[slot], atol=1e-6)
        assert frustum.score == pytest.approx(elite["score"])
