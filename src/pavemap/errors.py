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


#: What ``torch.save`` (its zip writer) raises, as a RuntimeError, when a write falls short: a full disk, mostly.
TORCH_WRITE_FAILED = ("unexpected pos", "file write failed", "PytorchStreamWriter failed writing")


__all__ = ["TORCH_WRITE_FAILED", "PavemapError", "SequenceError"]
