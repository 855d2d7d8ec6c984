"""The schema of ``sequence.json`` and ``detections.jsonl`` (pavemap.io.schema, pydantic models): typed
access, the exact JSON path of every problem, pavemap's own wording, the limit, refused member names."""

from __future__ import annotations

import copy

from pavemap.io.jsonfile import parse_json
from pavemap.io.schema import (
    DetectionJson,
    SequenceJson,
    check_detection,
    check_sequence,
    issues_text,
    parse_detection,
    parse_sequence,
)

POSE = [[0.0, 0.0, 1.0, 2.0], [-1.0, 0.0, 0.0, 0.5], [0.0, -1.0, 0.0, 1.5], [0, 0, 0, 1]]
BASE = {"format": "pavemap-sequence/1", "name": "s",
        "classes": [{"id": 0, "name": "road", "road": True}],
        "cameras": {"front": {"width": 32, "height": 24, "K": [[30, 0, 16], [0, 30, 12], [0, 0, 1]]}},
        "frames": [{"index": i, "views": {"front": {"image": f"images/{i}.png", "T_world_cam": POSE}}}
                   for i in range(5)]}


def _with(change) -> dict:  # noqa: ANN001
    d = copy.deepcopy(BASE)
    change(d)
    return d


def _texts(d: object, limit: int = 50) -> list[str]:
    return [str(i) for i in check_sequence(d, limit)]


def test_typed_access_of_a_valid_file():
    d = _with(lambda d: d["frames"][1].update(timestamp=3))
    doc, issues = parse_sequence(d)
    assert issues == [] and isinstance(doc, SequenceJson)
    f = doc.frames[1]
    assert f.index == 1 and isinstance(f.timestamp, float) and f.timestamp == 3.0 and doc.frames[0].timestamp is None
    assert f.views["front"].T_world_cam[0][3] == 2.0 and f.views["front"].semantics is None
    assert doc.cameras["front"].width == 32 and doc.classes[0].road and not doc.classes[0].sky
    assert doc.geo_origin is None


def test_a_matrix_entry_is_named_by_its_full_path():
    d = _with(lambda d: d["frames"][3]["views"]["front"].update(
        T_world_cam=[[1, 0, 0, 0], [0, 1, "x", 0], [0, 0, 1, float("nan")], [0, 0, True, 1e300]]))
    assert _texts(d) == ['frames[3].views.front.T_world_cam[1][2]: must be a number, got a string "x"',
                         "frames[3].views.front.T_world_cam[2][3]: must be a finite number, got NaN",
                         "frames[3].views.front.T_world_cam[3][2]: must be a number, got true/false true",
                         "frames[3].views.front.T_world_cam[3][3]: must be in [-1e+09, 1e+09], got 1e+300"]


def test_huge_integers_and_wrong_types_keep_pavemaps_words():
    d = parse_json('{"frame": ' + "7" * 5000 + ', "camera": "{message}", "box": [1, 2, 3, ' + "9" * 400
                   + '], "cls": "1", "conf": NaN}', "d.jsonl")
    assert [str(i) for i in check_detection(d)] == [
        "frame: must be in -2147483648..2147483647, got an integer of 5000 digits",
        "box[3]: must be in [-1e+12, 1e+12], got an integer of 400 digits",
        'cls: must be an integer, got a string "1"']
    rec, issues = parse_detection({"frame": 2.0, "camera": "c", "box": [1, 2, 3, 4], "cls": 1, "conf": float("inf")})
    assert issues == [] and isinstance(rec, DetectionJson)
    assert rec.frame == 2 and isinstance(rec.frame, int) and rec.box == [1.0, 2.0, 3.0, 4.0]
    assert rec.conf == float("inf")


def test_issues_come_in_document_order_up_to_the_limit():
    def change(d: dict) -> None:
        d["name"] = ""
        d["cameras"]["front"].pop("K")
        for f in d["frames"]:
            f["index"] = -1
    assert _texts(_with(change)) == ["name: must not be empty", "cameras.front.K: is missing"] + [
        f"frames[{i}].index: must be in 0..2147483647, got -1" for i in range(5)]
    issues = check_sequence(_with(change), limit=3)
    assert [str(i) for i in issues] == _texts(_with(change))[:3]
    assert issues_text(check_sequence(_with(change))) == (
        "name: must not be empty; cameras.front.K: is missing; frames[0].index: must be in 0..2147483647, got -1 "
        "(and 4 more)")


def test_a_refused_member_name_is_reported_once_and_its_value_not_checked():
    d = _with(lambda d: d["frames"][0]["views"].update({"a/b": {"image": 5}, "bad\ud800": 3, "[key]": 4}))
    assert _texts(d) == [
        """frames[0].views key "a/b": must not contain '/' or '\\' or be '.' or '..', got a string "a/b\"""",
        'frames[0].views key "bad\\ud800": contains an invalid Unicode escape (a lone surrogate)',
        "frames[0].views.[key]: must be an object, got an integer 4"]


def test_containers_of_the_wrong_kind_or_size():
    assert _texts([1, 2]) == ["must be an object, got a list"]
    assert _texts(_with(lambda d: d.update(frames=[], cameras=[], classes={}))) == [
        "classes: must be a list, got an object", "cameras: must be an object of name -> value, got a list",
        "frames: must have at least 1 entry, got 0"]
    assert _texts(_with(lambda d: d["cameras"]["front"].update(K=[[1, 2, 3], [4, 5]]))) == [
        "cameras.front.K: must be a 3x3 matrix, got 2 rows of lengths [2, 3]"]
    assert _texts(_with(lambda d: d.update(geo_origin={"lat": 91, "lon": "11"}))) == [
        "geo_origin.lat: must be in [-90, 90], got 91", 'geo_origin.lon: must be a number, got a string "11"']
