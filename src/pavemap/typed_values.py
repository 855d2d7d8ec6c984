"""Values checked against a config dataclass's type hints: YAML values and command-line text into typed values.

One schema for the YAML file and ``--set``: a field's type hint says what it accepts (:func:`coerce`), and the
error says it in words (:func:`describe`).
"""

from __future__ import annotations

import types
import typing
from pathlib import Path
from typing import Any, Literal

from pavemap.errors import PavemapError

_TRUE = {"true", "yes", "on", "1"}
_FALSE = {"false", "no", "off", "0"}
_NONE = {"none", "null", "~", ""}


class _MismatchError(Exception):
    """A value that does not fit a type hint (turned into a PavemapError by :func:`coerce`)."""


def describe(hint: Any) -> str:
    """How an error message says what a type hint accepts: ``a number``, ``one of frame, mesh, both`` …"""
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if origin in (typing.Union, types.UnionType):
        parts = [describe(a) for a in args if a is not type(None)]
        return " or ".join(parts) + (" or none" if type(None) in args else "")
    if origin is Literal:
        return "one of " + ", ".join(str(a) for a in args)
    if origin in (tuple, list):
        if origin is tuple and not (len(args) == 2 and args[1] is Ellipsis):
            return f"a list of {len(args)} values"
        if args and typing.get_origin(args[0]) is Literal:
            return "a list of values, each " + describe(args[0])
        return "a list of " + {bool: "true/false values", int: "integers", float: "numbers",
                               str: "strings"}.get(args[0] if args else str, "values")
    return {bool: "true or false", int: "an integer", float: "a number", str: "a string"}.get(hint, str(hint))


def _split_list(text: str) -> list:
    text = text.strip()
    if text[:1] in "[(":
        inner = text[1:-1] if text[-1:] in "])" else text[1:]
        text = inner
    return [t.strip() for t in text.split(",")] if text.strip() else []


def _scalar(value: Any, hint: type, text: bool) -> Any:
    if hint is bool:
        if isinstance(value, bool):
            return value
        if text and isinstance(value, str) and value.strip().lower() in _TRUE | _FALSE:
            return value.strip().lower() in _TRUE
    elif hint is int:
        if isinstance(value, int) and not isinstance(value, bool):
            return value
        if isinstance(value, float) and value.is_integer():
            return int(value)
        if text and isinstance(value, str):
            try:
                f = float(value)
            except ValueError:
                raise _MismatchError from None
            if f.is_integer():
                return int(f)
    elif hint is float:
        if isinstance(value, int | float) and not isinstance(value, bool):
            return float(value)
        if text and isinstance(value, str):
            try:
                return float(value)
            except ValueError:
                raise _MismatchError from None
    elif hint is str:
        if isinstance(value, str):
            return value
        if isinstance(value, int) and not isinstance(value, bool):  # YAML `device: 0` means GPU "0"
            return str(value)
    elif hint is Path:
        if isinstance(value, str | Path):
            return Path(value)
    else:
        raise TypeError(f"config fields must be bool, int, float, str, Path, Literal, X | None, tuple or list; "
                        f"got {hint!r}")
    raise _MismatchError


def _coerce(value: Any, hint: Any, text: bool) -> Any:
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if origin in (typing.Union, types.UnionType):
        if type(None) in args and (value is None or (text and isinstance(value, str)
                                                     and value.strip().lower() in _NONE)):
            return None
        for a in args:
            if a is type(None):
                continue
            try:
                return _coerce(value, a, text)
            except _MismatchError:
                pass
        raise _MismatchError
    if value is None:
        raise _MismatchError
    if origin is Literal:
        for a in args:
            if value == a and type(value) is type(a):
                return a
            if text and isinstance(value, str) and value.strip() == str(a):
                return a
        raise _MismatchError
    if origin in (tuple, list):
        items = _split_list(value) if text and isinstance(value, str) else value
        if not isinstance(items, list | tuple):
            raise _MismatchError
        if origin is tuple and not (len(args) == 2 and args[1] is Ellipsis):
            if len(items) != len(args):
                raise _MismatchError
            return tuple(_coerce(v, a, text) for v, a in zip(items, args, strict=True))
        inner = args[0] if args else Any
        out = [v if inner is Any else _coerce(v, inner, text) for v in items]
        return tuple(out) if origin is tuple else out
    if hint is Any:
        raise TypeError("config fields need a type hint, not Any")
    return _scalar(value, hint, text)


def coerce(value: Any, hint: Any, name: str, source: str = "<config>", text: bool = False) -> Any:
    """Check ``value`` against the type hint ``hint`` and return it in that type.

    Handles bool, int, float, str, Path, ``Literal[...]``, ``X | None``, ``tuple[X, ...]``, fixed tuples and
    ``list[X]``. ``text=True`` also parses command-line text (``"0.6"``, ``"true"``, ``"none"``,
    ``"0.1,0.2"`` or ``"[0.1, 0.2]"``). A mismatch raises PavemapError
    ``"<source>: <name> must be <what the hint accepts>, got <value>"``.
    """
    try:
        return _coerce(value, hint, text)
    except _MismatchError:
        raise PavemapError(f"{source}: {name} must be {describe(hint)}, got {value!r}") from None


__all__ = ["coerce", "describe"]
