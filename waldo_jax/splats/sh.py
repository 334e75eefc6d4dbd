"""Real spherical harmonics up to degree 3, as the reference 3DGS code evaluates a splat's colour.

The basis, its order and its signs are those of the reference implementation (and of gsplat and
Plenoxels before it): coefficient k of a degree-d splat multiplies basis function k below, for the
unit direction (x, y, z) from the camera centre to the splat's mean, in world coordinates. The
colour is max(sum_k sh[k] * Y_k(d) + 0.5, 0) per channel.
"""

from __future__ import annotations

import jax.numpy as jnp

from waldo_jax.types import Array

__all__ = ["SH_C0", "sh_basis", "sh_to_rgb"]

SH_C0 = 0.28209479177387814
_C1 = 0.4886025119029199
_C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
_C3 = (
    -0.5900435899266435,
    2.890611442640554,
    -0.4570457994644658,
    0.3731763325901154,
    -0.4570457994644658,
    1.445305721320277,
    -0.5900435899266435,
)


def sh_basis(direction: Array, degree: int) -> Array:
    """The (degree + 1)^2 basis values at unit `direction` [..., 3]; returns [..., (degree + 1)^2]."""
    x, y, z = direction[..., 0], direction[..., 1], direction[..., 2]
    terms = [jnp.full_like(x, SH_C0)]
    if degree >= 1:
        terms += [-_C1 * y, _C1 * z, -_C1 * x]
    if degree >= 2:
        xx, yy, zz = x * x, y * y, z * z
        terms += [_C2[0] * x * y, _C2[1] * y * z, _C2[2] * (2.0 * zz - xx - yy), _C2[3] * x * z, _C2[4] * (xx - yy)]
    if degree >= 3:
        terms += [
            _C3[0] * y * (3.0 * xx - yy),
            _C3[1] * x * y * z,
            _C3[2] * y * (4.0 * zz - xx - yy),
            _C3[3] * z * (2.0 * zz - 3.0 * xx - 3.0 * yy),
            _C3[4] * x * (4.0 * zz - xx - yy),
            _C3[5] * z * (xx - yy),
            _C3[6] * x * (xx - 3.0 * yy),
        ]
    return jnp.stack(terms, axis=-1)


def sh_to_rgb(sh: Array, direction: Array) -> Array:
    """Colour of splats with coefficients `sh` [..., K, 3] seen along unit `direction` [..., 3]: [..., 3] >= 0."""
    degree = int(round(sh.shape[-2] ** 0.5)) - 1
    basis = sh_basis(direction, degree)  # [..., K]
    return jnp.maximum(jnp.einsum("...k,...kc->...c", basis, sh) + 0.5, 0.0)
