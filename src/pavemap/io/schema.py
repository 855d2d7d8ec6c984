"""One schema for ``sequence.json`` and ``detections.jsonl``: types, finite numbers, shapes, enums,
string lengths and nesting depth.

The reader (:mod:`pavemap.io.sequence`) and ``pavemap info`` both check through here, so a bad file
gets the same answer everywhere: the file, the JSON path (``frames[3].views.CAM_FRONT.T_world_cam``)
and the problem, never a traceback from deep inside the reader. Parsing goes through
:func:`load_json`, which turns the ways ``json`` itself fails (bytes that are not UTF-8, nesting
deep enough to exhaust the stack, integers too long to convert) into the same kind of error.

The schema is data: a tree of small spec objects (:class:`Int`, :class:`Num`, :class:`Str`, :class:`Arr`,
:class:`Obj`, :class:`Map` …) walked by :func:`check`; the walk descends only where the schema does,
so its depth is the schema's, whatever the input holds.
"""

from __future__ import annotations

import contextlib
import json
import math
import re
from dataclasses import dataclass, field

from pavemap.io.jsonfile import MAX_DEPTH, DuplicateKeyError, HugeInt, decode_utf8, load_json, nesting_depth, parse_json

#: Deepest nesting of arrays / objects accepted in either file (sequence.json itself needs 7).
#: Largest magnitude of a coordinate or matrix entry: far beyond any survey (metres, pixels), small
#: enough that products and squares of it stay finite in float64.
MAX_ABS = 1e9
_CONTROL = re.compile(r"[\x00-\x1f\x7f]")


@dataclass(frozen=True)
class Issue:
    """One schema violation: where (a JSON path such as ``frames[3].views.CAM_FRONT.image``) and what."""

    path: str
    message: str

    def __str__(self) -> str:
        return f"{self.path}: {self.message}" if self.path else self.message


class _EnoughIssuesError(Exception):
    """Enough issues collected."""


# ---------------------------------------------------------------------------- specs


def _kind(v: object) -> str:
    if v is None:
        return "null"
    if isinstance(v, bool):
        return "true/false"
    if isinstance(v, int):
        return "an integer"
    if isinstance(v, float):
        return "a number"
    if isinstance(v, str):
        return "a string"
    if isinstance(v, list):
        return "a list"
    if isinstance(v, dict):
        return "an object"
    return type(v).__name__


def _got(v: object) -> str:
    """``got <kind> <value>`` for a message (the value only for scalars, shortened)."""
    if isinstance(v, HugeInt):
        return f"got an integer of {v.digits} digits"
    if isinstance(v, list | dict) or v is None:
        return f"got {_kind(v)}"
    if isinstance(v, float) and not math.isfinite(v):
        return f"got {_not_finite(v)}"
    text = json.dumps(v[:40] + ("…" if len(v) > 40 else "")) if isinstance(v, str) else json.dumps(v)
    return f"got {_kind(v)} {text}"


def _not_finite(v: float) -> str:
    return "NaN" if math.isnan(v) else ("Infinity" if v > 0 else "-Infinity")


@dataclass(frozen=True)
class Num:
    """A JSON number (int or float, not a boolean), finite, within [lo, hi]."""

    lo: float = -MAX_ABS
    hi: float = MAX_ABS
    finite: bool = True  # False: NaN / Infinity pass (a consumer counts them)

    def check(self, v: object, path: str, out: _Issues) -> None:
        if isinstance(v, bool) or not isinstance(v, int | float):
            out.add(path, f"must be a number, {_got(v)}")
            return
        f = float(v) if not isinstance(v, int) or abs(v) < 1e300 else math.inf
        if isinstance(v, HugeInt):
            out.add(path, f"must be in [{self.lo:g}, {self.hi:g}], {_got(v)}")
            return
        if not math.isfinite(f):
            if self.finite:
                out.add(path, f"must be a finite number, got {_not_finite(f)}")
            return
        if not self.lo <= f <= self.hi:
            out.add(path, f"must be in [{self.lo:g}, {self.hi:g}], got {f:g}")


@dataclass(frozen=True)
class Int:
    """A JSON integer (``3`` or ``3.0``; not ``3.5``, ``"3"`` or ``true``) within [lo, hi]."""

    lo: int = -(2**31)
    hi: int = 2**31 - 1

    def check(self, v: object, path: str, out: _Issues) -> None:
        if isinstance(v, HugeInt):
            out.add(path, f"must be in {self.lo}..{self.hi}, {_got(v)}")
            return
        if isinstance(v, float) and math.isfinite(v) and v.is_integer():
            v = int(v)
        if isinstance(v, bool) or not isinstance(v, int):
            out.add(path, f"must be an integer, {_got(v)}")
            return
        if not self.lo <= v <= self.hi:
            out.add(path, f"must be in {self.lo}..{self.hi}, got {v if abs(v) < 10**12 else 'a huge integer'}")


@dataclass(frozen=True)
class Bool:
    """``true`` or ``false`` (not the string ``"false"``, which would count as true)."""

    def check(self, v: object, path: str, out: _Issues) -> None:
        if not isinstance(v, bool):
            out.add(path, f"must be true or false, {_got(v)}")


@dataclass(frozen=True)
class Str:
    """A string of 1..``max_len`` characters, valid Unicode, without control characters.

    ``name``: also no path separators and not ``.`` / ``..`` (it becomes part of file names).
    ``choices``: one of these values.
    """

    max_len: int = 256
    name: bool = False
    choices: tuple[str, ...] = ()

    def check(self, v: object, path: str, out: _Issues) -> None:
        if not isinstance(v, str):
            out.add(path, f"must be a string, {_got(v)}")
            return
        if self.choices:
            if v not in self.choices:
                out.add(path, f"must be {' or '.join(repr(c) for c in self.choices)}, {_got(v)}")
            return
        if not v:
            out.add(path, "must not be empty")
        elif len(v) > self.max_len:
            out.add(path, f"is {len(v)} characters long, at most {self.max_len} allowed")
        elif _CONTROL.search(v):
            out.add(path, "contains a control character (e.g. a NUL byte or newline)")
        elif not _encodable(v):
            out.add(path, "contains an invalid Unicode escape (a lone surrogate)")
        elif self.name and (v in (".", "..") or "/" in v or "\\" in v):
            out.add(path, f"must not contain '/' or '\\' or be '.' or '..', {_got(v)}")


def _encodable(s: str) -> bool:
    try:
        s.encode("utf-8")
    except UnicodeEncodeError:
        return False
    return True


@dataclass(frozen=True)
class Opt:
    """``null`` or the inner spec."""

    inner: object

    def check(self, v: object, path: str, out: _Issues) -> None:
        if v is not None:
            self.inner.check(v, path, out)  # type: ignore[attr-defined]


@dataclass(frozen=True)
class Arr:
    """A list of ``item`` with ``min_len``..``max_len`` entries."""

    item: object
    min_len: int = 0
    max_len: int = 10**7

    def check(self, v: object, path: str, out: _Issues) -> None:
        if not isinstance(v, list):
            out.add(path, f"must be a list, {_got(v)}")
            return
        if not self.min_len <= len(v) <= self.max_len:
            want = (f"exactly {self.min_len}" if self.min_len == self.max_len
                    else f"at least {self.min_len}" if len(v) < self.min_len else f"at most {self.max_len}")
            out.add(path, f"must have {want} entr{'y' if want.endswith(' 1') else 'ies'}, got {len(v)}")
            return
        for i, x in enumerate(v):
            self.item.check(x, f"{path}[{i}]", out)  # type: ignore[attr-defined]


@dataclass(frozen=True)
class Matrix:
    """A ``rows`` x ``cols`` list of lists of finite numbers with |x| <= MAX_ABS."""

    rows: int
    cols: int

    def check(self, v: object, path: str, out: _Issues) -> None:
        shape = f"{self.rows}x{self.cols}"
        if not isinstance(v, list) or not all(isinstance(r, list) for r in v):
            out.add(path, f"must be a {shape} matrix (a list of {self.rows} lists of {self.cols} numbers), "
                          f"got {_kind(v)}")
            return
        if len(v) != self.rows or any(len(r) != self.cols for r in v):
            got = f"{len(v)} rows of lengths {sorted({len(r) for r in v})}" if v else "an empty list"
            out.add(path, f"must be a {shape} matrix, got {got}")
            return
        num = Num()
        for i, r in enumerate(v):
            for j, x in enumerate(r):
                num.check(x, f"{path}[{i}][{j}]", out)


@dataclass(frozen=True)
class Obj:
    """An object with ``required`` and ``optional`` members (name -> spec); other members are ignored."""

    required: dict[str, object] = field(default_factory=dict)
    optional: dict[str, object] = field(default_factory=dict)

    def check(self, v: object, path: str, out: _Issues) -> None:
        if not isinstance(v, dict):
            out.add(path, f"must be an object, {_got(v)}")
            return
        for k, spec in self.required.items():
            if k not in v:
                out.add(_join(path, k), "is missing")
            else:
                spec.check(v[k], _join(path, k), out)  # type: ignore[attr-defined]
        for k, spec in self.optional.items():
            if k in v:
                spec.check(v[k], _join(path, k), out)  # type: ignore[attr-defined]


@dataclass(frozen=True)
class Map:
    """An object of ``key`` name -> ``value`` with ``min_len``..``max_len`` members."""

    value: object
    key: Str = Str(max_len=128, name=True)
    min_len: int = 0
    max_len: int = 10**6

    def check(self, v: object, path: str, out: _Issues) -> None:
        if not isinstance(v, dict):
            out.add(path, f"must be an object of name -> value, {_got(v)}")
            return
        if not self.min_len <= len(v) <= self.max_len:
            out.add(path, f"must have {self.min_len}..{self.max_len} members, got {len(v)}")
            return
        for k, x in v.items():
            before = len(out.items)
            self.key.check(k, f"{path} key {json.dumps(k[:40])}", out)
            if len(out.items) == before:
                self.value.check(x, _join(path, k), out)  # type: ignore[attr-defined]


def _join(path: str, key: str) -> str:
    return f"{path}.{key}" if path else key


class _Issues:
    def __init__(self, limit: int):
        self.items: list[Issue] = []
        self.limit = limit

    def add(self, path: str, message: str) -> None:
        self.items.append(Issue(path, message))
        if len(self.items) >= self.limit:
            raise _EnoughIssuesError


def check(value: object, spec: object, limit: int = 50, path: str = "") -> list[Issue]:
    """Every way ``value`` breaks ``spec`` (at most ``limit``), in document order; empty when it fits."""
    out = _Issues(limit)
    with contextlib.suppress(_EnoughIssuesError):
        spec.check(value, path, out)  # type: ignore[attr-defined]
    return out.items


# ---------------------------------------------------------------------------- the two files

_PATH = Str(max_len=4096)
VIEW = Obj(required={"image": _PATH, "T_world_cam": Matrix(4, 4)},
           optional={"semantics": Opt(_PATH), "depth": Opt(_PATH)})
FRAME = Obj(required={"index": Int(0, 2**31 - 1), "views": Map(VIEW, min_len=1, max_len=64)},
            optional={"timestamp": Num(-1e20, 1e20)})
CAMERA = Obj(required={"width": Int(1, 100_000), "height": Int(1, 100_000), "K": Matrix(3, 3)},
             optional={"ego_mask": Opt(_PATH)})
CLASS = Obj(required={"id": Int(0, 255), "name": Str(max_len=128)},
            optional={"road": Bool(), "movable": Bool(), "sky": Bool()})
GEO_ORIGIN = Obj(required={"lat": Num(-90, 90), "lon": Num(-180, 180)},
                 optional={"alt": Num(-1e5, 1e5), "heading_deg": Num(-720, 720)})
SEQUENCE = Obj(
    required={"format": Str(choices=("pavemap-sequence/1",)), "name": Str(max_len=256),
              "classes": Arr(CLASS, 0, 256), "cameras": Map(CAMERA, min_len=1, max_len=64),
              "frames": Arr(FRAME, 1, 10**7)},
    optional={"geo_origin": Opt(GEO_ORIGIN)},
)
#: One line of ``detections.jsonl``. NaN / Infinity in ``box`` or ``conf`` are well-formed: the road
#: filter skips such detections and counts them (``bad_box``, ``bad_conf``); so does a frame or camera
#: the sequence lacks.
DETECTION = Obj(required={"frame": Int(-(2**31), 2**31 - 1), "camera": Str(max_len=128),
                          "box": Arr(Num(-1e12, 1e12, finite=False), 4, 4), "cls": Int(-(2**31), 2**31 - 1),
                          "conf": Num(-1e12, 1e12, finite=False)})


# ---------------------------------------------------------------------------- parsing


def check_sequence(d: object, limit: int = 50) -> list[Issue]:
    """Schema issues of a parsed ``sequence.json`` (empty when it fits)."""
    return check(d, SEQUENCE, limit)


def check_detection(d: object) -> list[Issue]:
    """Schema issues of one parsed ``detections.jsonl`` line."""
    return check(d, DETECTION, limit=5)


def issues_text(issues: list[Issue], shown: int = 3) -> str:
    """The first issues joined into one line, with a count of the rest."""
    rest = len(issues) - shown
    return "; ".join(str(i) for i in issues[:shown]) + (f" (and {rest} more)" if rest > 0 else "")


__all__ = ["DETECTION", "MAX_DEPTH", "SEQUENCE", "DuplicateKeyError", "Issue", "check", "check_detection",
           "check_sequence", "decode_utf8", "issues_text", "load_json", "nesting_depth", "parse_json"]
