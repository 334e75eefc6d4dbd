"""XLA settings that waldo_jax needs for correct results; imported first by `waldo_jax/__init__.py`.

jaxlib 0.10.2 on CPU miscompiles some fused reductions through its YNNPACK fusion: for example
`jax.vmap(lambda o: jnp.sum(n * (o - p), -1) / jnp.sqrt(jnp.sum((o - p) ** 2, -1)))` over 49 or
more cameras returns values off by O(1) (seen on x86-64, 2026-11; jaxlib 0.6 to 0.10.1 are correct).
Turning YNN fusions off (`--xla_cpu_experimental_ynn_fusion_type=`, a flag jaxlib knows from 0.8
on) restores exact results; `tests/test_xla_guard.py` checks it. The flag only concerns the CPU
backend and must be in XLA_FLAGS before JAX creates its CPU client, so import waldo_jax before
running any JAX computation. A user's own setting of that flag is left alone.
"""

from __future__ import annotations

import os
import warnings

_YNN_FLAG = "--xla_cpu_experimental_ynn_fusion_type"


def _jaxlib_version() -> tuple:
    try:
        from jaxlib import version as jaxlib_version

        return tuple(int(p) for p in jaxlib_version.__version__.split(".")[:3] if p.isdigit())
    except Exception:  # pragma: no cover - jaxlib always has a version module in practice
        return (0,)


def _backends_started() -> bool:
    try:
        from jax._src import xla_bridge

        return bool(getattr(xla_bridge, "_backends", {}))
    except Exception:  # pragma: no cover - private API moved
        return False


def apply() -> None:
    """Adds the YNN-fusion workaround to XLA_FLAGS when the installed jaxlib understands it."""
    flags = os.environ.get("XLA_FLAGS", "")
    if _YNN_FLAG in flags or _jaxlib_version() < (0, 8, 0):
        return
    if _backends_started():
        warnings.warn(
            "waldo_jax was imported after JAX started its backends, so the CPU workaround "
            f"{_YNN_FLAG}= could not be applied; import waldo_jax before running JAX code "
            "(or set XLA_FLAGS yourself) to avoid a jaxlib miscompilation on CPU.",
            RuntimeWarning,
            stacklevel=3,
        )
        return
    os.environ["XLA_FLAGS"] = f"{flags} {_YNN_FLAG}=".strip()


apply()
