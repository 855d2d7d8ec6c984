"""A pothole's floor from the images alone (pavemap.maintain.floor_sweep), on synthetic drives with truth."""

from __future__ import annotations

import json

import numpy as np
import pytest
from shapely.geometry import shape

from pavemap.io.sequence import read_sequence
from pavemap.io.truth import read_truth_height
from pavemap.maintain.floor_sweep import FloorSweepConfig, _road_plane, floor_samples

# the maintenance bench's kitti-like drive (40 frames, more defects than the preset; bench/maintenance_bench.py)
WORLD = dict(preset="kitti-like", seed=0, frames=40, depth="none", progress=False, road_after=30.0,
             defect_density=40.0, class_mix=(0.3, 0.2, 0.15, 0.35))


@pytest.fixture(scope="module")
def drives(tmp_path_factory) -> dict:
    from pavemap.synth import synthesize

    root = tmp_path_factory.mktemp("floor")
    out = {}
    for name, scale in (("full", 1.0), ("half", 0.5)):
        synthesize(root / name, scale=scale, **WORLD)
        out[name] = root / name
    return out


def _potholes(root) -> list[tuple[object, dict]]:
    feats = json.loads((root / "truth" / "defects.geojson").read_text())["features"]
    return [(shape(f["geometry"]), f["properties"]) for f in feats if f["properties"]["cls"] == 3]


def _deepest_mm(pts: np.ndarray, poly, surface) -> float:
    p0, n = _road_plane(poly, surface, FloorSweepConfig())
    return float(np.quantile((p0 - pts) @ n, 0.99)) * 1000.0


def test_full_size_frames_measure_the_floor_to_a_centimetre(drives):
    """On the true surface and outlines, the deepest point of every pothole near views see whole and past its
    near rim is within 12 mm of the truth (median within 8 mm), and the rest say why they were not measured."""
    root = drives["full"]
    seq, surface = read_sequence(root), read_truth_height(root)
    errors, reasons = [], []
    for poly, props in _potholes(root):
        pts, why = floor_samples(seq, [poly], surface)
        if why[0] is not None:
            reasons.append(why[0])
            assert len(pts) == 0
            continue
        assert len(pts) >= 5
        errors.append(_deepest_mm(pts, poly, surface) - 1000.0 * props["depth_max_m"])
    assert len(errors) >= 2, reasons
    assert max(abs(e) for e in errors) <= 12.0, errors
    assert float(np.median(np.abs(errors))) <= 8.0, errors
    assert all(r.startswith(("no two views", "images too coarse", "2 of 3 views", "its near rim hides"))
               for r in reasons), reasons


def test_hidden_share_is_the_strip_behind_the_near_rim():
    """A camera h above the road at range D sees a floor d deep only from d D / h past the near rim: the share of
    a polygon E long toward the camera that this strip covers."""
    from types import SimpleNamespace

    from shapely.geometry import MultiPolygon, box

    from pavemap.maintain.floor_sweep import _hidden_share

    h, D, E, d = 1.5, 9.0, 1.2, 0.05
    T = np.eye(4)
    T[:3, 3] = [0.0, 0.0, h]
    plane = (np.array([D, 0.0, 0.0]), np.array([0.0, 0.0, 1.0]))
    share = _hidden_share(SimpleNamespace(T_world_cam=T), box(D - E / 2, -0.3, D + E / 2, 0.3), plane, d)
    assert share == pytest.approx(d * D / h / E)
    # a pothole fused from parts: its largest part's own near rim hides its floor
    parts = MultiPolygon([box(D - E / 2, -0.3, D, 0.3), box(D + 0.1, -0.3, D + 0.3, 0.3)])
    assert _hidden_share(SimpleNamespace(T_world_cam=T), parts, plane, d) == pytest.approx(2 * share)


def test_a_floor_the_views_cannot_see_past_the_near_rim_is_not_measured(drives):
    """The near-rim rule: a pothole measured with the defaults is not measured when the floor that must be seen
    lies so deep that the rim hides its middle from the views, and says so."""
    root = drives["full"]
    seq, surface = read_sequence(root), read_truth_height(root)
    polys = [p for p, _ in _potholes(root)]
    _, why = floor_samples(seq, polys, surface)
    measured = [p for p, w in zip(polys, why, strict=True) if w is None]
    assert measured, why
    pts, why = floor_samples(seq, measured[:1], surface, FloorSweepConfig(hidden_depth_m=0.5))
    assert len(pts) == 0 and why[0].startswith("its near rim hides the middle of a 50 cm deep floor from"), why


def test_half_size_frames_are_too_coarse_and_say_so(drives):
    """At half KITTI's size a pixel row covers ~9 cm of road at a pothole 7 m away: no depth, a reason."""
    root = drives["half"]
    seq, surface = read_sequence(root), read_truth_height(root)
    pits = _potholes(root)
    pts, why = floor_samples(seq, [p for p, _ in pits], surface)
    assert len(pts) == 0
    coarse = [w for w in why if w and w.startswith("images too coarse")]
    assert coarse, why
    assert "a pixel covers" in coarse[0] and "1 cm of depth moves it" in coarse[0]


def test_flat_road_reads_no_dent(drives):
    """Pothole-sized disks of plain road 3-6 m ahead, 3 m aside, read as flat: their deepest points within 20 mm
    of 0, the median within 8 mm."""
    root = drives["full"]
    seq, surface = read_sequence(root), read_truth_height(root)
    import torch
    from shapely.geometry import Point

    feats = json.loads((root / "truth" / "defects.geojson").read_text())["features"]
    defects = [shape(f["geometry"]).buffer(0.7) for f in feats]
    plain = []
    for f in seq.frames[::2]:
        T = np.asarray(f.views["CAM_FRONT"].T_world_cam)
        fwd = T[:3, 2] / np.linalg.norm(T[:2, 2])
        left = np.array([-fwd[1], fwd[0], 0.0])
        for ahead, side in ((3.0, 3.0), (3.0, -3.0), (6.0, 3.0), (6.0, -3.0)):
            c = T[:3, 3] + ahead * fwd + side * left
            disk = Point(c[0], c[1]).buffer(0.3)
            g = np.stack(np.meshgrid(np.linspace(c[0] - 0.9, c[0] + 0.9, 19),
                                     np.linspace(c[1] - 0.9, c[1] + 0.9, 19)), -1).reshape(-1, 2)
            z, inside = surface.height_at(torch.from_numpy(g).float())
            A = np.c_[np.ones(len(g)), g - c[:2]]
            flat = inside.all() and np.abs(z.numpy() - A @ np.linalg.lstsq(A, z.numpy(), rcond=None)[0]).max() < 0.012
            if flat and not any(disk.intersects(d) for d in defects):  # plain road, no kerb
                plain.append(disk)
    plain = plain[:12]
    pts, why = floor_samples(seq, plain, surface)
    read = [(p, why[k]) for k, p in enumerate(plain)]
    measured = [p for p, w in read if w is None]
    assert len(measured) >= 3, why
    depths = [_deepest_mm(floor_samples(seq, [p], surface)[0], p, surface) for p in measured]
    # the bench's 169 disks on this drive: median 5.5 mm, p90 12, max 20 (the 0.99 quantile of noise)
    assert max(abs(d) for d in depths) <= 20.0 and float(np.median(np.abs(depths))) <= 8.0, depths


def test_a_pothole_no_view_sees_whole_is_not_measured(drives):
    root = drives["full"]
    seq, surface = read_sequence(root), read_truth_height(root)
    poly, _ = _potholes(root)[0]
    far = FloorSweepConfig(max_ref_range_m=1.0)
    pts, why = floor_samples(seq, [poly], surface, far)
    assert len(pts) == 0 and why[0].startswith("no two views within 1 m")


def test_run_measures_pothole_depth_without_depth_only_when_asked(drives, tmp_path):
    """`maintenance.floor_sweep`: off, a no-depth run says the floor was not measured; on, the potholes it
    measures carry a depth from the images' floor samples."""
    import pavemap
    from pavemap.export.geojson import read_geojson

    notes = {}
    for on in (False, True):
        cfg = pavemap.load_config("kitti")
        cfg.device = "cpu"
        cfg.maintenance.floor_sweep = on
        cfg.output.figures = False
        cfg.output.report = False
        out = tmp_path / f"run-{on}"
        pavemap.run(drives["full"], cfg, out, progress=False)
        layer = read_geojson(out / "defects.geojson")
        assert not any(k in p for p in layer.properties for k in ("footprint_outline", "floor_samples"))
        notes[on] = [(p.get("depth_max_mm"), p.get("measure_note")) for p in layer.properties
                     if p.get("class_code", p.get("code")) == "D40" or p.get("cls") == 3]
    assert notes[False] and all(d is None and "floor not measured (no depth measurements)" in n
                                for d, n in notes[False])
    measured = [(d, n) for d, n in notes[True] if d is not None]
    assert measured, notes[True]
    assert all("floor-sweep samples" in n for _, n in measured)
    assert all(20.0 < d < 120.0 for d, _ in measured)


def test_views_whose_bonnet_hides_the_pothole_are_not_used(drives):
    """A camera whose ego mask covers the whole image sees no pothole: none is measured, and the reason says so."""
    from PIL import Image

    root = drives["full"]
    seq, surface = read_sequence(root), read_truth_height(root)
    cam = seq.cameras["CAM_FRONT"]
    mask = root / "masks" / "all.png"
    mask.parent.mkdir(exist_ok=True)
    Image.fromarray(np.full((cam.height, cam.width), 255, np.uint8)).save(mask)
    try:
        cam.ego_mask = "masks/all.png"
        pts, why = floor_samples(seq, [p for p, _ in _potholes(root)], surface)
    finally:
        mask.unlink()
    assert len(pts) == 0 and all(w.startswith("no two views") for w in why), why


def test_the_sweep_outline_is_the_finest_detections_footprint():
    """instance_outlines: per pothole the footprint of its detection with the least road per pixel; none for
    other classes or without a usable footprint."""
    from shapely.geometry import box

    from pavemap.fuse.footprint import instance_outlines
    from pavemap.types import DefectInstance

    def inst(iid: int, cls: int) -> DefectInstance:
        return DefectInstance(id=iid, cls=cls, polygon=box(0, 0, 1, 1), severity_mean=0.5, severity_max=0.5,
                              confidence=0.9, observations=3, probability=0.9, area_m2=1.0, length_m=1.0,
                              centroid=(0.5, 0.5), priority="inspect", extra={})

    quads = np.array([np.full((4, 2), float(k)) for k in range(5)])
    quads[3] = np.nan  # no footprint (cut off by the image border)
    insts = [inst(1, 3), inst(2, 3), inst(3, 0)]
    inst_of = np.array([1, 1, 2, 2, 3])
    ground_px = np.array([0.05, 0.02, 0.04, 0.01, 0.01])
    instance_outlines(insts, inst_of, quads, ground_px)
    assert insts[0].extra["footprint_outline"] == [[1.0, 1.0]] * 4  # 0.02 m per pixel beats 0.05
    assert insts[1].extra["footprint_outline"] == [[2.0, 2.0]] * 4  # the finer one has no footprint
    assert "footprint_outline" not in insts[2].extra  # a crack needs none
