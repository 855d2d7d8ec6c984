"""Time the schema check of a large ``sequence.json`` (docs/guide/bad-input.md, "How long the check takes").

Builds a valid sequence of FRAMES x VIEWS views in memory, writes it to a temporary file, and times the
parse (:func:`pavemap.io.jsonfile.load_json`), the schema check (:func:`pavemap.io.schema.check_sequence`)
on the valid file and on one with an error in every view, and the whole reader
(:func:`pavemap.io.sequence.sequence_from_dict`). Best of REPEAT runs, in seconds.

    python scripts/schema_timing.py [FRAMES] [VIEWS] [REPEAT]
"""

from __future__ import annotations

import json
import sys
import tempfile
import time
from pathlib import Path

from pavemap.io.jsonfile import load_json
from pavemap.io.schema import check_sequence
from pavemap.io.sequence import sequence_from_dict


def big_sequence(frames: int, views: int) -> dict:
    """A valid ``sequence.json`` dict: ``frames`` frames, each with ``views`` cameras."""
    K = [[500.0, 0.0, 320.0], [0.0, 500.0, 240.0], [0.0, 0.0, 1.0]]
    cams = [f"CAM_{i}" for i in range(views)]

    def pose(i: int) -> list[list[float]]:
        return [[0.0, 0.0, 1.0, 0.1 * i], [-1.0, 0.0, 0.0, 0.5], [0.0, -1.0, 0.0, 1.5], [0.0, 0.0, 0.0, 1.0]]

    return {"format": "pavemap-sequence/1", "name": "timing",
            "geo_origin": {"lat": 48.1, "lon": 11.5, "alt": 500.0, "heading_deg": 90.0},
            "classes": [{"id": 0, "name": "road", "road": True}, {"id": 1, "name": "car", "movable": True}],
            "cameras": {c: {"width": 640, "height": 480, "K": K} for c in cams},
            "frames": [{"index": i, "timestamp": 0.1 * i,
                        "views": {c: {"image": f"images/{c}/{i:06d}.jpg", "T_world_cam": pose(i),
                                      "semantics": f"semantics/{c}/{i:06d}.png", "depth": None} for c in cams}}
                       for i in range(frames)]}


def best(fn, repeat: int) -> float:  # noqa: ANN001
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return min(times)


def main() -> None:
    frames, views, repeat = (int(a) for a in (sys.argv[1:] + ["5000", "6", "3"][len(sys.argv) - 1:]))
    d = big_sequence(frames, views)
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "sequence.json"
        path.write_text(json.dumps(d))
        size = path.stat().st_size
        parse = best(lambda: load_json(path), repeat)
    valid = best(lambda: check_sequence(d), repeat)
    bad = json.loads(json.dumps(d))
    for f in bad["frames"]:
        for v in f["views"].values():
            v["T_world_cam"][0][3] = "x"  # an error in every view: the check stops at its limit (50)
    invalid = best(lambda: check_sequence(bad), repeat)
    reader = best(lambda: sequence_from_dict(d), repeat)
    print(f"{frames} frames x {views} views, {size / 1e6:.1f} MB: parse {parse:.3f} s, check (valid) {valid:.3f} s, "
          f"check (an error in every view) {invalid:.3f} s, sequence_from_dict {reader:.3f} s (best of {repeat})")


if __name__ == "__main__":
    main()
