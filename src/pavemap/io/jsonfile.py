"""The one strict JSON reader of user files: UTF-8 named, nesting bounded, huge integers kept finite, and
duplicate keys refused (a hand edit or a bad merge silently dropping data), each error naming the file."""

from __future__ import annotations

import json
import os
import re
from pathlib import Path

import numpy as np

from pavemap.errors import SequenceError

MAX_DEPTH = 32


class HugeInt(float):
    """An integer literal too long to convert (Python stops at 4300 digits): kept as its float value."""

    digits: int = 0


class DuplicateKeyError(ValueError):
    """A JSON object holding the same key twice (``json`` would keep the last copy silently)."""

    def __init__(self, key: str):
        self.key = key
        super().__init__(f"duplicate key {key!r}")


def _unique_pairs(pairs: list[tuple[str, object]]) -> dict:
    """``object_pairs_hook`` refusing a repeated key: a hand edit or a bad merge that repeats ``"frames"``
    would otherwise drop the first copy without a word."""
    d = dict(pairs)
    if len(d) != len(pairs):
        seen: set[str] = set()
        for k, _ in pairs:
            if k in seen:
                raise DuplicateKeyError(k)
            seen.add(k)
    return d


class _Brackets(dict):
    """str.translate table keeping only quotes and brackets."""

    def __missing__(self, key: int) -> None:
        return None


_KEEP = _Brackets({ord(c): c for c in '"[]{}'})
_ESCAPE = re.compile(r"\\.", re.S)
_BARE_STRING = re.compile(r'"[^"]*"')


def nesting_depth(text: str) -> int:
    """Deepest nesting of ``[`` / ``{`` in JSON text (brackets inside strings do not count).

    Escapes go first (so ``\\"`` cannot end a string), then everything but quotes and brackets, then
    the strings: what is left is only the structure, counted with a cumulative sum (~0.15 s for 25 MB).
    """
    t = _ESCAPE.sub("", text) if "\\" in text else text
    t = _BARE_STRING.sub("", t.translate(_KEEP))
    a = np.frombuffer(t.encode("ascii"), dtype=np.uint8)
    step = (a == 0x5B).astype(np.int32) + (a == 0x7B) - (a == 0x5D) - (a == 0x7D)
    return int(np.cumsum(step).max(initial=0))


def decode_utf8(data: bytes, file: str | os.PathLike) -> str:
    """Bytes -> text; bytes that are not UTF-8 raise SequenceError naming the line and byte."""
    try:
        return data.decode("utf-8-sig")
    except UnicodeDecodeError as e:
        line = data[:e.start].count(b"\n") + 1
        raise SequenceError(file, f"is not UTF-8 text (byte 0x{data[e.start]:02x} at line {line}); save it as "
                                  "UTF-8") from None


def _parse_int(s: str) -> int | float:
    # Python refuses to convert integers of more than 4300 digits (and none is meaningful here).
    if len(s) <= 30:
        return int(s)
    v = HugeInt(float(s))
    v.digits = len(s.lstrip("-"))
    return v


def parse_json(text: str, file: str | os.PathLike, where: str = "") -> object:
    """JSON text -> value. Invalid JSON, a key repeated in an object and nesting deeper than MAX_DEPTH raise
    SequenceError.

    ``NaN`` / ``Infinity`` literals parse (as Python's json does) and are left to the schema, which
    names their path. ``where`` prefixes messages (``"line 3: "`` for a JSONL line).
    """
    depth = nesting_depth(text)
    if depth > MAX_DEPTH:
        raise SequenceError(file, f"{where}JSON nested {depth} levels deep; at most {MAX_DEPTH} allowed")
    try:
        return json.loads(text, parse_int=_parse_int, object_pairs_hook=_unique_pairs)
    except DuplicateKeyError as e:
        key = e.key if len(e.key) <= 40 else e.key[:40] + "…"
        raise SequenceError(file, f"{where}duplicate key {json.dumps(key)}: a key may appear once per object "
                                  "(a hand edit or a merge repeated it; only the last copy would be read)") from None
    except json.JSONDecodeError as e:
        pos = f"line {e.lineno}, column {e.colno}" if not where else f"column {e.colno}"
        raise SequenceError(file, f"{where}invalid JSON at {pos}: {e.msg}") from None
    except (RecursionError, ValueError) as e:  # belt and braces: depth is checked above
        raise SequenceError(file, f"{where}cannot be parsed as JSON ({type(e).__name__})") from None


def load_json(path: str | os.PathLike) -> object:
    """Read and parse a JSON file; every failure is a SequenceError naming the file."""
    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError as e:
        raise SequenceError(path, f"cannot be read ({e.strerror or e})") from None
    return parse_json(decode_utf8(data, path), path)


__all__ = ["MAX_DEPTH", "DuplicateKeyError", "HugeInt", "decode_utf8", "load_json", "nesting_depth", "parse_json"]
