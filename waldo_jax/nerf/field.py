"""The Instant-NGP radiance field (Müller et al., SIGGRAPH 2022, Sec. 5.4 "NeRF"), applied functionally.

For ONE point x (world coordinates, [3]) and ONE unit view direction d ([3]):
  x01   = (x - aabb_min) / (aabb_max - aabb_min)          the point in the unit cube
  h     = density_mlp(encode(table, x01))                 [16] geometry features, h[0] = log-density
  sigma = trunc_exp(h[0])  (0 outside the aabb)           [] volume density, >= 0
  rgb   = sigmoid(color_mlp(concat(h, SH_4(d))))          [3] colour in [0, 1]

`density_mlp` has one hidden layer of 64 ReLU units, `color_mlp` two; neither has biases, as in the
paper's fully-fused MLPs. SH_4 is the real spherical-harmonics basis up to degree 3 (16 coefficients),
in the order and sign convention of tiny-cuda-nn / Instant-NGP.

Parameters are one pytree {"hash": table [n_rows, F], "density_mlp": flax variables,
"color_mlp": flax variables}; the Flax modules only describe the MLPs and are called with
`module.apply(variables, inputs)`, so the field runs under `jit`, `vmap`, `grad` and `scan`.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from typing import Callable, Sequence, Tuple

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np

from waldo_jax.nerf.hashgrid import HashGridConfig, encode, init_hashgrid
from waldo_jax.types import Array, Field, PRNGKey

__all__ = [
    "MLP",
    "NGPFieldConfig",
    "init_field",
    "make_density",
    "make_field",
    "make_field_batch",
    "spherical_harmonics",
    "trunc_exp",
]

# trunc_exp clamps its argument here: exp(15) ~ 3.3e6 is far denser than any real scene needs.
_TRUNC_EXP_MAX = 15.0


# --------------------------------------------------------------------------------------------------
# Numerics


@jax.custom_jvp
def trunc_exp(x: Array) -> Array:
    """Density activation of torch-ngp: exp(min(x, 15)), with derivative exp(clip(x, -15, 15)).

    The forward clamp keeps densities finite for any logit; the derivative clamp keeps gradients
    finite and non-zero (so a saturated logit can still be pulled back), unlike a plain clamp.
    """
    return jnp.exp(jnp.minimum(x, _TRUNC_EXP_MAX))


@trunc_exp.defjvp
def _trunc_exp_jvp(primals, tangents):
    """Forward value as trunc_exp, tangent scaled by exp of the two-sided clamp."""
    (x,), (x_dot,) = primals, tangents
    return trunc_exp(x), x_dot * jnp.exp(jnp.clip(x, -_TRUNC_EXP_MAX, _TRUNC_EXP_MAX))


# Real spherical-harmonics constants from Y_l^m = sqrt((2l+1)/(4 pi) (l-|m|)!/(l+|m|)!) P_l^|m|(cos theta)
# times sqrt(2) cos(m phi) (m > 0) or sqrt(2) sin(|m| phi) (m < 0), with the Condon-Shortley phase
# (-1)^m kept in P_l^m, as tiny-cuda-nn does; then written as polynomials in the unit vector (x, y, z).
_C0 = 0.5 * math.sqrt(1.0 / math.pi)  # 0.28209479...
_C1 = math.sqrt(3.0 / (4.0 * math.pi))  # 0.48860251...
_C2_XY = 0.5 * math.sqrt(15.0 / math.pi)  # 1.09254843...
_C2_Z = 0.25 * math.sqrt(5.0 / math.pi)  # 0.31539157...
_C2_X2Y2 = 0.25 * math.sqrt(15.0 / math.pi)  # 0.54627422...
_C3_3 = 0.25 * math.sqrt(35.0 / (2.0 * math.pi))  # 0.59004359...
_C3_2 = 0.5 * math.sqrt(105.0 / math.pi)  # 2.89061144...
_C3_1 = 0.25 * math.sqrt(21.0 / (2.0 * math.pi))  # 0.45704580...
_C3_0 = 0.25 * math.sqrt(7.0 / math.pi)  # 0.37317633...
_C3_2Z = 0.25 * math.sqrt(105.0 / math.pi)  # 1.44530572...


def spherical_harmonics(d: Array, degree: int = 4) -> Array:
    """Real spherical-harmonics encoding of ONE unit direction, as tiny-cuda-nn's `SphericalHarmonics`.

    Coefficient l*l + l + m holds Y_l^m for l < degree, m = -l .. l. The basis is orthonormal on the
    unit sphere (integral of Y_i Y_j over the sphere is delta_ij).

    Args:
      d: unit direction, [3] (x, y, z).
      degree: number of bands, 1 .. 4 (Instant-NGP uses 4).

    Returns:
      coefficients: [degree**2].
    """
    if not 1 <= degree <= 4:
        raise ValueError(f"spherical_harmonics supports degree 1..4, got {degree!r}")
    x, y, z = d[0], d[1], d[2]
    xx, yy, zz = x * x, y * y, z * z
    bands = [
        [jnp.full_like(x, _C0)],
        [-_C1 * y, _C1 * z, -_C1 * x],
        [
            _C2_XY * x * y,
            -_C2_XY * y * z,
            _C2_Z * (3.0 * zz - 1.0),
            -_C2_XY * x * z,
            _C2_X2Y2 * (xx - yy),
        ],
        [
            -_C3_3 * y * (3.0 * xx - yy),
            _C3_2 * x * y * z,
            -_C3_1 * y * (5.0 * zz - 1.0),
            _C3_0 * z * (5.0 * zz - 3.0),
            -_C3_1 * x * (5.0 * zz - 1.0),
            _C3_2Z * z * (xx - yy),
            -_C3_3 * x * (xx - 3.0 * yy),
        ],
    ]
    return jnp.stack([c for band in bands[:degree] for c in band])  # [degree**2]


# --------------------------------------------------------------------------------------------------
# Networks


class MLP(nn.Module):
    """A bias-free ReLU perceptron: `hidden` widths, then a linear layer of `out` units.

    Attributes:
      hidden: widths of the hidden layers.
      out: output width.
      use_bias: add biases (Instant-NGP's fully-fused MLPs have none).
    """

    hidden: Sequence[int]
    out: int
    use_bias: bool = False

    @nn.compact
    def __call__(self, x: Array) -> Array:
        for width in self.hidden:
            x = nn.relu(nn.Dense(width, use_bias=self.use_bias)(x))
        return nn.Dense(self.out, use_bias=self.use_bias)(x)


def _as_aabb(aabb) -> Tuple[float, ...]:
    """(min_x, min_y, min_z, max_x, max_y, max_z) from a [6] or [2, 3] array-like, validated."""
    values = np.asarray(aabb, np.float64)
    if values.size != 6 or values.shape not in ((6,), (2, 3)):
        raise ValueError(f"aabb must have shape [6] or [2, 3], got {values.shape}: {aabb!r}")
    values = values.reshape(6)
    if not np.all(np.isfinite(values)) or np.any(values[3:] <= values[:3]):
        raise ValueError(f"aabb needs finite bounds with max > min on every axis, got {values.tolist()}")
    return tuple(float(v) for v in values)


@dataclasses.dataclass(frozen=True)
class NGPFieldConfig:
    """Static configuration of the Instant-NGP field (hashable, usable as a `jit` static argument).

    Attributes:
      aabb: scene bounding box (min_x, min_y, min_z, max_x, max_y, max_z) in world units; a [2, 3]
        or [6] array is accepted and stored as a tuple of 6 floats. Points outside have sigma = 0.
      hashgrid: hash encoding configuration.
      density_hidden: widths of the density MLP's hidden layers.
      geo_features: density MLP outputs (output 0 is the log-density).
      color_hidden: widths of the colour MLP's hidden layers.
      sh_degree: spherical-harmonics bands of the direction encoding (degree**2 coefficients).
      use_bias: biases in the MLPs (Instant-NGP: none).
    """

    aabb: Tuple[float, ...] = (-1.0, -1.0, -1.0, 1.0, 1.0, 1.0)
    hashgrid: HashGridConfig = HashGridConfig()
    density_hidden: Tuple[int, ...] = (64,)
    geo_features: int = 16
    color_hidden: Tuple[int, ...] = (64, 64)
    sh_degree: int = 4
    use_bias: bool = False

    def __post_init__(self):
        object.__setattr__(self, "aabb", _as_aabb(self.aabb))
        object.__setattr__(self, "density_hidden", tuple(int(w) for w in self.density_hidden))
        object.__setattr__(self, "color_hidden", tuple(int(w) for w in self.color_hidden))
        if self.geo_features < 1:
            raise ValueError(f"geo_features must be >= 1 (output 0 is the density), got {self.geo_features}")
        if not 1 <= self.sh_degree <= 4:
            raise ValueError(f"sh_degree must be in 1..4, got {self.sh_degree}")

    @classmethod
    def create(cls, aabb, aabb_scale: float = 1.0, **overrides) -> "NGPFieldConfig":
        """The Instant-NGP field for a scene box, with the paper's hash grid for N_max = 2048 * aabb_scale."""
        return cls(aabb=aabb, hashgrid=HashGridConfig.from_aabb_scale(aabb_scale), **overrides)

    @property
    def density_mlp(self) -> MLP:
        return MLP(self.density_hidden, self.geo_features, self.use_bias)

    @property
    def color_mlp(self) -> MLP:
        return MLP(self.color_hidden, 3, self.use_bias)


def init_field(key: PRNGKey, config: NGPFieldConfig) -> dict:
    """Initial parameters of the field.

    Args:
      key: PRNG key (consumed).
      config: static field configuration.

    Returns:
      params: {"hash": table [n_rows, F], "density_mlp": flax variables, "color_mlp": flax variables}.
    """
    key_hash, key_density, key_color = jax.random.split(key, 3)
    encoding = jnp.zeros((config.hashgrid.output_dim,), jnp.float32)  # [L * F]
    color_input = jnp.zeros((config.geo_features + config.sh_degree**2,), jnp.float32)  # [16 + 16]
    return {
        "hash": init_hashgrid(key_hash, config.hashgrid),
        "density_mlp": config.density_mlp.init(key_density, encoding),
        "color_mlp": config.color_mlp.init(key_color, color_input),
    }


def _to_unit_cube(x: Array, config: NGPFieldConfig) -> Tuple[Array, Array]:
    """World point [3] -> (point in the aabb's unit cube [3], inside flag [])."""
    aabb = np.asarray(config.aabb, np.float32).reshape(2, 3)
    x01 = (x - aabb[0]) / (aabb[1] - aabb[0])  # [3]
    inside = jnp.all((x01 >= 0.0) & (x01 <= 1.0))  # [], False for NaN
    return x01, inside


def _geometry(params: dict, x: Array, config: NGPFieldConfig) -> Tuple[Array, Array]:
    """(sigma [], geometry features h [geo_features]) at ONE world point."""
    x01, inside = _to_unit_cube(jnp.asarray(x, jnp.float32), config)  # [3], []
    encoding = encode(params["hash"], x01, config.hashgrid)  # [L * F]
    h = config.density_mlp.apply(params["density_mlp"], encoding)  # [geo_features]
    sigma = jnp.where(inside, trunc_exp(h[0]), 0.0)  # []
    return sigma, h


@functools.lru_cache(maxsize=None)
def make_density(config: NGPFieldConfig) -> Callable[[dict, Array], Array]:
    """The density alone (what the occupancy grid queries), for ONE point.

    Returns:
      density(params, x [3] world point) -> sigma [] >= 0, 0 outside the aabb.
    """

    def density(params: dict, x: Array) -> Array:
        return _geometry(params, x, config)[0]

    return density


@functools.lru_cache(maxsize=None)
def make_field(config: NGPFieldConfig) -> Field:
    """The radiance field for ONE point; batch it with `jax.vmap` (or use `make_field_batch`).

    The same config returns the same function object, so `jit` caches keyed on it are shared.

    Returns:
      field(params, x [3] world point, d [3] view direction) -> (sigma [] >= 0, rgb [3] in [0, 1]).
      `d` is normalised inside (a zero vector stays finite); sigma is 0 outside the aabb.
    """

    def field(params: dict, x: Array, d: Array) -> Tuple[Array, Array]:
        sigma, h = _geometry(params, x, config)  # [], [geo_features]
        d = jnp.asarray(d, jnp.float32)  # [3]
        # Norm floored inside the sqrt so that d = 0 gives finite values and gradients.
        d = d / jnp.sqrt(jnp.maximum(jnp.sum(d * d), jnp.finfo(jnp.float32).tiny))  # [3]
        sh = spherical_harmonics(d, config.sh_degree)  # [sh_degree**2]
        color_input = jnp.concatenate([h, sh])  # [geo_features + sh_degree**2]
        rgb = jax.nn.sigmoid(config.color_mlp.apply(params["color_mlp"], color_input))  # [3]
        return sigma, rgb

    return field


@functools.lru_cache(maxsize=None)
def make_field_batch(config: NGPFieldConfig) -> Callable[[dict, Array, Array], Tuple[Array, Array]]:
    """The field vmapped over points.

    Returns:
      field_batch(params, xs [N, 3], ds [N, 3]) -> (sigma [N], rgb [N, 3]).
    """
    return jax.vmap(make_field(config), in_axes=(None, 0, 0))
