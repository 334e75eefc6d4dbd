"""Backend settings that waldo_jax needs for correct, reproducible results; imported first by
`waldo_jax/__init__.py`.

jaxlib 0.10.2 on CPU miscompiles some fused reductions through its YNNPACK fusion: for example
`jax.vmap(lambda o: jnp.sum(n * (o - p), -1) / jnp.sqrt(jnp.sum((o - p) ** 2, -1)))` over 49 or
more cameras returns values off by O(1) (seen on x86-64, 2026-11; jaxlib 0.6 to 0.10.1 are correct).
Turning YNN fusions off (`--xla_cpu_experimental_ynn_fusion_type=`, a flag jaxlib knows from 0.8
on) restores exact results; `tests/test_xla_guard.py` checks it. The flag only concerns the CPU
backend and must be in XLA_FLAGS before JAX creates its CPU client, so import waldo_jax before
running any JAX computation. A user's own setting of that flag is left alone.

A seed fixes a run bit for bit on every backend. On a GPU, XLA by default lets some operations
(scatter-adds, reductions through atomics, autotuned algorithms) give different float rounding
from run to run: the same `waldo explore` run twice on an H100 gave different `scores_generated`.
`--xla_gpu_deterministic_ops=true` makes them deterministic (the issue that asked for it reported
28.0 s and 31.2 s for that run on an H100 without and with it: the same within that machine's
noise; not re-measured here, no GPU was lent); it is added by default. Set `WALDO_DETERMINISTIC=0`
in the environment to leave it out (faster on some GPU workloads, no longer bit-identical reruns
there); a user's own setting of it, or of
`--xla_gpu_exclude_nondeterministic_ops`, is left alone. It changes nothing on a CPU.

The same scores on every backend: JAX lets float32 matrix products and convolutions run in TF32
(10-bit mantissa, ~1e-3 relative error) on NVIDIA GPUs by default; 17 tests that compare with
NumPy were reported failing on an H100, TF32 the likely cause (not yet re-run on a GPU). waldo_jax sets
`jax_default_matmul_precision` to "highest" (full float32) at import, for every computation: users
compare criterion scores across machines, camera geometry must be exact, and the hash-grid field's
products are too small (64-wide layers) for TF32 to matter next to its table gathers. It changes
nothing on a CPU (bit-identical results). A user's own choice wins: the environment variable
`JAX_DEFAULT_MATMUL_PRECISION` (e.g. `tensorfloat32` to get TF32 back), or
`jax.config.update("jax_default_matmul_precision", ...)` after importing waldo_jax.
"""

from __future__ import annotations

import os
import warnings

_YNN_FLAG = "--xla_cpu_experimental_ynn_fusion_type"
# XLA flags that make GPU results deterministic; the first is the one added.
_DETERMINISM_FLAGS = ("--xla_gpu_deterministic_ops", "--xla_gpu_exclude_nondeterministic_ops")


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


def _wanted_flags(flags: str) -> list:
    """The flags to add to an XLA_FLAGS value `flags` (those the user has not set)."""
    wanted = []
    if _YNN_FLAG not in flags and _jaxlib_version() >= (0, 8, 0):
        wanted.append(f"{_YNN_FLAG}=")
    opted_out = os.environ.get("WALDO_DETERMINISTIC", "1").strip().lower() in ("0", "false", "no", "off")
    if not opted_out and not any(flag in flags for flag in _DETERMINISM_FLAGS):
        wanted.append(f"{_DETERMINISM_FLAGS[0]}=true")
    return wanted


def apply() -> None:
    """Adds the YNN-fusion workaround (jaxlib >= 0.8) and GPU determinism to XLA_FLAGS, unless set already."""
    flags = os.environ.get("XLA_FLAGS", "")
    wanted = _wanted_flags(flags)
    if not wanted:
        return
    if _backends_started():
        warnings.warn(
            "waldo_jax was imported after JAX started its backends, so the XLA flags "
            f"{' '.join(wanted)} could not be applied; import waldo_jax before running JAX code "
            "(or set XLA_FLAGS yourself): without them jaxlib 0.10.2 miscompiles some reductions on "
            "a CPU, and GPU reruns are not bit-identical.",
            RuntimeWarning,
            stacklevel=3,
        )
        return
    os.environ["XLA_FLAGS"] = " ".join([flags, *wanted]).strip()


def full_precision_matmuls() -> None:
    """Sets JAX's default matmul/convolution precision to "highest" unless the user has chosen one."""
    if os.environ.get("JAX_DEFAULT_MATMUL_PRECISION"):
        return
    import jax  # importing jax starts no backend; the XLA flags above are already in place

    if jax.config.jax_default_matmul_precision is None:
        jax.config.update("jax_default_matmul_precision", "highest")


apply()
full_precision_matmuls()
