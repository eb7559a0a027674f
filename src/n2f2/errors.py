"""Errors that reach the user as one clear line (the CLI prints them without a traceback)."""

from __future__ import annotations

from pathlib import Path


class N2F2Error(Exception):
    """Base class for errors caused by the user's input or environment, not by a bug."""


class InputError(N2F2Error):
    """Bad input: names the offending file and what is wrong with it."""

    def __init__(self, path: str | Path | None, problem: str):
        self.path = None if path is None else Path(path)
        self.problem = problem
        super().__init__(f"{self.path}: {problem}" if self.path is not None else problem)


class MissingModelError(N2F2Error):
    """A model's weights are neither cached locally nor downloadable."""


class OutputError(N2F2Error):
    """A result could not be written (full or read-only disk, I/O error): names the file."""

    def __init__(self, path: str | Path, problem: str):
        self.path = Path(path)
        self.problem = problem
        super().__init__(f"{self.path}: {problem}")
