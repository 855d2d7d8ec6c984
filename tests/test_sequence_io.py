"""The sequence folder (SPEC §6): round trip and every validation error names the file."""

from __future__ import annotations

import copy
import json
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from pavemap.io.sequence import (
    SequenceError,
    read_detections,
    read_sequence,
    sequence_from_dict,
    sequence_to_dict,
    write_detections,
    write_sequence,
)
from pavemap.types import Camera, Detection, Frame, GeoOrigin, SemanticClass, Sequence, View

W, H = 32, 24


def _pose(x: float) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
    T[:3, 3] = [x, 0.5, 1.5]
    return T


def _make(root: Path, n: int = 3) -> Sequence:
    K = np.array([[30.0, 0, W / 2], [0, 30.0, H / 2], [0, 0, 1]])
    frames = []
    for i in range(n):
        img = f"images/CAM_FRONT/{i:06d}.png"
        sem = f"semantics/CAM_FRONT/{i:06d}.png"
        for rel, arr in ((img, np.full((H, W, 3), 10 * i, np.uint8)), (sem, np.full((H, W), i % 2, np.uint8))):
            (root / rel).parent.mkdir(parents=True, exist_ok=True)
            Image.fromarray(arr).save(root / rel)
        frames.append(Frame(2 * i, 0.5 * i, {"CAM_FRONT": View("CAM_FRONT", img, _pose(float(i)), sem, None)}))
    classes = [SemanticClass(0, "road", road=True), SemanticClass(1, "car", movable=True),
               SemanticClass(2, "sky", sky=True)]
    seq = Sequence("roundtrip", classes, {"CAM_FRONT": Camera("CAM_FRONT", W, H, K)}, frames,
                   GeoOrigin(48.1, 11.5, 520.0, 80.0), root)
    write_sequence(seq, root)
    return seq


def _dict(root: Path) -> dict:
    return json.loads((root / "sequence.json").read_text())


def _rewrite(root: Path, d: dict) -> None:
    (root / "sequence.json").write_text(json.dumps(d))


def test_round_trip(tmp_path):
    seq = _make(tmp_path)
    back = read_sequence(tmp_path)
    assert back.name == seq.name
    assert back.classes == seq.classes
    assert back.road_class_ids == [0] and back.movable_class_ids == [1] and back.sky_class_ids == [2]
    assert [f.index for f in back.frames] == [0, 2, 4]
    assert [f.timestamp for f in back.frames] == [0.0, 0.5, 1.0]
    for a, b in zip(seq.frames, back.frames, strict=True):
        va, vb = a.views["CAM_FRONT"], b.views["CAM_FRONT"]
        assert (va.image, va.semantics, va.depth) == (vb.image, vb.semantics, vb.depth)
        np.testing.assert_allclose(va.T_world_cam, vb.T_world_cam)
    np.testing.assert_allclose(back.cameras["CAM_FRONT"].K, seq.cameras["CAM_FRONT"].K)
    assert back.geo_origin == seq.geo_origin
    # dict -> Sequence -> dict is the identity
    assert sequence_to_dict(sequence_from_dict(_dict(tmp_path), tmp_path)) == _dict(tmp_path)
    dets = [Detection(0, "CAM_FRONT", (1.0, 2.0, 10.0, 12.5), 3, 0.75), Detection(2, "CAM_FRONT", (0, 0, 5, 5), 0, 0.1)]
    write_detections(tmp_path / "detections.jsonl", dets)
    assert read_detections(tmp_path / "detections.jsonl") == dets
    read_sequence(tmp_path)  # still valid with detections present


def test_missing_image_names_the_file(tmp_path):
    _make(tmp_path)
    (tmp_path / "images/CAM_FRONT/000001.png").unlink()
    with pytest.raises(SequenceError) as e:
        read_sequence(tmp_path)
    assert e.value.file.endswith("images/CAM_FRONT/000001.png")
    assert "missing" in str(e.value)


def test_wrong_image_size(tmp_path):
    _make(tmp_path)
    Image.fromarray(np.zeros((H + 2, W, 3), np.uint8)).save(tmp_path / "images/CAM_FRONT/000000.png")
    with pytest.raises(SequenceError) as e:
        read_sequence(tmp_path)
    assert e.value.file.endswith("images/CAM_FRONT/000000.png")
    assert f"{W}x{H + 2}" in str(e.value)


@pytest.mark.parametrize(
    ("K", "words"),
    [
        ([[30.0, 0, 16], [0, 30.0, 12]], "3x3"),
        ([[30.0, 0, 16], [1.0, 30.0, 12], [0, 0, 1]], "upper-triangular"),
        ([[-30.0, 0, 16], [0, 30.0, 12], [0, 0, 1]], "positive"),
        ([[30.0, 0, 16], [0, 0.0, 12], [0, 0, 1]], "positive"),
    ],
)
def test_bad_intrinsics(tmp_path, K, words):
    _make(tmp_path)
    d = _dict(tmp_path)
    d["cameras"]["CAM_FRONT"]["K"] = K
    with pytest.raises(SequenceError) as e:
        sequence_from_dict(d, tmp_path)
    assert e.value.file.endswith("sequence.json")
    assert "CAM_FRONT" in str(e.value) and words in str(e.value)
    _rewrite(tmp_path, d)
    with pytest.raises(SequenceError, match=words):
        read_sequence(tmp_path)


@pytest.mark.parametrize(
    ("mutate", "words"),
    [
        (lambda T: T.__setitem__((0, 0), 2.0), "orthonormal"),  # scaled axis: not rigid
        (lambda T: T.__setitem__((slice(0, 3), 0), -T[:3, 0]), "det"),  # reflection
        (lambda T: T.__setitem__((1, 3), float("nan")), "NaN"),
    ],
)
def test_bad_pose(tmp_path, mutate, words):
    _make(tmp_path)
    d = _dict(tmp_path)
    T = np.array(d["frames"][1]["views"]["CAM_FRONT"]["T_world_cam"])
    mutate(T)
    d["frames"][1]["views"]["CAM_FRONT"]["T_world_cam"] = T.tolist()
    with pytest.raises(SequenceError) as e:
        sequence_from_dict(d, tmp_path)
    assert e.value.file.endswith("sequence.json")
    assert "frames[1]" in str(e.value) and words in str(e.value)


def test_nan_pose_through_json_file(tmp_path):
    _make(tmp_path)
    text = (tmp_path / "sequence.json").read_text()
    d = json.loads(text)
    d["frames"][0]["views"]["CAM_FRONT"]["T_world_cam"][0][3] = "NaN-marker"
    text = json.dumps(d).replace('"NaN-marker"', "NaN")  # Python's json reads the NaN literal
    (tmp_path / "sequence.json").write_text(text)
    with pytest.raises(SequenceError, match="NaN"):
        read_sequence(tmp_path)


@pytest.mark.parametrize(("indices", "words"), [([0, 2, 2], "repeats"), ([0, 4, 2], "decreases")])
def test_duplicate_or_decreasing_frames(tmp_path, indices, words):
    _make(tmp_path)
    d = _dict(tmp_path)
    for f, i in zip(d["frames"], indices, strict=True):
        f["index"] = i
    with pytest.raises(SequenceError) as e:
        sequence_from_dict(d, tmp_path)
    assert e.value.file.endswith("sequence.json") and words in str(e.value)
    # gaps alone are fine (dropped or held-out frames)
    d2 = copy.deepcopy(d)
    for f, i in zip(d2["frames"], [0, 5, 9], strict=True):
        f["index"] = i
    assert [f.index for f in sequence_from_dict(d2, tmp_path).frames] == [0, 5, 9]


def test_unknown_class_in_detections(tmp_path):
    _make(tmp_path)
    p = tmp_path / "detections.jsonl"
    p.write_text(json.dumps({"frame": 0, "camera": "CAM_FRONT", "box": [0, 0, 4, 4], "cls": 0, "conf": 0.5}) + "\n"
                 + json.dumps({"frame": 2, "camera": "CAM_FRONT", "box": [0, 0, 4, 4], "cls": 7, "conf": 0.5}) + "\n")
    with pytest.raises(SequenceError) as e:
        read_detections(p)
    assert e.value.file.endswith("detections.jsonl") and "line 2" in str(e.value) and "class id 7" in str(e.value)
    with pytest.raises(SequenceError, match="class id 7"):
        read_sequence(tmp_path)


def test_unknown_camera_and_missing_folder(tmp_path):
    _make(tmp_path)
    d = _dict(tmp_path)
    d["frames"][0]["views"]["CAM_BACK"] = d["frames"][0]["views"]["CAM_FRONT"]
    with pytest.raises(SequenceError, match="unknown camera 'CAM_BACK'"):
        sequence_from_dict(d, tmp_path)
    with pytest.raises(SequenceError, match="sequence.json"):
        read_sequence(tmp_path / "nope")
