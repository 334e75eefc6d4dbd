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
