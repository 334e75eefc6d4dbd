"""User-facing errors.

`WaldoError` is raised at the edges (files, configs, CLI arguments) with a message that names the
offending path or value. The CLI prints it as one line and exits non-zero, without a traceback.
Inside `jit`, failures are data (masks, -inf scores), never exceptions.
"""

from __future__ import annotations

import os

__all__ = ["WaldoError", "SceneFormatError", "DataNotFoundError"]


class WaldoError(Exception):
    """An error caused by the user's input, reported as one clear line."""


class SceneFormatError(WaldoError):
    """A scene on disk is malformed: the message names the file and the problem."""

    def __init__(self, path: str | os.PathLike, problem: str):
        self.path = os.fspath(path)
        self.problem = problem
        super().__init__(f"{self.path}: {problem}")


class DataNotFoundError(WaldoError, FileNotFoundError):
    """A data or weights file the project expects is missing."""
