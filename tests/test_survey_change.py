"""Change between two synthetic surveys of the same road, where defects were added and enlarged."""

from __future__ import annotations

import json

import pytest

import pavemap
from pavemap.compare import compare_runs
from pavemap.synth import synthesize


@pytest.fixture(scope="module")
def two_surveys(tmp_path_factory):
    root = tmp_path_factory.mktemp("surveys")
    kw = dict(preset="kitti-like", seed=5, frames=8, scale=0.25, progress=False, road_after=40.0,
              defect_density=40.0)
    a = synthesize(root / "survey0", survey=0, **kw)
    b = synthesize(root / "survey1", survey=1, survey_new_per_100m=15.0, **kw)
    return a, b, root


def _props(seq):
    doc = json.loads((seq.root / "truth" / "defects.geojson").read_text())
    return [f["properties"] for f in doc["features"]]


def test_later_survey_keeps_grows_and_adds(two_surveys):
    a, b, _ = two_surveys
    pa, pb = _props(a), _props(b)
    assert len(pb) > len(pa), "the later survey must add defects"
    by_id = {p["id"]: p for p in pa}
    grown = [p for p in pb if p.get("grown_in_survey")]
    assert grown, "the later survey must enlarge some defects"
    for p in grown:
        assert p["area_m2"] > 1.2 * by_id[p["id"]]["area_m2"]
    for p in pb:
        if p["id"] in by_id and not p.get("grown_in_survey"):
            assert p["area_m2"] == pytest.approx(by_id[p["id"]]["area_m2"])


def test_compare_classifies_truth_changes_exactly(two_surveys, tmp_path):
    a, b, _ = two_surveys
    pb = _props(b)
    summary = compare_runs(a.root / "truth" / "defects.geojson", b.root / "truth" / "defects.geojson",
                           tmp_path / "changes")
    counts = summary["counts"]
    n_new = sum(1 for p in pb if p.get("new_in_survey"))
    n_grown = sum(1 for p in pb if p.get("grown_in_survey"))
    assert counts["gone"] == 0
    assert counts["grown"] == n_grown
    # a new defect placed touching an old one may be matched to it; never more "new" than really new
    assert n_new - 1 <= counts["new"] <= n_new
    assert (tmp_path / "changes" / "changes.gpkg").is_file()  # truth is local metres: no GeoJSON
    assert not (tmp_path / "changes" / "changes.geojson").exists()
    assert (tmp_path / "changes" / "changes.png").is_file()


def test_compare_two_mapped_surveys_end_to_end(two_surveys, tmp_path):
    a, b, _ = two_surveys
    runs = []
    for seq in (a, b):
        cfg = pavemap.load_config("kitti")
        cfg.device = "cpu"
        cfg.mesh.epochs = 1
        cfg.output.figures = False
        out = tmp_path / seq.root.name
        pavemap.run(seq, cfg, out, progress=False)
        runs.append(out)
    summary = compare_runs(runs[0], runs[1], tmp_path / "changes")
    counts = summary["counts"]
    n_a = len(json.loads((runs[0] / "defects.geojson").read_text())["features"])
    n_b = len(json.loads((runs[1] / "defects.geojson").read_text())["features"])
    assert counts["gone"] + counts["grown"] + counts["unchanged"] == n_a
    assert counts["new"] + counts["grown"] + counts["unchanged"] == n_b
