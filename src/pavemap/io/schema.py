"""One schema for ``sequence.json`` and ``detections.jsonl``, as typed pydantic models: types, finite
numbers, shapes, enums, string lengths.

The reader (:mod:`pavemap.io.sequence`) and ``pavemap info`` both check through here, so a bad file
gets the same answer everywhere: the file, the JSON path (``frames[3].views.CAM_FRONT.T_world_cam[2][1]``)
and the problem, never a traceback from deep inside the reader. Parsing goes through :func:`load_json`
(:mod:`pavemap.io.jsonfile`), which bounds nesting, refuses duplicate keys and keeps huge integers finite.

pydantic walks the models and collects every error with its location; :func:`_issue` words each one as
pavemap always has. Scalars are checked by the small validators below (``_num``, ``_int``, ``_str`` …)
*before* pydantic's own coercion, so ``"3"`` is not an integer, ``true`` not a number and ``"false"`` not
a boolean; matrix entries, by far the most numerous values, are checked by pydantic itself (strict,
finite, within ±MAX_ABS) and only their errors are re-worded. The walk descends only where the models
do, so its depth is the schema's, whatever the input holds; members the schema does not name are ignored.
"""

from __future__ import annotations

import gc
import json
import math
import re
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Annotated, Any, NoReturn

from pydantic import BaseModel, BeforeValidator, Field, ValidationError
from pydantic_core import PydanticCustomError

from pavemap.io.jsonfile import MAX_DEPTH, DuplicateKeyError, HugeInt, decode_utf8, load_json, nesting_depth, parse_json

#: Largest magnitude of a coordinate or matrix entry: far beyond any survey (metres, pixels), small
#: enough that products and squares of it stay finite in float64.
MAX_ABS = 1e9
_CONTROL = re.compile(r"[\x00-\x1f\x7f]")
_ODD = re.compile("[\x00-\x1f\x7f\ud800-\udfff]")  # a control character or a lone surrogate: one scan finds both
_MESSAGE = "pavemap"  # the error type of every check below: its ctx holds the finished message
_KEY = "pavemap_key"  # the same for a map's key (its value is then not checked)


@dataclass(frozen=True)
class Issue:
    """One schema violation: where (a JSON path such as ``frames[3].views.CAM_FRONT.image``) and what."""

    path: str
    message: str

    def __str__(self) -> str:
        return f"{self.path}: {self.message}" if self.path else self.message


# ---------------------------------------------------------------------------- wording


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


def _fail(message: str, kind: str = _MESSAGE) -> NoReturn:
    # the message travels in ctx, not in the template, so braces in a user's value are not a format field
    raise PydanticCustomError(kind, "{message}", {"message": message})


# ---------------------------------------------------------------------------- scalar checks


def _num(lo: float = -MAX_ABS, hi: float = MAX_ABS, finite: bool = True) -> BeforeValidator:
    """A JSON number (int or float, not a boolean), finite, within [lo, hi] -> float.
    ``finite=False``: NaN / Infinity pass (a consumer counts them)."""

    def check(v: object) -> float:
        if isinstance(v, bool) or not isinstance(v, int | float):
            _fail(f"must be a number, {_got(v)}")
        if isinstance(v, HugeInt):
            _fail(f"must be in [{lo:g}, {hi:g}], {_got(v)}")
        f = float(v) if not isinstance(v, int) or abs(v) < 1e300 else math.inf
        if not math.isfinite(f):
            if finite:
                _fail(f"must be a finite number, got {_not_finite(f)}")
            return f
        if not lo <= f <= hi:
            _fail(f"must be in [{lo:g}, {hi:g}], got {f:g}")
        return f

    return BeforeValidator(check)


def _int(lo: int = -(2**31), hi: int = 2**31 - 1) -> BeforeValidator:
    """A JSON integer (``3`` or ``3.0``; not ``3.5``, ``"3"`` or ``true``) within [lo, hi] -> int."""

    def check(v: object) -> int:
        if isinstance(v, HugeInt):
            _fail(f"must be in {lo}..{hi}, {_got(v)}")
        if isinstance(v, float) and math.isfinite(v) and v.is_integer():
            v = int(v)
        if isinstance(v, bool) or not isinstance(v, int):
            _fail(f"must be an integer, {_got(v)}")
        if not lo <= v <= hi:
            _fail(f"must be in {lo}..{hi}, got {v if abs(v) < 10**12 else 'a huge integer'}")
        return v

    return BeforeValidator(check)


def _bool(v: object) -> bool:
    """``true`` or ``false`` (not the string ``"false"``, which would count as true)."""
    if not isinstance(v, bool):
        _fail(f"must be true or false, {_got(v)}")
    return v


def _text_problem(v: object, max_len: int, name: bool) -> str | None:
    """Why ``v`` is not a string of 1..``max_len`` characters, valid Unicode, without control characters
    (``name``: also no path separators and not ``.`` / ``..``, as it becomes part of file names); None if it is."""
    if not isinstance(v, str):
        return f"must be a string, {_got(v)}"
    if not v:
        return "must not be empty"
    if len(v) > max_len:
        return f"is {len(v)} characters long, at most {max_len} allowed"
    if _ODD.search(v):  # rare: then say which
        if _CONTROL.search(v):
            return "contains a control character (e.g. a NUL byte or newline)"
        return "contains an invalid Unicode escape (a lone surrogate)"
    if name and (v in (".", "..") or "/" in v or "\\" in v):
        return f"must not contain '/' or '\\' or be '.' or '..', {_got(v)}"
    return None


def _str(max_len: int = 256, name: bool = False, kind: str = _MESSAGE) -> BeforeValidator:
    def check(v: object) -> str:
        why = _text_problem(v, max_len, name)
        if why:
            _fail(why, kind)
        return v  # type: ignore[return-value]  # a str: _text_problem says so

    return BeforeValidator(check)


def _choice(*choices: str) -> BeforeValidator:
    def check(v: object) -> str:
        if not isinstance(v, str) or v not in choices:
            what = f"must be a string, {_got(v)}" if not isinstance(v, str) else \
                f"must be {' or '.join(repr(c) for c in choices)}, {_got(v)}"
            _fail(what)
        return v

    return BeforeValidator(check)


# ---------------------------------------------------------------------------- container checks


def _list(min_len: int = 0, max_len: int = 10**7) -> BeforeValidator:
    """A list of ``min_len``..``max_len`` entries (the entries are the annotation's business)."""

    def check(v: object) -> list:
        if not isinstance(v, list):
            _fail(f"must be a list, {_got(v)}")
        if not min_len <= len(v) <= max_len:
            want = (f"exactly {min_len}" if min_len == max_len
                    else f"at least {min_len}" if len(v) < min_len else f"at most {max_len}")
            _fail(f"must have {want} entr{'y' if want.endswith(' 1') else 'ies'}, got {len(v)}")
        return v

    return BeforeValidator(check)


def _matrix(rows: int, cols: int) -> BeforeValidator:
    """The shape of a ``rows`` x ``cols`` list of lists (the entries are :data:`Entry`)."""
    shape = f"{rows}x{cols}"

    def check(v: object) -> list:
        if isinstance(v, list) and len(v) == rows and all(isinstance(r, list) and len(r) == cols for r in v):
            return v  # the common case, in one pass
        if not isinstance(v, list) or not all(isinstance(r, list) for r in v):
            _fail(f"must be a {shape} matrix (a list of {rows} lists of {cols} numbers), got {_kind(v)}")
        if len(v) != rows or any(len(r) != cols for r in v):
            got = f"{len(v)} rows of lengths {sorted({len(r) for r in v})}" if v else "an empty list"
            _fail(f"must be a {shape} matrix, got {got}")
        return v

    return BeforeValidator(check)


def _map(min_len: int = 0, max_len: int = 10**6) -> BeforeValidator:
    """An object of name -> value with ``min_len``..``max_len`` members (names: :data:`Key`)."""

    def check(v: object) -> dict:
        if not isinstance(v, dict):
            _fail(f"must be an object of name -> value, {_got(v)}")
        if not min_len <= len(v) <= max_len:
            _fail(f"must have {min_len}..{max_len} members, got {len(v)}")
        return v

    return BeforeValidator(check)


def _optional(inner: BeforeValidator) -> BeforeValidator:
    """``null`` or what ``inner`` accepts."""
    return BeforeValidator(lambda v: v if v is None else inner.func(v))


#: A matrix entry: checked by pydantic itself (hundreds of thousands in a long drive), re-worded by _issue.
Entry = Annotated[float, Field(strict=True, allow_inf_nan=False, ge=-MAX_ABS, le=MAX_ABS)]
Key = Annotated[str, _str(max_len=128, name=True, kind=_KEY)]
RelPath = Annotated[str, _str(max_len=4096)]  # a file relative to the sequence folder
OptPath = Annotated[str | None, _optional(_str(max_len=4096))]
Flag = Annotated[bool, BeforeValidator(_bool)]


# ---------------------------------------------------------------------------- the two files


class ViewJson(BaseModel):
    """One camera's view of a frame: image (and optional layers) relative to the sequence folder, pose."""

    image: RelPath
    T_world_cam: Annotated[list[list[Entry]], _matrix(4, 4)]  # (4, 4) camera -> world, rigid
    semantics: OptPath = None
    depth: OptPath = None


class FrameJson(BaseModel):
    index: Annotated[int, _int(0, 2**31 - 1)]
    views: Annotated[dict[Key, ViewJson], _map(min_len=1, max_len=64)]
    timestamp: Annotated[float | None, _num(-1e20, 1e20)] = None  # None: the index stands in


class CameraJson(BaseModel):
    width: Annotated[int, _int(1, 100_000)]
    height: Annotated[int, _int(1, 100_000)]
    K: Annotated[list[list[Entry]], _matrix(3, 3)]  # (3, 3) pinhole intrinsics
    ego_mask: OptPath = None
    height_m: Annotated[float | None, _num(0.05, 100.0)] = None  # the mount's height over the road, metres


class ClassJson(BaseModel):
    id: Annotated[int, _int(0, 255)]
    name: Annotated[str, _str(max_len=128)]
    road: Flag = False
    movable: Flag = False
    sky: Flag = False


class GeoOriginJson(BaseModel):
    lat: Annotated[float, _num(-90, 90)]
    lon: Annotated[float, _num(-180, 180)]
    alt: Annotated[float, _num(-1e5, 1e5)] = 0.0
    heading_deg: Annotated[float, _num(-720, 720)] = 90.0
    georef: Any = None  # how the origin was fitted (GPS); kept as written, not checked


class SequenceJson(BaseModel):
    """A whole ``sequence.json`` (docs: the sequence folder format)."""

    format: Annotated[str, _choice("pavemap-sequence/1")]
    name: Annotated[str, _str(max_len=256)]
    classes: Annotated[list[ClassJson], _list(0, 256)]
    cameras: Annotated[dict[Key, CameraJson], _map(min_len=1, max_len=64)]
    frames: Annotated[list[FrameJson], _list(1, 10**7)]
    geo_origin: GeoOriginJson | None = None


class DetectionJson(BaseModel):
    """One line of ``detections.jsonl``. NaN / Infinity in ``box`` or ``conf`` are well-formed: the road
    filter skips such detections and counts them (``bad_box``, ``bad_conf``); so does a frame or camera
    the sequence lacks."""

    frame: Annotated[int, _int()]
    camera: Annotated[str, _str(max_len=128)]
    box: Annotated[list[Annotated[float, _num(-1e12, 1e12, finite=False)]], _list(4, 4)]  # x1, y1, x2, y2 pixels
    cls: Annotated[int, _int()]
    conf: Annotated[float, _num(-1e12, 1e12, finite=False)]


# ---------------------------------------------------------------------------- pydantic's errors, worded


def _path(loc: tuple) -> str:
    """pydantic's location -> ``frames[3].views.CAM_FRONT.T_world_cam[2][1]``."""
    out = ""
    for x in loc:
        out = f"{out}[{x}]" if isinstance(x, int) else (f"{out}.{x}" if out else str(x))
    return out


def _issue(e: dict) -> Issue:
    """One pydantic error (``ValidationError.errors()``) as pavemap words it."""
    kind, loc, v = e["type"], e["loc"], e.get("input")
    if kind == _KEY:  # loc ends (..., key, "[key]"); the key itself may not survive pydantic's loc intact
        return Issue(f"{_path(loc[:-2])} key {json.dumps(v[:40])}", e["ctx"]["message"])
    path = _path(loc)
    if kind == _MESSAGE:
        return Issue(path, e["ctx"]["message"])
    if kind == "missing":
        return Issue(path, "is missing")
    if kind in ("model_type", "model_attributes_type", "dict_type"):
        return Issue(path, f"must be an object, {_got(v)}")
    if kind == "float_type":  # an Entry: a string, true/false, null
        return Issue(path, f"must be a number, {_got(v)}")
    if kind in ("finite_number", "greater_than_equal", "less_than_equal"):  # an Entry, the only native range
        if isinstance(v, float) and not isinstance(v, HugeInt) and not math.isfinite(v):
            return Issue(path, f"must be a finite number, got {_not_finite(v)}")
        got = _got(v) if isinstance(v, HugeInt) else f"got {v:g}"
        return Issue(path, f"must be in [{-MAX_ABS:g}, {MAX_ABS:g}], {got}")
    return Issue(path, e["msg"])  # not expected: pydantic's own words still name the place


@contextmanager
def _no_gc() -> Iterator[None]:
    """The cyclic collector paused: validating builds tens of thousands of small acyclic objects next to the
    parsed file's million, and the collections they trigger took over half the time (5,000 frames x 6 views:
    0.54 s -> 0.20 s)."""
    was = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        if was:
            gc.enable()


def _validate(model: type[BaseModel], d: object, limit: int) -> tuple[Any, list[Issue]]:
    with _no_gc():
        try:
            return model.model_validate(d), []
        except ValidationError as err:
            errors = err.errors(include_url=False)  # all of them: pydantic has no "stop after n"
    # a member whose name is refused is not checked further (as one would read it: the name is the problem)
    bad_keys = {e["loc"][:-1] for e in errors if e["type"] == _KEY}
    if bad_keys:
        errors = [e for e in errors if e["type"] == _KEY or not any(e["loc"][:len(k)] == k for k in bad_keys)]
    return None, [_issue(e) for e in errors[:limit]]


def parse_sequence(d: object, limit: int = 50) -> tuple[SequenceJson | None, list[Issue]]:
    """A parsed ``sequence.json`` as typed models, or None and its schema issues (at most ``limit``, in the
    schema's order)."""
    return _validate(SequenceJson, d, limit)


def parse_detection(d: object) -> tuple[DetectionJson | None, list[Issue]]:
    """One parsed ``detections.jsonl`` line as a typed record, or None and its schema issues (at most 5)."""
    return _validate(DetectionJson, d, 5)


def check_sequence(d: object, limit: int = 50) -> list[Issue]:
    """Schema issues of a parsed ``sequence.json`` (empty when it fits)."""
    return parse_sequence(d, limit)[1]


def check_detection(d: object) -> list[Issue]:
    """Schema issues of one parsed ``detections.jsonl`` line."""
    return parse_detection(d)[1]


def issues_text(issues: list[Issue], shown: int = 3) -> str:
    """The first issues joined into one line, with a count of the rest."""
    rest = len(issues) - shown
    return "; ".join(str(i) for i in issues[:shown]) + (f" (and {rest} more)" if rest > 0 else "")


__all__ = ["MAX_ABS", "MAX_DEPTH", "CameraJson", "ClassJson", "DetectionJson", "DuplicateKeyError", "FrameJson",
           "GeoOriginJson", "Issue", "SequenceJson", "ViewJson", "check_detection", "check_sequence", "decode_utf8",
           "issues_text", "load_json", "nesting_depth", "parse_detection", "parse_json", "parse_sequence"]
