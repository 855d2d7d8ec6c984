"""End to end on a tiny synthetic drive: outputs, resume, refusal of a foreign run folder, bad input."""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

import pavemap
from pavemap.config import load_config
from pavemap.errors import PavemapError

ROOT = Path(__file__).resolve().parents[1]


def _fast_config(preset: str = "nuscenes"):
    cfg = load_config(preset)
    cfg.device = "cpu"
    cfg.mesh.epochs = 1
    cfg.output.overlay_frames = 1
    return cfg


@pytest.fixture(scope="module")
def finished_run(tiny_nuscenes_seq, tmp_path_factory):
    out = tmp_path_factory.mktemp("run") / "run"
    result = pavemap.run(tiny_nuscenes_seq, _fast_config(), out, progress=False)
    return result, out


def test_run_writes_every_output(finished_run):
    result, out = finished_run
    for name in ("defects.geojson", "defect_map.tif", "defects.csv", "road_mesh.ply", "bev_rgb.png",
                 "bev_semantic.png", "metrics.json", "report.html", "config.yaml", "run.log", "eval.json"):
        assert (out / name).is_file(), name
    metrics = json.loads((out / "metrics.json").read_text())
    assert set(metrics["seconds"]) >= {"mesh", "detect", "fuse", "export", "total"}
    assert "evaluation" in metrics and 0.0 <= metrics["evaluation"]["f1"] <= 1.0
    gj = result.to_geojson()
    assert gj["type"] == "FeatureCollection" and len(gj["features"]) == len(result.defects)
    on_disk = json.loads((out / "defects.geojson").read_text())
    assert len(on_disk["features"]) == len(result.defects)
    assert result.prob_map.ndim == 2 and result.class_maps.shape[0] == 4
    # no temporary files left behind
    assert not [p for p in out.rglob("*") if ".partial-" in p.name]


def test_rerun_resumes_without_redoing_the_mesh(finished_run, tiny_nuscenes_seq):
    result, out = finished_run
    ply = out / "mesh" / "mesh.ply"
    before = ply.stat().st_mtime_ns
    again = pavemap.run(tiny_nuscenes_seq, _fast_config(), out, progress=False)
    assert ply.stat().st_mtime_ns == before, "the mesh stage was redone although nothing changed"
    assert len(again.defects) == len(result.defects)
    # a changed fusion setting reuses the mesh and detections too
    cfg = _fast_config()
    cfg.filter.tau_road = 0.7
    pavemap.run(tiny_nuscenes_seq, cfg, out, progress=False)
    assert ply.stat().st_mtime_ns == before


def test_refuses_a_folder_holding_another_run(finished_run, tiny_seq, tmp_path):
    _, out = finished_run
    with pytest.raises(PavemapError, match="holds another run"):
        pavemap.run(tiny_seq, _fast_config("kitti"), out, progress=False)
    stray = tmp_path / "stray"
    stray.mkdir()
    (stray / "notes.txt").write_text("mine")
    with pytest.raises(PavemapError, match="not empty"):
        pavemap.run(tiny_seq, _fast_config("kitti"), stray, progress=False)


def test_no_detections_gives_a_valid_empty_report(tiny_seq, tmp_path):
    empty = tmp_path / "empty.jsonl"
    empty.write_text("")
    cfg = _fast_config("kitti")
    cfg.detector.backend = "file"
    cfg.detector.file = str(empty)
    res = pavemap.run(tiny_seq, cfg, tmp_path / "run", progress=False)
    assert res.defects == []
    html = (tmp_path / "run" / "report.html").read_text()
    assert "no defects" in html.lower()


def test_read_only_output_is_a_clear_error(tiny_seq, tmp_path):
    if os.geteuid() == 0:
        target = Path("/proc/pavemap-run")  # root ignores permission bits; /proc is never writable
    else:
        ro = tmp_path / "ro"
        ro.mkdir()
        ro.chmod(0o500)
        target = ro / "run"
    with pytest.raises(PavemapError, match="cannot write|not a folder|cannot create"):
        pavemap.run(tiny_seq, _fast_config("kitti"), target, progress=False)


def test_missing_weights_is_a_clear_cli_error(tiny_seq, tmp_path):
    proc = subprocess.run(
        [sys.executable, "-m", "pavemap.cli", "run", str(tiny_seq.root), "--out", str(tmp_path / "r"),
         "--detector", "yolo", "--weights", str(tmp_path / "nope.pt")],
        capture_output=True, text=True,
    )
    assert proc.returncode == 2
    assert "nope.pt" in proc.stderr and "not found" in proc.stderr
    assert "Traceback" not in proc.stderr


def test_readme_python_example_runs(tiny_seq, tmp_path):
    """The README's Python API example, executed as written (with the paths swapped for the tiny drive)."""
    readme = (ROOT / "README.md").read_text()
    m = re.search(r"```python\n(# README API example.*?)```", readme, re.S)
    assert m, "README lost its Python API example"
    code = m.group(1)
    seq_copy = tmp_path / "my_drive"
    shutil.copytree(tiny_seq.root, seq_copy)
    code = code.replace('"my_drive"', repr(str(seq_copy))).replace('"runs/my_drive"', repr(str(tmp_path / "r")))
    code = code.replace("config.mesh.epochs = 7", "config.mesh.epochs = 1")
    namespace: dict = {}
    exec(compile(code, "README.md", "exec"), namespace)
    assert namespace["result"].out_dir == tmp_path / "r"


def test_all_detections_filtered_gives_a_clear_report(tiny_seq, tmp_path):
    """Every box lies in the sky: nothing survives the road filter, and the report says why."""
    cam = next(iter(tiny_seq.cameras.values()))
    lines = [
        json.dumps({"frame": f.index, "camera": cam.name, "box": [10, 0, 40, 8], "cls": 0, "conf": 0.9})
        for f in tiny_seq.frames
    ]
    dets = tmp_path / "sky.jsonl"
    dets.write_text("\n".join(lines) + "\n")
    cfg = _fast_config("kitti")
    cfg.detector.backend = "file"
    cfg.detector.file = str(dets)
    res = pavemap.run(tiny_seq, cfg, tmp_path / "run", progress=False)
    assert res.defects == []
    assert res.metrics["filtered_detections"] == len(lines)
    assert res.metrics["valid_detections"] == 0
    html = (tmp_path / "run" / "report.html").read_text().lower()
    assert "no defects" in html and "filter" in html


def test_stage_keys_know_the_code_not_only_the_version(tmp_path):
    """A stage done by other code is redone: the key holds a hash of the package's code, which an edit changes."""
    from pavemap import __version__
    from pavemap.run_folder import mesh_parts
    from pavemap.version import code_version

    pkg = tmp_path / "pkg"
    (pkg / "configs").mkdir(parents=True)
    (pkg / "a.py").write_text("x = 1\n")
    (pkg / "configs" / "p.yaml").write_text("k: 1\n")
    before = code_version(pkg)
    (pkg / "a.py").write_text("x = 2\n")
    code_version.cache_clear()
    assert code_version(pkg) != before and before.startswith(f"{__version__}+")
    (pkg / "notes.txt").write_text("not code")
    assert code_version.__wrapped__(pkg) == code_version(pkg)
    from pavemap.mesh import MeshConfig

    assert mesh_parts("seq", MeshConfig())["version"] == code_version()  # the package's own, in every mesh key
