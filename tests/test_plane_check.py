"""The plane-parallax check of a road mask (pavemap.segment.plane_check): what stands above the road and was
called road is found, the road itself is kept, and a drive it cannot check is left as it was, with the reason."""

from __future__ import annotations

import copy
import shutil

import numpy as np
import pytest

from pavemap.io.sequence import load_semantics, read_sequence
from pavemap.segment.plane_check import plane_check_sequence
from pavemap.types import SemanticClass


def _vehicles_called_road(src, dst):
    """A copy of the synthetic drive whose label maps call its vehicles road (a segmenter's typical mistake),
    with an above_road class in its table; returns (sequence, {view: true vehicle mask}, {view: true road})."""
    shutil.copytree(src.root, dst)
    seq = read_sequence(dst)
    road_id = next(c.id for c in seq.classes if c.name == "road")
    veh_id = next(c.id for c in seq.classes if c.name == "vehicle")
    road_ids = [c.id for c in seq.classes if c.road]
    seq.classes = [*seq.classes, SemanticClass(max(c.id for c in seq.classes) + 1, "above_road", movable=True)]
    vehicle, road = {}, {}
    from PIL import Image

    for f in seq.frames:
        for cam, v in f.views.items():
            lab = load_semantics(seq.path(v.semantics))
            vehicle[(f.index, cam)], road[(f.index, cam)] = lab == veh_id, np.isin(lab, road_ids)
            Image.fromarray(np.where(lab == veh_id, road_id, lab).astype(np.uint8)).save(seq.path(v.semantics))
    return seq, vehicle, road


def test_vehicles_called_road_are_found_and_the_road_is_kept(tiny_seq, tmp_path):
    seq, vehicle, road = _vehicles_called_road(tiny_seq, tmp_path / "drive")
    above = seq.classes[-1].id
    if sum(int(m.sum()) for m in vehicle.values()) < 200:
        pytest.skip("the synthetic drive shows no vehicle")
    rep = plane_check_sequence(seq, camera_height=1.65)
    assert rep.checked >= len(seq.frames) - 2, rep.describe()
    found = lost = veh = rd = 0
    for f in seq.frames:
        for cam, v in f.views.items():
            lab = load_semantics(seq.path(v.semantics))
            found += int((lab[vehicle[(f.index, cam)]] == above).sum())
            lost += int((lab[road[(f.index, cam)]] == above).sum())
            veh, rd = veh + int(vehicle[(f.index, cam)].sum()), rd + int(road[(f.index, cam)].sum())
    assert found / veh > 0.1, f"only {found / veh:.1%} of the vehicles called road were found"
    assert lost / rd < 0.03, f"{lost / rd:.1%} of the true road was taken for something above it"


def test_a_wrong_camera_height_or_none_is_not_a_silent_check(tiny_seq, tmp_path):
    seq, _, _ = _vehicles_called_road(tiny_seq, tmp_path / "drive")
    for cam in seq.cameras.values():
        cam.height_m = None
    before = [load_semantics(seq.path(v.semantics)) for f in seq.frames for v in f.views.values()]
    rep = plane_check_sequence(seq)  # no height known
    assert rep.checked == 0 and "no camera height known" in " ".join(rep.skipped)
    after = [load_semantics(seq.path(v.semantics)) for f in seq.frames for v in f.views.values()]
    assert all((a == b).all() for a, b in zip(before, after, strict=True))


def test_a_drive_without_an_above_road_class_is_left_alone(tiny_seq, tmp_path):
    seq, _, _ = _vehicles_called_road(tiny_seq, tmp_path / "drive")
    seq = copy.deepcopy(seq)
    seq.classes = seq.classes[:-1]
    rep = plane_check_sequence(seq, camera_height=1.65)
    assert rep.checked == 0 and "no above_road class" in " ".join(rep.skipped)


def test_a_standing_car_gives_no_partner(tiny_seq, tmp_path):
    seq, _, _ = _vehicles_called_road(tiny_seq, tmp_path / "drive")
    T0 = seq.frames[0].views[next(iter(seq.frames[0].views))].T_world_cam
    for f in seq.frames:
        for v in f.views.values():
            v.T_world_cam = T0.copy()  # the camera never moves: no baseline, no parallax
    rep = plane_check_sequence(seq, camera_height=1.65)
    assert rep.checked == 0 and rep.no_partner == rep.views
    assert "without a partner view" in rep.describe()
