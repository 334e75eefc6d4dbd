"""Criteria: what a scene-space search maximises or minimises (the paper's "user criterion").

A `Criterion` scores a batch of views inside the search's jit; `make_criterion(name, context)`
builds one from the registry `CRITERIA` (the names `--criterion` accepts): the procedural room's
oracles `waldo_oracle` and `waldo_visible`, and `trust` (the training cameras' coverage), on poses;
`colorfulness`, `saliency` (CSNet), `iqa_cnn` (CNNIQA), `niqe`, `brisque`, `composition` and `waldo`
(the finder, with `--target`) on images; `opacity` on renders. `build_criterion(spec, context, guards)`
(in `combine`) adds `weighted:NAME=W,...` and `--guard` (`constrained`) on top of the registry.
Every criterion scores `Views` (renders, poses, intrinsics) through `Criterion.evaluate`; what its
kind of input needs is `criterion.needs` (`INPUT_NEEDS`).

What each criterion scores, with its input, direction and range: see docs/design.md, section
"Criteria > The registry".
"""

from waldo_jax.criteria import brisque as brisque
from waldo_jax.criteria import cnniqa as cnniqa
from waldo_jax.criteria import colorfulness as colorfulness
from waldo_jax.criteria import combine as combine
from waldo_jax.criteria import composition as composition
from waldo_jax.criteria import csnet as csnet
from waldo_jax.criteria import finder as finder
from waldo_jax.criteria import niqe as niqe
from waldo_jax.criteria import oracle as oracle
from waldo_jax.criteria import trust as trust
from waldo_jax.criteria.base import CRITERIA as CRITERIA
from waldo_jax.criteria.base import Criterion as Criterion
from waldo_jax.criteria.base import CriterionContext as CriterionContext
from waldo_jax.criteria.base import CriterionError as CriterionError
from waldo_jax.criteria.base import CriterionSpec as CriterionSpec
from waldo_jax.criteria.base import INPUT_NEEDS as INPUT_NEEDS
from waldo_jax.criteria.base import InputNeeds as InputNeeds
from waldo_jax.criteria.base import Views as Views
from waldo_jax.criteria.base import make_criterion as make_criterion
from waldo_jax.criteria.base import register as register
from waldo_jax.criteria.combine import build_criterion as build_criterion
from waldo_jax.criteria.combine import constrained as constrained
from waldo_jax.criteria.combine import weighted as weighted
