"""The viewer's own renders: the current camera rendered by the run's renderer, and scored by its criterion.

`LiveView` loads the SOURCE of what `waldo view` shows (an explore output's source, or the SOURCE given)
the first time it is asked, at the run's resolution capped to `MAX_LIVE_SIDE` pixels a side (a render
on demand must come back in seconds on a CPU), and builds the run's criterion from its recorded name
(`criterion_spec`: a guarded `PRIMARY|GUARD>=T` back into `build_criterion`'s spec and guards, with the
source's room and training poses). A score is placed among the search's own scores: the rank it would have had.

Poses are OpenGL camera-to-world [4, 4], as everywhere in waldo_jax; `opengl_c2w` turns a browser
camera (viser's OpenCV convention: wxyz and position) into one.
"""

from __future__ import annotations

from typing import List, Optional, Tuple

import numpy as np

from waldo_jax.errors import WaldoError
from waldo_jax.viewer.scene import quaternion_matrices

__all__ = ["MAX_LIVE_SIDE", "LiveView", "criterion_spec", "opengl_c2w"]

MAX_LIVE_SIDE = 128
_OPENCV_TO_OPENGL = np.diag([1.0, -1.0, -1.0])


def opengl_c2w(wxyz, position) -> np.ndarray:
    """The OpenGL camera-to-world [4, 4] of a camera given as viser gives it (OpenCV axes: x right, y down,
    z forward; rotation as a unit quaternion w, x, y, z)."""
    wxyz = np.asarray(wxyz, np.float64)
    rotation = quaternion_matrices(wxyz / np.linalg.norm(wxyz))
    c2w = np.eye(4)
    c2w[:3, :3] = rotation @ _OPENCV_TO_OPENGL
    c2w[:3, 3] = np.asarray(position, np.float64)
    return c2w


def criterion_spec(name: str) -> Tuple[str, List[str]]:
    """(spec, guards) that `build_criterion` takes for a criterion's recorded name.

    A guarded criterion is recorded as `PRIMARY|GUARD>=T|...` (`criteria.combine.constrained`, "<=" for a
    "min" guard); its guards come back as `GUARD:T`, in order.

    Raises:
      WaldoError: a `|` part that is no `GUARD>=T` / `GUARD<=T`.
    """
    primary, *guarded = name.split("|")
    guards = []
    for part in guarded:
        relation = ">=" if ">=" in part else "<=" if "<=" in part else None
        if relation is None:
            raise WaldoError(f"criterion {name!r}: {part!r} is not a guard GUARD>=T or GUARD<=T")
        guard, _, threshold = part.partition(relation)
        guards.append(f"{guard}:{threshold}")
    return primary, guards


class LiveView:
    """Renders and scores poses of one SOURCE with one criterion, loading both on first use.

    Args:
      spec: the SOURCE string ("" where there is none: nothing can be rendered).
      criterion: the criterion's name as results.json gives it ("" for a SOURCE alone: no score).
      resolution: (width, height) of the run's renders, or None (the source's own).
      scores: the search's scores (training views and generated ones), for the rank of a new score.
      direction: "max" or "min", the criterion's.
      room_metadata: the procedural room's metadata (`procedural.room_from_metadata`) where the source's
        checkpoint does not record it (a `waldo demo` run older than that record), else None.
    """

    def __init__(
        self,
        spec: str,
        criterion: str = "",
        resolution: Optional[Tuple[int, int]] = None,
        scores: Tuple[Optional[float], ...] = (),
        direction: str = "max",
        room_metadata: Optional[dict] = None,
    ):
        self.spec, self.criterion_name, self.direction = spec, criterion, direction
        self.room_metadata = room_metadata
        side = max(resolution) if resolution else MAX_LIVE_SIDE
        self.side = int(min(side, MAX_LIVE_SIDE))
        self.scores: List[float] = [float(s) for s in scores if s is not None and np.isfinite(s)]
        self._source = None
        self._score_fn = None

    @property
    def source(self):
        """The loaded `waldo_jax.pipeline.Source` (loaded on first use)."""
        if self._source is None:
            if not self.spec:
                raise WaldoError("nothing to render: this view has no SOURCE")
            from waldo_jax.pipeline import load_source

            self._source = load_source(self.spec, resolution=self.side)
        return self._source

    def render(self, c2w: np.ndarray) -> np.ndarray:
        """The source's render of one OpenGL c2w [4, 4]: float32 [H, W, 3] in [0, 1]."""
        import jax.numpy as jnp

        image = self.source.render(jnp.asarray(np.asarray(c2w, np.float32)[None]))
        return np.clip(np.asarray(image, np.float32)[0], 0.0, 1.0)

    def score(self, c2w: np.ndarray) -> Tuple[float, Optional[int]]:
        """(score, rank it would have among the search's scores, 1 = best; None where it is not finite)."""
        if not self.criterion_name:
            raise WaldoError("no criterion to score with: view an explore output to score its views")
        import jax.numpy as jnp

        if self._score_fn is None:
            from waldo_jax.criteria import CriterionContext
            from waldo_jax.criteria.combine import build_criterion
            from waldo_jax.pipeline.experiment import score_function

            source = self.source
            room = source.room
            if self.room_metadata is not None:
                from waldo_jax.procedural import room_from_metadata

                room = room_from_metadata(self.room_metadata)
            context = CriterionContext(room=room, source=self.spec, train_c2w=source.train_c2w)
            spec, guards = criterion_spec(self.criterion_name)
            self._score_fn = score_function(source, build_criterion(spec, context, guards))
        value = float(np.asarray(self._score_fn(jnp.asarray(np.asarray(c2w, np.float32)[None])))[0])
        if not np.isfinite(value):
            return value, None
        better = sum(1 for s in self.scores if (s > value if self.direction != "min" else s < value))
        return value, better + 1
