"""Road segments of chainage and the PCI-like index (issue 16)."""

from __future__ import annotations

import csv
import json

import numpy as np
import pytest

from pavemap.export.segments import write_segments_csv
from pavemap.geometry.chainage import chainage, route_polyline
from pavemap.maintain.policy import load_policy, severity_level
from pavemap.maintain.segments import (
    SEGMENT_SCHEMA,
    build_segments,
    corrected_deduct,
    segment_edges,
)

ROUTE = np.column_stack([np.linspace(0.0, 300.0, 61), np.zeros(61)])  # 300 m straight along x


def _potholes(n, level="high", s0=10.0, ds=7.0):
    return [{"cls": 3, "chainage_m": s0 + ds * k, "severity_level": level, "area_m2": 0.3, "length_m": 0.7}
            for k in range(n)]


def test_segment_edges_merge_or_keep_the_last_short_piece():
    assert segment_edges(300.0, 100.0).tolist() == [0, 100, 200, 300]
    assert segment_edges(340.0, 100.0).tolist() == [0, 100, 200, 340]  # 40 m < half a segment: merged
    assert segment_edges(370.0, 100.0).tolist() == [0, 100, 200, 300, 370]  # 70 m: a short segment of its own
    assert segment_edges(30.0, 100.0).tolist() == [0, 30]
    assert segment_edges(0.0, 100.0).tolist() == [0, 0]


def test_clean_road_scores_100_and_segments_tile_the_route():
    segs = build_segments(ROUTE, [])
    assert [s.id for s in segs] == [1, 2, 3] and all(s.pci == 100.0 and s.grade == 1 for s in segs)
    half = 0.5 * 3 * 3.5  # corridor_lanes x lane width / 2
    assert segs[0].corridor_area_m2 == pytest.approx(100.0 * 2 * half, rel=1e-6)
    assert segs[1].polygon.bounds == pytest.approx((100.0, -half, 200.0, half))


@pytest.mark.parametrize("cls, level, rec", [
    (3, "high", {"area_m2": 0.3}), (3, "low", {"area_m2": 0.05}), (2, "medium", {"area_m2": 1.5}),
    (0, "medium", {"crack_length_m": 2.0}), (1, "low", {"length_m": 1.0})])
def test_index_falls_monotonically_with_density(cls, level, rec):
    pcis = []
    for n in range(0, 13):
        recs = [{"cls": cls, "chainage_m": 5.0 + 7.0 * k, "severity_level": level, **rec} for k in range(n)]
        pcis.append(build_segments(ROUTE, recs)[0].pci)
    d = np.diff(pcis)
    assert pcis[0] == 100.0 and np.all(d <= 0), pcis
    assert np.all(d[: 3] < 0), pcis  # strictly while the index is not yet at 0


def test_worse_severity_lowers_the_index_and_grades_follow():
    lo, mid, hi = (build_segments(ROUTE, _potholes(3, lv))[0] for lv in ("low", "medium", "high"))
    assert 100 > lo.pci > mid.pci > hi.pci >= 0
    assert lo.grade <= mid.grade <= hi.grade and 1 <= hi.grade <= 5
    assert hi.rating in ("good", "satisfactory", "fair", "poor", "very poor", "serious", "failed")


def test_corrected_deduct_is_monotone_in_every_deduct():
    rng = np.random.default_rng(1)
    for _ in range(300):
        dv = rng.uniform(0, 60, rng.integers(1, 7)).tolist()
        k = int(rng.integers(0, len(dv)))
        up = list(dv)
        up[k] += float(rng.uniform(0, 20))
        assert corrected_deduct(up)[1] >= corrected_deduct(dv)[1] - 1e-9
    assert corrected_deduct([30.0]) == (30.0, 30.0)  # one distress: CDV = TDV (q = 1)
    assert corrected_deduct([30.0, 30.0])[1] < 60.0  # several: corrected down
    assert corrected_deduct([1.0, 1.5]) == (2.5, 2.5)


def test_counts_lengths_areas_per_class_and_record(tmp_path):
    recs = (_potholes(2, s0=10.0)
            + [{"cls": 0, "chainage_m": 50.0, "severity_level": "medium", "crack_length_m": 2.0, "length_m": 1.8,
                "area_m2": 0.4},
               {"cls": 2, "chainage_m": 150.0, "severity_level": "high", "area_m2": 3.0, "length_m": 2.2},
               {"cls": 1, "chainage_m": 450.0, "severity_level": "low", "length_m": 1.0, "area_m2": 0.2}])
    segs = build_segments(ROUTE, recs)
    a, b, c = segs
    assert a.counts == {"D40": 2, "D00": 1} and a.lengths_m["D00"] == pytest.approx(2.0)  # skeleton length first
    assert a.areas_m2["D40"] == pytest.approx(0.6) and b.counts == {"D20": 1} and c.counts == {"D10": 1}
    assert [r["segment"] for r in recs] == [1, 1, 1, 2, 3]  # past the route's end: the last segment
    row = a.record()
    assert [n for n, *_ in SEGMENT_SCHEMA] == list(row)
    assert row["n_D40"] == 2 and row["defects"] == 3 and "D40 high" in row["deducts"]
    assert row["corrected_deduct"] == pytest.approx(100 - row["pci"], abs=0.06)
    p = write_segments_csv(tmp_path / "segments.csv", segs)
    rows = list(csv.DictReader(p.open()))
    assert len(rows) == 3 and rows[2]["segment"] == "3" and float(rows[0]["pci"]) == row["pci"]
    empty = write_segments_csv(tmp_path / "e.csv", [])
    assert empty.read_text().startswith("segment,chainage_start_m")


def test_clean_then_damaged_synthetic_drive(tmp_path):
    """A drive whose first half is clean and second half damaged: the clean segments score higher."""
    from pavemap.io.sequence import read_sequence
    from pavemap.synth import synthesize

    root = tmp_path / "half"
    synthesize(root, preset="kitti-like", seed=3, frames=9, hz=1.0, speed=10.0, scale=0.05, road_after=5.0,
               defect_free_until_m=40.0, defect_density=40.0, progress=False)
    seq = read_sequence(root)
    route = route_polyline(seq.trajectory())
    truth = json.loads((root / "truth" / "defects.geojson").read_text())["features"]
    recs = [dict(f["properties"]) for f in truth]
    s, _ = chainage(route, np.array([[r["x_m"], r["y_m"]] for r in recs]))
    assert len(recs) >= 6 and s.min() >= 40.0 - 1.0  # the generator kept the first 40 m clean
    pol = load_policy()
    for r, sk in zip(recs, s, strict=True):
        r["chainage_m"] = float(sk)
        r["severity_level"] = severity_level(r["cls"], r, pol)  # truth records: depth_m, length_m, area_m2
    segs = build_segments(route, recs, pol, segment_m=20.0)
    assert len(segs) == 4
    clean, damaged = segs[:2], segs[2:]
    assert all(sg.pci == 100.0 and sum(sg.counts.values()) == 0 for sg in clean)
    assert all(sg.pci < 100.0 for sg in damaged) and max(sg.pci for sg in damaged) < min(sg.pci for sg in clean)
