"""The run's confidence threshold is the detector's operating point unless the config gives one (issue 41)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import yaml

import pavemap
from pavemap.config import load_config
from pavemap.detect.backends import resolve_tau_conf
from pavemap.detect.config import PAPER_TAU_CONF, FilterConfig
from pavemap.detect.filter import filter_detections
from pavemap.detect.sources import detections_model
from pavemap.errors import PavemapError
from pavemap.weights.registry import SHIPPED_WEIGHTS, known

ROOT = Path(__file__).resolve().parents[1]
SHIPPED = known(SHIPPED_WEIGHTS)


def test_resolution_order():
    assert SHIPPED is not None and SHIPPED.tau_conf is not None
    assert resolve_tau_conf(0.3, "kitti", SHIPPED.sha256) == (0.3, "set in the config")  # a given number wins
    for preset, paper in PAPER_TAU_CONF.items():
        tau, why = resolve_tau_conf(None, preset, None)  # the simulated detector: the paper's
        assert tau == paper and "paper" in why
        tau, why = resolve_tau_conf(None, preset, SHIPPED.sha256)
        assert tau == SHIPPED.tau_conf and SHIPPED_WEIGHTS in why
        assert resolve_tau_conf(None, preset, SHIPPED.sha256[:16])[0] == SHIPPED.tau_conf  # a prefix names it too
        tau, why = resolve_tau_conf(None, preset, "0" * 64)  # weights pavemap has not measured
        assert tau == paper and "not measured" in why
    assert resolve_tau_conf(None, "kitti", SHIPPED.sha256[:8])[0] == PAPER_TAU_CONF["kitti"]  # too short to name
    with pytest.raises(PavemapError, match="unknown preset"):
        resolve_tau_conf(None, "waymo", None)


def test_shipped_operating_point_follows_its_benchmark():
    """The registry's threshold is the rule applied to the bench: the largest tau_conf whose F1 on the car-mounted
    Czech val is within 0.01 of the peak, measured on these very weights."""
    bench = json.loads((ROOT / "bench" / "results" / "detector.json").read_text())["operating_point_imgsz800"]
    assert Path(bench["weights"]).name == SHIPPED_WEIGHTS
    rows = bench["czech_val"]["summary"]
    peak = max(r["f1"] for r in rows)
    rule = max(r["tau"] for r in rows if r["f1"] >= peak - 0.01)
    assert SHIPPED.tau_conf == pytest.approx(rule)
    at = next(r for r in rows if r["tau"] == pytest.approx(rule))
    assert at["bg_boxes_per_frame"] < next(r for r in rows if r["f1"] == peak)["bg_boxes_per_frame"]


def test_detections_model(tmp_path: Path):
    line = {"frame": 0, "camera": "cam", "box": [1, 2, 3, 4], "cls": 0, "conf": 0.5}
    f = tmp_path / "d.jsonl"
    f.write_text("".join(json.dumps({**line, "model": "ab" * 32}) + "\n" for _ in range(3)))
    assert detections_model(f) == "ab" * 32
    f.write_text(json.dumps({**line, "model": "ab" * 32}) + "\n" + json.dumps(line) + "\n")
    assert detections_model(f) is None  # one line does not name it: not known for all
    f.write_text(json.dumps({**line, "model": "ab" * 32}) + "\n" + json.dumps({**line, "model": "cd" * 32}) + "\n")
    assert detections_model(f) is None  # two models
    f.write_text("")
    assert detections_model(f) is None
    f.write_text("[" * 50000 + "]" * 50000 + "\n")  # hostile nesting: no answer, not a traceback
    assert detections_model(f) is None
    assert detections_model(tmp_path / "missing.jsonl") is None


def test_unresolved_threshold_is_refused(tiny_seq):
    with pytest.raises(PavemapError, match="tau_conf is none"):
        filter_detections(tiny_seq, [], FilterConfig())


def _file_config(path: Path, tau: float | None = None):
    cfg = load_config("kitti")
    cfg.device, cfg.mesh.epochs, cfg.output.overlay_frames = "cpu", 0, 1
    cfg.detector.backend, cfg.detector.file = "file", str(path)
    cfg.filter.tau_conf = tau
    return cfg


def _shipped_boxes(tiny_seq, tmp_path: Path) -> tuple[Path, Path, int]:
    """The tiny drive's boxes at conf 0.15 and 0.25: a file whose lines name the shipped detector, one without."""
    recs = [json.loads(s) for s in (tiny_seq.root / "detections.jsonl").read_text().splitlines()]
    assert len(recs) >= 4
    for i, r in enumerate(recs):
        r["conf"] = 0.15 if i % 2 else 0.25
    named, plain = tmp_path / "named.jsonl", tmp_path / "plain.jsonl"
    named.write_text("".join(json.dumps({**r, "model": SHIPPED.sha256}) + "\n" for r in recs))
    plain.write_text("".join(json.dumps(r) + "\n" for r in recs))
    return named, plain, len(recs) // 2


def test_fuse_reads_the_model_from_the_detections(tiny_seq, tmp_path: Path):
    from typer.testing import CliRunner

    from pavemap.cli import app

    named, plain, low = _shipped_boxes(tiny_seq, tmp_path)
    for path, tau, below in ((named, 0.2, low), (plain, 0.1, 0)):
        out = tmp_path / path.stem
        r = CliRunner().invoke(app, ["fuse", str(tiny_seq.root), "--detections", str(path), "--surface", "truth",
                                     "-o", str(out), "--config", "kitti"])
        assert r.exit_code == 0, r.output
        assert f"filter.tau_conf {tau:g} (" in r.output
        assert json.loads((out / "metrics.json").read_text())["below_conf"] == below


def test_a_run_uses_the_detectors_operating_point(tiny_seq, tmp_path: Path):
    """Boxes at conf 0.15 and 0.25 from the shipped detector (the lines name its hash): the run drops the 0.15 ones
    (its threshold 0.20), the same boxes without a model name keep the paper's 0.10, and a given 0.05 keeps all."""
    named, plain, low = _shipped_boxes(tiny_seq, tmp_path)
    out = tmp_path / "run"
    res = pavemap.run(tiny_seq, _file_config(named), out, progress=False)
    assert res.metrics["below_conf"] == low
    assert "filter.tau_conf 0.2 (the measured operating point" in res.detector
    assert yaml.safe_load((out / "config.yaml").read_text())["filter"]["tau_conf"] == pytest.approx(0.20)
    res = pavemap.run(tiny_seq, _file_config(plain), out, progress=False)  # the mesh is reused
    assert res.metrics["below_conf"] == 0 and "paper's for the kitti preset" in res.detector
    res = pavemap.run(tiny_seq, _file_config(named, 0.05), out, progress=False)
    assert res.metrics["below_conf"] == 0 and "set in the config" in res.detector
