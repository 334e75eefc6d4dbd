"""A `ViewScene` in the browser, on viser (the viewer nerfstudio and gsplat use): `Viewer`, `serve`, `export_html`.

The scene graph: `/scene/splats` (Gaussian splats) or `/scene/points` (a point cloud), one camera frustum per
`Frustum` under `/train`, `/views`, `/topk` and `/path`, coloured by score (viridis, the best yellow; grey when
unscored), the top-k larger and orange, a camera path's line `/path/line`. Clicking a frustum (`Viewer.select`)
moves the client's camera onto it and shows its rank, score and, for the top-k, its image in the panel; a camera
path has a frame slider and a play button (`Viewer.show_frame`, `Viewer.play_path`); "Render this view" and
"Score this view" render and score the browser's camera (`waldo_jax.viewer.live`). viser is imported here
only, so `import waldo_jax` does not need it (the `view` extra installs it).

viser's frustums and client cameras follow OpenCV (x right, y down, z forward); our poses are OpenGL (y up,
z backwards): R_cv = R_gl diag(1, -1, -1).
"""

from __future__ import annotations

import contextlib
import io
import math
import time
from pathlib import Path
from typing import Dict, List, Optional, Tuple

import numpy as np

from waldo_jax.errors import WaldoError
from waldo_jax.viewer.live import LiveView, opengl_c2w
from waldo_jax.viewer.scene import Frustum, ViewerError, ViewScene

__all__ = ["Viewer", "export_html", "import_viser", "serve"]

TOPK_COLOR = (255, 120, 0)
UNSCORED_COLOR = (150, 150, 150)
PATH_COLOR = (220, 40, 40)
ELITE_COLOR = (150, 60, 200)
FRUSTUM_SHARE = 0.02  # a frustum's depth over the scene's extent
TOPK_SCALE = 1.8  # the top-k's frustums over the others'
ELITE_SCALE = 1.3  # an archive elite's frustum over the view it holds (drawn around it)
_OPENGL_TO_OPENCV = np.diag([1.0, -1.0, -1.0])


@contextlib.contextmanager
def _quiet(silent: bool):
    """Silences stdout inside (viser's rich prints) when `silent`."""
    if not silent:
        yield
        return
    with contextlib.redirect_stdout(io.StringIO()):
        yield


def import_viser():
    """The viser module, or a `ViewerError` saying how to install it."""
    try:
        import viser
    except ImportError:
        raise ViewerError("waldo view needs viser: pip install 'waldo_jax[view]' (or pip install viser)") from None
    return viser


def opencv_pose(c2w: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
    """(wxyz [4], position [3]) of an OpenGL camera-to-world [4, 4] in viser's OpenCV camera convention."""
    import viser.transforms as tf

    rotation = np.asarray(c2w, np.float64)[:3, :3] @ _OPENGL_TO_OPENCV
    return tf.SO3.from_matrix(rotation).wxyz, np.asarray(c2w, np.float64)[:3, 3]


def score_colors(frustums: Tuple[Frustum, ...], direction: str) -> List[Tuple[int, int, int]]:
    """An RGB colour per frustum: viridis over the finite scores (the best yellow), grey unscored, orange top-k."""
    from matplotlib import colormaps

    scores = np.array([np.nan if f.score is None else f.score for f in frustums], np.float64)
    finite = np.isfinite(scores)
    colors: List[Tuple[int, int, int]] = []
    low, high = (float(np.min(scores[finite])), float(np.max(scores[finite]))) if finite.any() else (0.0, 1.0)
    viridis = colormaps["viridis"]
    for frustum, score in zip(frustums, scores):
        if frustum.kind == "topk":
            colors.append(TOPK_COLOR)
        elif frustum.kind == "elite":
            colors.append(ELITE_COLOR)
        elif not math.isfinite(score):
            colors.append(UNSCORED_COLOR)
        else:
            t = (score - low) / (high - low) if high > low else 1.0
            t = 1.0 - t if direction == "min" else t
            rgba = viridis(float(t))
            colors.append(tuple(int(round(255 * c)) for c in rgba[:3]))
    return colors


def describe(frustum: Frustum, scene: ViewScene, scored: int) -> str:
    """The panel's Markdown for a selected frustum: what it is, its score and rank, its position."""
    lines = [f"**{frustum.label}**", ""]
    if frustum.score is not None:
        lines.append(
            f"score ({scene.criterion or 'criterion'}, {scene.direction or 'max'} is better): **{frustum.score:.6g}**"
        )
    else:
        lines.append("score: none (not scored, or its render failed)")
    if frustum.rank is not None:
        lines.append(f"rank **{frustum.rank}** of {scored} scored views")
    if frustum.topk_rank is not None:
        lines.append(f"top-k different shot **#{frustum.topk_rank}**")
    x, y, z = frustum.c2w[:3, 3]
    lines.append(f"position ({x:.3f}, {y:.3f}, {z:.3f}); node `{frustum.name}`")
    return "  \n".join(lines)


class Viewer:
    """A `ViewScene` on a viser server: the scene, the frustums and the panel.

    Attributes:
      server: the `viser.ViserServer`. scene: the `ViewScene`. handles: frustum node name -> its viser handle.
      panel: the GUI Markdown that `select` writes. selected: the last selected `Frustum` (None at first).
      live: the `LiveView` behind "Render this view" and "Score this view"; live_panel its GUI Markdown (for a
        scene with a SOURCE) and live_image the last image rendered there (None before).
      url: the address to open.
    """

    def __init__(self, scene: ViewScene, host: str = "127.0.0.1", port: int = 8080, verbose: bool = False):
        viser = import_viser()
        self.scene = scene
        with _quiet(not verbose):  # viser prints its own address box; `waldo view` prints one line
            self.server = viser.ViserServer(host=host, port=port, label="waldo view", verbose=verbose)
        self.handles: Dict[str, object] = {}
        self.frustums: Dict[str, Frustum] = {f.name: f for f in scene.frustums}
        self.selected: Optional[Frustum] = None
        self._scored = sum(1 for f in scene.frustums if f.rank is not None and f.kind != "topk")
        self._image = None
        self.live_image = None
        self.live = LiveView(scene.source, scene.criterion, scene.resolution, scene.scores, scene.direction or "max")
        self._build()

    @property
    def url(self) -> str:
        host = self.server.get_host()
        shown = "127.0.0.1" if host in ("0.0.0.0", "") else host
        return f"http://{shown}:{self.server.get_port()}"

    def _build(self) -> None:
        scene, api = self.scene, self.server.scene
        api.set_up_direction(self._up())
        self._frame_initial_camera()
        if scene.splats is not None:
            s = scene.splats
            api.add_gaussian_splats("/scene/splats", s.centers, s.covariances, s.rgbs, s.opacities)
        if scene.points is not None:
            xyz, rgb = scene.points
            api.add_point_cloud("/scene/points", xyz, rgb, point_size=0.01 * scene.extent() ** 0.5)
        depth = FRUSTUM_SHARE * scene.extent()
        colors = score_colors(scene.frustums, scene.direction)
        for frustum, color in zip(scene.frustums, colors):
            wxyz, position = opencv_pose(frustum.c2w)
            big = frustum.kind == "topk"
            handle = api.add_camera_frustum(
                frustum.name,
                fov=scene.fov_y,
                aspect=scene.aspect,
                scale=depth * (TOPK_SCALE if big else ELITE_SCALE if frustum.kind == "elite" else 1.0),
                thickness=depth * (0.04 if big else 0.02),
                color=color,
                wxyz=wxyz,
                position=position,
            )
            handle.on_click(lambda event, name=frustum.name: self.select(name, [event.client]))
            self.handles[frustum.name] = handle
            if big:
                api.add_label(f"{frustum.name}/label", f"#{frustum.topk_rank}")
        gui = self.server.gui
        gui.add_markdown(f"**waldo view**: {scene.title}")
        counts = {k: sum(1 for f in scene.frustums if f.kind == k) for k in ("train", "view", "topk", "elite", "path")}
        gui.add_markdown(
            f"{counts['train']} training views, {counts['view']} searched views, {counts['topk']} top-k shots "
            f"(orange), {counts['elite']} archive elites (purple, under /archive); colour: score, yellow best. "
            "Click a camera."
        )
        for note in scene.notes:
            gui.add_markdown(f"*{note}*")
        self.panel = gui.add_markdown("*no camera selected*")
        best = next((f for f in scene.frustums if f.topk_rank == 1), None)
        if best is not None:
            button = gui.add_button("Go to the best shot")
            button.on_click(lambda event, name=best.name: self.select(name, [event.client]))
        self._add_live_controls()
        self._add_path_controls()

    def _add_path_controls(self) -> None:
        """A camera path (a `waldo path` output): its line, a frame slider that moves the cameras along it and
        a button that plays it at its frame rate."""
        path = self.scene.camera_path
        self.frame_slider = None
        if path is None or not len(path):
            return
        self.server.scene.add_spline_catmull_rom(
            "/path/line",
            points=np.asarray(path[:, :3, 3], np.float64),
            color=PATH_COLOR,
            thickness=3.0,
            thickness_units="screen",
        )
        gui = self.server.gui
        gui.add_markdown(f"camera path: {len(path)} frames at {self.scene.path_fps:g} fps")
        self.frame_slider = gui.add_slider("path frame", min=0, max=max(len(path) - 1, 1), step=1, initial_value=0)
        self.frame_slider.on_update(
            lambda event: self.show_frame(int(self.frame_slider.value), [event.client] if event.client else None)
        )
        gui.add_button("Play the path").on_click(lambda event: self.play_path([event.client]))

    def show_frame(self, index: int, clients=None) -> Frustum:
        """Shows frame `index` of the camera path in the panel and moves `clients`' cameras onto it (default:
        every connected client)."""
        clients = list(self.server.get_clients().values()) if clients is None else clients
        return self.select(f"/path/{int(index):04d}", clients)

    def play_path(self, clients=None) -> None:
        """Moves the cameras along the whole path at its frame rate (in a background thread)."""
        import threading

        def run():
            for index in range(len(self.scene.camera_path)):
                self.show_frame(index, clients)
                time.sleep(1.0 / max(self.scene.path_fps, 1e-3))

        threading.Thread(target=run, daemon=True).start()

    def _add_live_controls(self) -> None:
        """Adds the buttons "Render this view" (the run's renderer at the browser's camera) and, for an explore
        output, "Score this view" (its criterion, and the rank the score would have had)."""
        gui = self.server.gui
        self.live_panel = gui.add_markdown("")
        if not self.scene.source:
            return
        gui.add_button("Render this view").on_click(lambda event: self._on_live(event.client, score=False))
        if self.scene.criterion:
            gui.add_button("Score this view").on_click(lambda event: self._on_live(event.client, score=True))

    def _on_live(self, client, score: bool) -> None:
        c2w = opengl_c2w(client.camera.wxyz, client.camera.position)
        try:
            self.render_view(c2w) if not score else self.score_view(c2w)
        except WaldoError as e:  # shown in the panel: a viewer keeps serving
            self.live_panel.content = f"*{e}*"

    def render_view(self, c2w: np.ndarray) -> np.ndarray:
        """Renders OpenGL c2w [4, 4] with the scene's SOURCE (`LiveView`) and shows the image in the panel."""
        self.live_panel.content = "*rendering (the first render loads the source and compiles) ...*"
        image = self.live.render(c2w)
        if self.live_image is not None:
            self.live_image.remove()
        self.live_image = self.server.gui.add_image(image, label="this view")
        self.live_panel.content = f"**this view**, rendered at {image.shape[1]}x{image.shape[0]}"
        return image

    def score_view(self, c2w: np.ndarray) -> Tuple[float, Optional[int]]:
        """Scores OpenGL c2w [4, 4] with the run's criterion and shows the score and its rank in the panel."""
        self.live_panel.content = "*scoring (the first score loads the source and the criterion) ...*"
        value, rank = self.live.score(c2w)
        where = f"rank {rank} of {len(self.live.scores) + 1}" if rank is not None else "no finite score"
        shown = f"{self.scene.criterion} {value:.4g}"
        self.live_panel.content = f"**this view**: {shown} ({where} among the search's views)"
        return value, rank

    def _frame_initial_camera(self) -> None:
        """A new client looks at the scene's centre from behind the best shot (else the first camera), pulled back;
        at a point cloud (the room) from above."""
        scene = self.scene
        if scene.splats is not None:
            target = np.median(scene.splats.centers, axis=0)
        elif scene.points is not None:
            target = np.median(scene.points[0], axis=0)
        elif scene.frustums:
            target = np.mean([f.c2w[:3, 3] for f in scene.frustums], axis=0)
        else:
            return
        eye_from = next((f for f in scene.frustums if f.topk_rank == 1), scene.frustums[0] if scene.frustums else None)
        eye = eye_from.c2w[:3, 3] if eye_from is not None else target + np.array([0.0, 0.0, scene.extent()])
        offset = eye - target
        if float(np.linalg.norm(offset)) < 1e-6:
            offset = np.array([0.0, 0.0, scene.extent()])
        position = target + 2.5 * offset
        if scene.points is not None:  # a room seen from outside is its walls: look down into it
            position = target + 0.4 * offset + 1.2 * scene.extent() * self._up()
        camera = self.server.initial_camera
        camera.look_at = target
        camera.position = position
        camera.up = self._up()
        camera.fov = scene.fov_y

    def _up(self) -> np.ndarray:
        """The cameras' mean up (OpenGL column 1), else +y."""
        if not self.scene.frustums:
            return np.array([0.0, 1.0, 0.0])
        up = np.mean([f.c2w[:3, 1] for f in self.scene.frustums], axis=0)
        norm = float(np.linalg.norm(up))
        return up / norm if norm > 1e-6 else np.array([0.0, 1.0, 0.0])

    def select(self, name: str, clients=()) -> Frustum:
        """Shows frustum `name` in the panel (rank, score, image) and moves each of `clients`' cameras onto it.

        This is the click handler of every frustum (there `clients` is the client that clicked).
        """
        frustum = self.frustums[name]
        self.selected = frustum
        self.panel.content = describe(frustum, self.scene, self._scored)
        if self._image is not None:
            self._image.remove()
            self._image = None
        if frustum.image is not None:
            import imageio.v3 as iio

            self._image = self.server.gui.add_image(
                np.asarray(iio.imread(frustum.image))[..., :3], label=frustum.image.name
            )
        wxyz, position = opencv_pose(frustum.c2w)
        forward = -np.asarray(frustum.c2w, np.float64)[:3, 2]
        for client in clients:
            with client.atomic():
                client.camera.fov = self.scene.fov_y
                client.camera.position = position
                client.camera.look_at = position + forward * FRUSTUM_SHARE * self.scene.extent() * 4
                client.camera.up_direction = np.asarray(frustum.c2w, np.float64)[:3, 1]
        return frustum

    def frustum_handles(self) -> List[object]:
        """The viser camera-frustum handles in the server's scene graph (what a browser draws)."""
        import viser

        nodes = self.server.scene._handle_from_node_name  # viser keeps no public list of nodes
        return [h for h in nodes.values() if isinstance(h, viser.CameraFrustumHandle)]

    def html(self) -> str:
        """A self-contained HTML page of the current scene (viser's client with the scene embedded)."""
        return self.server.scene.as_html()

    def stop(self) -> None:
        """Stops serving (the port is free again)."""
        with _quiet(True):
            self.server.stop()


def serve(scene: ViewScene, host: str = "127.0.0.1", port: int = 8080) -> Viewer:
    """Starts a `Viewer` of `scene` (returns once it serves; `Viewer.url` is its address)."""
    return Viewer(scene, host=host, port=port)


def export_html(scene: ViewScene, path: Path) -> Tuple[int, float]:
    """Writes a self-contained HTML snapshot of `scene` to `path` (opens without a server).

    viser's `scene.as_html()` embeds its web client and the serialized scene; a JSON block
    `<script id="waldo-frustums" type="application/json">` adds every frustum's pose, score and rank for readers
    of the file. The server it builds the scene on listens on an ephemeral 127.0.0.1 port and is stopped before
    returning.

    Returns:
      (bytes written, seconds taken).
    """
    import json

    start = time.perf_counter()
    viewer = Viewer(scene, host="127.0.0.1", port=0)
    try:
        page = viewer.html()
    finally:
        viewer.stop()
    data = [
        {
            "name": f.name,
            "kind": f.kind,
            "label": f.label,
            "score": f.score,
            "rank": f.rank,
            "topk_rank": f.topk_rank,
            "c2w": np.round(f.c2w, 6).tolist(),
        }
        for f in scene.frustums
    ]
    block = json.dumps({"title": scene.title, "criterion": scene.criterion, "frustums": data})
    block = block.replace("</", "<\\/")  # never closes the script element early
    page = page.replace("</head>", f'<script id="waldo-frustums" type="application/json">{block}</script></head>', 1)
    path = Path(path)
    path.write_text(page, encoding="utf-8")
    return len(page.encode("utf-8")), time.perf_counter() - start
