"""The interface every search method of `waldo_jax.search` implements (one method per module).

A method is three things kept apart, as in evosax:
  * `Params`: a pytree of its numeric hyper-parameters (mutation probabilities, scales, ...), so a
    sweep can `vmap` over them;
  * `Config`: a frozen dataclass of static, shape-setting settings (`children_per_epoch`, ...);
  * `propose(key, population, params, config, epoch) -> (children, child_mask, population')`: a
    pure function that draws one epoch's children from the population. `children` is a `Pose` with
    [children_per_epoch, 3] fields, `child_mask` a bool [children_per_epoch] telling which children
    are real (masked ones are neither counted nor kept, but still have finite poses so a
    fixed-shape renderer can process them), and `population'` the population with the method's own
    bookkeeping updated (PIBS's explored pairs); the children are not written yet.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Callable

__all__ = ["ChildrenConfig", "SearchMethod"]


@dataclasses.dataclass(frozen=True)
class ChildrenConfig:
    """Static settings of a method whose only static setting is its child count (GRS, EGPS).

    Attributes:
      children_per_epoch: poses proposed per epoch.
    """

    children_per_epoch: int

    def __post_init__(self):
        if self.children_per_epoch < 1:
            raise ValueError(f"children_per_epoch must be >= 1, got {self.children_per_epoch}")

    @classmethod
    def create(cls, children_per_epoch: int, **options: Any) -> "ChildrenConfig":
        """Ignores the options of other methods (e.g. PIBS's top_c)."""
        del options
        return cls(children_per_epoch=int(children_per_epoch))


@dataclasses.dataclass(frozen=True)
class SearchMethod:
    """One entry of the `waldo_jax.search.METHODS` registry (hashable: usable as a static argument).

    Attributes:
      name: the registry key ("grs", "pibs", "egps").
      params_type: the method's `Params` class; `params_type()` gives the paper's defaults.
      config_type: the method's `Config` class, with a `create(children_per_epoch, **options)`
        constructor that ignores the options of other methods.
      propose: the method's `propose` function.
    """

    name: str
    params_type: type
    config_type: type
    propose: Callable[..., Any]

    def default_params(self) -> Any:
        """The paper's numeric hyper-parameters for this method."""
        return self.params_type()

    def make_config(self, children_per_epoch: int, **options: Any) -> Any:
        """The method's static `Config` for `children_per_epoch` children per epoch."""
        return self.config_type.create(children_per_epoch, **options)
