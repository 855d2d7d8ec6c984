"""Ground-truth evaluation: matching rule, visibility rule, detection-level scores, run folder I/O."""

from __future__ import annotations

import json

import numpy as np
import pytest
from shapely.geometry import box, mapping

from pavemap.evaluate import evaluate, match
from pavemap.evaluate.gt import detection_scores, visible_defects
from pavemap.export.run_files import write_fusion_outputs
from pavemap.geometry import HeightField
from test_fuse import DEFECTS, detections_for, make_seq, run_fusion


def sq(x: float, y: float, h: float = 0.2):  # noqa: ANN201
    return box(x - h, y - h, x + h, y + h)


def test_match_rule() -> None:
    gt = [sq(0, 0), sq(5, 0, 0.1), sq(10, 0, 0.1)]
    gxy = np.array([[0, 0], [5, 0], [10, 0]], dtype=float)
    preds = [sq(0.4, 0, 0.05),          # centroid 0.4 m away, no overlap: allowed (< 0.5 m)
             sq(0.1, 0, 0.05),          # closer to gt 0: takes it first (one-to-one)
             box(5.05, -0.1, 7.0, 0.1),  # centroid 1 m away but overlapping: allowed
             sq(10.6, 0, 0.05)]         # 0.6 m, no overlap: not allowed
    pxy = np.array([[p.centroid.x, p.centroid.y] for p in preds])
    m = sorted(match(preds, pxy, gt, gxy))
    assert [(p, g) for p, g, _ in m] == [(1, 0), (2, 1)]
    assert m[0][2] == pytest.approx(0.1)


def test_visible_and_detection_scores() -> None:
    recs = [{"frame": f, "kept": k, "reason": r, "mapped": k} for f, k, r in
            [(0, True, "kept"), (1, True, "kept"), (0, True, "kept"), (2, False, "off_road"),
             (3, False, "off_road"), (3, True, "kept"), (4, False, "low_conf")]]
    truth = [{"true": True, "defect_id": 1}, {"true": True, "defect_id": 1}, {"true": True, "defect_id": 2},
             {"true": False, "offroad": True}, {"true": False, "offroad": True}, {"true": False, "offroad": True},
             {"true": True, "defect_id": 2}]
    assert visible_defects(recs, truth) == {1, 2}  # defect 2: frames 0 and 4 (the low-conf one counts)
    s = detection_scores(recs, truth)
    assert s["fp_removed"] == pytest.approx(2 / 3) and s["tp_lost"] == pytest.approx(1 / 4)


def _write_truth(root, defects, lines) -> None:  # noqa: ANN001
    (root / "truth").mkdir(parents=True, exist_ok=True)
    feats = [{"type": "Feature", "geometry": mapping(sq(x, y)), "properties": {"id": k, "cls": c,
              "name": ("D00", "D10", "D20", "D40")[c]}} for k, ((x, y), c) in enumerate(defects)]
    (root / "truth" / "defects.geojson").write_text(json.dumps({"type": "FeatureCollection", "features": feats}))
    (root / "truth" / "detections_truth.jsonl").write_text("".join(json.dumps(t) + "\n" for t in lines))


def test_evaluate_run_folder(tmp_path) -> None:  # noqa: ANN001
    seq = make_seq(5, root=tmp_path)
    dets = detections_for(seq)
    ids = {cls: k for k, (_, cls) in enumerate(DEFECTS)}
    lines = [{"true": True, "defect_id": ids[d.cls], "offroad": False, "source": "defect"} for d in dets]
    # A fourth true defect the detector never saw: not visible, so it does not hurt recall.
    _write_truth(tmp_path, DEFECTS + [((16.0, 0.0), 1)], lines)
    plane = HeightField.plane(0.0, -5.0, 0.1, 251, 101)
    res = run_fusion(seq, dets, plane)
    write_fusion_outputs(tmp_path / "run", res)
    ev = evaluate(tmp_path / "run", tmp_path)
    ev_mem = evaluate(res, tmp_path)  # the in-memory result scores the same as the written folder
    for k in ("precision", "recall", "median_error_m"):
        assert ev_mem[k] == pytest.approx(ev[k], abs=1e-3)  # centroids are written to the mm
    assert ev["precision"] == 1.0 and ev["recall"] == 1.0 and ev["f1"] == 1.0
    assert ev["visible_defects"] == 3 and ev["truth_defects"] == 4
    assert ev["median_error_m"] < 0.05 and ev["msr"] == 1.0
    assert ev["per_class"]["D40"]["f1"] == 1.0 and ev["per_class"]["D10"]["truth"] == 0  # unseen
    # The single-frame baseline maps every detection alone: one TP per defect, the rest duplicates.
    b = ev["baseline"]
    assert b["recall"] == 1.0 and b["precision"] == pytest.approx(3 / len(dets))
    for key in ("precision", "recall", "f1", "median_error_m", "p90_error_m", "msr", "fp_removed", "tp_lost"):
        assert key in ev
    json.dumps(ev, allow_nan=False)


def test_evaluate_without_truth_side_file(tmp_path) -> None:  # noqa: ANN001
    seq = make_seq(5, root=tmp_path)
    dets = detections_for(seq)
    _write_truth(tmp_path, DEFECTS, [])
    (tmp_path / "truth" / "detections_truth.jsonl").unlink()
    res = run_fusion(seq, dets, HeightField.plane(0.0, -5.0, 0.1, 251, 101))
    ev = evaluate(res, tmp_path)
    assert ev["fp_removed"] is None and ev["recall"] == 1.0 and "no truth" in ev["truth_detections_source"]
