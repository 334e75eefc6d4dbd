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
from pathlib import Path
from typing import Any, Dict, List, Optional, Tuple

import numpy as np

from waldo_jax.io import read_json_file
from waldo_jax.errors import WaldoError

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


class ViewerError(WaldoError, ValueError):
    """A PATH `waldo view` cannot show (the message names it and says why)."""


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


def _intrinsics_of(out: Path, results: Dict[str, Any]) -> Tuple[float, float]:
    """(fov_y radians, aspect) of an explore output: poses.json's camera, else its resolution at 50 degrees."""
    width, height = (results.get("resolution") or [1, 1])[:2]
    aspect = float(width) / float(height) if height else 1.0
    try:
        poses = read_json_file(out / "poses.json", "poses file")
        if "fl_y" in poses and "h" in poses:
            return 2 * math.atan(0.5 * float(poses["h"]) / float(poses["fl_y"])), aspect
        if "camera_angle_x" in poses:
            return 2 * math.atan(math.tan(0.5 * float(poses["camera_angle_x"])) / aspect), aspect
    except (WaldoError, ValueError, KeyError, TypeError):
        pass
    return math.radians(DEFAULT_FOV_Y_DEG), aspect


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
        np.asarray(model.splats.means), np.asarray(model.splats.valid), intrinsics, upright=splat_upright(model)
    )
    return np.asarray(c2w, np.float64), tuple(f"ring_{i:02d}" for i in range(len(c2w)))


def archive_frustums(results: Dict[str, Any], train_c2w: np.ndarray, generated_c2w: np.ndarray) -> List[Frustum]:
    """The elites of an explore's view archive (`results["archive"]["elites"]`: the best view of each
    (azimuth, elevation, distance) cell) as frustums of kind "elite", at the pose of the view each holds.

    An elite names a population slot: a training view below `n_train`, else a generated view, found through
    results.json's `generated_slots` (the slots of `generated_c2w`; masked slots hold no view). Outputs
    without `generated_slots` have no elites drawn.

    Args:
      results: the explore's results.json.
      train_c2w, generated_c2w: float [N, 4, 4] and [G, 4, 4] its training and generated poses.
    """
    elites = ((results.get("archive") or {}).get("elites")) or []
    if "generated_slots" not in results:
        return []
    pose_of = {i: m for i, m in enumerate(train_c2w)}
    pose_of.update({int(s): m for s, m in zip(results["generated_slots"], generated_c2w)})
    frustums = []
    for elite in elites:
        slot = elite.get("slot")
        if not isinstance(slot, int) or slot not in pose_of:
            continue
        label = (
            f"archive cell {elite['cell']}: azimuth {elite.get('azimuth', float('nan')):.0f} deg, elevation "
            f"{elite.get('elevation', float('nan')):.0f} deg, distance band {elite.get('distance_band')}"
        )
        frustums.append(
            Frustum(f"/archive/{int(elite['cell']):03d}", "elite", pose_of[slot], elite.get("score"), None, None, label)
        )
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

    Args:
      out: the folder (its results.json, poses.json, topk/).
      geometry: False: the cameras only, no splats or points.
      demo: the `viewer.demo.DemoRoom` of the `waldo demo` the folder is a method of (its room is drawn, and
        scored with where its NeRF does not record it), or None.
    """

    results = read_json_file(
        out / "results.json", "results file", lambda problem: ViewerError(f"{out / 'results.json'}: {problem}")
    )
    if not isinstance(results, dict) or "topk" not in results or "source" not in results:
        raise ViewerError(f"{out / 'results.json'}: not the results of `waldo explore` (no topk / source)")
    notes: List[str] = []
    spec = resolve_source(str(results["source"]), out)
    direction = str(results.get("direction", "max"))
    splats = points = None
    train_c2w, names, fov_y, aspect = None, (), None, None
    try:
        if geometry and demo is not None:  # the room the demo's NeRF learnt, not the NeRF's density
            points = room_points(demo.room, seed=demo.seed)
            notes.append(f"a method folder of the `waldo demo` {out.resolve().parent}: its room is drawn")
        elif geometry:
            splats, points, train_c2w, names, _, _ = source_geometry(spec, notes)
    except WaldoError as e:
        notes.append(f"the scene's geometry is not drawn: {e}")
    fov_y, aspect = _intrinsics_of(out, results)
    if "train_c2w" in results:
        train_c2w = np.asarray(results["train_c2w"], np.float64).reshape(-1, 4, 4)
    elif train_c2w is None and splats is not None:
        train_c2w, names = ring_of(spec)
        notes.append("results.json predates train_c2w: the training views are the default ring (--up/--orbit lost)")
    generated = results.get("generated_c2w")
    if generated is None:
        notes.append("results.json predates generated_c2w: only the top-k and the paper's top-k views are drawn")
    scores_train = list(results.get("scores_train") or [])
    scores_generated = list(results.get("scores_generated") or []) if generated is not None else []
    train_count = 0 if train_c2w is None else len(train_c2w)
    if train_count != len(scores_train):
        scores_train = (scores_train + [None] * train_count)[:train_count]
    ranks = _ranks(scores_train + scores_generated, direction)
    epochs = results.get("generated_epochs") or []
    frustums: List[Frustum] = []
    for i in range(train_count):
        name = names[i] if i < len(names) else f"{i:04d}"
        frustums.append(
            Frustum(f"/train/{i:04d}", "train", train_c2w[i], scores_train[i], ranks[i], None, f"training view {name}")
        )
    if generated is not None:
        for j, c2w in enumerate(np.asarray(generated, np.float64).reshape(-1, 4, 4)):
            epoch = f", epoch {epochs[j]}" if j < len(epochs) else ""
            score = scores_generated[j] if j < len(scores_generated) else None
            frustums.append(
                Frustum(f"/views/{j:04d}", "view", c2w, score, ranks[train_count + j], None, f"view {j}{epoch}")
            )
    else:
        for entry in results.get("paper_topk") or []:
            if not entry.get("in_topk"):
                frustums.append(
                    Frustum(
                        f"/views/paper_{entry['rank']:02d}",
                        "view",
                        np.asarray(entry["c2w"], np.float64),
                        entry.get("score"),
                        None,
                        None,
                        f"paper top-k #{entry['rank'] + 1}",
                    )
                )
    if generated is not None and train_c2w is not None:
        frustums += archive_frustums(results, train_c2w, np.asarray(generated, np.float64).reshape(-1, 4, 4))
    all_scores = [s for s in scores_train + scores_generated if s is not None]
    for entry in results["topk"]:
        rank = int(entry["rank"])
        score = entry.get("score")
        overall = None
        if score is not None and all_scores:
            overall = 1 + sum(1 for s in all_scores if (s > score if direction != "min" else s < score))
        image = out / entry["image"] if entry.get("image") and (out / entry["image"]).is_file() else None
        what = "a training view" if entry.get("training_view") else f"epoch {entry.get('epoch')}"
        frustums.append(
            Frustum(
                f"/topk/{rank:02d}",
                "topk",
                np.asarray(entry["c2w"], np.float64),
                score,
                overall,
                rank + 1,
                f"top-k shot #{rank + 1} ({what})",
                image,
            )
        )
    criterion = str(results.get("criterion", ""))
    title = f"{str(results.get('method', '')).upper()} on {spec}, {criterion}"
    resolution = results.get("resolution")
    return ViewScene(
        str(out),
        title,
        splats,
        points,
        tuple(frustums),
        fov_y,
        aspect or 1.0,
        criterion,
        direction,
        tuple(notes),
        source=spec,
        resolution=tuple(int(v) for v in resolution[:2]) if resolution else None,
        scores=tuple(scores_train + scores_generated),
        source_info=dict(results.get("source_info") or {}),
        room_metadata=None if demo is None or demo.recorded else demo.metadata,
        output=out,
    )


def path_scene(out: Path, results: Dict[str, Any]) -> ViewScene:
    """The `ViewScene` of a `waldo path` output folder: the scene, its training views and the camera path
    (poses.json, one camera per frame, each with its frame's score)."""
    from waldo_jax.scenes import read_poses_file
    from waldo_jax.types import Intrinsics

    notes: List[str] = []
    spec = resolve_source(str(results["source"]), out)
    splats = points = train_c2w = None
    names: Tuple[str, ...] = ()
    try:
        splats, points, train_c2w, names, _, _ = source_geometry(spec, notes)
    except WaldoError as e:
        notes.append(f"the scene's geometry is not drawn: {e}")
    size = (results.get("video") or {}).get("frame_size") or [64, 64]
    c2w, intrinsics, _ = read_poses_file(out / "poses.json", Intrinsics.from_fov(int(size[0]), int(size[1]), 0.9))
    c2w = np.asarray(c2w, np.float64)
    scores = list(((results.get("found") or {}).get("frame_scores")) or [])
    scores = (scores + [None] * len(c2w))[: len(c2w)]
    direction = str(results.get("direction", "max"))
    ranks = _ranks(scores, direction)
    frustums = [
        Frustum(f"/train/{i:04d}", "train", m, None, None, None, f"training view {names[i] if i < len(names) else i}")
        for i, m in enumerate(() if train_c2w is None else train_c2w)
    ]
    frustums += [
        Frustum(f"/path/{i:04d}", "path", m, scores[i], ranks[i], None, f"path frame {i}") for i, m in enumerate(c2w)
    ]
    criterion = str(results.get("criterion", ""))
    fov_y = 2 * math.atan(0.5 * intrinsics.height / float(intrinsics.fy))
    return ViewScene(
        str(out),
        f"camera path ({str(results.get('method', '')).upper()}) on {spec}, {criterion}",
        splats,
        points,
        tuple(frustums),
        fov_y,
        intrinsics.width / intrinsics.height,
        criterion,
        direction,
        tuple(notes),
        source=spec,
        resolution=(int(intrinsics.width), int(intrinsics.height)),
        camera_path=c2w,
        path_fps=float((results.get("video") or {}).get("fps") or 12.0),
        source_info=dict(results.get("source_info") or {}),
        output=out,
    )
