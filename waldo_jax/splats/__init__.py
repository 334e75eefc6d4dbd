"""3D Gaussian Splatting scenes: reading and writing the reference layout, a batched, differentiable
tile renderer in pure JAX, and fitting splats to a scene's images."""

from waldo_jax.splats.model import MAX_SH_DEGREE as MAX_SH_DEGREE
from waldo_jax.splats.model import Splats as Splats
from waldo_jax.splats.model import make_splats as make_splats
from waldo_jax.splats.model import sh_coefficients as sh_coefficients
from waldo_jax.splats.model import sh_degree_of as sh_degree_of
