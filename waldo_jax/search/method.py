"""The interface every search method of `waldo_jax.search` implements (one method per module).

A method is three things kept apart, as in evosax:
  * `Params`: a pytree of its numeric hyper-parameters (mutation probabilities, scales, ...), so a
    sweep can `vmap` over them;
  * `Config`: a frozen dataclass of static, shape-setting settings (`children_per_epoch`, PIBS's
    `top_c`, ...), built by `Config.create(children_per_epoch, epochs, method=name, **options)`,
    which refuses an option the method does not have (`ConfigError` naming it and the method);
  * `ask(key, population, params, config, epoch) -> (children, child_mask, population')`: a
    pure function that draws one epoch's children from the population. `children` is a `Pose` with
    [children_per_epoch, 3] fields, `child_mask` a bool [children_per_epoch] telling which children
    are real (masked ones are neither counted nor kept, but still have finite poses so a
    fixed-shape renderer can process them), and `population'` the population with the method's own
    bookkeeping updated (PIBS's explored pairs); the children are not written yet.

A method may also carry a state across epochs (evosax strategies: their search distribution; the
`+refine` methods: their base method's state). Such a method has `init` and `tell` as well, and its
`ask` takes and returns the state and receives the differentiable objective:
  * `init(key, population, params, config) -> state`, once, from the scored training views;
  * `ask(key, population, state, params, config, epoch, objective)
    -> (children, child_mask, population', state')`;
  * `tell(key, state, fitness, params, config) -> state'`, after the children are scored
    (`fitness` [children_per_epoch]: signed, higher is better, -inf for masked or failed children).
`SearchMethod.init`, `ask` and `tell` call either kind the same way, so `explore` carries
`(population, state)` through its scan whatever the method; a stateless method's state is `()` and
its random numbers are exactly those it drew before states existed.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Callable, Iterable, Mapping, Optional, Tuple

import jax

from waldo_jax.errors import ConfigError

__all__ = ["ChildrenConfig", "SearchMethod", "check_options", "split_for_state"]


def check_options(method: Optional[str], options: Mapping[str, Any], accepted: Iterable[str] = ()) -> None:
    """Raises `ConfigError` naming the first option of `options` (by name) that `method` does not accept."""
    accepted = tuple(accepted)
    unknown = sorted(name for name in options if name not in accepted)
    if unknown:
        who = "this search method" if method is None else f"search method {method!r}"
        choices = ", ".join(accepted) if accepted else "none"
        raise ConfigError(f"{who} has no option {unknown[0]!r} (its options: {choices})")


@dataclasses.dataclass(frozen=True)
class ChildrenConfig:
    """Static settings of a method whose only static setting is its child count (GRS, EGPS).

    Attributes:
      children_per_epoch: poses proposed per epoch.
    """

    children_per_epoch: int

    # The options `create` accepts besides children_per_epoch and epochs.
    OPTIONS = ()

    def __post_init__(self):
        if self.children_per_epoch < 1:
            raise ValueError(f"children_per_epoch must be >= 1, got {self.children_per_epoch}")

    @classmethod
    def create(
        cls, children_per_epoch: int, epochs: Optional[int] = None, method: Optional[str] = None, **options: Any
    ) -> "ChildrenConfig":
        """The config for `children_per_epoch` children (`epochs` unused).

        Raises:
          ConfigError: any option (this config has none); the message names it and `method`.
        """
        del epochs
        check_options(method, options, cls.OPTIONS)
        return cls(children_per_epoch=int(children_per_epoch))


@dataclasses.dataclass(frozen=True)
class SearchMethod:
    """One entry of the `waldo_jax.search.METHODS` registry (hashable: usable as a static argument).

    Its `init`, `ask` and `tell` methods run one method's protocol the same way whether or not it
    carries a state (the module docstring).

    Attributes:
      name: the registry key ("grs", "pibs", "egps").
      params_type: the method's `Params` class; `params_type()` gives the paper's defaults.
      config_type: the method's `Config` class, with a `create(children_per_epoch, epochs, method=name,
        **options)` constructor that refuses options the method does not have, and an `OPTIONS` tuple
        naming those it has.
      ask_fn: the method module's `ask` function.
      init_fn: for a method with a state, its `init(key, population, params, config) -> state`; None
        for a stateless method (GRS, PIBS, EGPS).
      tell_fn: for a method with a state, its `tell(key, state, fitness, params, config) -> state`.
      differentiable: the method takes gradient steps on the objective (the `+refine` methods), so
        `explore` must be given a differentiable one.
    """

    name: str
    params_type: Callable[[], Any]
    config_type: Any
    ask_fn: Callable[..., Any]
    init_fn: Optional[Callable[..., Any]] = None
    tell_fn: Optional[Callable[..., Any]] = None
    differentiable: bool = False

    @property
    def stateful(self) -> bool:
        """Whether the method carries a state across epochs (`init_fn` / `tell_fn`)."""
        return self.init_fn is not None

    @property
    def options(self) -> Tuple[str, ...]:
        """The names of the options its config takes (`make_config`): e.g. ("top_c", "fallback") for PIBS."""
        return tuple(self.config_type.OPTIONS)

    def default_params(self) -> Any:
        """The paper's numeric hyper-parameters for this method."""
        return self.params_type()

    def make_config(self, children_per_epoch: int, epochs: Optional[int] = None, **options: Any) -> Any:
        """The method's static `Config` for `children_per_epoch` children per epoch over `epochs` epochs.

        Raises:
          ConfigError: an option the method does not have (the message names it and the method).
        """
        return self.config_type.create(children_per_epoch, epochs, method=self.name, **options)

    def init(self, key, population, params, config) -> Any:
        """The method's state before epoch 1 (`()` for a stateless method, which does not use the key)."""
        return () if self.init_fn is None else self.init_fn(key, population, params, config)

    def ask(self, key, population, state, params, config, epoch, objective) -> Tuple[Any, Any, Any, Any]:
        """One epoch's (children, child_mask, population', state') for either kind of method."""
        if self.init_fn is None:
            children, mask, population = self.ask_fn(key, population, params, config, epoch)
            return children, mask, population, state
        return self.ask_fn(key, population, state, params, config, epoch, objective)

    def tell(self, key, state, fitness, params, config) -> Any:
        """The state after the epoch's children were scored (unchanged for a stateless method)."""
        return state if self.tell_fn is None else self.tell_fn(key, state, fitness, params, config)


def split_for_state(key: jax.Array, method: SearchMethod) -> Tuple[jax.Array, jax.Array]:
    """(ask key, tell key) of one epoch: a stateless method gets the epoch key itself (so GRS, PIBS
    and EGPS draw what they always drew), a method with a state two keys split from it."""
    if not method.stateful:
        return key, key
    ask_key, tell_key = jax.random.split(key)
    return ask_key, tell_key
