"""The jaxlib CPU miscompilation that `waldo_jax._xla_flags` works around stays worked around; the
flags it adds, and the suite's faster CPU compiles giving the answers of XLA's default ones."""

import json
import os
import subprocess
import sys

import numpy as np
import pytest

import waldo_jax  # noqa: F401  (applies the XLA flags before the first computation)
import jax
import jax.numpy as jnp


def fused_reduction_error() -> float:
    """Largest error against NumPy of a vmapped ratio of two fused reductions over 72 cameras (what
    jaxlib 0.10.2 miscompiles on a CPU through its YNN fusions: errors of O(1))."""
    rng = np.random.default_rng(0)
    normals = rng.normal(size=(672, 3)).astype(np.float32)
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    points = rng.normal(size=(672, 3)).astype(np.float32)
    origins = 3 * rng.normal(size=(72, 3)).astype(np.float32)

    def cosine(o):
        return jnp.sum(normals * (o - points), -1) / jnp.sqrt(jnp.sum((o - points) ** 2, -1))

    got = np.asarray(jax.jit(jax.vmap(cosine))(origins))
    diff = origins[:, None, :] - points[None]
    want = (normals * diff).sum(-1) / np.sqrt((diff**2).sum(-1))
    return float(np.abs(got - want).max())


def test_fused_reduction_ratio_matches_numpy():
    assert fused_reduction_error() < 1e-5


def _flags_after_import(env_changes: dict) -> str:
    """XLA_FLAGS as a fresh process sees it after `import waldo_jax`, with `env_changes` applied."""
    dropped = ("XLA_FLAGS", "WALDO_DETERMINISTIC", "WALDO_FAST_COMPILE", "WALDO_CPU_DEVICES")
    env = {k: v for k, v in os.environ.items() if k not in dropped}
    env.update(env_changes)
    result = subprocess.run(
        [sys.executable, "-c", "import os, waldo_jax; print(os.environ.get('XLA_FLAGS', ''))"],
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert result.returncode == 0, result.stderr[-2000:]
    return result.stdout.strip()


def test_gpu_determinism_is_on_by_default_with_an_opt_out():
    """A seed fixes a run bit for bit on every backend: the GPU determinism flag is added at import
    (it changes nothing on a CPU), unless the user opts out or sets it (or its sibling) themselves."""
    assert "--xla_gpu_deterministic_ops=true" in _flags_after_import({}).split()
    assert "xla_gpu_deterministic_ops" not in _flags_after_import({"WALDO_DETERMINISTIC": "0"})
    own = _flags_after_import({"XLA_FLAGS": "--xla_gpu_deterministic_ops=false"})
    assert own.split().count("--xla_gpu_deterministic_ops=false") == 1 and "=true" not in own
    sibling = _flags_after_import({"XLA_FLAGS": "--xla_gpu_exclude_nondeterministic_ops=true"})
    assert "xla_gpu_deterministic_ops" not in sibling
    # Other flags of the user's are kept.
    kept = _flags_after_import({"XLA_FLAGS": "--xla_force_host_platform_device_count=2"}).split()
    assert "--xla_force_host_platform_device_count=2" in kept and "--xla_gpu_deterministic_ops=true" in kept


def test_matmuls_run_at_full_float32_precision_unless_the_user_chooses():
    """Criterion scores and geometry must not depend on TF32 on NVIDIA GPUs: after `import waldo_jax`
    every float32 product lowers with precision HIGHEST (a no-op on a CPU), and the user's own
    JAX_DEFAULT_MATMUL_PRECISION is kept."""
    assert jax.config.jax_default_matmul_precision == "highest"
    x = jnp.ones((4, 8), jnp.float32)
    text = jax.jit(lambda a: a @ a.T).lower(x).as_text()
    assert "precision = [HIGHEST, HIGHEST]" in text, text

    import os
    import subprocess
    import sys

    env = dict(os.environ, JAX_DEFAULT_MATMUL_PRECISION="tensorfloat32")
    code = "import jax, waldo_jax; print(jax.config.jax_default_matmul_precision)"
    result = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr[-2000:]
    assert result.stdout.strip() == "tensorfloat32"


def test_fast_cpu_compiles_only_when_asked():
    """`WALDO_FAST_COMPILE=1` adds XLA's legacy CPU fusion emitters and LLVM's optimisation level 1;
    unset or 0 leaves XLA's default; a setting of the user's own wins, flag by flag. (`JAX_PLATFORMS=cpu`,
    so that a GPU machine's plugin does not withhold the level: that case is the test below.)"""
    flags = {"--xla_cpu_use_fusion_emitters": ("false", "true"), "--xla_backend_optimization_level": ("1", "2")}
    cpu = {"JAX_PLATFORMS": "cpu"}
    for flag, (ours, theirs) in flags.items():
        assert flag not in _flags_after_import(cpu)
        assert flag not in _flags_after_import({**cpu, "WALDO_FAST_COMPILE": "0"})
        assert f"{flag}={ours}" in _flags_after_import({**cpu, "WALDO_FAST_COMPILE": "1"}).split()
        own = _flags_after_import({**cpu, "WALDO_FAST_COMPILE": "1", "XLA_FLAGS": f"{flag}={theirs}"}).split()
        assert own.count(f"{flag}={theirs}") == 1 and f"{flag}={ours}" not in own
        other = next(f for f in flags if f != flag)
        assert f"{other}={flags[other][0]}" in own


def test_the_fast_compiles_leave_a_gpus_code_generation_alone(monkeypatch):
    """LLVM's level, which XLA's GPU code generation reads too, is added only where no GPU can be used:
    with a JAX GPU plugin installed only under `JAX_PLATFORMS=cpu`; the CPU emitters' flag either way."""
    from waldo_jax import _xla_flags

    monkeypatch.setenv("WALDO_FAST_COMPILE", "1")
    monkeypatch.delenv("JAX_PLATFORMS", raising=False)
    level, emitters = "--xla_backend_optimization_level=1", "--xla_cpu_use_fusion_emitters=false"
    real = _xla_flags._gpu_possible
    monkeypatch.setattr(_xla_flags, "_gpu_possible", lambda: True)  # as with a CUDA plugin installed
    assert emitters in _xla_flags._wanted_flags("") and level not in _xla_flags._wanted_flags("")
    monkeypatch.setattr(_xla_flags, "_gpu_possible", real)
    monkeypatch.setenv("JAX_PLATFORMS", "cpu")
    assert not _xla_flags._gpu_possible() and level in _xla_flags._wanted_flags("")


def test_one_cpu_device_per_usable_core_unless_set():
    """A CPU gets as many XLA host devices as this process may use cores (at most 8), `WALDO_CPU_DEVICES`
    sets the number, a count in the user's XLA_FLAGS wins, and one device adds no flag."""
    from waldo_jax._xla_flags import MAX_CPU_DEVICES, cpu_devices

    flag = "--xla_force_host_platform_device_count"
    cores = min(len(os.sched_getaffinity(0)), MAX_CPU_DEVICES)
    assert cpu_devices({}) == cores and cpu_devices({"WALDO_CPU_DEVICES": "3"}) == 3
    default = _flags_after_import({}).split()
    assert (f"{flag}={cores}" in default) if cores > 1 else not any(f.startswith(flag) for f in default)
    assert f"{flag}=3" in _flags_after_import({"WALDO_CPU_DEVICES": "3"}).split()
    assert not any(f.startswith(flag) for f in _flags_after_import({"WALDO_CPU_DEVICES": "1"}).split())
    own = _flags_after_import({"WALDO_CPU_DEVICES": "3", "XLA_FLAGS": f"{flag}=5"}).split()
    assert [f for f in own if f.startswith(flag)] == [f"{flag}=5"]


EXPLORE = [
    "explore",
    "procedural:1",
    "--resolution",
    "16",
    "--views",
    "8",
    "--epochs",
    "2",
    "--children-per-epoch",
    "6",
    "--top-k",
    "4",
    "--criterion",
    "colorfulness",
    "--method",
    "egps",
    "--seed",
    "5",
    "--quiet",
]

# Run with XLA's default CPU emitters: the miscompilation guard, then `waldo explore`.
_DEFAULT_EMITTERS = """
import sys
sys.path.insert(0, sys.argv[1])
import test_xla_guard
from waldo_jax.cli import main
print(test_xla_guard.fused_reduction_error())
sys.exit(main(test_xla_guard.EXPLORE + ["--out", sys.argv[2]]))
"""


def test_the_suites_fast_compiles_give_the_answers_of_xlas_default_compiles(tmp_path):
    """The suite runs with `WALDO_FAST_COMPILE=1` (tests/conftest.py), users by default without it:
    under XLA's default CPU emitters the guard above holds too, and `waldo explore` with an image
    criterion on rendered views selects the same poses with scores equal to float32 rounding."""
    from waldo_jax.cli import main

    if os.environ.get("WALDO_FAST_COMPILE") != "1" or jax.default_backend() != "cpu":
        pytest.skip("compares WALDO_FAST_COMPILE=1 with XLA's default, on a CPU (the suite's default there)")
    env = {k: v for k, v in os.environ.items() if k not in ("XLA_FLAGS", "WALDO_FAST_COMPILE")}
    result = subprocess.run(
        [sys.executable, "-c", _DEFAULT_EMITTERS, os.path.dirname(__file__), str(tmp_path / "default")],
        env=env,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert result.returncode == 0, result.stderr[-2000:]
    assert float(result.stdout.split()[0]) < 1e-5
    assert main(EXPLORE + ["--out", str(tmp_path / "fast")]) == 0
    default, fast = (json.loads((tmp_path / run / "results.json").read_text()) for run in ("default", "fast"))
    # The same views (rank, epoch, training view or not), their poses equal to float32 rounding: the two
    # emitters may round a child's matrix differently in its last bit.
    same = ("rank", "epoch", "training_view")
    assert [[t[k] for k in same] for t in fast["topk"]] == [[t[k] for k in same] for t in default["topk"]]
    np.testing.assert_allclose([t["c2w"] for t in fast["topk"]], [t["c2w"] for t in default["topk"]], atol=1e-6)
    for key in ("scores_train", "scores_generated"):
        np.testing.assert_allclose(fast[key], default[key], rtol=1e-5)
