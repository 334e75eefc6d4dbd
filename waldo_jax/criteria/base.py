"""The criterion interface: what a search maximises (or minimises), as a pure, batched function.

A `Criterion` is a pytree whose numeric `params` (network weights, the procedural room, ...) are
traced leaves and whose name, direction and function are static. It scores P views in one call as
float32 [P] (NaN marks a failure, never selected), from one of four `inputs`: "images" (float32
[P, H, W, 3] in [0, 1]), "renders" (rgba float32 [P, H, W, 4]: the colour and the renderer's
opacity), "poses" (c2w float32 [P, 4, 4] and intrinsics, for oracles that need no render) or
"posed" (renders and their poses: a combination of pose and view criteria, `criteria.combine`).
`make_criterion(name, context)` builds one from the registry; `CriterionContext` carries what some
criteria need (the procedural room, a weights folder, a target image, the training cameras).

The inputs in detail: see docs/design.md, section "Criteria > The interface".
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Any, Callable, Dict, Iterable, NamedTuple, Optional, Tuple

import flax.struct
import jax
import jax.numpy as jnp
import numpy as np

from waldo_jax.errors import WaldoError
from waldo_jax.types import Array, Intrinsics

__all__ = [
    "INPUTS",
    "INPUT_NEEDS",
    "InputNeeds",
    "Views",
    "rendered_views",
    "combined_inputs",
    "criterion_args",
    "views_of_args",
    "Criterion",
    "CriterionContext",
    "CriterionError",
    "CriterionSpec",
    "register",
    "make_criterion",
    "check_registered",
    "CRITERIA",
    "worst_score",
    "finite_or_worst",
    "sanitize_images",
    "with_opacity",
]


class InputNeeds(NamedTuple):
    """What a kind of criterion input needs of a view: `render` (the view rendered), `opacity` (its
    renderer's opacity with the colour, rgba) and `pose` (its camera, c2w and intrinsics)."""

    render: bool
    opacity: bool
    pose: bool


# The one place that says what each kind of `Criterion.inputs` is; everything else asks `Criterion.needs`.
INPUT_NEEDS: Dict[str, InputNeeds] = {
    "images": InputNeeds(render=True, opacity=False, pose=False),
    "renders": InputNeeds(render=True, opacity=True, pose=False),
    "poses": InputNeeds(render=False, opacity=False, pose=True),
    "posed": InputNeeds(render=True, opacity=True, pose=True),
}
INPUTS = tuple(INPUT_NEEDS)


class Views(NamedTuple):
    """P views of a scene, as a criterion scores them (a pytree: it passes through jit and vmap).

    Attributes:
      rgba: float32 [P, H, W, 4] renders (colour and opacity), or [P, H, W, 3] photographs (opacity 1);
        None where only the poses are scored.
      c2w: float32 [P, 4, 4] camera-to-world poses; None where only the pixels are scored.
      intrinsics: the cameras' `Intrinsics` (with `c2w`), or None.
    """

    rgba: Optional[Array] = None
    c2w: Optional[Array] = None
    intrinsics: Optional[Intrinsics] = None


def rendered_views(rgb: Array, acc: Array, c2w: Array, intrinsics: Intrinsics) -> Views:
    """`Views` of a renderer's output: rgba [P, H, W, 4] from the colour rgb [P, H, W, 3] and the
    accumulated opacity acc [P, H, W], with the cameras that rendered them."""
    return Views(jnp.concatenate([rgb, acc[..., None]], axis=-1), c2w, intrinsics)


def criterion_args(inputs: str, views: Views) -> tuple:
    """The arguments after `params` that a criterion of these `inputs` takes from `views`: (images,),
    (rgba,), (c2w, intrinsics) or (rgba, c2w, intrinsics)."""
    needs = INPUT_NEEDS[inputs]
    pixels = ()
    if needs.render:
        pixels = (with_opacity(views.rgba),) if needs.opacity else (views.rgba[..., :3],)
    return pixels + ((views.c2w, views.intrinsics) if needs.pose else ())


def views_of_args(inputs: str, args: tuple) -> Views:
    """`Views` from the arguments a criterion of these `inputs` takes (the inverse of `criterion_args`)."""
    needs = INPUT_NEEDS[inputs]
    rgba = args[0] if needs.render else None
    return Views(rgba, *args[int(needs.render) :]) if needs.pose else Views(rgba)


def combined_inputs(kinds: Iterable[str]) -> str:
    """The inputs of a combination of criteria with these `inputs`: "poses" when all score poses,
    "posed" when some score poses and some views, else "renders" when any needs the opacity, else "images"."""
    needs = [INPUT_NEEDS[kind] for kind in kinds]
    render, pose = any(n.render for n in needs), any(n.pose for n in needs)
    opacity = any(n.opacity for n in needs) or (render and pose)
    return next(kind for kind, n in INPUT_NEEDS.items() if n == InputNeeds(render, opacity, pose))


class CriterionError(WaldoError, ValueError):
    """An unknown criterion name, or a criterion that cannot be built from what was given."""


@flax.struct.dataclass
class Criterion:
    """A scoring function for a population of views.

    Attributes:
      params: pytree of arrays the function needs (traced under jit).
      name: registry name, e.g. "waldo_oracle".
      direction: "max" when higher scores are better, "min" when lower ones are.
      value_range: (low, high) of the scores (inf where unbounded), for plots and reports.
      inputs: "images", "renders", "poses" or "posed" (`INPUT_NEEDS`; docs/design.md, "Criteria").
      apply: the pure function, `apply(params, images)`, `apply(params, rgba)`,
        `apply(params, c2w, intrinsics)` or `apply(params, rgba, c2w, intrinsics)` (`criterion_args`);
        `evaluate(views)` calls it on any `Views`.
      description: one line for reports and `--help`.
      smooth_apply: a differentiable stand-in for `apply` (same params and inputs) that gradient
        refinement follows, or None when the criterion has none (`smooth` refuses it). For a
        differentiable criterion it is `apply` itself; where `apply` counts or thresholds (the
        salient fraction, the oracles' in-frame test) a sigmoid replaces the step.
    """

    params: Any
    name: str = flax.struct.field(pytree_node=False, default="")
    direction: str = flax.struct.field(pytree_node=False, default="max")
    value_range: Tuple[float, float] = flax.struct.field(pytree_node=False, default=(-np.inf, np.inf))
    inputs: str = flax.struct.field(pytree_node=False, default="images")
    apply: Callable = flax.struct.field(pytree_node=False, default=None)
    description: str = flax.struct.field(pytree_node=False, default="")
    smooth_apply: Optional[Callable] = flax.struct.field(pytree_node=False, default=None)

    @property
    def needs(self) -> InputNeeds:
        """What the criterion needs of a view (`INPUT_NEEDS` of its `inputs`)."""
        return INPUT_NEEDS[self.inputs]

    def evaluate(self, views: Views) -> Array:
        """Scores [P] of `views` (traced: for use inside jit, vmap and grad)."""
        return self.apply(self.params, *criterion_args(self.inputs, views))

    def score_views(self, views: Views) -> Array:
        """Scores [P] of `views`, as one compiled program per shape (for host code)."""
        return jnp.asarray(_compiled(self.apply, self.params, *criterion_args(self.inputs, views)), jnp.float32)

    @property
    def differentiable(self) -> bool:
        """Whether gradient refinement can use the criterion (it has a `smooth_apply`)."""
        return self.smooth_apply is not None

    def smooth(self) -> "Criterion":
        """This criterion with `smooth_apply` as its function: the objective of gradient refinement.

        Raises:
          CriterionError: the criterion has no differentiable stand-in (the message lists those that do).
        """
        if self.smooth_apply is None:
            usable = ", ".join(sorted(name for name, spec in CRITERIA.items() if spec.smooth))
            raise CriterionError(
                f"criterion {self.name!r} is not differentiable and has no smooth stand-in, so gradient "
                f"refinement (the +refine methods) cannot follow it; use a method without +refine, or one of: {usable}"
            )
        return self.replace(apply=self.smooth_apply, name=self.name + ":smooth")

    def score_images(self, images: Array) -> Array:
        """Scores [P] of images float32 [P, H, W, 3] in [0, 1] (photographs: opacity 1).

        Also takes rgba renders [P, H, W, 4]; an "images" criterion ignores their opacity and a
        "renders" criterion given colour alone treats every pixel as opaque.
        """
        if not self.needs.render:
            raise CriterionError(f"criterion {self.name!r} scores camera poses, not images")
        if self.needs.pose:
            raise CriterionError(
                f"criterion {self.name!r} scores renders together with their camera poses, "
                "not images alone (`score_posed`)"
            )
        images = jnp.asarray(images, jnp.float32)
        if images.ndim != 4 or images.shape[-1] not in (3, 4):
            raise CriterionError(
                f"criterion {self.name!r} expects images [P, H, W, 3] (or rgba [P, H, W, 4]), got shape {images.shape}"
            )
        return self.score_views(Views(images))

    def score_poses(self, c2w: Array, intrinsics: Intrinsics) -> Array:
        """Scores [P] of cameras c2w [P, 4, 4] with the given intrinsics (a "poses" criterion)."""
        if self.needs.render:
            raise CriterionError(f"criterion {self.name!r} scores images: render the poses first")
        return self.score_views(Views(None, jnp.asarray(c2w, jnp.float32), intrinsics))

    def score_posed(self, images: Array, c2w: Array, intrinsics: Intrinsics) -> Array:
        """Scores [P] of renders [P, H, W, 4] (or photographs [P, H, W, 3], opacity 1) taken from cameras
        c2w [P, 4, 4] with `intrinsics`: any criterion but an image criterion given poses alone."""
        if not self.needs.pose:
            return self.score_images(images)
        return self.score_views(Views(jnp.asarray(images, jnp.float32), jnp.asarray(c2w, jnp.float32), intrinsics))


@functools.partial(jax.jit, static_argnums=0)
def _compiled(apply: Callable, *args) -> Array:
    """`apply(*args)` as one compiled program: called from host code, a criterion runs as one XLA
    program per input shape instead of one small program per operation (inside a trace it is inlined)."""
    return apply(*args)


def worst_score(direction: str, value_range: Tuple[float, float]) -> float:
    """The finite score a failed view gets: the bad end of `value_range` (which must be finite there)."""
    worst = value_range[0] if direction == "max" else value_range[1]
    if not np.isfinite(worst):
        raise ValueError(f"the bad end of value_range {value_range} (direction {direction}) must be finite")
    return float(worst)


def with_opacity(images: Array) -> Array:
    """rgba [P, H, W, 4]: `images` as given if they have 4 channels, else colour with opacity 1."""
    images = jnp.asarray(images, jnp.float32)
    if images.shape[-1] == 4:
        return images
    return jnp.concatenate([images, jnp.ones_like(images[..., :1])], axis=-1)


def sanitize_images(images: Array) -> Tuple[Array, Array]:
    """Images with NaN/inf replaced by 0 and clipped to [0, 1], and a mask [P] of the images that had any.

    Image criteria run on the sanitised images (so no NaN reaches a network) and then give the
    flagged images the worst score with `finite_or_worst`.
    """
    images = jnp.asarray(images, jnp.float32)
    bad = ~jnp.all(jnp.isfinite(images), axis=tuple(range(1, images.ndim)))  # [P]
    clean = jnp.clip(jnp.where(jnp.isfinite(images), images, 0.0), 0.0, 1.0)
    return clean, bad


def finite_or_worst(scores: Array, bad: Array, worst: float) -> Array:
    """Scores [P] with failed views (`bad`, or a non-finite score) set to the finite `worst`."""
    scores = jnp.asarray(scores, jnp.float32)
    return jnp.where(bad | ~jnp.isfinite(scores), jnp.float32(worst), scores)


@dataclasses.dataclass(frozen=True)
class CriterionContext:
    """What building a criterion may need (each criterion takes what it uses and names what is missing).

    Attributes:
      room: the procedural `WaldoRoom` of the source, for the oracles.
      weights_dir: folder in the `../shared/weights` layout (default: `WALDO_WEIGHTS`).
      target: reference image float32 [h, w, 3] of the object to find.
      source: the SOURCE the search runs on, in words (for error messages).
      train_c2w: float32 [N, 4, 4] the source's training camera poses, for `trust`.
    """

    room: Any = None
    weights_dir: Optional[str] = None
    target: Optional[np.ndarray] = None
    source: str = ""
    train_c2w: Optional[np.ndarray] = None


@dataclasses.dataclass(frozen=True)
class CriterionSpec:
    """A registry entry: how to build a criterion, and what it is.

    Attributes:
      name: the registry name.
      direction: "max" or "min".
      inputs: one of `INPUTS`.
      description: one line.
      build: `build(context) -> Criterion`; raises `CriterionError` naming anything missing.
      smooth: the criterion it builds has a `smooth_apply` (gradient refinement can use it).
      reads: the `CriterionContext` fields of a user's choosing that `build` uses ("weights_dir",
        "target"), so that a command can say when a flag giving one has no effect.
    """

    name: str
    direction: str
    inputs: str
    description: str
    build: Callable[[CriterionContext], Criterion]
    smooth: bool = False
    reads: Tuple[str, ...] = ()

    @property
    def needs(self) -> InputNeeds:
        """What the criterion it builds needs of a view (`INPUT_NEEDS` of its `inputs`)."""
        return INPUT_NEEDS[self.inputs]


CRITERIA: Dict[str, CriterionSpec] = {}


def register(spec: CriterionSpec) -> CriterionSpec:
    """Adds a criterion to the registry (by `spec.name`; a second registration of a name is an error)."""
    if spec.direction not in ("max", "min"):
        raise ValueError(f"criterion {spec.name!r}: direction must be 'max' or 'min', got {spec.direction!r}")
    if spec.inputs not in INPUTS:
        raise ValueError(f"criterion {spec.name!r}: inputs must be one of {INPUTS}, got {spec.inputs!r}")
    unknown = [field for field in spec.reads if field not in ("weights_dir", "target")]
    if unknown:
        raise ValueError(f"criterion {spec.name!r}: reads names no user-chosen context field: {unknown}")
    if spec.name in CRITERIA and CRITERIA[spec.name] is not spec:
        raise ValueError(f"criterion {spec.name!r} is already registered")
    CRITERIA[spec.name] = spec
    return spec


def check_registered(name: str) -> None:
    """Raises `CriterionError` (listing the registered names) when `name` is not in the registry."""
    if name not in CRITERIA:
        raise CriterionError(f"unknown criterion {name!r}; choose one of {', '.join(sorted(CRITERIA))}")


def make_criterion(name: str, context: Optional[CriterionContext] = None) -> Criterion:
    """Builds the registered criterion `name`.

    Raises:
      CriterionError: unknown name (the message lists the registered ones) or missing context.
    """
    check_registered(name)
    criterion = CRITERIA[name].build(context or CriterionContext())
    if (
        criterion.name != name
        or criterion.direction != CRITERIA[name].direction
        or criterion.differentiable != CRITERIA[name].smooth
    ):
        raise AssertionError(f"criterion {name!r} built with a mismatching name or direction")  # a registry bug
    return criterion
