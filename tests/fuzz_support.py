"""A small valid sequence folder, hypothesis strategies that break its ``sequence.json`` and
``detections.jsonl``, the fuzz targets (shared by tests/test_fuzz.py and bench/fuzz_bench.py), and the
command-line checks of the bad-input tests (``invoke``, ``check``, ``looks_complete``).

A target returns ``"ok"`` (the file was accepted, and what was read survives its consumers: validation,
the trajectory, the filter's sanitising, writing it back as strict JSON) or ``"error"`` (the project's
own one-line error: SequenceError / PavemapError); anything else it raises is a bug.
"""

from __future__ import annotations

import json
import math
import re
from pathlib import Path

import numpy as np
from hypothesis import strategies as st
from PIL import Image

from pavemap.errors import PavemapError, SequenceError

W, H = 32, 24
CAM = "CAM_FRONT"


def pose(x: float) -> list[list[float]]:
    T = np.eye(4)
    T[:3, :3] = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])  # looking along +x
    T[:3, 3] = [x, 0.5, 1.5]
    return T.tolist()


def make_seq(root: Path, frames: int = 3) -> Path:
    """A small valid sequence: ``frames`` frames of one 32x24 camera, semantics, depth (mm), detections."""
    root.mkdir(parents=True, exist_ok=True)
    sem = np.full((H, W), 2, np.uint8)
    sem[H // 2:] = 0  # road below the horizon, sky above
    depth = np.zeros((H, W), np.uint16)
    depth[H // 2 + 2:, ::3] = 6000
    views = []
    for i in range(frames):
        rel = {k: f"{k}/{CAM}/{i:06d}.png" for k in ("images", "semantics", "depth")}
        for k, a in (("images", np.full((H, W, 3), 40 + 30 * i, np.uint8)), ("semantics", sem), ("depth", depth)):
            (root / rel[k]).parent.mkdir(parents=True, exist_ok=True)
            Image.fromarray(a).save(root / rel[k])
        views.append({"index": i, "timestamp": 0.5 * i, "views": {CAM: {
            "image": rel["images"], "T_world_cam": pose(float(i)), "semantics": rel["semantics"],
            "depth": rel["depth"]}}})
    d = {"format": "pavemap-sequence/1", "name": "bad-input-test",
         "geo_origin": {"lat": 48.1, "lon": 11.5, "alt": 500.0, "heading_deg": 90.0},
         "classes": [{"id": 0, "name": "road", "road": True}, {"id": 1, "name": "car", "movable": True},
                     {"id": 2, "name": "sky", "sky": True}],
         "cameras": {CAM: {"width": W, "height": H, "K": [[30.0, 0, 15.5], [0, 30.0, 11.5], [0, 0, 1]]}},
         "frames": views}
    (root / "sequence.json").write_text(json.dumps(d))
    (root / "detections.jsonl").write_text("".join(json.dumps(r) + "\n" for r in DETECTIONS))
    return root


DETECTIONS = [{"frame": 0, "camera": CAM, "box": [4, 14, 12, 20], "cls": 0, "conf": 0.8},
              {"frame": 1, "camera": CAM, "box": [10, 15, 20, 22], "cls": 3, "conf": 0.6}]

# ---------------------------------------------------------------------------- strategies

_NUMBERS = st.one_of(
    st.integers(), st.integers(min_value=-(10**40), max_value=10**40),
    st.floats(allow_nan=True, allow_infinity=True), st.sampled_from([0, -1, 1, 255, 256, 2**31, 2**63, 1e308, 5e-324]),
)
_TEXT = st.one_of(st.text(max_size=20), st.sampled_from(["", "a/b", "..", "\x00", "\ud800", "x" * 5000, "NaN",
                                                          "false", "1234", CAM, "images/CAM_FRONT/000000.png"]))
JSON = st.recursive(st.one_of(st.none(), st.booleans(), _NUMBERS, _TEXT),
                    lambda inner: st.one_of(st.lists(inner, max_size=5),
                                            st.dictionaries(_TEXT, inner, max_size=5)),
                    max_leaves=12)


def _paths(v: object, prefix: tuple = ()) -> list[tuple]:
    """Every path into a JSON value (dict keys and list indices), the root included."""
    out = [prefix]
    if isinstance(v, dict):
        for k, x in v.items():
            out += _paths(x, (*prefix, k))
    elif isinstance(v, list):
        for i, x in enumerate(v):
            out += _paths(x, (*prefix, i))
    return out


def _deep(n: int) -> str:
    """A stand-in for ``n`` nested lists, expanded by :func:`dump` (too deep for json.dumps itself)."""
    return f"__deep_{n}__"


_DEEP = re.compile(r'"__deep_(\d+)__"')


@st.composite
def mutated(draw: st.DrawFn, base: object) -> object:
    """``base`` with one to three edits: a value replaced (by any JSON, a deep nesting, NaN …), a key
    dropped or added, a list shortened or lengthened."""
    v = json.loads(json.dumps(base))
    for _ in range(draw(st.integers(1, 3))):
        paths = _paths(v)
        path = draw(st.sampled_from(paths[1:] + paths[:1]))  # hypothesis favours the first: not the root
        action = draw(st.sampled_from(["replace", "replace", "drop", "add", "grow", "deep"]))
        new = draw(JSON) if action != "deep" else _deep(draw(st.sampled_from([40, 2000, 50000])))
        if not path:
            v = new if action in ("replace", "deep") else v
            continue
        parent = v
        for k in path[:-1]:
            parent = parent[k]
        key = path[-1]
        if action in ("replace", "deep"):
            parent[key] = new
        elif action == "drop":
            del parent[key]
        elif action == "add" and isinstance(parent[key], dict):
            parent[key][draw(_TEXT)] = new
        elif action == "grow" and isinstance(parent[key], list):
            parent[key] = parent[key] + parent[key][:1] if draw(st.booleans()) else parent[key][:-1]
    return v


def dump(v: object) -> bytes:
    """JSON text of ``v`` with NaN / Infinity literals allowed (Python's json writes them), deep stand-ins
    expanded."""
    text = json.dumps(v, allow_nan=True)
    text = _DEEP.sub(lambda m: "[" * int(m.group(1)) + "0" + "]" * int(m.group(1)), text)
    return text.encode("utf-8", "surrogatepass")


@st.composite
def mutated_bytes(draw: st.DrawFn, base: bytes) -> bytes:
    """``base`` cut short, with bytes inserted, flipped or replaced, a number turned into a literal
    JSON cannot hold as a float, or the whole wrapped in deep nesting."""
    b = bytearray(base)
    action = draw(st.sampled_from(["truncate", "insert", "flip", "number", "wrap", "encoding"]))
    pos = draw(st.integers(0, max(0, len(b) - 1)))
    if action == "truncate":
        return bytes(b[:pos])
    if action == "insert":
        return bytes(b[:pos]) + draw(st.binary(min_size=1, max_size=8)) + bytes(b[pos:])
    if action == "flip":
        for _ in range(draw(st.integers(1, 4))):
            i = draw(st.integers(0, max(0, len(b) - 1)))
            if b:
                b[i] = draw(st.integers(0, 255))
        return bytes(b)
    if action == "number":
        text = base.decode("utf-8", "replace")
        digits = [i for i, ch in enumerate(text) if ch.isdigit() and (i == 0 or not text[i - 1].isdigit())]
        if not digits:
            return base
        i = draw(st.sampled_from(digits))
        j = i
        while j < len(text) and (text[j].isdigit() or text[j] in ".eE-+"):
            j += 1
        lit = draw(st.sampled_from(["NaN", "Infinity", "-Infinity", "1e999", "9" * 5000, "-0", "1e-400"]))
        return (text[:i] + lit + text[j:]).encode()
    if action == "wrap":
        n = draw(st.sampled_from([5, 100, 100000]))
        return b"[" * n + base + b"]" * n
    return base.decode("utf-8", "replace").encode(draw(st.sampled_from(["utf-16", "latin-1", "cp1252"])), "replace")


# ---------------------------------------------------------------------------- the command line


def invoke(*args: object):  # noqa: ANN201
    """``pavemap ARGS`` in this process (typer's CliRunner); the result has exit_code and output."""
    from typer.testing import CliRunner

    from pavemap.cli import app

    return CliRunner().invoke(app, [str(a) for a in args])


def check(r, code: int, *words: str) -> None:  # noqa: ANN001
    """Exit status ``code``, no traceback, and every word in the output."""
    assert r.exception is None or isinstance(r.exception, SystemExit), f"traceback: {r.exception!r}\n{r.output}"
    assert "Traceback" not in r.output, r.output
    assert r.exit_code == code, f"exit {r.exit_code}, wanted {code}:\n{r.output}"
    for w in words:
        assert w.lower() in r.output.lower(), f"{w!r} not in:\n{r.output}"


def looks_complete(out: Path) -> list[str]:
    """Files whose presence says a command finished (a run's metrics.json, a sequence's sequence.json …)."""
    names = ("metrics.json", "defects.geojson", "report.html", "sequence.json", "eval.json", "changes.geojson",
             "changes.gpkg")
    return [n for n in names if (out / n).exists()]


# ---------------------------------------------------------------------------- targets


def sequence_target(root: Path, data: bytes) -> str:
    """Write ``data`` as ``root/sequence.json`` and read the folder the way every command does."""
    from pavemap.config import preset_for
    from pavemap.io.sequence import read_sequence, sequence_to_dict, validate_sequence

    (root / "sequence.json").write_bytes(data)
    try:
        seq = read_sequence(root)
        validate_sequence(seq, deep=True)  # what `pavemap info` adds
        traj = seq.trajectory()
        assert np.isfinite(traj).all(), "a non-finite trajectory was accepted"
        preset_for(seq)
        json.dumps(sequence_to_dict(seq), allow_nan=False)  # what was accepted can be written back
    except (SequenceError, PavemapError):
        return "error"
    return "ok"


def detections_target(seq: object, path: Path, data: bytes) -> str:
    """Write ``data`` as a detections file, read it, sanitise it against ``seq`` and write it back."""
    from pavemap.detect.filter import sanitize
    from pavemap.io.sequence import read_detections, write_detections

    path.write_bytes(data)
    try:
        dets = read_detections(path)
        clean, reasons = sanitize(seq, dets)  # type: ignore[arg-type]
        kept = [d for d in clean if d is not None]
        assert all(math.isfinite(v) for d in kept for v in (*d.box, d.conf)), "a non-finite detection was kept"
        back = path.with_suffix(".back.jsonl")
        write_detections(back, dets)
        assert len(read_detections(back)) == len(dets)
        assert len(reasons) == len(dets)
    except (SequenceError, PavemapError):
        return "error"
    return "ok"


__all__ = ["CAM", "DETECTIONS", "JSON", "check", "detections_target", "dump", "invoke", "looks_complete",
           "make_seq", "mutated", "mutated_bytes", "sequence_target"]
