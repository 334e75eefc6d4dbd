"""The jaxlib CPU miscompilation that `waldo_jax._xla_flags` works around stays worked around."""

import numpy as np

import waldo_jax  # noqa: F401  (applies the XLA flags before the first computation)
import jax
import jax.numpy as jnp


def test_fused_reduction_ratio_matches_numpy():
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
    np.testing.assert_allclose(got, want, atol=1e-5)


def _flags_after_import(env_changes: dict) -> str:
    """XLA_FLAGS as a fresh process sees it after `import waldo_jax`, with `env_changes` applied."""
    import os
    import subprocess
    import sys

    env = {k: v for k, v in os.environ.items() if k not in ("XLA_FLAGS", "WALDO_DETERMINISTIC")}
    env.update(env_changes)
    result = subprocess.run([sys.executable, "-c", "import os, waldo_jax; print(os.environ.get('XLA_FLAGS', ''))"],
                            env=env, capture_output=True, text=True, timeout=300)
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
