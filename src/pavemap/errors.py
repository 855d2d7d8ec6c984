"""Errors that reach the user as one clear line (the CLI prints them without a traceback)."""

from pavemap.io.sequence import SequenceError


class PavemapError(Exception):
    """A problem with the user's input or environment, worded for the user."""


__all__ = ["PavemapError", "SequenceError"]
