"""The package's version: the installed distribution's metadata, else pyproject.toml's `version`.

A source checkout that was never installed (PYTHONPATH pointing at it) has no metadata; its
pyproject.toml, one folder above the package, then gives the version. `waldo --version` prints it.
"""

from __future__ import annotations

import re
from importlib import metadata
from pathlib import Path

__all__ = ["package_version", "UNKNOWN_VERSION"]

UNKNOWN_VERSION = "0+unknown"  # neither installed nor beside its pyproject.toml
_PYPROJECT = Path(__file__).resolve().parent.parent / "pyproject.toml"
# `version = "..."` of the [project] table (the first `version` key of the file, before any other table).
_PROJECT_VERSION = re.compile(r'^\[project\][^\[]*?^version\s*=\s*"([^"]+)"', re.M | re.S)


def package_version(distribution: str = "waldo_jax", pyproject: Path = _PYPROJECT) -> str:
    """The version string of `distribution` (e.g. "0.1.0").

    Args:
      distribution: the installed distribution's name.
      pyproject: the pyproject.toml read when the distribution is not installed.

    Returns:
      The installed metadata's version, else the `[project]` version of `pyproject`, else
      `UNKNOWN_VERSION`.
    """
    try:
        return metadata.version(distribution)
    except metadata.PackageNotFoundError:
        pass
    try:
        found = _PROJECT_VERSION.search(pyproject.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError):
        found = None
    return found.group(1) if found else UNKNOWN_VERSION
