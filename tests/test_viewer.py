"""`waldo view` and `waldo_jax.view` (issue 44): the viser server and its page, the scene graph of a donut explore
output, the click handler, bad input, the --export snapshot, and (marked `browser`) headless Chromium drawing it."""

import base64
import contextlib
import html.parser
import json
import shutil
import signal
import subprocess
import sys
import time
import types
import urllib.request
import warnings
from collections import Counter

import numpy as np
import pytest

from conftest import built_once
from test_splat_cli import TINY, require_donut
from waldo_jax.cli import main

viser = pytest.importorskip("viser", reason="the viewer needs viser (pip install 'waldo_jax[view]')")

from waldo_jax.viewer import load_view_scene  # noqa: E402
from waldo_jax.viewer.server import address_url, serve  # noqa: E402

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


@pytest.mark.slow
def test_import_waldo_jax_does_not_need_viser():
    code = "import sys, waldo_jax, waldo_jax.viewer; assert 'viser' not in sys.modules; print('ok')"
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0 and done.stdout.strip() == "ok", done.stderr


@pytest.mark.slow
def test_the_printed_url_is_one_a_browser_opens_for_every_host_kind():
    """`--host ::1` printed http://::1:8080, which no browser opens; every interface shows as the loopback."""
    assert address_url("::1", 8080) == "http://[::1]:8080"
    assert address_url("::", 8080) == "http://[::1]:8080"
    assert address_url("0.0.0.0", 81) == "http://127.0.0.1:81"
    assert address_url("", 81) == "http://127.0.0.1:81"
    assert address_url("fe80::1%eth0", 9) == "http://[fe80::1%25eth0]:9"
    assert address_url("localhost", 9) == "http://localhost:9"


@pytest.mark.slow  # the donut explore it serves takes 15 s; hand-made folders are served in the fast tier
def test_serves_its_page_over_http_in_time(donut_viewer):
    viewer, seconds = donut_viewer
    assert seconds <= SERVE_SECONDS, f"served in {seconds:.1f} s (target {SERVE_SECONDS} s)"
    assert viewer.url.startswith("http://127.0.0.1:") and viewer.server.get_port() > 0
    with urllib.request.urlopen(viewer.url, timeout=20) as response:
        body = response.read().decode("utf-8", "replace")
        assert response.status == 200
    assert "<html" in body.lower() and "</html>" in body.lower()


@pytest.mark.slow
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


@pytest.mark.slow
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


@pytest.mark.slow
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
    # A host this machine cannot listen on (viser tried port after port for ever), seconds without end, and
    # --seconds beside --export (which serves nothing): each refused before the scene loads.
    for host, says in (("999.1.1.1", "not an address this machine can resolve"), ("192.0.2.1", "cannot listen")):
        assert f"--host {host}: {says}" in _one_error_line(capsys, ["view", str(other), "--host", host])
    assert "--seconds inf" in _one_error_line(capsys, ["view", str(other), "--seconds", "inf"])
    line = _one_error_line(capsys, ["view", str(other), "--seconds", "1", "--export", str(tmp_path / "s.html")])
    assert "give one" in line and not (tmp_path / "s.html").exists()


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
    return Counter(message.get("type") for message in _embedded_scene(page))


def _embedded_scene(page: str) -> list:
    """The messages of the viser scene embedded in an exported page."""
    import msgspec
    import zstandard

    b64 = page.split('window.__VISER_EMBED_DATA__="', 1)[1].split('"', 1)[0]
    raw = base64.b64decode(b64)
    inner = zstandard.ZstdDecompressor().decompress(raw[8:], max_output_size=int.from_bytes(raw[:8], "little"))
    length = int.from_bytes(inner[:8], "little")
    recording = msgspec.msgpack.decode(inner[8 : 8 + length])
    return [message for _, message in recording["messages"]]


@pytest.mark.slow
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
    # The top-k shots' thumbnails: on their frustums in the scene, and in the page's shots panel.
    topk = [m for m in _embedded_scene(page) if m.get("type") == "CameraFrustumMessage" and "/topk/" in m["name"]]
    assert len(topk) == len(results["topk"]) and all(len(m["props"]["_image_data"] or b"") > 100 for m in topk)
    gallery = page.split('<details id="waldo-shots"', 1)[1].split("</details>", 1)[0]
    assert gallery.count('src="data:image/jpeg;base64,') == len(results["topk"])
    assert f"#1 {results['topk'][0]['score']:.4g}" in gallery
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
    # The served page gets its scene over viser's websocket in real time, which chromium's virtual time
    # does not wait for: on a loaded machine a first screenshot can come before the scene (seen once in
    # CI: 0.3 % drawn). Up to three tries; the exported page holds its scene and is taken once.
    for attempt in range(3):
        served = _screenshot(viewer.url, tmp_path / f"served_{attempt}.png")
        if _drawn_share(served) >= 0.05:
            break
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


def _half_occupied_run(folder):
    """A NeRF run folder of an untrained tiny field whose occupancy grid marks only the x > 0 half of its box."""
    import jax

    from test_bad_input import _write_scene

    from waldo_jax.nerf import HashGridConfig, NGPFieldConfig, init_field
    from waldo_jax.nerf.checkpoint import save_checkpoint
    from waldo_jax.nerf.config import TrainConfig
    from waldo_jax.nerf.samplers import make_sampler
    from waldo_jax.scenes import load_scene

    _write_scene(folder / "scene")
    scene = load_scene(folder / "scene")
    field = NGPFieldConfig(
        aabb=tuple(map(tuple, scene.aabb.tolist())),
        hashgrid=HashGridConfig(L=2, T=2**8, F=2, N_min=4, N_max=8),
        density_hidden=(8,),
        color_hidden=(8,),
    )
    config = TrainConfig(field=field, steps=1, sampler="occupancy", occupancy_resolution=8, num_samples=8)
    params = init_field(jax.random.key(0), field)
    grid = make_sampler(config).init(jax.random.key(1), params)
    x_index = np.arange(grid.bitfield.shape[1]) % grid.resolution  # cells run x fastest
    grid = grid.replace(bitfield=np.broadcast_to(x_index >= grid.resolution // 2, grid.bitfield.shape).copy())
    run = folder / "run"
    run.mkdir()
    save_checkpoint(run / "checkpoint.ckpt", params, config, scene, occupancy=grid)
    return run


@pytest.mark.slow
def test_a_nerf_run_is_drawn_as_points_of_its_dense_occupied_cells(tmp_path, monkeypatch):
    """A `waldo train` run: points only in the occupancy grid's occupied cells (here the x > 0 half), each where
    the field makes a cell at least MIN_ALPHA opaque (checked against the field itself), the same points on a
    second load, and its training cameras."""
    import jax.numpy as jnp

    import waldo_jax.viewer.nerf_points as module
    from waldo_jax.nerf.checkpoint import load_checkpoint
    from waldo_jax.nerf.field import make_field_batch
    from waldo_jax.nerf.samplers import make_sampler

    run = _half_occupied_run(tmp_path)
    checkpoint = load_checkpoint(run)
    every, _ = module.nerf_points(checkpoint, count=10**6, min_alpha=0.0)
    low, high = make_sampler(checkpoint.config).view_grid(checkpoint.occupancy).base_aabb
    centre = 0.5 * (low[0] + high[0])
    assert len(every) > 1000 and np.all(every[:, 0] > centre - 1e-6)  # the occupied half only
    field = make_field_batch(checkpoint.config.field)
    sigma = np.asarray(field(checkpoint.params, jnp.asarray(every), jnp.asarray(every))[0])
    cell = float(np.max(high - low)) / module.DENSITY_GRID
    threshold = float(np.median(1.0 - np.exp(-sigma * cell)))  # keeps about half of them
    monkeypatch.setattr(module, "MIN_ALPHA", threshold)
    view = load_view_scene(str(run))
    xyz, rgb = view.points
    assert 0.3 * len(every) < len(xyz) < 0.7 * len(every) and rgb.shape == xyz.shape
    assert np.all((rgb >= 0) & (rgb <= 1)) and len(xyz) <= module.MAX_POINTS
    kept = np.asarray(field(checkpoint.params, jnp.asarray(xyz), jnp.asarray(xyz))[0])
    assert np.all(1.0 - np.exp(-kept * cell) >= threshold - 1e-6)  # every point is that opaque
    np.testing.assert_array_equal(xyz, load_view_scene(str(run)).points[0])  # deterministic
    few, _ = module.nerf_points(checkpoint, count=500, min_alpha=threshold)
    assert len(few) == 500  # bounded
    assert len(view.frustums) == 8 and all(f.kind == "train" for f in view.frustums)
    assert any("points of its density" in note for note in view.notes)


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


@pytest.mark.slow
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


@pytest.mark.slow
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


@pytest.mark.slow
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
        assert shown.name == "/path/0005" and viewer.selected is shown and viewer.frame_slider.value == 5
        np.testing.assert_allclose(shown.c2w, view.camera_path[5])
        assert "path frame 5" in viewer.panel.content
        # One browser drags the slider: every connected browser's camera follows.
        dragging, watching = _Client(), _Client()
        viewer.server.get_clients = lambda: {1: dragging, 2: watching}
        viewer.frame_slider._impl.value = 3  # what the browser's drag sets, then its update event
        for callback in viewer.frame_slider._impl.update_cb:
            callback(types.SimpleNamespace(client=dragging, client_id=1, target=viewer.frame_slider))
        for client in (dragging, watching):
            np.testing.assert_allclose(client.camera.position, view.camera_path[3][:3, 3], atol=1e-6)
        viewer.play_path(fps=200).join(timeout=30)  # the slider follows the play
        assert viewer.frame_slider.value == 7 and viewer.selected.name == "/path/0007"
        np.testing.assert_allclose(watching.camera.position, view.camera_path[7][:3, 3], atol=1e-6)
        written = viewer.export_path()  # "Export this path": the path itself, in `waldo path`'s formats
    finally:
        viewer.stop()
    assert [p.name for p in written] == ["camera_path.json", "instant_ngp_path.json"]
    ours, theirs = (json.loads((folder / "camera_path.json").read_text()) for folder in (written[0].parent, out))
    assert ours["waldo"]["source_world"] == theirs["waldo"]["source_world"] == "procedural:1"  # the run's world
    for key in ("render_width", "render_height", "fps", "seconds"):
        assert ours[key] == theirs[key]
    for name, key in (("camera_path", "camera_to_world"), ("keyframes", "matrix"), ("camera_path", "fov")):
        # The path's own frames (read back from poses.json: equal up to its rounding).
        np.testing.assert_allclose([f[key] for f in ours[name]], [f[key] for f in theirs[name]], atol=1e-6)
    ours, theirs = (json.loads((folder / "instant_ngp_path.json").read_text()) for folder in (written[0].parent, out))
    assert len(ours["path"]) == len(theirs["path"]) and ours["duration_seconds"] == theirs["duration_seconds"]
    for key in ("R", "T", "fov", "timestamp"):
        np.testing.assert_allclose([k[key] for k in ours["path"]], [k[key] for k in theirs["path"]], atol=1e-6)


@pytest.mark.slow
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


def _demo_folder(donut_explore, folder, settings=None):
    """A `waldo demo`-shaped folder: summary.json (room seed 0, `settings`) and two method folders (copies of the
    donut explore; a demo's are explores of its NeRF) without a nerf/ run."""
    out, results = donut_explore
    folder.mkdir()
    for method in ("egps", "grs"):
        shutil.copytree(out, folder / method)
    summary = {"room_seed": 0, "criterion": results["criterion"], "settings": settings or {}}
    summary["methods"] = {"egps": {}, "grs": {}}
    (folder / "summary.json").write_text(json.dumps(summary))
    return folder


@pytest.mark.slow
def test_a_demo_output_shows_every_methods_shots_over_its_room(donut_explore, tmp_path):
    """`waldo view runs/demo-X`: the room as points, the training cameras, each method's top-k under
    /topk/<method> in its own colour and panel folder (hiding one hides its frustums); a method's folder alone
    draws the same room. A demo whose NeRF does not record its room takes it from summary.json for scoring."""
    from waldo_jax.viewer.server import GROUP_COLORS

    _, results = donut_explore
    settings = {"waldo_scale": 1.5, "stripe_width": 0.15}
    demo = _demo_folder(donut_explore, tmp_path / "demo", settings)
    scene = load_view_scene(str(demo))
    k = len(results["topk"])
    names = {f.name for f in scene.frustums}
    assert {f"/topk/{m}/{r:02d}" for m in ("egps", "grs") for r in range(k)} <= names
    assert sum(f.kind == "train" for f in scene.frustums) == results["n_train"]
    assert {f.group for f in scene.frustums if f.kind == "topk"} == {"egps", "grs"}
    assert scene.splats is None and scene.points is not None and len(scene.points[0]) > 1000  # the room
    assert scene.room_metadata == {"seed": 0, **settings} and "egps" in scene.notes[0]
    method = load_view_scene(str(demo / "grs"))
    assert method.splats is None and np.array_equal(method.points[0], scene.points[0])
    assert method.room_metadata == scene.room_metadata and any("waldo demo" in n for n in method.notes)
    viewer = serve(scene, port=0)
    try:
        assert len(viewer.frustum_handles()) == results["n_train"] + 2 * k
        assert tuple(viewer.handles["/topk/egps/00"].color) == GROUP_COLORS[0]
        assert tuple(viewer.handles["/topk/grs/00"].color) == GROUP_COLORS[1]
        viewer.select("/topk/grs/00", [_Client()])
        assert "GRS" in viewer.panel.content and "top-k different shot **#1**" in viewer.panel.content
        viewer.show_group("grs", False)
        assert not viewer.handles["/topk/grs/03"].visible and viewer.handles["/topk/egps/03"].visible
        assert viewer.live.room_metadata == scene.room_metadata
    finally:
        viewer.stop()


def test_a_relative_source_is_found_again_beside_the_output(tmp_path, monkeypatch):
    """results.json names its SOURCE as given where the run started (`runs/demo/nerf`); viewed from elsewhere, the
    viewer finds it relative to the output's parents, or by name beside the output folder."""
    from waldo_jax.viewer.scene import resolve_source

    (tmp_path / "runs" / "demo" / "nerf").mkdir(parents=True)
    out = tmp_path / "runs" / "demo" / "egps"
    out.mkdir()
    monkeypatch.chdir(out)  # not where the run started
    assert resolve_source("runs/demo/nerf", out) == str(tmp_path / "runs" / "demo" / "nerf")
    assert resolve_source("moved/elsewhere/nerf", out) == str(tmp_path / "runs" / "demo" / "nerf")
    assert resolve_source("procedural:3", out) == "procedural:3"
    assert resolve_source("missing/run", out) == "missing/run"  # nothing found: as written (its error says so)


def test_a_guarded_criterion_is_rebuilt_from_its_recorded_name(monkeypatch):
    """ "Score this view" builds the run's criterion from its recorded name: a guarded one's guards come back."""
    from waldo_jax.criteria import build_criterion
    from waldo_jax.errors import WaldoError
    from waldo_jax.viewer.live import LiveView, criterion_spec

    guarded = build_criterion("colorfulness", guards=["opacity:0.9"])
    spec, guards = criterion_spec(guarded.name)
    assert (spec, guards) == ("colorfulness", ["opacity:0.9"])
    assert build_criterion(spec, guards=guards).name == guarded.name
    assert criterion_spec("colorfulness") == ("colorfulness", [])
    with pytest.raises(WaldoError, match="not a guard"):
        criterion_spec("colorfulness|opacity")
    built = []

    def score_function(source, criterion):  # what the viewer scores with, without rendering anything
        built.append(criterion)
        return lambda c2w: np.full(len(c2w), 0.5, np.float32)

    monkeypatch.setattr("waldo_jax.pipeline.experiment.score_function", score_function)
    live = LiveView("procedural:0", guarded.name, scores=(0.9, 0.1), direction="max")
    live._source = types.SimpleNamespace(room=None, train_c2w=None)  # loading the room is not what is tested
    assert live.score(np.eye(4)) == (0.5, 2)
    assert [c.name for c in built] == [guarded.name]


@pytest.mark.slow
def test_export_path_writes_the_top_shots_as_keyframes(donut_explore, tmp_path):
    """ "Export this path" on an explore output: its top-k shots in rank order as keyframes, written by `waldo
    path`'s writers as camera_path.json and instant_ngp_path.json into a new viewer_path_NN (never over an
    earlier one), read back by `waldo render --poses`'s reader, and listed in the panel."""
    from waldo_jax.scenes.camera_paths import read_camera_path
    from waldo_jax.types import Intrinsics
    from waldo_jax.viewer.paths import FRAMES_PER_SHOT

    out, results = donut_explore
    copy = tmp_path / "run"
    shutil.copytree(out, copy)
    (copy / "viewer_path_01").mkdir()  # an earlier export
    (copy / "viewer_path_01" / "camera_path.json").write_text("{}")
    viewer = serve(load_view_scene(str(copy)), port=0)
    try:
        written = viewer.export_path()
        assert written == [
            copy / "viewer_path_02" / "camera_path.json",
            copy / "viewer_path_02" / "instant_ngp_path.json",
        ]
        assert (copy / "viewer_path_01" / "camera_path.json").read_text() == "{}"
        assert all(str(p) in viewer.export_panel.content for p in written)
        assert viewer.export_path()[0].parent.name == "viewer_path_03"
    finally:
        viewer.stop()
    shots = np.stack([np.asarray(t["c2w"]) for t in sorted(results["topk"], key=lambda t: t["rank"])])
    default = Intrinsics.create(8, 8, 8.0, 8.0)
    for path in written:
        frames, intrinsics = read_camera_path(json.loads(path.read_text()), default)
        assert len(frames) == (len(shots) - 1) * FRAMES_PER_SHOT + 1
        np.testing.assert_allclose(frames[::FRAMES_PER_SHOT], shots, atol=1e-5)  # the shots are the keyframes
        assert (intrinsics.width, intrinsics.height) == tuple(results["resolution"])


@pytest.mark.slow  # a `waldo view` process: 7 s
def test_a_malformed_request_is_one_line_and_the_server_serves_on(tmp_path):
    """`waldo view` given a client's junk (bytes that are no HTTP request, a 100 KB header) prints one
    "waldo: view:" line for each, naming what the websockets server refused, not its traceback (14 of them
    and 137 lines for a fuzzer's dozen requests), and serves the page after."""
    import socket

    with socket.socket() as probe:  # a free port for the child
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    err, out = tmp_path / "view.err", tmp_path / "view.out"
    argv = [sys.executable, "-m", "waldo_jax.cli", "view", "procedural:0", "--port", str(port), "--seconds", "60"]
    with open(err, "w") as stream, open(out, "w") as printed:
        child = subprocess.Popen(argv, stdout=printed, stderr=stream)
    try:
        deadline = time.monotonic() + 120
        while "ready in" not in out.read_text():  # its one line: serving
            assert child.poll() is None and time.monotonic() < deadline, err.read_text()
            time.sleep(0.5)
        # The junk before any page: once this websockets server has served one, it logs nothing of later junk
        # (nothing at all, which is as good for the user but leaves nothing to check; seen 2026-12-08).
        for junk in (b"GARBAGE\r\n\r\n", b"GET / HTTP/1.1\r\nX: " + b"b" * 100_000 + b"\r\n\r\n"):
            with socket.create_connection(("127.0.0.1", port), timeout=5) as client:
                client.sendall(junk)
                client.recv(200)
        deadline = time.monotonic() + 20
        while err.read_text().count("opening handshake failed") < 2 and time.monotonic() < deadline:
            time.sleep(0.2)
        with urllib.request.urlopen(f"http://127.0.0.1:{port}/", timeout=10) as page:
            assert page.status == 200
    finally:
        child.send_signal(signal.SIGINT)
        child.wait(timeout=30)
    text = err.read_text()
    lines = [line for line in text.splitlines() if "opening handshake" in line or "Traceback" in line]
    assert "Traceback" not in text, text
    assert len(lines) == 2 and all(line.startswith("waldo: view: opening handshake failed (") for line in lines), text


def test_images_swapped_by_two_clicks_at_once_are_removed_once(monkeypatch):
    """viser runs its callbacks in a thread pool, so two "Render this view" clicks swap the panel's image at
    once: each removed the same old handle, and viser warned "Attempted to remove an already removed
    GuiImageHandle" (as waldo's warning). The swap is now one at a time: each handle is removed once."""
    import threading

    viewer = serve(load_view_scene("procedural:0"), port=0)
    try:
        monkeypatch.setattr(viewer.live, "render", lambda c2w: np.zeros((8, 8, 3), np.float32))
        add_image = viewer.server.gui.add_image
        removed = Counter()

        def slow_handles(*args, **kwargs):  # a wide window between reading the old handle and replacing it
            handle = add_image(*args, **kwargs)
            remove = handle.remove

            def slow_remove():
                removed[id(handle)] += 1
                time.sleep(0.05)
                remove()

            monkeypatch.setattr(handle, "remove", slow_remove)
            return handle

        monkeypatch.setattr(viewer.server.gui, "add_image", slow_handles)
        viewer.render_view(viewer.scene.frustums[0].c2w)
        c2w = [f.c2w for f in viewer.scene.frustums[:8]]
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            threads = [threading.Thread(target=viewer.render_view, args=(pose,)) for pose in c2w]
            for thread in threads:
                thread.start()
            for thread in threads:
                thread.join(timeout=60)
    finally:
        viewer.stop()
    assert not [w for w in caught if "already removed" in str(w.message)]
    assert removed and set(removed.values()) == {1}, removed  # every old image removed once, none twice
