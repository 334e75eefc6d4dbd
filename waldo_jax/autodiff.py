"""Which way the derivative being traced runs, for derivative rules whose fast form depends on it.

A rule of a linear op can be fast in one mode only: written as the transpose of the op's adjoint, reverse
mode (which transposes it again) runs the adjoint in the op's own gathering form, while forward mode
runs the transposed form, padded copies that are several times slower on a CPU. `search.refine` traces
its six forward-mode tangents inside `tangents("forward")`, and such a rule (CSNet's depthwise
convolutions and upsampling) then lets autodiff differentiate the op's own form. Only speed depends on
it: both forms give the same derivative (to float rounding), and a trace reads the mode once, at trace
time, so a compiled program is always one or the other.
"""

from __future__ import annotations

import contextlib
import contextvars
from typing import Iterator

__all__ = ["MODES", "tangents", "forward_tangents"]

MODES = ("forward", "reverse")
_MODE: contextvars.ContextVar[str] = contextvars.ContextVar("waldo_jax_tangents", default="reverse")


@contextlib.contextmanager
def tangents(mode: str) -> Iterator[None]:
    """Traces inside run derivatives in `mode` ("forward" or "reverse"; outside: "reverse")."""
    if mode not in MODES:
        raise ValueError(f"derivative mode must be one of {MODES}, got {mode!r}")
    token = _MODE.set(mode)
    try:
        yield
    finally:
        _MODE.reset(token)


def forward_tangents() -> bool:
    """True inside `tangents("forward")`: rules should let autodiff push the tangents forward."""
    return _MODE.get() == "forward"
