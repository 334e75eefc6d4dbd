"""A `waldo demo` output folder as one `ViewScene`: the room, the NeRF's training cameras and every method's shots.

A demo folder holds summary.json, the NeRF run `nerf/` and one explore output per method (`grs/`, `pibs/`,
`egps/`, ...; `waldo_jax.pipeline.demo`). The room is the one the NeRF learnt: its checkpoint records it
(`procedural.room_from_metadata`: seed, Waldo's size, stripe width); a demo written before that record has
them in summary.json (`room_seed`, `settings.waldo_scale`, `settings.stripe_width`), read as a fallback. Each
method's top-k shots become frustums `/topk/<method>/NN` of group `<method>` (their own colour and GUI folder in
`server`); a method's folder viewed alone (`waldo view runs/demo/egps`) shows all its views over the same room.
"""

from __future__ import annotations

import dataclasses
import functools
from pathlib import Path
from typing import Any, Dict, List, Optional

import numpy as np

from waldo_jax.errors import WaldoError
from waldo_jax.io import read_json_file
from waldo_jax.viewer.fields import Fields
from waldo_jax.viewer.scene import Frustum, ViewerError, ViewScene, explore_scene, room_points

__all__ = ["DemoRoom", "demo_methods", "demo_room", "demo_scene", "is_demo_output"]


@dataclasses.dataclass(frozen=True)
class DemoRoom:
    """The procedural room of a demo.

    Attributes:
      seed: the room's seed. metadata: `procedural.room_from_metadata`'s argument (seed, waldo_scale,
        stripe_width). recorded: whether the NeRF's checkpoint holds it (False: read from summary.json; a run
        rebuilt from the checkpoint alone has the default room, so scoring needs `metadata`).
    """

    seed: int
    metadata: Dict[str, Any]
    recorded: bool

    @functools.cached_property
    def room(self):
        """The `WaldoRoom`."""
        from waldo_jax.procedural import room_from_metadata

        return room_from_metadata(self.metadata)


def _summary(folder: Path) -> Optional[Dict[str, Any]]:
    """summary.json of a demo folder, or None where there is none or it is not a demo's."""
    path = folder / "summary.json"
    # is_file: a folder or a FIFO is no demo's summary (reading a FIFO had waited for a writer for ever). One
    # that is not JSON may be another tool's (this is also asked of an explore output's parent): not a demo.
    if not path.is_file():
        return None
    try:
        summary = read_json_file(path, "demo summary")
    except WaldoError:
        return None
    return summary if isinstance(summary, dict) and "room_seed" in summary else None


def demo_methods(folder: Path) -> List[Path]:
    """The method folders of a demo (explore outputs: results.json with `topk`), in summary.json's order."""
    summary = _summary(folder)
    methods = Fields(summary, Path(folder) / "summary.json").object("methods", None) if summary else None
    names = list(methods.data) if methods is not None else []
    names += sorted(p.name for p in Path(folder).iterdir() if p.is_dir() and p.name not in names)
    found = []
    for name in names:
        results = Path(folder) / name / "results.json"
        try:
            data = read_json_file(results, "results file") if results.is_file() else None
        except WaldoError:
            data = None
        if isinstance(data, dict) and "topk" in data and "found" not in data:
            found.append(Path(folder) / name)
    return found


def is_demo_output(folder: Path) -> bool:
    """Whether `folder` is a `waldo demo` output (a summary.json with `room_seed` and a method folder)."""
    return _summary(Path(folder)) is not None and bool(demo_methods(Path(folder)))


def demo_room(folder: Path) -> Optional[DemoRoom]:
    """The room of the demo in `folder` (the NeRF checkpoint's record, else summary.json's), or None where
    `folder` is not a demo."""
    folder = Path(folder)
    summary = _summary(folder)
    if summary is None:
        return None
    fields = Fields(summary, folder / "summary.json")  # each value by its key: one line naming it, no TypeError
    seed = fields.integer("room_seed")
    if (folder / "nerf" / "checkpoint.ckpt").is_file():
        from waldo_jax.nerf.checkpoint import load_checkpoint

        try:
            metadata = load_checkpoint(folder / "nerf").scene.metadata
        except WaldoError:
            metadata = {}
        if "waldo_scale" in metadata:
            return DemoRoom(int(metadata.get("seed", seed)), dict(metadata), True)
    settings = fields.object("settings", None) or Fields({}, folder / "summary.json", "settings")
    metadata = {"seed": seed, "waldo_scale": settings.number("waldo_scale", 1.0, positive=True)}
    if settings.has("stripe_width"):
        metadata["stripe_width"] = settings.number("stripe_width", positive=True)
    return DemoRoom(seed, metadata, False)


def _nerf_cameras(folder: Path, fallback: List[Frustum]) -> List[Frustum]:
    """The NeRF's training cameras (its checkpoint's), else the first method's training views."""
    try:
        from waldo_jax.nerf.checkpoint import load_checkpoint

        record = load_checkpoint(folder / "nerf").scene
    except (WaldoError, OSError):
        return fallback
    names = tuple(record.file_names)
    frustums = []
    for i, c2w in enumerate(np.asarray(record.c2w, np.float64)):
        label = f"NeRF training view {names[i] if i < len(names) else i}"
        frustums.append(Frustum(f"/train/{i:04d}", "train", c2w, None, None, None, label))
    return frustums


def demo_scene(folder: Path) -> ViewScene:
    """The `ViewScene` of a `waldo demo` output: its room as points, the NeRF's training cameras and each
    method's top-k shots (group = the method's folder name).

    Raises:
      ViewerError: no method folder in it (not a demo's output).
    """
    folder = Path(folder)
    methods = demo_methods(folder)
    room = demo_room(folder)
    if not methods or room is None:
        raise ViewerError(f"{folder}: not a `waldo demo` output (summary.json with room_seed, method folders)")
    scenes = [explore_scene(sub, geometry=False) for sub in methods]
    first = scenes[0]
    frustums = _nerf_cameras(folder, [f for f in first.frustums if f.kind == "train"])
    for sub, scene in zip(methods, scenes):
        for f in scene.frustums:
            if f.kind == "topk":
                name = f"/topk/{sub.name}/{f.topk_rank - 1:02d}"
                label = f"{sub.name.upper()} {f.label}"
                frustums.append(dataclasses.replace(f, name=name, label=label, group=sub.name))
    notes = [
        f"a `waldo demo`: the room (seed {room.seed}) and the top-k shots of {', '.join(m.name for m in methods)}, "
        f"one colour and panel folder per method (ranks within each method); `waldo view {methods[0]}` shows one "
        "method's every view"
    ]
    if not room.recorded:
        notes.append("the NeRF's checkpoint predates its room's record: the room is summary.json's (seed, size)")
    try:
        points = room_points(room.room, seed=room.seed)
    except (WaldoError, ValueError) as e:
        points = None
        notes.append(f"the room is not drawn: {e}")
    scores = tuple(s for scene in scenes for s in scene.scores)
    return dataclasses.replace(
        first,
        path=str(folder),
        title=f"waldo demo {folder.name}: {', '.join(m.name.upper() for m in methods)} on the room (seed {room.seed})",
        splats=None,
        points=points,
        frustums=tuple(frustums),
        notes=tuple(notes),
        scores=scores,
        room_metadata=None if room.recorded else room.metadata,
        output=folder,
    )
