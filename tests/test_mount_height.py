"""The mount height an import knew (``Camera.height_m``) travels in sequence.json and becomes stage 1's
camera-height prior unless the user's config sets one."""

from __future__ import annotations

import json

import numpy as np
import pytest

from pavemap.commands.options import resolve_config
from pavemap.errors import SequenceError
from pavemap.io.sequence import read_sequence, write_sequence
from pavemap.types import Camera, Frame, Sequence, View


def _seq(tmp_path, heights: dict[str, float | None]) -> Sequence:
    from PIL import Image

    cams = {n: Camera(n, 32, 24, np.array([[30.0, 0, 16], [0, 30, 12], [0, 0, 1]]), height_m=h)
            for n, h in heights.items()}
    views = {}
    for n in cams:
        (tmp_path / "images" / n).mkdir(parents=True, exist_ok=True)
        Image.new("RGB", (32, 24)).save(tmp_path / "images" / n / "000000.png")
        views[n] = View(n, f"images/{n}/000000.png", np.eye(4))
    seq = Sequence("s", [], cams, [Frame(0, 0.0, views)])
    write_sequence(seq, tmp_path)
    return read_sequence(tmp_path)


def test_height_round_trips_and_is_validated(tmp_path):
    seq = _seq(tmp_path, {"front": 1.32})
    assert seq.cameras["front"].height_m == pytest.approx(1.32)
    doc = json.loads((tmp_path / "sequence.json").read_text())
    doc["cameras"]["front"]["height_m"] = -1.0
    (tmp_path / "sequence.json").write_text(json.dumps(doc))
    with pytest.raises(SequenceError, match=r"cameras.front.height_m: must be in"):
        read_sequence(tmp_path)


def test_the_sequence_height_is_the_prior_unless_the_user_sets_one(tmp_path):
    seq = _seq(tmp_path / "a", {"front": 1.32})
    assert resolve_config(seq, None, None).mesh.camera_height == pytest.approx(1.32)  # not the kitti preset's 1.65
    assert resolve_config(seq, None, ["mesh.camera_height=1.7"]).mesh.camera_height == pytest.approx(1.7)
    yml = tmp_path / "c.yaml"
    yml.write_text("mesh:\n  camera_height: 1.65\n")
    assert resolve_config(seq, str(yml), None).mesh.camera_height == pytest.approx(1.65)
    # unknown, or cameras that disagree: the preset's
    assert resolve_config(_seq(tmp_path / "b", {"front": None}), None, None).mesh.camera_height == pytest.approx(1.65)
    two = _seq(tmp_path / "c", {"f": 1.5, "r": 1.8})
    assert resolve_config(two, None, None).mesh.camera_height == pytest.approx(1.5)  # the nuscenes preset's own
