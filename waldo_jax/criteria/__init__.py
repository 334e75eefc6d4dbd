"""Criteria: what a scene-space search maximises or minimises (the paper's "user criterion").

A `Criterion` scores a batch of views inside the search's jit; `make_criterion(name, context)`
builds one from the registry `CRITERIA` (the names `--criterion` accepts):

  * `waldo_oracle` (poses, max): the share of the image showing un-occluded Waldo, exact, for the
    procedural room;
  * `waldo_visible` (poses, max): the visible fraction of Waldo, exact, for the procedural room;
  * `colorfulness` (images, max): Hasler and Suesstrunk's colourfulness M.
"""

from waldo_jax.criteria import colorfulness as colorfulness
from waldo_jax.criteria import oracle as oracle
from waldo_jax.criteria.base import CRITERIA as CRITERIA
from waldo_jax.criteria.base import Criterion as Criterion
from waldo_jax.criteria.base import CriterionContext as CriterionContext
from waldo_jax.criteria.base import CriterionError as CriterionError
from waldo_jax.criteria.base import CriterionSpec as CriterionSpec
from waldo_jax.criteria.base import make_criterion as make_criterion
from waldo_jax.criteria.base import register as register
