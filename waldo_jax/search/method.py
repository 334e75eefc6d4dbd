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

A method may also carry a state across epochs (evosax strategies: their search distribution; the
`+refine` methods: their base method's state). Such a method sets `init` and `tell`, and its
`propose` takes and returns the state and receives the differentiable objective as well:
  * `init(key, population, params, config) -> state`, once, from the scored training views;
  * `propose(key, population, state, params, config, epoch, objective)
    -> (children, child_mask, population', state')`;
  * `tell(key, state, fitness, params, config) -> state'`, after the children are scored
    (`fitness` [children_per_epoch]: signed, higher is better, -inf for masked or failed children).
`SearchMethod.start`, `ask` and `told` call either kind the same way, so `explore` carries
`(population, state)` through its scan whatever the method; a stateless method's state is `()` and
its random numbers are exactly those it drew before states existed.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Callable, Optional, Tuple

import jax

__all__ = ["ChildrenConfig", "SearchMethod", "split_for_state"]


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
      init: for a method with a state, `init(key, population, params, config) -> state`; None for a
        stateless method (GRS, PIBS, EGPS).
      tell: for a method with a state, `tell(key, state, fitness, params, config) -> state`.
      differentiable: the method takes gradient steps on the objective (the `+refine` methods), so
        `explore` must be given a differentiable one.
    """

    name: str
    params_type: Callable[[], Any]
    config_type: Any
    propose: Callable[..., Any]
    init: Optional[Callable[..., Any]] = None
    tell: Optional[Callable[..., Any]] = None
    differentiable: bool = False

    @property
    def stateful(self) -> bool:
        """Whether the method carries a state across epochs (`init` / `tell`)."""
        return self.init is not None

    def default_params(self) -> Any:
        """The paper's numeric hyper-parameters for this method."""
        return self.params_type()

    def make_config(self, children_per_epoch: int, **options: Any) -> Any:
        """The method's static `Config` for `children_per_epoch` children per epoch."""
        return self.config_type.create(children_per_epoch, **options)

    def start(self, key, population, params, config) -> Any:
        """The method's state before epoch 1 (`()` for a stateless method, which does not use the key)."""
        return () if self.init is None else self.init(key, population, params, config)

    def ask(self, key, population, state, params, config, epoch, objective) -> Tuple[Any, Any, Any, Any]:
        """One epoch's (children, child_mask, population', state') for either kind of method."""
        if self.init is None:
            children, mask, population = self.propose(key, population, params, config, epoch)
            return children, mask, population, state
        return self.propose(key, population, state, params, config, epoch, objective)

    def told(self, key, state, fitness, params, config) -> Any:
        """The state after the epoch's children were scored (unchanged for a stateless method)."""
        return state if self.tell is None else self.tell(key, state, fitness, params, config)


def split_for_state(key: jax.Array, method: SearchMethod) -> Tuple[jax.Array, jax.Array]:
    """(propose key, tell key) of one epoch: a stateless method gets the epoch key itself (so GRS, PIBS
    and EGPS draw what they always drew), a method with a state two keys split from it."""
    if not method.stateful:
        return key, key
    ask_key, tell_key = jax.random.split(key)
    return ask_key, tell_key
