"""What `waldo view` draws, read from disk without a browser library: a `ViewScene`.

PATH is an output folder of `waldo explore` or `waldo path` (its results.json), of `waldo demo`
(`viewer.demo`), or a SOURCE (a splat scene, `procedural[:SEED]`, a NeRF run). The scene's geometry comes from
the SOURCE: a splat scene gives its Gaussians (`SplatCloud`: means, covariances from scales and rotations,
colours from the SH DC term, opacities); the procedural room a point cloud of its surfaces (`room_points`); a
NeRF run a point cloud of its density (`viewer.nerf_points`). The cameras are `Frustum`s: the training views
and every scored view of the search, with their scores, ranks among all scored views and, for the top-k
different shots, their rank there and image.

Poses are OpenGL camera-to-world [4, 4] (x right, y up, z backwards), as everywhere in waldo_jax.
"""

from __future__ import annotations

import dataclasses
import math
import os
import warnings
from pathlib import Path
from typing import Any, Dict, List, Optional, Tuple

import numpy as np

from waldo_jax.errors import WaldoError
from waldo_jax.viewer.fields import MAX_FRUSTUMS, Fields, ViewerError, check_image_file, read_json, relative_file

__all__ = [
    "Frustum",
    "SplatCloud",
    "ViewScene",
    "ViewerError",
    "archive_frustums",
    "quaternion_matrices",
    "explore_scene",
    "path_scene",
    "ring_of",
    "source_geometry",
    "resolve_source",
    "room_points",
    "splat_cloud",
]

DEFAULT_FOV_Y_DEG = 50.0
MAX_ROOM_POINTS = 60_000


@dataclasses.dataclass(frozen=True)
class SplatCloud:
    """Gaussians as a browser draws them.

    Attributes:
      centers: float32 [N, 3]. covariances: float32 [N, 3, 3]. rgbs: float32 [N, 3] in [0, 1] (the SH DC term).
      opacities: float32 [N, 1] in [0, 1].
    """

    centers: np.ndarray
    covariances: np.ndarray
    rgbs: np.ndarray
    opacities: np.ndarray


@dataclasses.dataclass(frozen=True)
class Frustum:
    """One camera to draw.

    Attributes:
      name: its scene-graph name ("/train/003", "/views/0042", "/topk/01").
      kind: "train", "view" (a view the search generated), "topk" (one of the k best different shots),
        "elite" (the best view of a cell of the explore's view archive) or "path" (a frame of a camera path).
      c2w: float64 [4, 4] OpenGL camera-to-world.
      score: the criterion's score (None: not scored or failed).
      rank: 1-based rank of its score among all scored views, best first (None without a score).
      topk_rank: 1-based rank among the top-k different shots (None if not one of them).
      label: what it is, in words ("training view ring_03", "view 17, epoch 2").
      image: the PNG of its render on disk (the top-k's), or None.
      group: the method whose shot it is in a `waldo demo` output ("egps", ...); "" elsewhere.
    """

    name: str
    kind: str
    c2w: np.ndarray
    score: Optional[float]
    rank: Optional[int]
    topk_rank: Optional[int]
    label: str
    image: Optional[Path] = None
    group: str = ""


@dataclasses.dataclass(frozen=True)
class ViewScene:
    """Everything `waldo view` shows.

    Attributes:
      path: the PATH given. title: a one-line description.
      splats: the scene's Gaussians, or None. points: (xyz float32 [P, 3], rgb float32 [P, 3]) or None.
      frustums: the cameras, training views first.
      fov_y: vertical field of view in radians. aspect: width / height.
      criterion, direction: the run's criterion and its direction ("max"/"min"; "" for a SOURCE).
      notes: what is not shown, and why (one line each).
      source: the SOURCE that renders it (an explore's source, or the SOURCE given; "" for none).
      resolution: (width, height) of the run's renders, or None (a SOURCE's own).
      scores: the search's scores, training views first (for the rank of a view scored in the viewer).
      camera_path: a `waldo path` output's camera path, float [F, 4, 4] OpenGL c2w per frame, or None; path_fps
        its frame rate.
      source_info: results.json's `source_info` (Instant-NGP's frame of the scene, for exported paths).
      room_metadata: the procedural room's metadata (`procedural.room_from_metadata`) for scoring, where the
        source's checkpoint does not record it (a `waldo demo` run older than that record); None otherwise.
      output: the output folder an exported camera path goes into (None for a SOURCE: nothing to export).
    """

    path: str
    title: str
    splats: Optional[SplatCloud]
    points: Optional[Tuple[np.ndarray, np.ndarray]]
    frustums: Tuple[Frustum, ...]
    fov_y: float
    aspect: float
    criterion: str = ""
    direction: str = ""
    notes: Tuple[str, ...] = ()
    source: str = ""
    resolution: Optional[Tuple[int, int]] = None
    scores: Tuple[Optional[float], ...] = ()
    camera_path: Optional[np.ndarray] = None
    path_fps: float = 12.0
    source_info: Dict[str, Any] = dataclasses.field(default_factory=dict)
    room_metadata: Optional[Dict[str, Any]] = None
    output: Optional[Path] = None

    def extent(self) -> float:
        """A length for the scene's size: the diagonal of the cameras' (or the geometry's) box."""
        if self.frustums:
            xyz = np.stack([f.c2w[:3, 3] for f in self.frustums])
        elif self.splats is not None:
            xyz = self.splats.centers
        elif self.points is not None:
            xyz = self.points[0]
        else:
            return 1.0
        low, high = np.quantile(xyz, 0.02, axis=0), np.quantile(xyz, 0.98, axis=0)
        return float(max(np.linalg.norm(high - low), 1e-3))


def quaternion_matrices(wxyz: np.ndarray) -> np.ndarray:
    """Rotation matrices [..., 3, 3] of unit quaternions [..., 4] (w first), in NumPy (host-side drawing)."""
    w, x, y, z = np.moveaxis(wxyz, -1, 0)
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
            np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
            np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
        ],
        -2,
    )


def splat_cloud(splats) -> SplatCloud:
    """A `waldo_jax.splats.Splats` as a `SplatCloud` (valid rows only): Sigma = R diag(s^2) R^T."""
    from waldo_jax.splats.sh import SH_C0

    valid = np.asarray(splats.valid, bool)
    rotations = quaternion_matrices(np.asarray(splats.rotations(), np.float64)[valid])  # [N, 3, 3]
    scales = np.asarray(splats.scales(), np.float64)[valid]  # [N, 3]
    covariances = np.einsum("nij,nj,nkj->nik", rotations, scales * scales, rotations)
    rgbs = np.clip(0.5 + SH_C0 * np.asarray(splats.sh, np.float64)[valid, 0, :], 0.0, 1.0)
    return SplatCloud(
        centers=np.asarray(splats.means, np.float32)[valid],
        covariances=covariances.astype(np.float32),
        rgbs=rgbs.astype(np.float32),
        opacities=np.asarray(splats.opacities(), np.float32)[valid][:, None],
    )


def room_points(room, count: int = MAX_ROOM_POINTS, seed: int = 0) -> Tuple[np.ndarray, np.ndarray]:
    """Surface points of the procedural room and their albedo-shaded colours: (xyz [P, 3], rgb [P, 3]), P <= count.

    Random points in the room's box are kept where the room's signed distance is within a few centimetres
    of zero (its surfaces), coloured by `room_field`.
    """
    import jax
    import jax.numpy as jnp

    from waldo_jax.procedural.room import room_field, room_sdf

    low, high = room.aabb
    key = jax.random.key(seed)
    candidates = jax.random.uniform(key, (count * 12, 3), minval=jnp.asarray(low), maxval=jnp.asarray(high))
    distance = jax.jit(jax.vmap(lambda p: room_sdf(room, p)))(candidates)
    near = np.abs(np.asarray(distance)) < 0.03
    xyz = np.asarray(candidates)[near][:count]
    _, rgb = jax.jit(jax.vmap(lambda p: room_field(room, p, jnp.zeros(3))))(jnp.asarray(xyz))
    return xyz.astype(np.float32), np.asarray(rgb, np.float32)


def _run_geometry(spec: str, notes: List[str]):
    """(None, points, train_c2w, names, fov_y, aspect) of a `waldo train` / `waldo demo` run folder."""
    from waldo_jax.nerf.checkpoint import load_checkpoint
    from waldo_jax.viewer.nerf_points import density_note, nerf_points

    checkpoint = load_checkpoint(spec)
    record = checkpoint.scene
    c2w = np.asarray(record.c2w, np.float64)
    points = nerf_points(checkpoint)
    notes.append(density_note(points[0]))
    intrinsics = record.intrinsics
    fov_y = 2 * math.atan(0.5 * intrinsics.height / float(intrinsics.fy))
    return None, points, c2w, tuple(record.file_names), fov_y, intrinsics.width / intrinsics.height


def _ranks(scores: List[Optional[float]], direction: str) -> List[Optional[int]]:
    """1-based ranks of the finite scores (best first under `direction`); None for the others."""
    finite = [(s, i) for i, s in enumerate(scores) if s is not None and math.isfinite(s)]
    finite.sort(key=lambda t: -t[0] if direction != "min" else t[0])
    ranks: List[Optional[int]] = [None] * len(scores)
    for rank, (_, i) in enumerate(finite, 1):
        ranks[i] = rank
    return ranks


def _intrinsics_of(out: Path, resolution: Optional[Tuple[int, int]]) -> Tuple[float, float]:
    """(fov_y radians, aspect) of an explore output: poses.json's camera, its keys checked by key (a damaged
    one is refused, not drawn at a NaN field of view; `fl_y: 0` was a ZeroDivisionError), else its
    resolution at 50 degrees. The aspect is the run's resolution's, else the camera's. Only the camera is
    read: a run whose every view failed its guard writes `frames: []`, and its views may be under 8 px a side."""
    width, height = resolution or (64, 64)
    fov_y = math.radians(DEFAULT_FOV_Y_DEG)
    aspect = width / height
    if os.path.lexists(out / "poses.json"):  # a directory, a FIFO or a dangling link is said as such there
        camera = Fields(read_json(out / "poses.json", "poses file"), out / "poses.json")
        w, h = camera.number("w", None, positive=True), camera.number("h", None, positive=True)
        focal = camera.number("fl_y", None, positive=True) or camera.number("fl_x", None, positive=True)
        angle_x = camera.number("camera_angle_x", None, positive=True)
        aspect = aspect if resolution or w is None or h is None else w / h
        if focal is not None and h is not None:
            fov_y = 2 * math.atan(0.5 * h / focal)
        elif angle_x is not None:
            if angle_x >= math.pi:
                raise camera.error(f"expected an angle under pi radians, got {angle_x:g}", "camera_angle_x")
            fov_y = 2 * math.atan(math.tan(0.5 * angle_x) / aspect)
    return fov_y, aspect


def _source_info(results: Fields) -> Dict[str, Any]:
    """results.json's `source_info` with the keys an exported camera path reads (Instant-NGP's frame:
    `ngp_scale`, `ngp_offset`, `ngp_from_mitsuba`) checked; {} where absent."""
    info = results.object("source_info", None)
    if info is None:
        return {}
    info.number("ngp_scale", None, positive=True)
    if isinstance(info.data.get("ngp_offset"), list):  # one offset per axis, or one for all (a number)
        if None in info.scores("ngp_offset", 3, of="axes"):  # finite numbers, where a score may be null
            raise info.error("expected 3 numbers, got a null", "ngp_offset")
    else:
        info.number("ngp_offset", None)
    info.flag("ngp_from_mitsuba", None)
    return dict(info.data)


def _topk_image(entry: Fields, out: Path) -> Optional[Path]:
    """A top-k shot's image (`image`, relative to the output folder) if it is there; a missing one is shown
    without its image and said in a warning; one that is not a readable image of a usable size is refused."""
    image = relative_file(entry, "image", out)
    if image is None:
        return None
    if not os.path.lexists(image):
        warnings.warn(f"{image} ({entry.key('image')}) is missing: the shot is drawn without its image", stacklevel=3)
        return None
    return check_image_file(image, f"{entry.path}: {entry.key('image')}")


def _capped(frustums: List[Frustum], path: Path) -> List[Frustum]:
    """`frustums` with at most MAX_FRUSTUMS in all: the search's views past it are left out, the unscored
    and the worst first, with a warning; more training views, shots, elites or path frames than that alone
    are refused (the page would take minutes to build, and as long to open)."""
    if len(frustums) <= MAX_FRUSTUMS:
        return frustums
    others = [f for f in frustums if f.kind != "view"]
    if len(others) > MAX_FRUSTUMS:
        raise ViewerError(
            f"{path}: {len(others):,} cameras to draw (training views, top-k shots, archive elites or path "
            f"frames); waldo view draws at most {MAX_FRUSTUMS:,} (about a millisecond and 250 bytes of page each)"
        )
    views = [f for f in frustums if f.kind == "view"]
    room = MAX_FRUSTUMS - len(others)
    kept = set(id(f) for f in sorted(views, key=lambda f: (f.rank is None, f.rank or 0))[:room])
    warnings.warn(
        f"{path}: {len(views):,} searched views; waldo view draws the best {room:,} of them (at most "
        f"{MAX_FRUSTUMS:,} cameras in all)",
        stacklevel=3,
    )
    return [f for f in frustums if f.kind != "view" or id(f) in kept]


def source_geometry(spec: str, notes: List[str]):
    """(splats, points, train_c2w or None, train names, fov_y or None, aspect or None) of a SOURCE string."""
    from waldo_jax.pipeline.sources import parse_procedural
    from waldo_jax.pipeline.splat_sources import is_splat_spec

    seed = parse_procedural(spec)
    if seed is not None:
        from waldo_jax.procedural import room_scene

        scene, room = room_scene(seed, num_views=24, resolution=16, num_samples=8)
        fov_y = 2 * math.atan(0.5 * scene.height / float(scene.intrinsics.fy))
        c2w = np.asarray(scene.c2w, np.float64)
        return None, room_points(room, seed=seed), c2w, tuple(scene.file_names), fov_y, 1.0
    if is_splat_spec(spec):
        from waldo_jax.splats.io import load_splat_model

        model = load_splat_model(spec)
        c2w, names, fov_y, aspect = None, (), None, None
        if model.cameras is not None:
            c2w, names = np.asarray(model.cameras.c2w, np.float64), tuple(model.cameras.names)
            first = model.cameras.shared_intrinsics or model.cameras.intrinsics[0]
            fov_y, aspect = 2 * math.atan(0.5 * first.height / float(first.fy)), first.width / first.height
        return splat_cloud(model.splats), None, c2w, names, fov_y, aspect
    if Path(spec).is_dir() and (Path(spec) / "checkpoint.ckpt").is_file():
        return _run_geometry(spec, notes)
    raise ViewerError(
        f"PATH {spec!r} is neither an output folder of `waldo explore` (results.json), a run of `waldo train` "
        "(checkpoint.ckpt), a splat scene "
        "(a .ply / .splat / .spz, a 3DGS folder) nor procedural[:SEED]"
    )


def ring_of(spec: str) -> Tuple[Optional[np.ndarray], Tuple[str, ...]]:
    """The default ring of views of a splat scene without cameras (what `waldo explore` starts from)."""
    from waldo_jax.pipeline.splat_sources import RING_FOV_DEG, SPLAT_RESOLUTION, ring_cameras, splat_upright
    from waldo_jax.splats.io import load_splat_model
    from waldo_jax.types import Intrinsics

    model = load_splat_model(spec)
    intrinsics = Intrinsics.from_fov(SPLAT_RESOLUTION, SPLAT_RESOLUTION, math.radians(RING_FOV_DEG))
    c2w, _ = ring_cameras(
        np.asarray(model.splats.means),
        np.asarray(model.splats.valid),
        intrinsics,
        upright=splat_upright(model),
        bounds=model.bounds,
    )
    return np.asarray(c2w, np.float64), tuple(f"ring_{i:02d}" for i in range(len(c2w)))


def archive_frustums(results, train_c2w: np.ndarray, generated_c2w: np.ndarray) -> List[Frustum]:
    """The elites of an explore's view archive (`results["archive"]["elites"]`: the best view of each
    (azimuth, elevation, distance) cell) as frustums of kind "elite", at the pose of the view each holds.

    An elite names a population slot: a training view below `n_train`, else a generated view, found through
    results.json's `generated_slots` (the slots of `generated_c2w`; masked slots hold no view). Outputs
    without `generated_slots` have no elites drawn.

    Args:
      results: the explore's results.json (a dict, or its `Fields`: each value is checked by its key).
      train_c2w, generated_c2w: float [N, 4, 4] and [G, 4, 4] its training and generated poses.
    """
    results = results if isinstance(results, Fields) else Fields(results, Path("results.json"))
    archive = results.object("archive", None)
    elites = archive.items("elites", []) if archive is not None else []
    if not results.has("generated_slots"):
        return []
    pose_of = {i: m for i, m in enumerate(train_c2w)}
    pose_of.update(zip(results.integers("generated_slots", len(generated_c2w)), generated_c2w))
    frustums, cells = [], set()
    for elite in elites:
        slot = elite.integer("slot", None)
        cell = elite.integer("cell")
        if cell in cells:
            raise elite.error(f"cell {cell} holds two elites", "cell")
        cells.add(cell)
        azimuth, elevation = elite.number("azimuth", math.nan), elite.number("elevation", math.nan)
        band, score = elite.integer("distance_band", None), elite.score("score")
        if slot not in pose_of:  # a masked slot: no view to draw
            continue
        label = f"archive cell {cell}: azimuth {azimuth:.0f} deg, elevation {elevation:.0f} deg, distance band {band}"
        frustums.append(Frustum(f"/archive/{cell:03d}", "elite", pose_of[slot], score, None, None, label))
    return frustums


def resolve_source(spec: str, out: Path) -> str:
    """The SOURCE a results.json names, found again: as written (procedural, absolute, or relative to the
    working folder), else relative to one of the output folder's parents, else its last part beside the output
    folder (`waldo demo --out runs/demo` writes `runs/demo/nerf` into its method folders `runs/demo/egps`, ...).
    `spec` itself where none of these exists."""
    from waldo_jax.pipeline.sources import parse_procedural

    if not spec or parse_procedural(spec) is not None or Path(spec).exists() or Path(spec).is_absolute():
        return spec
    for folder in list(Path(out).resolve().parents)[:3]:
        if (folder / spec).exists():
            return str(folder / spec)
    beside = Path(out).resolve().parent / Path(spec).name
    return str(beside) if beside.exists() else spec


def explore_scene(out: Path, geometry: bool = True, demo=None) -> ViewScene:
    """The `ViewScene` of an explore output folder.

    Every value read from results.json is checked by its key first (`viewer.fields`: a missing or wrong-typed
    value, a NaN, lists of the views' poses and scores of different lengths, a top-k image outside the folder
    or not an image are refused, naming the key), before the scene's geometry is loaded.

    Args:
      out: the folder (its results.json, poses.json, topk/).
      geometry: False: the cameras only, no splats or points.
      demo: the `viewer.demo.DemoRoom` of the `waldo demo` the folder is a method of (its room is drawn, and
        scored with where its NeRF does not record it), or None.
    """
    path = out / "results.json"
    raw = read_json(path, "results file")
    if not isinstance(raw, dict) or "topk" not in raw or "source" not in raw:
        raise ViewerError(f"{path}: not the results of `waldo explore` (no topk / source)")
    results = Fields(raw, path)
    source = results.text("source")
    direction = results.text("direction", "max", choices=("max", "min"))
    criterion, method = results.text("criterion", ""), results.text("method", "")
    resolution = results.resolution("resolution", None)
    source_info = _source_info(results)
    recorded_train = results.poses("train_c2w", None)
    generated = results.poses("generated_c2w", None)
    count = None if recorded_train is None else len(recorded_train)
    scores_train = results.scores("scores_train", count, [])
    scores_generated = [] if generated is None else results.scores("scores_generated", len(generated), [])
    if generated is not None and not scores_generated:
        scores_generated = [None] * len(generated)
    epochs = [] if generated is None else results.integers("generated_epochs", len(generated), 0, [])
    topk = results.items("topk")
    ranks_seen = set()
    for entry in topk:
        rank = entry.integer("rank", maximum=len(topk) - 1)
        if rank in ranks_seen:
            raise entry.error(f"rank {rank} is given to two shots", "rank")
        ranks_seen.add(rank)
    shots = [
        (
            e.integer("rank"),
            e.pose("c2w"),
            e.score("score"),
            _topk_image(e, out),
            e.flag("training_view", False),
            e.integer("epoch", None),
        )
        for e in topk
    ]
    paper = []
    if generated is None:
        for entry in results.items("paper_topk", []):
            if not entry.flag("in_topk", False):
                paper.append((entry.integer("rank"), entry.pose("c2w"), entry.score("score")))
    archive = (
        [] if generated is None or recorded_train is None else archive_frustums(results, recorded_train, generated)
    )
    fov_y, aspect = _intrinsics_of(out, resolution)

    notes: List[str] = []
    spec = resolve_source(source, out)
    splats = points = None
    train_c2w, names = None, ()
    try:
        if geometry and demo is not None:  # the room the demo's NeRF learnt, not the NeRF's density
            points = room_points(demo.room, seed=demo.seed)
            notes.append(f"a method folder of the `waldo demo` {out.resolve().parent}: its room is drawn")
        elif geometry:
            splats, points, train_c2w, names, _, _ = source_geometry(spec, notes)
    except WaldoError as e:
        notes.append(f"the scene's geometry is not drawn: {e}")
    if recorded_train is not None:
        train_c2w = recorded_train
    elif train_c2w is None and splats is not None:
        train_c2w, names = ring_of(spec)
        notes.append("results.json predates train_c2w: the training views are the default ring (--up/--orbit lost)")
    if generated is None:
        notes.append("results.json predates generated_c2w: only the top-k and the paper's top-k views are drawn")
    train_count = 0 if train_c2w is None else len(train_c2w)
    if train_count != len(scores_train):  # an output older than train_c2w: its scores of the source's views
        scores_train = (scores_train + [None] * train_count)[:train_count]
    ranks = _ranks(scores_train + scores_generated, direction)
    frustums: List[Frustum] = []
    for i in range(train_count):
        name = names[i] if i < len(names) else f"{i:04d}"
        frustums.append(
            Frustum(f"/train/{i:04d}", "train", train_c2w[i], scores_train[i], ranks[i], None, f"training view {name}")
        )
    for j, c2w in enumerate(() if generated is None else generated):
        epoch = f", epoch {epochs[j]}" if j < len(epochs) else ""
        frustums.append(
            Frustum(
                f"/views/{j:04d}", "view", c2w, scores_generated[j], ranks[train_count + j], None, f"view {j}{epoch}"
            )
        )
    for rank, c2w, score in paper:
        frustums.append(Frustum(f"/views/paper_{rank:02d}", "view", c2w, score, None, None, f"paper top-k #{rank + 1}"))
    frustums += archive
    all_scores = [s for s in scores_train + scores_generated if s is not None]
    for rank, c2w, score, image, training_view, epoch in shots:
        overall = None
        if score is not None and all_scores:
            overall = 1 + sum(1 for s in all_scores if (s > score if direction != "min" else s < score))
        what = "a training view" if training_view else f"epoch {epoch}"
        frustums.append(
            Frustum(
                f"/topk/{rank:02d}", "topk", c2w, score, overall, rank + 1, f"top-k shot #{rank + 1} ({what})", image
            )
        )
    title = f"{method.upper()} on {spec}, {criterion}"
    return ViewScene(
        str(out),
        title,
        splats,
        points,
        tuple(_capped(frustums, path)),
        fov_y,
        aspect or 1.0,
        criterion,
        direction,
        tuple(notes),
        source=spec,
        resolution=resolution,
        scores=tuple(scores_train + scores_generated),
        source_info=source_info,
        room_metadata=None if demo is None or demo.recorded else demo.metadata,
        output=out,
    )


def path_scene(out: Path, results: Dict[str, Any]) -> ViewScene:
    """The `ViewScene` of a `waldo path` output folder: the scene, its training views and the camera path
    (poses.json, one camera per frame, each with its frame's score). The values read from results.json are
    checked by their keys first, as `explore_scene`'s."""
    from waldo_jax.scenes import read_poses_file
    from waldo_jax.types import Intrinsics

    fields = Fields(results, out / "results.json")
    source = fields.text("source")
    direction = fields.text("direction", "max", choices=("max", "min"))
    criterion, method = fields.text("criterion", ""), fields.text("method", "")
    source_info = _source_info(fields)
    video = fields.object("video", None)
    size = (video.resolution("frame_size", None) if video is not None else None) or (64, 64)
    fps = video.number("fps", 12.0, positive=True) if video is not None else 12.0
    found = fields.object("found", None)
    c2w, intrinsics, _ = read_poses_file(out / "poses.json", Intrinsics.from_fov(int(size[0]), int(size[1]), 0.9))
    c2w = np.asarray(c2w, np.float64)
    scores = (found.scores("frame_scores", len(c2w), None, of="frames") if found is not None else None) or [None] * len(
        c2w
    )
    if len(c2w) > MAX_FRUSTUMS:
        raise ViewerError(f"{out / 'poses.json'}: {len(c2w):,} path frames; waldo view draws at most {MAX_FRUSTUMS:,}")
    notes: List[str] = []
    spec = resolve_source(source, out)
    splats = points = train_c2w = None
    names: Tuple[str, ...] = ()
    try:
        splats, points, train_c2w, names, _, _ = source_geometry(spec, notes)
    except WaldoError as e:
        notes.append(f"the scene's geometry is not drawn: {e}")
    ranks = _ranks(scores, direction)
    frustums = [
        Frustum(f"/train/{i:04d}", "train", m, None, None, None, f"training view {names[i] if i < len(names) else i}")
        for i, m in enumerate(() if train_c2w is None else train_c2w)
    ]
    frustums += [
        Frustum(f"/path/{i:04d}", "path", m, scores[i], ranks[i], None, f"path frame {i}") for i, m in enumerate(c2w)
    ]
    fov_y = 2 * math.atan(0.5 * intrinsics.height / float(intrinsics.fy))
    return ViewScene(
        str(out),
        f"camera path ({method.upper()}) on {spec}, {criterion}",
        splats,
        points,
        tuple(_capped(frustums, out / "results.json")),
        fov_y,
        intrinsics.width / intrinsics.height,
        criterion,
        direction,
        tuple(notes),
        source=spec,
        resolution=(int(intrinsics.width), int(intrinsics.height)),
        camera_path=c2w,
        path_fps=fps,
        source_info=source_info,
        output=out,
    )
