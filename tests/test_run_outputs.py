"""One writer per output: a run folder's files written once, atomically, readable by `pavemap eval`.

Also: stage 2 and stage 3 do not import each other; ``detector.backend: auto`` and the preset fit the input.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from collections import Counter
from pathlib import Path

import pytest
from typer.testing import CliRunner

import pavemap
from pavemap.cli import app
from pavemap.detect import backends
from pavemap.detect.backends import resolve_backend
from pavemap.detect.config import PAPER_TAU_CONF, DetectorConfig
from pavemap.errors import PavemapError
from pavemap.export.geojson import PROPERTY_SCHEMA
from pavemap.export.tables import CSV_COLUMNS, GEO_COLUMNS
from pavemap.io.sequence import read_sequence
from test_pipeline import _fast_config

SCHEMA = {name for name, *_ in PROPERTY_SCHEMA}


class WriteCounter:
    """Counts every atomic write (write-then-rename) by its final path."""

    def __init__(self) -> None:
        self.count: Counter[Path] = Counter()
        self._replace = os.replace

    def __call__(self, src, dst, *args, **kwargs):  # noqa: ANN001, ANN002, ANN003, ANN204
        self.count[Path(dst).resolve()] += 1
        return self._replace(src, dst, *args, **kwargs)

    def under(self, folder: Path) -> Counter[Path]:
        root = folder.resolve()
        return Counter({p: n for p, n in self.count.items() if root in p.parents})


def _assert_written_once_atomically(out: Path, writes: WriteCounter) -> None:
    counts = writes.under(out)
    twice = {str(p.relative_to(out.resolve())): n for p, n in counts.items() if n > 1}
    assert not twice, f"written more than once in one run: {twice}"
    files = {p.resolve() for p in out.rglob("*") if p.is_file() and p.name != "run.log"}  # the log is appended
    not_atomic = sorted(str(p.relative_to(out.resolve())) for p in files - set(counts))
    assert not not_atomic, f"written without the atomic writer: {not_atomic}"


@pytest.fixture(scope="module")
def counted_run(tiny_seq, tmp_path_factory):
    """``pavemap.run`` on the synthetic kitti-like drive (it has a geo origin), counting every write."""
    out = tmp_path_factory.mktemp("counted") / "run"
    writes = WriteCounter()
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(os, "replace", writes)
        result = pavemap.run(tiny_seq, _fast_config("kitti"), out, progress=False)
    return result, out, writes


def test_run_writes_each_file_once_atomically(counted_run):
    result, out, writes = counted_run
    _assert_written_once_atomically(out, writes)
    for name in ("defects.geojson", "baseline_defects.geojson", "metrics.json", "eval.json", "defects.csv",
                 "detections_mapped.jsonl", "defect_map.json", "report.html", "segments.csv", "segments.geojson"):
        assert writes.count[(out / name).resolve()] == 1, name
    assert result.detector.startswith("sim") and "truth" in result.detector  # auto on a synthetic drive


def test_one_defect_schema_in_every_file(counted_run, tiny_seq):
    result, out, _ = counted_run
    run_fc = json.loads((out / "defects.geojson").read_text())
    assert run_fc["pavemap"]["coordinates"] == "lonlat"
    seq_origin = json.loads((tiny_seq.root / "sequence.json").read_text())["geo_origin"]
    assert {k: run_fc["pavemap"]["geo_origin"][k] for k in ("lat", "lon")} == {k: seq_origin[k] for k in ("lat", "lon")}
    truth_fc = json.loads((tiny_seq.root / "truth" / "defects.geojson").read_text())
    assert truth_fc["pavemap"]["coordinates"] == "local"
    for fc in (run_fc, json.loads((out / "baseline_defects.geojson").read_text()), truth_fc):
        assert fc["features"], "nothing to check"
        for f in fc["features"]:
            p = f["properties"]
            assert p["code"] in ("D00", "D10", "D20", "D40") and p["name"] != p["code"]  # code vs readable name
            assert not {"severity_mean", "type", "centre", "centroid"} & set(p)
            assert {"id", "cls", "x_m", "y_m", "area_m2", "length_m"} <= set(p)
    assert set(result.to_geojson()["features"][0]["properties"]) == set(run_fc["features"][0]["properties"])
    # every run defect is assessed (issue 16): severity level, certainty, urgency and a unique rank
    props = [f["properties"] for f in run_fc["features"]]
    assert all(p["severity_level"] in ("low", "medium", "high") and p["priority"] in ("repair now", "schedule",
               "monitor") and p["certainty"] and p["segment"] >= 1 and "paper_severity" in p for p in props)
    assert sorted(p["priority_rank"] for p in props) == list(range(1, len(props) + 1))
    segs = (out / "segments.csv").read_text().splitlines()
    assert segs[0].startswith("segment,chainage_start_m") and len(segs) >= 2
    assert set(CSV_COLUMNS + GEO_COLUMNS) <= SCHEMA
    header = (out / "defects.csv").read_text().splitlines()[0].split(",")
    assert set(header) <= SCHEMA
    # the GeoJSON: schema keys (those known) plus the fusion's vertex counts; survey.gpkg: exactly the schema,
    # as `pavemap fuse` writes it (tests/test_gis_outputs.py)
    assert all(set(f["properties"]) <= SCHEMA | {"vertices", "vertex_observations"} for f in run_fc["features"])
    import pyogrio

    for layer in ("defects", "defect_points", "baseline_defects"):
        assert list(pyogrio.read_info(out / "survey.gpkg", layer=layer)["fields"]) == [n for n, *_ in PROPERTY_SCHEMA]


def test_cli_eval_on_a_run_folder(counted_run, tiny_seq):
    """`pavemap eval` on a `pavemap run` folder (lon/lat defects.geojson) scores as the run did."""
    result, out, _ = counted_run
    (out / "eval.json").unlink()
    r = CliRunner().invoke(app, ["eval", str(out), "--truth", str(tiny_seq.root)])
    assert r.exit_code == 0, r.output
    ev = json.loads((out / "eval.json").read_text())
    mem = result.evaluation
    assert ev["truth_defects"] == mem["truth_defects"] and ev["matched"] == mem["matched"]
    for k in ("precision", "recall", "f1"):
        assert ev[k] == pytest.approx(mem[k], abs=1e-9), k
    if mem["median_error_m"] is not None:
        assert ev["median_error_m"] == pytest.approx(mem["median_error_m"], abs=2e-3)  # centres written to the mm


def test_cli_fuse_folder_then_eval(tiny_seq, tmp_path):
    out = tmp_path / "fused"
    writes = WriteCounter()
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(os, "replace", writes)
        r = CliRunner().invoke(app, ["fuse", str(tiny_seq.root), "--out", str(out), "--surface", "truth"])
    assert r.exit_code == 0, r.output
    _assert_written_once_atomically(out, writes)
    fused_eval = json.loads((out / "eval.json").read_text())
    assert json.loads((out / "defects.geojson").read_text())["pavemap"]["coordinates"] == "lonlat"
    (out / "eval.json").unlink()
    r = CliRunner().invoke(app, ["eval", str(out), "--truth", str(tiny_seq.root)])
    assert r.exit_code == 0, r.output
    ev = json.loads((out / "eval.json").read_text())
    assert ev["f1"] == pytest.approx(fused_eval["f1"], abs=1e-9) and ev["recall"] > 0


@pytest.mark.parametrize(("one", "other"), [("pavemap.fuse", "pavemap.detect"), ("pavemap.detect", "pavemap.fuse")])
def test_fuse_and_detect_do_not_import_each_other(one, other):
    code = (f"import sys, {one}; "
            f"print(sorted(m for m in sys.modules if m == {other!r} or m.startswith({other!r} + '.')))")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert proc.stdout.strip() == "[]", f"importing {one} loaded {proc.stdout.strip()}"


def _without_truth(seq, tmp_path: Path):  # noqa: ANN001, ANN202
    """A copy of a synthetic drive that looks like an imported one: no truth/ folder."""
    root = tmp_path / "own_drive"
    shutil.copytree(seq.root, root, ignore=shutil.ignore_patterns("truth"))
    return read_sequence(root)


def test_auto_backend_fits_the_input(tiny_seq, tmp_path, monkeypatch):
    det, why = resolve_backend(DetectorConfig(), tiny_seq)
    assert det.backend == "sim" and "truth" in why
    own = _without_truth(tiny_seq, tmp_path)
    fake = tmp_path / "models" / "pavemap-yolov5n-rdd2022.pt"
    fake.parent.mkdir()
    fake.write_bytes(b"weights")
    monkeypatch.setattr(backends, "weights_candidates", lambda: [fake])
    det, why = resolve_backend(DetectorConfig(), own)
    assert det.backend == "yolo" and det.weights == str(fake) and "shipped" in why
    monkeypatch.setattr(backends, "weights_candidates", lambda: [tmp_path / "nowhere" / "w.pt"])
    with pytest.raises(PavemapError, match="pavemap-yolov5n-rdd2022.pt.*missing.*--weights"):
        resolve_backend(DetectorConfig(), own)
    assert DetectorConfig().backend == "auto"


def test_shipped_weights_are_found_from_the_package():
    assert backends.shipped_weights().name == "pavemap-yolov5n-rdd2022.pt"


def test_sim_on_an_imported_drive_is_a_clear_error(tiny_seq, tmp_path):
    own = _without_truth(tiny_seq, tmp_path)
    cfg = _fast_config("kitti")
    cfg.detector.backend = "sim"
    with pytest.raises(PavemapError, match=r"truth/defects.geojson: not found.*--detector yolo"):
        pavemap.run(own, cfg, tmp_path / "run", progress=False)
    assert not (tmp_path / "run").exists(), "the error must come before any stage writes"


def test_run_without_config_uses_the_rig_preset(tiny_seq, tmp_path, monkeypatch, caplog):
    import pavemap.pipeline as pipeline

    seen = {}

    def fake_run(seq, cfg, detector, device, out, progress, semantics=None):  # noqa: ANN001, ANN202
        seen["cfg"] = cfg
        return pipeline.RunResult(out, [], None, None, None, {})

    monkeypatch.setattr(pipeline, "_run", fake_run)
    with caplog.at_level("INFO", logger="pavemap"):
        res = pavemap.run(tiny_seq, None, tmp_path / "run", progress=False)
    assert seen["cfg"].preset == "kitti" and seen["cfg"].filter.tau_conf == PAPER_TAU_CONF["kitti"]  # sim: the paper's
    assert res.preset.startswith("kitti") and "camera" in res.preset
    assert "preset kitti" in caplog.text and "detector sim" in caplog.text
