"""waldo_jax: exploring NeRF scene spaces in JAX ("Finding Waldo", Skartados, Yucel et al., MMSys'24)."""

from waldo_jax import _xla_flags  # noqa: F401  (must run before JAX starts its CPU backend)
from waldo_jax.version import package_version as _package_version

__version__ = _package_version()
