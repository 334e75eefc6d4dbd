"""The search methods by name: the paper's three, MAP-Elites, their `+refine` variants and any evosax strategy.

`METHODS` holds the fixed ones ("grs", "pibs", "egps", "map-elites" and each + "+refine");
`get_method(name)` also builds "evosax:NAME" for any strategy of evosax's registry.
"""

from waldo_jax.search import egps, grs, map_elites, pibs
from waldo_jax.search.method import SearchMethod
from waldo_jax.search.refine import refined_method
from waldo_jax.search.strategy import PREFIX as EVOSAX_PREFIX
from waldo_jax.search.strategy import evosax_method

__all__ = ["METHODS", "PAPER_METHODS", "get_method", "method_names"]

PAPER_METHODS = {"grs": grs.METHOD, "pibs": pibs.METHOD, "egps": egps.METHOD}
_BASE_METHODS = dict(PAPER_METHODS, **{"map-elites": map_elites.METHOD})
METHODS = dict(_BASE_METHODS, **{f"{name}+refine": refined_method(method) for name, method in _BASE_METHODS.items()})


def method_names() -> str:
    """The method names a user can give, in words (for help texts and errors)."""
    return ", ".join(METHODS) + f", {EVOSAX_PREFIX}NAME (any evosax strategy, e.g. {EVOSAX_PREFIX}CMA_ES)"


def get_method(name: str) -> SearchMethod:
    """The method called `name`.

    Raises:
      ValueError: an unknown name or evosax strategy (the message lists the choices).
    """
    if name in METHODS:
        return METHODS[name]
    if isinstance(name, str) and name.startswith(EVOSAX_PREFIX):
        return evosax_method(name[len(EVOSAX_PREFIX) :])
    raise ValueError(f"unknown search method {name!r}; choose one of {method_names()}")
