"""Backend settings that waldo_jax needs for correct, reproducible results; imported first by
`waldo_jax/__init__.py`, before JAX creates a backend.

  * CPU: YNNPACK fusions off (`--xla_cpu_experimental_ynn_fusion_type=`), as jaxlib 0.10.2
    miscompiles some fused reductions through them; so import waldo_jax before any JAX computation.
  * GPU: `--xla_gpu_deterministic_ops=true`, so a seed fixes a run bit for bit
    (`WALDO_DETERMINISTIC=0` leaves it out).
  * Every backend: `jax_default_matmul_precision` = "highest" (full float32, no TF32).
  * CPU: as many host devices as usable cores, at most 8
    (`--xla_force_host_platform_device_count`; `WALDO_CPU_DEVICES=N` sets N): the splat renderer
    splits its poses over them (`splats.render.render_splats_on_devices`), and XLA runs the devices'
    parts side by side, where one program's small loops keep one core busy (a search of 1M splats at
    128 px on the 2-core CPU: 2.3 -> 1.2 s a view). Programs that are not split run on the first
    device as before.
  * CPU, only when asked (`WALDO_FAST_COMPILE=1`): XLA's legacy CPU fusion emitters
    (`--xla_cpu_use_fusion_emitters=false`) and, where no GPU can be used (`JAX_PLATFORMS=cpu`, or no
    JAX GPU plugin installed), LLVM's optimisation level 1 instead of 3
    (`--xla_backend_optimization_level=1`, which XLA's GPU code generation would read too); they
    compile faster and run the NeRF field slower; the test suite turns them on (tests/conftest.py).

A user's own setting of any of these is left alone. `apply()` adds the flags to XLA_FLAGS,
`full_precision_matmuls()` sets the precision. Why, with what was measured: see docs/design.md,
section "XLA flags".
"""

from __future__ import annotations

import os
import warnings

_YNN_FLAG = "--xla_cpu_experimental_ynn_fusion_type"
# XLA flags that make GPU results deterministic; the first is the one added.
_DETERMINISM_FLAGS = ("--xla_gpu_deterministic_ops", "--xla_gpu_exclude_nondeterministic_ops")
# Opt-in faster XLA:CPU compiles, for short runs that compile more than they compute (tests, quick
# notebook explorations): the suite on the 2-core CPU took 10:07 instead of 12:40-12:56 with it, a
# fox training step 145 ms instead of 108 ms (docs/design.md, "Faster CPU compiles on request").
# jaxlib knows the flag from 0.7 (the oldest that pyproject allows) on.
_FAST_COMPILE_FLAG = "--xla_cpu_use_fusion_emitters"
# With it, LLVM's level 1 (level 0 compiles faster still but its programs run slower by more).
_FAST_COMPILE_LEVEL_FLAG = "--xla_backend_optimization_level"
_HOST_DEVICES_FLAG = "--xla_force_host_platform_device_count"
# More host devices than this replicate a scene's arrays (a copy per device) for little more speed.
MAX_CPU_DEVICES = 8


def cpu_devices(environ=None) -> int:
    """The host devices to make: `WALDO_CPU_DEVICES` (checked by `waldo_jax.environment`), else the
    cores this process may use, at most `MAX_CPU_DEVICES`."""
    environ = os.environ if environ is None else environ
    value = environ.get("WALDO_CPU_DEVICES", "").strip()
    if value:
        return int(value)
    try:
        cores = len(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover - macOS, Windows
        cores = os.cpu_count() or 1
    return max(1, min(cores, MAX_CPU_DEVICES))


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


def _gpu_possible() -> bool:
    """Whether this process may run on an accelerator: `JAX_PLATFORMS` does not name the CPU alone and a
    JAX plugin is installed (anything in the `jax_plugins` namespace: CUDA, ROCm, ...). Imports none of
    them and starts no backend."""
    if os.environ.get("JAX_PLATFORMS", "").strip().lower() == "cpu":
        return False
    try:
        import pkgutil

        import jax_plugins
    except ImportError:
        return False
    return any(True for _ in pkgutil.iter_modules(jax_plugins.__path__))


def _env_on(name: str, default: str) -> bool:
    """Whether the environment variable `name` is on (unset or empty: `default`)."""
    value = os.environ.get(name, "").strip().lower() or default
    return value not in ("0", "false", "no", "off")


def _wanted_flags(flags: str) -> list:
    """The flags to add to an XLA_FLAGS value `flags` (those the user has not set)."""
    wanted = []
    if _YNN_FLAG not in flags and _jaxlib_version() >= (0, 8, 0):
        wanted.append(f"{_YNN_FLAG}=")
    if _env_on("WALDO_DETERMINISTIC", "1") and not any(flag in flags for flag in _DETERMINISM_FLAGS):
        wanted.append(f"{_DETERMINISM_FLAGS[0]}=true")
    if _env_on("WALDO_FAST_COMPILE", "0"):
        if _FAST_COMPILE_FLAG not in flags:
            wanted.append(f"{_FAST_COMPILE_FLAG}=false")
        if _FAST_COMPILE_LEVEL_FLAG not in flags and not _gpu_possible():
            wanted.append(f"{_FAST_COMPILE_LEVEL_FLAG}=1")
    if _HOST_DEVICES_FLAG not in flags and cpu_devices() > 1:
        wanted.append(f"{_HOST_DEVICES_FLAG}={cpu_devices()}")
    return wanted


def apply() -> None:
    """Adds the YNN-fusion workaround (jaxlib >= 0.8), GPU determinism, the host devices and, when asked,
    the faster CPU compiles to XLA_FLAGS, unless set already."""
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
