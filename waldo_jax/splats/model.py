"""The 3D Gaussian Splatting scene as a pytree, in the reference implementation's raw parameters.

A `Splats` holds the parameters exactly as the reference 3DGS code stores them in its `.ply`
(Kerbl et al., SIGGRAPH 2023), before their activations:

  means       float32 [N, 3]     centres in world coordinates;
  log_scales  float32 [N, 3]     scale = exp(log_scale), the Gaussian's standard deviations along its axes;
  quats       float32 [N, 4]     rotation as a quaternion (w, x, y, z), w first, not necessarily unit
                                 (normalised where it is used);
  logits      float32 [N]        opacity = sigmoid(logit);
  sh          float32 [N, K, 3]  spherical-harmonics coefficients, K = (degree + 1)^2, index 0 the DC
                                 term; colour = max(SH(d) + 0.5, 0) for a unit direction d from the
                                 camera centre to the mean;
  valid       bool    [N]        which rows hold a splat (fitting keeps a fixed capacity and masks the rest).

The degree is not stored: it is set by K (`sh_degree`), a static shape.
"""

from __future__ import annotations

import math

import flax.struct
import jax
import jax.numpy as jnp
import numpy as np

from waldo_jax.types import Array

__all__ = ["Splats", "sh_coefficients", "sh_degree_of", "make_splats", "MAX_SH_DEGREE"]

MAX_SH_DEGREE = 3


def sh_coefficients(degree: int) -> int:
    """Number of SH coefficients per channel of `degree`: (degree + 1)^2."""
    return (int(degree) + 1) ** 2


def sh_degree_of(coefficients: int) -> int:
    """The degree d with (d + 1)^2 == coefficients; a ValueError when there is none in 0..3."""
    degree = int(round(math.sqrt(coefficients))) - 1
    if degree < 0 or degree > MAX_SH_DEGREE or sh_coefficients(degree) != coefficients:
        raise ValueError(
            f"{coefficients} SH coefficients per channel is no degree 0..{MAX_SH_DEGREE} "
            "((degree + 1)^2: 1, 4, 9 or 16)"
        )
    return degree


@flax.struct.dataclass
class Splats:
    """Gaussian splats in the reference layout's raw parameters (see the module docstring)."""

    means: Array
    log_scales: Array
    quats: Array
    logits: Array
    sh: Array
    valid: Array

    @property
    def count(self) -> int:
        """Rows (capacity), valid or not."""
        return int(self.means.shape[0])

    @property
    def sh_degree(self) -> int:
        return sh_degree_of(int(self.sh.shape[1]))

    def opacities(self) -> Array:
        """sigmoid(logits), zero on invalid rows, [N]."""
        return jnp.where(self.valid, jax.nn.sigmoid(self.logits), 0.0)

    def scales(self) -> Array:
        """exp(log_scales), [N, 3]."""
        return jnp.exp(self.log_scales)

    def rotations(self) -> Array:
        """Unit quaternions (w, x, y, z), [N, 4] (a zero quaternion gives the identity)."""
        squared = jnp.sum(self.quats * self.quats, axis=-1, keepdims=True)
        identity = jnp.array([1.0, 0.0, 0.0, 0.0], self.quats.dtype)
        # The guarded root keeps the gradient of a zero quaternion finite (no 0 * inf).
        return jnp.where(squared > 0, self.quats * jax.lax.rsqrt(jnp.where(squared > 0, squared, 1.0)), identity)


def make_splats(means, log_scales, quats, logits, sh, valid=None) -> Splats:
    """A `Splats` from arrays (NumPy or JAX), cast to float32; `valid` defaults to all rows.

    Shapes: means [N, 3], log_scales [N, 3], quats [N, 4] (w first), logits [N], sh [N, K, 3].
    """
    means = np.asarray(means, np.float32)
    n = means.shape[0]
    sh = np.asarray(sh, np.float32)
    if sh.ndim == 2:  # DC only, [N, 3]
        sh = sh[:, None, :]
    arrays = dict(
        means=means,
        log_scales=np.asarray(log_scales, np.float32),
        quats=np.asarray(quats, np.float32),
        logits=np.asarray(logits, np.float32).reshape(n),
        sh=sh,
    )
    expected = {"means": (n, 3), "log_scales": (n, 3), "quats": (n, 4), "logits": (n,)}
    for name, shape in expected.items():
        if arrays[name].shape != shape:
            raise ValueError(f"splats: {name} has shape {arrays[name].shape}, expected {shape}")
    if sh.shape[0] != n or sh.shape[2] != 3:
        raise ValueError(f"splats: sh has shape {sh.shape}, expected ({n}, K, 3)")
    sh_degree_of(sh.shape[1])
    valid = np.ones(n, bool) if valid is None else np.asarray(valid, bool).reshape(n)
    return Splats(**{k: jnp.asarray(v) for k, v in arrays.items()}, valid=jnp.asarray(valid))
