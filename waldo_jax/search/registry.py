"""The registry of search methods, by the names the paper uses (`explore` looks names up here)."""

from waldo_jax.search import egps, grs, pibs

__all__ = ["METHODS"]

METHODS = {"grs": grs.METHOD, "pibs": pibs.METHOD, "egps": egps.METHOD}
