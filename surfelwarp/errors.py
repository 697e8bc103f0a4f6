"""Errors that end a run with one clear line (exit status 2) instead of a traceback."""
from __future__ import annotations

from pathlib import Path


class InputError(Exception):
    """Bad user input: a file or folder that cannot be used, and why."""

    def __init__(self, path: str | Path | None, problem: str):
        self.path = None if path is None else Path(path)
        self.problem = problem
        super().__init__(f"{self.path}: {problem}" if self.path is not None else problem)


class OutputError(InputError):
    """An output that cannot be written (full disk, no permission): the run ends with one line,
    the files written before it stay whole."""


class GLUnavailableError(RuntimeError):
    """No headless OpenGL context could be created."""
