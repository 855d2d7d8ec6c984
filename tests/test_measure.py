"""Surface measures (pavemap.maintain.measure): pothole depth / volume, crack length / orientation, truth."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from shapely.geometry import box

from pavemap.geometry import HeightField
from pavemap.maintain.measure import measure_instances, robust_plane, skeleton_length
from pavemap.types import DefectInstance

RES = 0.1
NX, NY = 80, 60  # 8 m x 6 m


def _inst(iid: int, cls: int, centroid=(0.0, 0.0)) -> DefectInstance:
    return DefectInstance(id=iid, cls=cls, polygon=box(0, 0, 1, 1), severity_mean=0.5, severity_max=0.5,
                          confidence=0.9, observations=5, probability=0.9, area_m2=1.0, length_m=1.0,
                          centroid=centroid, priority="inspect", extra={})


def _road(noise_m: float = 0.0, seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(ny, nx) heights of a tilted, crowned road (2 % grade, 1.5 % cross slope, 5 cm crown over 3.5 m), X, Y."""
    x = np.arange(NX) * RES
    y = np.arange(NY) * RES
    X, Y = np.meshgrid(x, y)
    z = 10.0 + 0.02 * X + 0.015 * Y - 0.05 * ((Y - 3.0) / 3.5) ** 2
    if noise_m:
        z = z + np.random.default_rng(seed).normal(0, noise_m, z.shape)
    return z, X, Y


def _bowl(X: np.ndarray, Y: np.ndarray, cx: float, cy: float, R: float, D: float) -> np.ndarray:
    """Paraboloid dent D (1 - r²/R²) inside r < R: volume pi R² D / 2 (m³), max D."""
    r2 = ((X - cx) ** 2 + (Y - cy) ** 2) / (R * R)
    return np.where(r2 < 1, D * (1 - r2), 0.0)


def _surface(z: np.ndarray, valid: np.ndarray | None = None) -> HeightField:
    v = np.ones_like(z, dtype=bool) if valid is None else valid
    return HeightField(0.0, 0.0, RES, torch.as_tensor(z, dtype=torch.float32), torch.as_tensor(v))


def _labels_disk(X, Y, cx, cy, R, iid=1) -> np.ndarray:
    lab = np.zeros(X.shape, np.int32)
    lab[(X - cx) ** 2 + (Y - cy) ** 2 < R * R] = iid
    return lab


@pytest.mark.parametrize("footprint", [0.5, 0.4, 0.6])  # instance smaller / larger than the dent
def test_bowl_depth_and_volume(footprint):
    z, X, Y = _road()
    cx, cy, R, D = 4.0, 2.0, 0.5, 0.06  # off the crown: the cross slope and crown both act on the ring
    z = z - _bowl(X, Y, cx, cy, R, D)
    inst = _inst(1, 3)
    measure_instances([inst], _surface(z), _labels_disk(X, Y, cx, cy, footprint))
    e = inst.extra
    assert e["measurable"] is True and e["measure_note"] == ""
    assert abs(e["depth_max_mm"] - D * 1000) <= 2.0, e
    vol_l = math.pi * R * R * D / 2 * 1000
    assert abs(e["volume_l"] - vol_l) <= 0.05 * vol_l, (e, vol_l)
    assert e["depth_mean_mm"] == pytest.approx(D * 1000 / 2, rel=0.15)
    assert e["depth_sigma_mm"] < 1.0


def test_bowl_on_noisy_mesh_has_sigma():
    z, X, Y = _road(noise_m=0.004, seed=3)
    z = z - _bowl(X, Y, 4.0, 3.0, 0.6, 0.08)
    inst = _inst(1, 3)
    measure_instances([inst], _surface(z), _labels_disk(X, Y, 4.0, 3.0, 0.6))
    e = inst.extra
    assert e["measurable"]
    assert abs(e["depth_max_mm"] - 80) < 15
    assert 2.5 < e["depth_sigma_mm"] < 8.0  # the ring residual (4 mm) shows up in the uncertainty


def test_plane_fit_ignores_outliers():
    rng = np.random.default_rng(0)
    x, y = rng.uniform(-1, 1, 200), rng.uniform(-1, 1, 200)
    z = 1.0 + 0.1 * x - 0.2 * y + rng.normal(0, 0.001, 200)
    z[:30] -= 0.05  # a wall of the dent inside the ring
    coef, sigma, keep = robust_plane(x, y, z)
    assert coef[0] == pytest.approx(1.0, abs=0.001)
    assert not keep[:30].any() and sigma < 0.002


def test_pothole_at_mesh_edge_not_measurable():
    z, X, Y = _road()
    z = z - _bowl(X, Y, 0.2, 3.0, 0.5, 0.06)  # cut by the grid's left edge
    inst = _inst(1, 3)
    measure_instances([inst], _surface(z), _labels_disk(X, Y, 0.2, 3.0, 0.5))
    assert inst.extra["measurable"] is False and "mesh edge" in inst.extra["measure_note"]
    assert all(inst.extra[k] is None for k in ("depth_max_mm", "depth_mean_mm", "volume_l", "depth_sigma_mm"))


def test_pothole_next_to_invalid_mesh_not_measurable():
    z, X, Y = _road()
    z = z - _bowl(X, Y, 4.0, 3.0, 0.5, 0.06)
    valid = X < 4.2  # the crop ends through the pothole
    inst = _inst(1, 3)
    measure_instances([inst], _surface(z, valid), _labels_disk(X, Y, 4.0, 3.0, 0.5))
    assert inst.extra["measurable"] is False and inst.extra["depth_max_mm"] is None


def test_pothole_on_unobserved_ground_not_measurable():
    z, X, Y = _road()
    z = z - _bowl(X, Y, 4.0, 3.0, 0.5, 0.06)
    observed = ~(((X - 4.0) ** 2 + (Y - 3.0) ** 2) < 0.8 ** 2)
    inst = _inst(1, 3)
    measure_instances([inst], _surface(z), _labels_disk(X, Y, 4.0, 3.0, 0.5), observed=torch.as_tensor(observed))
    assert inst.extra["measurable"] is False and inst.extra["measure_note"] == "unobserved ground"
    assert inst.extra["volume_l"] is None


def test_ring_excludes_other_instances():
    z, X, Y = _road()
    z = z - _bowl(X, Y, 4.0, 3.0, 0.5, 0.06)
    lab = _labels_disk(X, Y, 4.0, 3.0, 0.5)
    # a neighbouring patch (instance 2) raised 5 cm over half the ring: it must not lift the plane
    other = (X > 4.8) & (X < 5.4) & (np.abs(Y - 3.0) < 1.0)
    lab[other] = 2
    z = np.where(other, z + 0.05, z)
    inst = _inst(1, 3)
    measure_instances([inst, _inst(2, 2)], _surface(z), lab)
    assert abs(inst.extra["depth_max_mm"] - 60) <= 2.0


def _line_mask(pts: np.ndarray, width: int = 1, shape=(60, 80)) -> tuple[np.ndarray, float]:
    """Rasterise a polyline (vertices in cells) with a square brush; returns the mask and its length (m)."""
    m = np.zeros(shape, bool)
    length = 0.0
    for a, b in zip(pts[:-1], pts[1:], strict=True):
        n = int(np.ceil(np.hypot(*(b - a)) * 4)) + 1
        t = np.linspace(0, 1, n)[:, None]
        p = np.round(a + t * (b - a)).astype(int)
        for dj in range(-(width // 2), width // 2 + 1):
            for di in range(-(width // 2), width // 2 + 1):
                m[p[:, 1] + dj, p[:, 0] + di] = True
        length += float(np.hypot(*(b - a))) * RES
    return m, length


SHARP_ZIGZAG = np.array([[10, 20], [20, 32], [30, 20], [40, 32], [50, 20], [60, 32]], float)  # 100° turns
GENTLE_ZIGZAG = np.array([[5, 25], [20, 33], [35, 25], [50, 33], [65, 25], [75, 30]], float)  # ~60° turns


@pytest.mark.parametrize(("width", "zigzag"), [(1, SHARP_ZIGZAG), (3, GENTLE_ZIGZAG), (1, GENTLE_ZIGZAG)])
def test_skeleton_length_straight_and_zigzag(width, zigzag):
    # (thinning cuts the corners of a thick mask: a 3-cell-wide sharp zig-zag reads ~10 % short)
    straight, L = _line_mask(np.array([[10, 30], [60, 30]], float), width)
    assert skeleton_length(straight, RES) == pytest.approx(L, rel=0.1)
    zig, Lz = _line_mask(zigzag, width)
    assert skeleton_length(zig, RES) == pytest.approx(Lz, rel=0.1)


def test_crack_orientation_against_route():
    route = np.array([[0.0, 3.0], [8.0, 3.0]])  # driving along +x
    along, _ = _line_mask(np.array([[10, 30], [60, 32]], float), 3)
    across, _ = _line_mask(np.array([[40, 5], [41, 55]], float), 3)
    lab = np.zeros(along.shape, np.int32)
    lab[along] = 1
    lab[across] = 2
    d00 = _inst(1, 0, (3.5, 3.1))
    d00_across = _inst(2, 0, (4.0, 3.0))
    d10 = _inst(2, 1, (4.0, 3.0))
    z, _, _ = _road()
    measure_instances([d00, d00_across], _surface(z), lab, route=route)
    assert d00.extra["orientation_ok"] is True and d00.extra["orientation_deg"] < 10
    assert d00_across.extra["orientation_ok"] is False and d00_across.extra["orientation_deg"] > 80
    measure_instances([d10], _surface(z), lab, route=route)
    assert d10.extra["orientation_ok"] is True
    assert d00.extra["crack_length_m"] == pytest.approx(5.0, rel=0.1)
    no_route = _inst(1, 0)
    measure_instances([no_route], _surface(z), lab)
    assert no_route.extra["orientation_ok"] is None and no_route.extra["crack_length_m"] > 4


def test_truth_volume_is_the_integral_of_the_height_dent(tmp_path):
    """A synthesised pothole's truth volume equals the integral of truth/height.npy's dent."""
    from pavemap.export.geojson import read_geojson
    from pavemap.synth import synthesize
    from pavemap.synth.generate import load_truth_height, load_world
    from pavemap.synth.world import _height_raster, pothole_window

    root = tmp_path / "scene"
    synthesize(root, preset="kitti-like", seed=0, frames=2, scale=0.05, depth="none", progress=False,
               road_after=30.0, defect_density=40.0, class_mix=(0, 0, 0, 1), clutter=0.0, shadows=False)
    height, grid = load_truth_height(root)
    layer = read_geojson(root / "truth" / "defects.geojson")
    pits = [p for p in layer.properties if p["cls"] == 3]
    assert pits
    w = load_world(root)
    w.defects = [d for d in w.defects if d["cls"] != 3]  # the same road without its potholes
    w._cache.clear()
    flat = _height_raster(w)
    w2 = load_world(root)
    for p in pits:
        d = w2.defects[p["id"]]
        rows, cols = pothole_window(d, grid)
        dent = flat[rows, cols].astype(np.float64) - height[rows, cols]
        vol_l = dent.sum() * grid.res ** 2 * 1000
        assert p["volume_l"] == pytest.approx(vol_l, rel=1e-3, abs=1e-3)
        assert p["depth_max_m"] == pytest.approx(dent.max(), abs=2e-4)
        assert p["depth_m"] - 0.0005 <= p["depth_max_m"] <= p["depth_m"] + 0.0065
        assert 0.2 * p["depth_m"] < p["depth_mean_m"] < p["depth_m"]


def test_pothole_depth_from_height_samples_where_the_surface_is_smooth():
    """The mesh lost the dent (its relief lattice is coarser than a pothole), the samples inside it did not."""
    z, X, Y = _road()
    cx, cy, R, D = 4.0, 2.0, 0.5, 0.06
    rng = np.random.default_rng(3)
    xy = np.column_stack([rng.uniform(cx - R, cx + R, 400), rng.uniform(cy - R, cy + R, 400)])
    road = 10.0 + 0.02 * xy[:, 0] + 0.015 * xy[:, 1] - 0.05 * ((xy[:, 1] - 3.0) / 3.5) ** 2
    dent = _bowl(xy[:, 0], xy[:, 1], cx, cy, R, D)
    samples = np.column_stack([xy, road - dent + rng.normal(0, 0.002, len(xy))])
    flat, with_samples, too_few = _inst(1, 3), _inst(1, 3), _inst(1, 3)
    lab = _labels_disk(X, Y, cx, cy, R)
    measure_instances([flat], _surface(z), lab)
    measure_instances([with_samples], _surface(z), lab, samples=samples)
    measure_instances([too_few], _surface(z), lab, samples=samples[np.hypot(*(xy - [cx, cy]).T) < R][:3])
    assert flat.extra["depth_max_mm"] < 3.0  # the smooth surface alone sees no pothole
    e = with_samples.extra
    assert e["measure_note"].startswith("from ") and abs(e["depth_max_mm"] - D * 1000) <= 6.0, e
    vol_l = math.pi * R * R * D / 2 * 1000
    assert abs(e["volume_l"] - vol_l) <= 0.25 * vol_l, (e, vol_l)
    assert too_few.extra["measure_note"] == "" and too_few.extra["depth_max_mm"] < 3.0  # 3 samples: the surface


def test_stage1_mesh_gives_no_depth_without_depth_measurements():
    """On stage 1's mesh (surface_floor False) a pothole's depth comes from depth samples inside it or not at all;
    the maintenance stage on a drive without a depth layer marks it not measurable (its ground points are not
    floor measurements) and grades it by its area, saying so."""
    from shapely.geometry import Point

    from pavemap.maintain import assess
    from pavemap.maintain.measure import MeasureConfig
    from pavemap.types import Camera, Frame, Sequence, View

    z, X, Y = _road()
    cx, cy, R, D = 4.0, 2.0, 0.5, 0.06
    z = z - _bowl(X, Y, cx, cy, R, D)  # even a mesh that kept the dent: no samples, no depth
    lab = _labels_disk(X, Y, cx, cy, R)
    rng = np.random.default_rng(4)
    xy = np.column_stack([rng.uniform(cx - 0.3, cx + 0.3, 40), rng.uniform(cy - 0.3, cy + 0.3, 40)])
    pts = np.column_stack([xy, np.full(len(xy), 9.99)])
    mesh_cfg = MeasureConfig(surface_floor=False)
    none, few, enough = _inst(1, 3), _inst(1, 3), _inst(1, 3)
    measure_instances([none], _surface(z), lab, config=mesh_cfg)
    measure_instances([few], _surface(z), lab, samples=pts[:3], config=mesh_cfg)
    measure_instances([enough], _surface(z), lab, samples=pts, config=mesh_cfg)
    assert none.extra["measurable"] is False and none.extra["depth_max_mm"] is None
    assert none.extra["measure_note"] == "floor not measured (no depth measurements)"
    assert few.extra["measure_note"] == "floor not measured (3 height samples inside it, 5 needed)"
    assert enough.extra["measurable"] is True and enough.extra["measure_note"].startswith("from 40 height samples")
    views = [Frame(k, float(k), {"cam": View("cam", f"{k}.png", np.array(
        [[1.0, 0, 0, 0.5 * k], [0, 1, 0, 2.0], [0, 0, 1, 11.5], [0, 0, 0, 1]]))}) for k in range(16)]
    seq = Sequence("t", [], {"cam": Camera("cam", 64, 48, np.eye(3))}, views)  # no depth layer
    pot = _inst(1, 3, centroid=(cx, cy))
    pot.polygon, pot.area_m2 = Point(cx, cy).buffer(R), 0.6
    assess([pot], seq, _surface(z), lab, samples=pts)  # the mesh's samples: triangulated ground points
    e = pot.extra
    assert e["measurable"] is False and e["depth_max_mm"] is None and e["severity_level"] == "high"
    assert e["measure_note"].startswith("floor not measured (no depth measurements); severity from area_m2 = ")


@pytest.mark.parametrize("a, b", [((6.0, 2.5), (6.3, 0.5)),  # transverse, left of the camera, slanted
                                  ((5.0, 1.5), (9.0, 1.5)),  # longitudinal, 1.5 m left of the camera axis
                                  ((6.0, -2.0), (6.4, 0.2))])  # transverse across the camera axis
def test_crack_length_is_the_footprints_longer_midline(a, b):
    """A straight crack from a to b (world x ahead, y left, on the road z = 0) and its tight box: the footprint's
    longer mid-line is the crack's length within 3 %; the longer diagonal (the former measure) is 5-11 % long."""
    from pavemap.fuse.footprint import detection_footprints, footprint_quads
    from pavemap.types import Camera, Detection, Frame, Sequence, View

    T = np.eye(4)
    T[:3, :3] = [[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]]  # looking along +x, 1.5 m up
    T[2, 3] = 1.5
    K = np.array([[500.0, 0.0, 320.0], [0.0, 500.0, 240.0], [0.0, 0.0, 1.0]])
    u = [320 - 500 * y / x for x, y in (a, b)]
    v = [240 + 500 * 1.5 / x for x, _ in (a, b)]
    bx = (min(u), min(v), max(u), max(v))
    seq = Sequence("t", [], {"cam": Camera("cam", 640, 480, K)}, [Frame(0, 0.0, {"cam": View("cam", "0.png", T)})])
    hit = np.array([[(a[0] + b[0]) / 2, (a[1] + b[1]) / 2, 0.0]])
    area, length, ok, _ = detection_footprints(seq, [Detection(0, "cam", bx, 1, 0.9)], hit)
    true = math.dist(a, b)
    assert bool(ok[0]) and abs(length[0] - true) <= 0.03 * true, (length[0], true)
    q, _ = footprint_quads(torch.tensor([bx], dtype=torch.float64), torch.tensor(K[None]), torch.tensor(T[None]),
                           torch.zeros(1, dtype=torch.float64))
    diag = max(float((q[0, 0] - q[0, 2]).norm()), float((q[0, 1] - q[0, 3]).norm()))
    assert diag > 1.05 * true  # the case tells the two measures apart


def test_a_box_near_the_image_edge_gives_no_footprint():
    """A box 7 px from the edge of a 640 px image may be cut off (2 % of the side is the margin); 20 px in, it
    measures. A cut crack measured short is what decided a severity level wrongly on the maintenance bench."""
    from pavemap.fuse.footprint import detection_footprints
    from pavemap.types import Camera, Detection, Frame, Sequence, View

    T = np.eye(4)
    T[:3, :3] = [[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]]
    T[2, 3] = 1.5
    K = np.array([[500.0, 0.0, 320.0], [0.0, 500.0, 240.0], [0.0, 0.0, 1.0]])
    seq = Sequence("t", [], {"cam": Camera("cam", 640, 480, K)}, [Frame(0, 0.0, {"cam": View("cam", "0.png", T)})])
    hit = np.array([[6.0, 2.0, 0.0]] * 2)
    dets = [Detection(0, "cam", (x0, 360.0, 200.0, 380.0), 1, 0.9) for x0 in (7.0, 20.0)]
    area, length, ok, _ = detection_footprints(seq, dets, hit)
    assert not ok[0] and np.isnan(length[0]) and ok[1] and length[1] > 0
    assert detection_footprints(seq, dets[:1], hit[:1], border_frac=0.0)[2][0]  # the old 2 px margin passed it


def test_footprint_sizes_become_the_defect_sizes():
    """area_m2 of a pothole / patch and crack_length_m of a crack come from the detections' footprints; the
    fused vertices' area stays as mapped_area_m2."""
    from pavemap.fuse.footprint import FILL, footprint_quads, instance_sizes, shoelace
    from pavemap.maintain import adopt_footprint_sizes

    # a camera 1.5 m above the ground looking along +x (OpenCV axes: x right, y down, z forward)
    T = torch.eye(4, dtype=torch.float64)
    T[:3, :3] = torch.tensor([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]], dtype=torch.float64)
    T[2, 3] = 1.5
    K = torch.tensor([[500.0, 0.0, 320.0], [0.0, 500.0, 240.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
    # the box of a 1 m x 0.5 m patch 6-7 m ahead: rows where the ground is 6 and 7 m away, columns +-0.25 m
    v6, v7 = 240 + 500 * 1.5 / 6, 240 + 500 * 1.5 / 7
    box = torch.tensor([[320 - 500 * 0.25 / 7, v7, 320 + 500 * 0.25 / 7, v6]], dtype=torch.float64)
    q, ok = footprint_quads(box, K[None], T[None], torch.zeros(1, dtype=torch.float64))
    assert bool(ok[0]) and abs(float(shoelace(q).abs()[0]) - 0.5 * (0.5 * 6 / 7 + 0.5) / 1.0) < 0.01
    pot, crack = _inst(1, 3), _inst(2, 0)
    inst_of = np.array([1, 1, 1, 2, 2])
    area = np.array([0.5, 0.52, 0.9, 0.1, 0.1])  # one far, inflated view
    length = np.array([1.0, 1.0, 1.5, 2.4, 2.6])
    gpx = np.array([0.01, 0.01, 0.2, 0.02, 0.02])
    instance_sizes([pot, crack], inst_of, area, length, gpx)
    adopt_footprint_sizes([pot, crack])
    assert pot.area_m2 == pytest.approx(0.5 * FILL[3], rel=0.05) and pot.extra["mapped_area_m2"] == 1.0
    assert pot.extra["size_views"] == 3 and crack.extra["crack_length_m"] in (2.4, 2.6)
    none = _inst(3, 2)
    instance_sizes([none], np.zeros(0, np.int64), np.zeros(0), np.zeros(0), np.zeros(0))
    adopt_footprint_sizes([none])
    assert none.area_m2 == 1.0 and none.extra["size_views"] == 0  # no footprint: the vertex area stays
