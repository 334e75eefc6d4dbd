"""A `ViewScene` in the browser, on viser (the viewer nerfstudio and gsplat use): `Viewer`, `serve`, `export_html`.

The scene graph: `/scene/splats` (Gaussian splats) or `/scene/points` (a point cloud), one camera frustum per
`Frustum` under `/train`, `/views`, `/topk` and `/path`, coloured by score (viridis, the best yellow; grey when
unscored), the top-k larger, orange (a demo: one colour per method, `/topk/<method>`, a panel folder each) and
showing their image as a thumbnail, a camera path's line `/path/line`. Clicking a frustum (`Viewer.select`)
moves the client's camera onto it and shows its rank, score and, for the top-k, its image in the panel; a camera
path has a frame slider and a play button that move every client's camera (`Viewer.show_frame`,
`Viewer.play_path`); "Render this view" and "Score this view" render and score the browser's camera
(`waldo_jax.viewer.live`); "Export this path" writes the path shown (`waldo_jax.viewer.paths`). viser is
imported here only, so `import waldo_jax` does not need it (the `view` extra installs it).

viser's frustums and client cameras follow OpenCV (x right, y down, z forward); our poses are OpenGL (y up,
z backwards): R_cv = R_gl diag(1, -1, -1).
"""

from __future__ import annotations

import contextlib
import io
import logging
import math
import sys
import threading
import time
from pathlib import Path
from typing import Dict, List, Optional, Tuple

import numpy as np

from waldo_jax.errors import WaldoError, one_line
from waldo_jax.viewer.live import LiveView, opengl_c2w
from waldo_jax.viewer.paths import export_camera_path
from waldo_jax.viewer.scene import Frustum, ViewerError, ViewScene
from waldo_jax.viewer.fields import MIN_SIDE

__all__ = ["Viewer", "address_url", "export_html", "import_viser", "serve"]

TOPK_COLOR = (255, 120, 0)
# A demo's methods' top-k, in the order of its method folders (the first orange, as a lone explore's).
GROUP_COLORS = ((255, 120, 0), (0, 150, 255), (230, 0, 130), (0, 170, 70), (120, 80, 40), (0, 0, 0))
UNSCORED_COLOR = (150, 150, 150)
PATH_COLOR = (220, 40, 40)
ELITE_COLOR = (150, 60, 200)
FRUSTUM_SHARE = 0.02  # a frustum's depth over the scene's extent
TOPK_SCALE = 1.8  # the top-k's frustums over the others'
ELITE_SCALE = 1.3  # an archive elite's frustum over the view it holds (drawn around it)
DEMO_LABELS = 3  # a demo labels each method's best shots up to this rank (all of them crowd the room)
THUMBNAIL_SIDE = 96  # pixels on the longer side of a top-k's image on its frustum and in the export
_OPENGL_TO_OPENCV = np.diag([1.0, -1.0, -1.0])


@contextlib.contextmanager
def _quiet(silent: bool):
    """Silences stdout inside (viser's rich prints) when `silent`."""
    if not silent:
        yield
        return
    with contextlib.redirect_stdout(io.StringIO()):
        yield


class _OneLine(logging.Handler):
    """A library's log record as one line on stderr ("waldo: view: ..."), its exception as its type and
    message: a client's malformed request (junk bytes, a 100 KB header, a bad websocket frame) had printed
    a traceback of the websockets server per request; the server goes on serving either way."""

    def emit(self, record: logging.LogRecord) -> None:
        try:
            said = record.getMessage()
            if record.exc_info and record.exc_info[1] is not None:
                error = record.exc_info[1]
                said += f" ({type(error).__name__}: {one_line(str(error)) or 'no message'})"
            print(f"waldo: view: {one_line(said)}", file=sys.stderr, flush=True)
        except Exception:  # a log line must never take the server down
            self.handleError(record)


_LIBRARY_LOGGERS = ("websockets", "viser")


def _library_logs_one_line() -> None:
    """Routes the websockets and viser loggers through `_OneLine` (once per process)."""
    for name in _LIBRARY_LOGGERS:
        logger = logging.getLogger(name)
        if not any(isinstance(h, _OneLine) for h in logger.handlers):
            logger.addHandler(_OneLine(logging.WARNING))
            logger.propagate = False


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


def groups_of(frustums) -> List[str]:
    """The demo methods of the frustums ("" outside a demo), in order of first appearance."""
    return list(dict.fromkeys(f.group for f in frustums if f.group))


def score_colors(frustums: Tuple[Frustum, ...], direction: str) -> List[Tuple[int, int, int]]:
    """An RGB colour per frustum: viridis over the finite scores (the best yellow), grey unscored, orange top-k
    (a demo's: its method's colour of `GROUP_COLORS`)."""
    from matplotlib import colormaps

    scores = np.array([np.nan if f.score is None else f.score for f in frustums], np.float64)
    finite = np.isfinite(scores)
    colors: List[Tuple[int, int, int]] = []
    low, high = (float(np.min(scores[finite])), float(np.max(scores[finite]))) if finite.any() else (0.0, 1.0)
    viridis = colormaps["viridis"]
    groups = groups_of(frustums)
    for frustum, score in zip(frustums, scores):
        if frustum.kind == "topk" and frustum.group:
            colors.append(GROUP_COLORS[groups.index(frustum.group) % len(GROUP_COLORS)])
        elif frustum.kind == "topk":
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


def shot_image(path: Path) -> np.ndarray:
    """The image at `path` (a top-k shot's) as uint8 [h, w, 3], read as every image waldo reads
    (`io.read_image`: grey, palette, 16-bit and CMYK files as RGB; a truncated, HDR or oversized one refused
    with a `ViewerError` naming the file, not an OSError from the middle of drawing)."""
    from waldo_jax.io import read_image, to_uint8

    try:
        return to_uint8(read_image(path, what="top-k image", min_side=MIN_SIDE))
    except WaldoError as e:
        raise ViewerError(str(e)) from None


def thumbnail(path: Path, side: int = THUMBNAIL_SIDE) -> np.ndarray:
    """The image at `path` as uint8 [h, w, 3], shrunk to at most `side` pixels on its longer side."""
    from PIL import Image

    image = Image.fromarray(shot_image(path))
    image.thumbnail((side, side))
    return np.asarray(image, np.uint8)


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


def address_url(host: str, port: int) -> str:
    """The URL a browser on this machine opens for a server on `host`: every interface is shown as the
    loopback address of its family, and an IPv6 address in brackets (`http://[::1]:8080`)."""
    shown = {"": "127.0.0.1", "0.0.0.0": "127.0.0.1", "::": "::1"}.get(host, host)
    if ":" in shown and not shown.startswith("["):
        shown = "[" + shown.replace("%", "%25") + "]"  # a zone index's "%" escaped in a URL (RFC 6874)
    return f"http://{shown}:{port}"


class Viewer:
    """A `ViewScene` on a viser server: the scene, the frustums and the panel.

    Attributes:
      server: the `viser.ViserServer`. scene: the `ViewScene`. handles: frustum node name -> its viser handle.
      panel: the GUI Markdown that `select` writes. selected: the last selected `Frustum` (None at first).
      live: the `LiveView` behind "Render this view" and "Score this view"; live_panel its GUI Markdown (for a
        scene with a SOURCE) and live_image the last image rendered there (None before).
      export_panel: the GUI Markdown listing the camera paths "Export this path" wrote (None for a scene with
        no output folder); exported: those files.
      url: the address to open.
    """

    def __init__(self, scene: ViewScene, host: str = "127.0.0.1", port: int = 8080, verbose: bool = False):
        viser = import_viser()
        self.scene = scene
        _library_logs_one_line()
        with _quiet(not verbose):  # viser prints its own address box; `waldo view` prints one line
            self.server = viser.ViserServer(host=host, port=port, label="waldo view", verbose=verbose)
        self.handles: Dict[str, object] = {}
        self.frustums: Dict[str, Frustum] = {f.name: f for f in scene.frustums}
        self.selected: Optional[Frustum] = None
        self._scored = sum(1 for f in scene.frustums if f.rank is not None and f.kind != "topk")
        self._image = None
        self.live_image = None
        # viser runs its callbacks in a thread pool: two clicks swap an image at once, and the second removed
        # the handle the first had removed (viser's "already removed GuiImageHandle" warning).
        self._images_lock = threading.Lock()
        self._syncing = False
        self.live = LiveView(
            scene.source, scene.criterion, scene.resolution, scene.scores, scene.direction or "max", scene.room_metadata
        )
        self.exported: List[Path] = []
        try:
            self._build()
        except BaseException:  # a shot's image that cannot be read: the server it started stops with it
            self.stop()
            raise

    @property
    def url(self) -> str:
        return address_url(self.server.get_host(), self.server.get_port())

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
                image=thumbnail(frustum.image) if big and frustum.image is not None else None,
                format="jpeg",
                wxyz=wxyz,
                position=position,
            )
            handle.on_click(lambda event, name=frustum.name: self.select(name, [event.client]))
            self.handles[frustum.name] = handle
            if big and (not frustum.group or (frustum.topk_rank or 0) <= DEMO_LABELS):
                tag = f"{frustum.group.upper()} #{frustum.topk_rank}" if frustum.group else f"#{frustum.topk_rank}"
                api.add_label(f"{frustum.name}/label", tag)
        gui = self.server.gui
        gui.add_markdown(f"**waldo view**: {scene.title}")
        counts = {k: sum(1 for f in scene.frustums if f.kind == k) for k in ("train", "view", "topk", "elite", "path")}
        groups = groups_of(scene.frustums)
        if groups:  # a demo: its methods' shots only
            shown = f"{counts['topk']} top-k shots of {len(groups)} methods (a colour each, see their folders)"
        else:
            shown = (
                f"{counts['view']} searched views, {counts['topk']} top-k shots (orange), {counts['elite']} archive "
                "elites (purple, under /archive)"
            )
        gui.add_markdown(f"{counts['train']} training views, {shown}; colour: score, yellow best. Click a camera.")
        for note in scene.notes:
            gui.add_markdown(f"*{note}*")
        self.panel = gui.add_markdown("*no camera selected*")
        best = next((f for f in scene.frustums if f.topk_rank == 1 and not f.group), None)
        if best is not None:
            button = gui.add_button("Go to the best shot")
            button.on_click(lambda event, name=best.name: self.select(name, [event.client]))
        self._add_live_controls()
        self._add_path_controls()
        self._add_export_controls()
        self._add_group_controls()

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
        # Every browser follows the slider (one viewer, one scene on screen), not only the one that moved it.
        self.frame_slider.on_update(lambda event: self._syncing or self.show_frame(int(self.frame_slider.value)))
        gui.add_button("Play the path").on_click(lambda event: self.play_path())

    def show_frame(self, index: int, clients=None) -> Frustum:
        """Shows frame `index` of the camera path in the panel, sets the slider to it and moves `clients`'
        cameras onto it (default: every connected client)."""
        index = int(min(max(int(index), 0), len(self.scene.camera_path) - 1))
        if self.frame_slider is not None and int(self.frame_slider.value) != index:
            self._syncing = True  # the slider follows without calling back here
            try:
                self.frame_slider.value = index
            finally:
                self._syncing = False
        clients = list(self.server.get_clients().values()) if clients is None else clients
        return self.select(f"/path/{index:04d}", clients)

    def play_path(self, clients=None, fps: Optional[float] = None):
        """Moves the cameras (default: every connected client's) along the whole path at `fps` (default the path's
        frame rate), the slider following, in a background thread; returns the thread."""
        import threading

        delay = 1.0 / max(float(fps or self.scene.path_fps), 1e-3)

        def run():
            for index in range(len(self.scene.camera_path)):
                self.show_frame(index, clients)
                time.sleep(delay)

        thread = threading.Thread(target=run, name="waldo-view-play", daemon=True)
        thread.start()
        return thread

    def _add_export_controls(self) -> None:
        """ "Export this path" (a camera path, or an explore's top-k shots as keyframes) and its panel, for a
        scene with an output folder; a demo has one per method (`_add_group_controls`)."""
        self.export_panel = None
        scene = self.scene
        own = scene.camera_path is not None or any(f.kind == "topk" and not f.group for f in scene.frustums)
        if scene.output is None or not (own or groups_of(scene.frustums)):
            return
        if own:
            what = "the camera path" if scene.camera_path is not None else "the top-k shots as a path"
            button = self.server.gui.add_button("Export this path", hint=f"writes {what} for nerfstudio / Instant-NGP")
            button.on_click(lambda event: self._on_export(""))
        self.export_panel = self.server.gui.add_markdown("")

    def _add_group_controls(self) -> None:
        """A demo: a panel folder per method (its colour, shot count, best shot, show / hide, export)."""
        for group in groups_of(self.scene.frustums):
            shots = [f for f in self.scene.frustums if f.group == group]
            color = GROUP_COLORS[groups_of(self.scene.frustums).index(group) % len(GROUP_COLORS)]
            with self.server.gui.add_folder(group.upper()):
                self.server.gui.add_markdown(
                    f"<span style='color: rgb{color}'>&#9632;</span> {len(shots)} top-k shots under `/topk/{group}`"
                )
                best = min(shots, key=lambda f: f.topk_rank or 1 << 30)
                self.server.gui.add_button(f"Go to {group.upper()}'s best shot").on_click(
                    lambda event, name=best.name: self.select(name, [event.client])
                )
                shown = self.server.gui.add_checkbox("show", True)
                shown.on_update(lambda event, group=group, box=shown: self.show_group(group, bool(box.value)))
                self.server.gui.add_button(f"Export {group.upper()}'s shots as a path").on_click(
                    lambda event, group=group: self._on_export(group)
                )

    def _on_export(self, group: str) -> None:
        """The export buttons' handler: `export_path`, its error shown in the panel."""
        try:
            self.export_path(group)
        except WaldoError as e:  # shown in the panel: a viewer keeps serving
            self.export_panel.content = f"*{e}*"
        except OSError as e:  # a full disk, a folder made read-only since: the same, naming the file
            self.export_panel.content = f"*{e.filename or self.scene.output}: {e.strerror or e}*"

    def show_group(self, group: str, visible: bool) -> None:
        """Shows or hides a demo method's top-k frustums."""
        for frustum in self.scene.frustums:
            if frustum.group == group:
                self.handles[frustum.name].visible = visible

    def export_path(self, group: str = "") -> List[Path]:
        """Writes the path shown (a camera path; else the top-k shots of `group`, "" outside a demo) as
        camera_path.json and instant_ngp_path.json in a new `viewer_path_NN` of the output folder
        (`waldo_jax.viewer.paths`), lists them in the panel and returns them."""
        written = export_camera_path(self.scene, group)
        self.exported += written
        if self.export_panel is not None:
            self.export_panel.content = "wrote  \n" + "  \n".join(f"`{p}`" for p in self.exported)
        return written

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
        with self._images_lock:
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
        with self._images_lock:
            if self._image is not None:
                self._image.remove()
                self._image = None
            if frustum.image is not None:  # a grey or 16-bit image as RGB 8-bit ([..., :3] cut a grey one's width)
                try:
                    pixels = shot_image(frustum.image)
                except ViewerError as e:  # replaced or removed since the page was built: said in the panel
                    self.panel.content += f"  \n*{e}*"
                else:
                    self._image = self.server.gui.add_image(pixels, label=frustum.image.name)
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


def _jpeg_data_uri(image: np.ndarray) -> str:
    """A `data:image/jpeg;base64,...` URI of uint8 [h, w, 3]."""
    import base64

    from PIL import Image

    buffer = io.BytesIO()
    Image.fromarray(image).save(buffer, format="JPEG", quality=85)
    return "data:image/jpeg;base64," + base64.b64encode(buffer.getvalue()).decode("ascii")


def shots_gallery(scene: ViewScene) -> str:
    """HTML of the top-k shots' thumbnails (a demo: a row per method), each with its rank and score, in a
    `<details id="waldo-shots">` fixed to the page's lower left corner; "" without top-k images."""
    import html

    shots = [f for f in scene.frustums if f.kind == "topk" and f.image is not None]
    if not shots:
        return ""
    rows = []
    for group in dict.fromkeys(f.group for f in shots):
        cells = []
        for f in sorted((f for f in shots if f.group == group), key=lambda f: f.topk_rank or 0):
            score = "no score" if f.score is None else f"{f.score:.4g}"
            cells.append(
                f'<figure style="margin:0;text-align:center"><img src="{_jpeg_data_uri(thumbnail(f.image, 64))}" '
                f'alt="{html.escape(f.label)}" title="{html.escape(f.label)}" style="display:block;height:48px">'
                f"<figcaption>#{f.topk_rank} {score}</figcaption></figure>"
            )
        head = f"<div><b>{html.escape(group.upper())}</b></div>" if group else ""
        rows.append(f'{head}<div style="display:flex;flex-wrap:wrap;gap:3px">{"".join(cells)}</div>')
    title = html.escape(f"top-k shots ({scene.criterion or 'score'})")
    return (
        '<details id="waldo-shots" open style="position:fixed;left:8px;bottom:8px;z-index:1000;max-width:300px;'
        "max-height:45%;overflow:auto;background:rgba(255,255,255,0.92);font:11px sans-serif;padding:4px 6px;"
        f'border-radius:6px;box-shadow:0 1px 4px rgba(0,0,0,0.3)"><summary>{title}</summary>{"".join(rows)}</details>'
    )


def export_html(scene: ViewScene, path: Path) -> Tuple[int, float]:
    """Writes a self-contained HTML snapshot of `scene` to `path` (opens without a server).

    viser's `scene.as_html()` embeds its web client and the serialized scene (the top-k frustums show their
    images); a JSON block `<script id="waldo-frustums" type="application/json">` adds every frustum's pose, score
    and rank for readers of the file, and a panel `<details id="waldo-shots">` in the page's corner the top-k
    shots' thumbnails with rank and score (`shots_gallery`). The server it builds the scene on listens on an
    ephemeral 127.0.0.1 port and is stopped before returning.

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
    page = page.replace("</body>", f"{shots_gallery(scene)}</body>", 1)
    from waldo_jax import io as waldo_io

    waldo_io.write_text(Path(path), page)  # atomically: an interrupt or a full disk leaves no half page
    return len(page.encode("utf-8")), time.perf_counter() - start
