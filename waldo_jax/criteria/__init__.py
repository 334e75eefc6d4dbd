"""Criteria: what a scene-space search maximises or minimises (the paper's "user criterion").

A `Criterion` scores a batch of views inside the search's jit; `make_criterion(name, context)`
builds one from the registry `CRITERIA` (the names `--criterion` accepts):

  * `waldo_oracle` (poses, max): the share of the image showing un-occluded Waldo, exact, for the
    procedural room;
  * `waldo_visible` (poses, max): the visible fraction of Waldo, exact, for the procedural room;
  * `colorfulness` (images, max): Hasler and Suesstrunk's colourfulness M;
  * `saliency` (images, max, [0, 1]): share of pixels CSNet-L-x1 finds salient (> 0.5), the
    paper's BASNet salient-pixel count;
  * `iqa_cnn` (images, max): CNNIQA's quality, 100 - predicted LIVE DMOS;
  * `niqe`, `brisque` (images, min): the classic no-reference quality models;
  * `composition` (images, max, [1, 5]): rule-based composition from the CSNet saliency map;
  * `waldo` (images, max): best normalised cross-correlation with a reference image (`--target`);
  * `opacity` (renders, max, [0, 1]): mean accumulated opacity, the guard against empty views.

`build_criterion(spec, context, guards)` (in `combine`) adds `weighted:NAME=W,...` and `--guard`
(`constrained`) on top of the registry.
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
from waldo_jax.criteria.base import CRITERIA as CRITERIA
from waldo_jax.criteria.base import Criterion as Criterion
from waldo_jax.criteria.base import CriterionContext as CriterionContext
from waldo_jax.criteria.base import CriterionError as CriterionError
from waldo_jax.criteria.base import CriterionSpec as CriterionSpec
from waldo_jax.criteria.base import make_criterion as make_criterion
from waldo_jax.criteria.base import register as register
from waldo_jax.criteria.combine import build_criterion as build_criterion
from waldo_jax.criteria.combine import constrained as constrained
from waldo_jax.criteria.combine import weighted as weighted
