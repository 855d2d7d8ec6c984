"""Not assessed is not perfect (issue 41, part 3): a segment the survey could not see has no index."""

from __future__ import annotations

import json
import logging

import numpy as np
import pytest

from pavemap.maintain import summary
from pavemap.maintain.assessment import (
    apply_detector_check,
    assess_coverage,
    detector_check,
    input_scale,
    mark_not_assessed,
)
from pavemap.maintain.policy import load_policy
from pavemap.maintain.segments import build_segments, segments_csv_text
from pavemap.types import Camera, Frame, Sequence, View

# nuScenes CAM_FRONT: 1600 x 900, fx = fy = 1266.4, 1.5 m above the road, looking along world +x
CAM = Camera("front", 1600, 900, np.array([[1266.4, 0, 800.0], [0, 1266.4, 450.0], [0, 0, 1]]))
R_FORWARD = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])  # OpenCV camera axes, +x ahead


def _drive(xs: np.ndarray) -> Sequence:
    frames = []
    for k, x in enumerate(xs):
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = R_FORWARD, (float(x), 0.0, 1.5)
        frames.append(Frame(k, float(k), {"front": View("front", f"{k}.jpg", T)}))
    return Sequence("straight", [], {"front": CAM}, frames)


def _near_then_far() -> tuple[Sequence, list]:
    """200 m straight: a frame every metre over the first 100 m, then one every 25 m (a cell there is seen
    from 5 m to 30 m away, mostly far), segments of 100 m at yolo's 640 px input."""
    xs = np.concatenate([np.arange(0.0, 100.0, 1.0), np.arange(100.0, 201.0, 25.0)])
    seq = _drive(xs)
    route = np.column_stack([np.linspace(0, 200, 41), np.zeros(41)])
    recs = [{"cls": 3, "chainage_m": 50.0, "severity_level": "high", "area_m2": 0.3, "length_m": 0.7}]
    return seq, build_segments(route, recs, load_policy(), segment_m=100.0)


def test_a_segment_seen_only_from_far_away_is_not_assessed():
    seq, segs = _near_then_far()
    pol = load_policy()
    assert [s.pci is not None for s in segs] == [True, True] and segs[1].pci == 100.0  # before: far one "perfect"
    assess_coverage(segs, seq, pol, scale=input_scale(seq, "yolo", 640))
    near, far = segs
    assert far.assessed is False and far.pci is None and far.grade is None and far.rating is None
    assert far.coverage_share < pol.assessment.min_covered_share and "seen finely enough" in far.not_assessed_reason
    # the well-seen segment keeps its index (and its pothole's deduct)
    assert near.assessed and near.pci is not None and near.pci < 100.0 and near.not_assessed_reason == ""
    assert near.coverage_share >= pol.assessment.min_covered_share > far.coverage_share
    assert near.px_per_cm_median > far.px_per_cm_median
    m = summary([], segs)
    assert (m["assessed_segments"], m["not_assessed_segments"], m["not_assessed_length_m"]) == (1, 1, 100.0)
    assert m["pci_mean"] == round(near.pci, 1)  # the mean leaves the not-assessed segment out
    row = segments_csv_text(segs).splitlines()[2].split(",")
    assert row[5:8] == ["False", "", ""]  # assessed, pci, grade


def test_the_detector_input_size_decides():
    """px/cm count at the detector's input: the well-seen segment at 640 px is not assessed at 320 px (a 20 cm
    pothole then spans < 8 px wherever the camera sees the road), and the far one not at full resolution either."""
    seq, segs = _near_then_far()
    assess_coverage(segs, seq, load_policy(), scale=input_scale(seq, "yolo", 320))
    assert [s.assessed for s in segs] == [False, False] and segs[0].coverage_share == 0.0
    seq, segs = _near_then_far()
    assess_coverage(segs, seq, load_policy(), scale=input_scale(seq, "file"))
    assert [s.assessed for s in segs] == [True, False] and input_scale(seq, "yolo", 4000) == {"front": 1.0}


@pytest.mark.parametrize("n_low, n_high, fires", [(57, 3, True), (10, 40, False), (0, 0, True)])
def test_low_confidence_warning_on_real_footage(tiny_seq, tmp_path, caplog, n_low, n_high, fires):
    """A detections file with almost every box below tau_conf (3 of 60 in 8 images; or none at all): the run warns
    and assesses no segment; 40 of 50 above it do not."""
    from pavemap.detect.config import FilterConfig
    from pavemap.detect.sources import load_detections
    from pavemap.fuse import FusionConfig
    from pavemap.geometry.heightfield import HeightField
    from pavemap.io.sequence import write_detections
    from pavemap.pipeline import filter_and_fuse
    from pavemap.types import Detection

    rng = np.random.default_rng(0)
    views = [(f.index, c) for f in tiny_seq.frames for c in f.views]
    cam = next(iter(tiny_seq.cameras.values()))
    dets = []
    for k in range(n_low + n_high):
        fr, c = views[k % len(views)]
        x, y = rng.uniform(0, cam.width - 30), rng.uniform(cam.height / 2, cam.height - 20)
        dets.append(Detection(fr, c, (x, y, x + 20, y + 12), 3, 0.02 if k < n_low else 0.6))
    path = write_detections(tmp_path / "detections.jsonl", dets)
    surface = HeightField.plane(-20, -20, 0.5, 200, 80)
    result = filter_and_fuse(tiny_seq, load_detections(path, tiny_seq), surface, FilterConfig(tau_conf=0.05),
                             FusionConfig(), progress=False)
    pol = load_policy()
    with caplog.at_level(logging.WARNING, logger="pavemap"):
        chk = detector_check(result.metrics, tiny_seq, True, pol, 0.05)
    assert chk.low is fires and chk.below_conf == n_low and chk.confident <= n_high
    warned = [r for r in caplog.records if "almost nothing above filter.tau_conf" in r.getMessage()]
    assert bool(warned) is fires and all(r.levelno == logging.WARNING for r in warned)
    assert not detector_check(result.metrics, tiny_seq, False, pol).low  # the simulated detector: no such claim
    seq, segs = _near_then_far()
    apply_detector_check(segs, chk)
    assert all(s.assessed is not fires for s in segs)
    m = summary([], segs, chk)
    assert m["detector_confidence"]["low"] is fires and json.dumps(m)


def test_not_assessed_in_the_gpkg_the_report_and_the_network_map(tmp_path):
    import pyogrio

    from pavemap.export.gis import write_gis
    from pavemap.export.report import build_report_html
    from pavemap.export.report_worklist import NOT_ASSESSED_FILL, index_colour
    from pavemap.network.report import _assessed

    route = np.column_stack([np.linspace(0, 200, 41), np.zeros(41)])
    segs = build_segments(route, [], load_policy(), segment_m=100.0)
    mark_not_assessed(segs[1], "seen finely enough on 3 % of its road, 50 % needed")
    write_gis(tmp_path, [], segments=segs)
    df = pyogrio.read_dataframe(tmp_path / "survey.gpkg", layer="segments")
    assert df["pci"].isna().tolist() == [False, True] and df["grade"].isna().tolist() == [False, True]
    assert df["assessed"].tolist() == [True, False] and df["pci"][0] == 100.0
    assert df["not_assessed_reason"][1].startswith("seen finely enough")
    html = build_report_html([], segments=segs)
    strip = html[html.index('<svg id="segment-strip"'):html.index("</svg>", html.index('<svg id="segment-strip"'))]
    na = strip[strip.index('data-seg="2"'):]
    assert f'fill="{NOT_ASSESSED_FILL}"' in na and index_colour(100.0) not in na and "not assessed" in na
    assert "not assessed (not seen well enough)" in html and 'id="not-assessed"' in html
    assert "Not assessed: 1 of 2 segments (100 m)" in html
    recs = [dict(zip(df.columns, row, strict=False)) for row in df.itertuples(index=False)]
    assert [_assessed(r, "pci") for r in recs] == [True, False]
