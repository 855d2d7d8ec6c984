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


def _level_camera(height: float = 1.5):
    """A 200 x 100 camera looking along +x, level, ``height`` over the road z = 0; its pose."""
    from pavemap.types import Camera

    cam = Camera("front", 200, 100, np.array([[100.0, 0, 100], [0, 100.0, 50], [0, 0, 1]]))
    T = np.eye(4)
    T[:3, :3] = np.array([[0, 0, 1], [-1, 0, 0], [0, -1, 0]], float)  # camera z forward = world x
    T[2, 3] = height
    return cam, T


def test_no_road_rises_above_the_horizon_of_the_path():
    from pavemap.segment.plane_check import PlaneCheckConfig, above_path_horizon

    cam, T = _level_camera()
    flat = np.array([[x, 0.0, 1.5] for x in range(0, 100, 5)])
    up = above_path_horizon(cam, T, flat, 1.5, PlaneCheckConfig(horizon_margin_deg=1.0))
    # the horizon is row 50; 1 deg above it is 100 * tan(1 deg) = 1.75 rows up: the centre column's rows
    # 0..48 are above it (a ray off the centre rises less at the same row)
    assert np.where(up[:, 100])[0].max() == 48 and not up[49:].any()
    # a path that climbs 10 m in 100 m ahead: its road rises up to ~5 deg; that road stays road
    climb = np.array([[x, 0.0, 1.5 + 0.1 * x] for x in range(0, 100, 5)])
    up = above_path_horizon(cam, T, climb, 1.5, PlaneCheckConfig(horizon_margin_deg=1.0))
    row_5deg = int(50 - 100 * np.tan(np.radians(5.0)))
    assert not up[row_5deg:].any() and up[: row_5deg - 3, 100].all()


def test_sky_called_road_is_taken_out_and_the_road_is_kept(tiny_seq, tmp_path):
    seq, _, road = _vehicles_called_road(tiny_seq, tmp_path / "drive")
    above = seq.classes[-1].id
    road_id = next(c.id for c in seq.classes if c.name == "road")
    sky_ids = [c.id for c in seq.classes if c.sky]
    from PIL import Image

    sky = {}
    for f in seq.frames:
        for cam, v in f.views.items():
            lab = load_semantics(seq.path(v.semantics))
            sky[(f.index, cam)] = np.isin(lab, sky_ids)
            Image.fromarray(np.where(sky[(f.index, cam)], road_id, lab).astype(np.uint8)).save(seq.path(v.semantics))
    rep = plane_check_sequence(seq, camera_height=1.65)
    assert rep.checked >= len(seq.frames) - 2, rep.describe()
    found = lost = n_sky = n_road = 0
    for f in seq.frames:
        for cam, v in f.views.items():
            lab, k = load_semantics(seq.path(v.semantics)), (f.index, cam)
            found, n_sky = found + int((lab[sky[k]] == above).sum()), n_sky + int(sky[k].sum())
            lost, n_road = lost + int((lab[road[k]] == above).sum()), n_road + int(road[k].sum())
    assert found / n_sky > 0.9, f"only {found / n_sky:.1%} of the sky called road was taken out"
    assert lost / n_road < 0.03, f"{lost / n_road:.1%} of the true road was taken out"


def test_a_uniform_panel_goes_with_its_edges_and_the_road_stays():
    """A flat, uniform panel disagrees only at its edges under the road's warp; the region verdict takes the
    whole panel. The road around it, with scattered disagreeing pixels and a textured surface, stays road."""
    import torch

    from pavemap.segment.plane_check import PlaneCheckConfig, _region_verdict

    rng = np.random.default_rng(0)
    h, w = 120, 240
    img = np.full((3, h, w), 0.35) + rng.normal(0, 0.03, (1, h, w))  # textured asphalt
    img[:, 40:80, 60:110] = 0.75  # the panel: uniform
    panel = np.zeros((h, w), bool)
    panel[40:80, 60:110] = True
    inner = np.zeros((h, w), bool)
    inner[43:77, 63:107] = True
    ring = panel & ~inner  # its edges, 3 px wide
    noise = rng.random((h, w)) < 0.02
    off = torch.from_numpy(ring | noise)
    road = torch.ones(h, w, dtype=torch.bool)
    got = _region_verdict(torch.from_numpy(img.astype(np.float32)), off, ~off, road, PlaneCheckConfig()).numpy()
    assert got[panel].mean() > 0.9, f"{got[panel].mean():.0%} of the panel found"
    assert got[~panel].mean() < 0.01, f"{got[~panel].mean():.1%} of the road taken"
    # a region holding most of the view's road is the road itself, whatever its edges say (a sliver of the
    # panel that the segmentation cut off may still go)
    big = _region_verdict(torch.from_numpy(img.astype(np.float32)), off, ~off, torch.from_numpy(panel),
                          PlaneCheckConfig()).numpy()
    assert big[panel].mean() < 0.2
