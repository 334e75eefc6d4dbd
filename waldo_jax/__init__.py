"""waldo_jax: exploring NeRF scene spaces in JAX ("Finding Waldo", Skartados, Yucel et al., MMSys'24)."""

from waldo_jax import _startup

_startup.guard_startup()  # the `waldo` command: Ctrl-C while JAX imports ends it at once, cleanly

from waldo_jax import environment as _environment  # noqa: E402

# The environment variables waldo_jax, JAX and XLA read, checked before JAX starts (one line naming a bad one).
_environment.install_excepthook()
_environment.check_environment()
_environment.import_jax()

from waldo_jax import _xla_flags  # noqa: E402, F401  (must run before JAX starts its CPU backend)
from waldo_jax.version import package_version as _package_version  # noqa: E402

__version__ = _package_version()


def view(path, port: int = 0, host: str = "127.0.0.1", height: int = 600):
    """Shows PATH (a `waldo explore` output or a SOURCE) in 3D; see `waldo_jax.viewer.view` (needs viser)."""
    from waldo_jax.viewer import view as _view

    return _view(path, port=port, host=host, height=height)
