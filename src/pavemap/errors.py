"""Errors that reach the user as one clear line (the CLI prints them without a traceback).

This module imports nothing from the package, so every layer (geometry, io, stages) can raise them.
"""

from __future__ import annotations

import os


class PavemapError(Exception):
    """A problem with the user's input or environment, worded for the user."""


class SequenceError(ValueError):
    """A problem with a sequence folder; the message names the file and the problem."""

    def __init__(self, file: str | os.PathLike, problem: str):
        self.file = str(file)
        self.problem = problem
        super().__init__(f"{self.file}: {problem}")


__all__ = ["PavemapError", "SequenceError"]
