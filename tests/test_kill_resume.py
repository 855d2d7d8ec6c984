"""SIGKILL during each stage (mesh, detect, fuse, export), then a rerun: outputs identical to an
uninterrupted run; a kill followed by a rerun with other settings redoes the stage.

The killed runs are real processes that SIGKILL themselves at a chosen point of a stage (a patched
function inside that stage), so what they leave behind is what a power cut or the OOM killer leaves.
One chain of runs keeps this fast: a run killed in stage 1 after its first epoch's checkpoint; a rerun
(resuming stage 1) killed in detection just before ``detections.jsonl`` lands; a rerun killed in fusion;
one killed in the export before ``defect_map.tif``; the last rerun finishes. Each rerun must resume
what the previous one left, and the end result must equal the uninterrupted run's, file by file.
"""

from __future__ import annotations

import json
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import pavemap
from pavemap.config import load_config

OVERRIDES = ["device=cpu", "mesh.epochs=2", "mesh.threads=1", "output.figures=false", "output.report=false",
             "output.overlay_frames=0"]

# Runs pavemap.run in a child that SIGKILLs itself at the point named by argv[3].
DRIVER = r"""
import json, os, signal, sys
import pavemap
from pavemap.config import load_config

seq, out, stage, overrides = sys.argv[1], sys.argv[2], sys.argv[3], json.loads(sys.argv[4])

def die():
    os.kill(os.getpid(), signal.SIGKILL)

def kill_on_rename(name):
    real = os.replace
    def replace(src, dst, *a, **k):
        if os.path.basename(str(dst)) == name:
            die()
        return real(src, dst, *a, **k)
    os.replace = replace

if stage == "mesh":  # after the first epoch's checkpoint
    import pavemap.mesh.train as train
    real_save = train.save_checkpoint
    def save(path, model, opt, delta, epoch, *a, **k):
        real_save(path, model, opt, delta, epoch, *a, **k)
        if epoch == 1:
            die()
    train.save_checkpoint = save
elif stage == "detect":  # the detections computed, the file not yet in place
    kill_on_rename("detections.jsonl")
elif stage == "fuse":  # the road filter done, fusion not
    import pavemap.detect.filter as filt
    real_filter = filt.filter_detections
    def filter_detections(*a, **k):
        real_filter(*a, **k)
        die()
    filt.filter_detections = filter_detections
elif stage == "export":  # defects.geojson and others written, the GeoTIFF not
    kill_on_rename("defect_map.tif")
pavemap.run(seq, load_config("kitti", overrides=overrides), out, progress=False)
sys.exit(3)  # the kill point was never reached
"""

#: Bookkeeping that legitimately differs between two runs (timestamps, timings, the log).
VOLATILE = {"run.log", "run.json", ".pavemap-owner.json", "mesh/checkpoint.pt"}


def _killed_run(seq_root: Path, out: Path, stage: str, overrides: list[str]) -> None:
    proc = subprocess.run([sys.executable, "-c", DRIVER, str(seq_root), str(out), stage, json.dumps(overrides)],
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == -signal.SIGKILL, f"not killed in {stage} (rc {proc.returncode}): {proc.stderr[-2000:]}"
    assert not (out / "metrics.json").exists(), f"killed in {stage}, the folder looks complete"


def _run(seq_root: Path, out: Path, overrides: list[str] = OVERRIDES):
    return pavemap.run(seq_root, load_config("kitti", overrides=overrides), out, progress=False)


def _no_seconds(o: object) -> object:
    if isinstance(o, dict):
        return {k: _no_seconds(v) for k, v in o.items() if "second" not in k and k != "finished"}  # timings
    if isinstance(o, list):
        return [_no_seconds(v) for v in o]
    return o


def _first_difference(a: object, b: object, path: str = "") -> str:
    if isinstance(a, dict) and isinstance(b, dict):
        for k in sorted(set(a) | set(b), key=str):
            if a.get(k) != b.get(k):
                return _first_difference(a.get(k), b.get(k), f"{path}.{k}")
    if isinstance(a, list) and isinstance(b, list) and len(a) == len(b):
        for i, (x, y) in enumerate(zip(a, b, strict=True)):
            if x != y:
                return _first_difference(x, y, f"{path}[{i}]")
    return f"{path}: {a!r} != {b!r}"


def _files(root: Path) -> dict[str, Path]:
    rels = {p.relative_to(root).as_posix(): p for p in root.rglob("*") if p.is_file()}
    return {r: p for r, p in rels.items() if r not in VOLATILE and not r.startswith(".stages/")}


def _gpkg_rows(path: Path) -> dict[str, list]:
    import sqlite3

    with sqlite3.connect(path) as db:
        tables = [r[0] for r in db.execute("SELECT name FROM sqlite_master WHERE type='table'")]
        out = {}
        for t in tables:
            cur = db.execute(f'SELECT * FROM "{t}"')
            cols = [c[0] for c in cur.description]
            # time stamps: a table's last change, a run's processing time, a QGIS style's save time
            out[t] = [tuple(v for c, v in zip(cols, row, strict=True)
                            if c not in ("last_change", "processed_utc", "update_time"))
                      for row in cur]
    return out


def assert_same_outputs(a: Path, b: Path) -> None:
    fa, fb = _files(a), _files(b)
    assert sorted(fa) == sorted(fb), f"different files: {sorted(set(fa) ^ set(fb))}"
    for rel, pa in fa.items():
        pb = fb[rel]
        if rel.endswith(".json"):
            ja, jb = _no_seconds(json.loads(pa.read_text())), _no_seconds(json.loads(pb.read_text()))
            assert ja == jb, f"{rel}: {_first_difference(ja, jb)}"
        elif rel.endswith(".gpkg"):  # GeoPackage tables carry a last_change time stamp
            assert _gpkg_rows(pa) == _gpkg_rows(pb), rel
        elif rel.endswith(".npz"):  # zip entries carry a time stamp; compare the arrays
            za, zb = np.load(pa), np.load(pb)
            assert sorted(za.files) == sorted(zb.files), rel
            for k in za.files:
                assert np.array_equal(za[k], zb[k], equal_nan=True), f"{rel}:{k}"
        else:
            assert pa.read_bytes() == pb.read_bytes(), rel


@pytest.fixture(scope="module")
def reference(tiny_seq, tmp_path_factory):
    out = tmp_path_factory.mktemp("kill") / "reference"
    _run(tiny_seq.root, out)
    return out


def test_sigkill_in_each_stage_then_rerun_gives_the_uninterrupted_outputs(tiny_seq, reference, tmp_path):
    out = tmp_path / "run"
    _killed_run(tiny_seq.root, out, "mesh", OVERRIDES)
    ck = out / "mesh" / "checkpoint.pt"
    assert ck.is_file() and not (out / ".stages" / "mesh.json").exists()  # stage 1 started, not finished

    _killed_run(tiny_seq.root, out, "detect", OVERRIDES)
    log = (out / "run.log").read_text()
    assert "mesh: resuming the interrupted stage" in log
    assert (out / ".stages" / "mesh.json").is_file() and not (out / "detections.jsonl").exists()
    assert list(out.glob(".detections.jsonl.partial-*")), "the kill point left no temporary: not inside the write"

    _killed_run(tiny_seq.root, out, "fuse", OVERRIDES)
    assert not list(out.glob(".*.partial-*")), "a rerun keeps a killed run's temporaries"
    assert (out / ".stages" / "detect.json").is_file() and not (out / ".stages" / "fuse.json").exists()

    _killed_run(tiny_seq.root, out, "export", OVERRIDES)
    assert (out / "defects.geojson").is_file() and not (out / "defect_map.tif").exists()

    result = _run(tiny_seq.root, out)
    log = (out / "run.log").read_text().split("preset kitti")[-1]  # the last run's part of the log
    assert "mesh: up to date" in log and "detect: up to date" in log
    assert result.metrics["input_detections"] > 0
    assert_same_outputs(reference, out)
    owner = json.loads((out / ".pavemap-owner.json").read_text())
    assert owner["status"] == "complete" and "defects.geojson" in owner["files"]


def test_kill_then_rerun_with_other_settings_redoes_the_stage(tiny_seq, tmp_path):
    from pavemap.mesh import load_mesh, reconstruct

    out = tmp_path / "run"
    _killed_run(tiny_seq.root, out, "mesh", OVERRIDES)  # 1 of 2 epochs done
    fewer = [*OVERRIDES, "mesh.epochs=1", "detector.seed=1"]
    result = _run(tiny_seq.root, out, fewer)
    log = (out / "run.log").read_text()
    assert "checkpoint discarded" in log and "epochs 2 -> 1" in log
    history = json.loads((out / "mesh" / "metrics.json").read_text())["history"]
    assert len(history) == 1
    # the mesh is the one a fresh 1-epoch run gives, not the killed 2-epoch run's first epoch continued
    cfg = load_config("kitti", overrides=fewer)
    fresh, _ = reconstruct(pavemap.read_sequence(tiny_seq.root), None, cfg.mesh, progress=False)
    assert np.array_equal(load_mesh(out / "mesh").surface.heights.numpy(), fresh.surface.heights.numpy())
    # a finished stage is redone too when a setting it depends on changes, and the log says which
    result = _run(tiny_seq.root, out, [*fewer, "detector.seed=2"])
    log = (out / "run.log").read_text().split("preset kitti")[-1]
    assert "mesh: up to date" in log and "detect: backend sim (config: seed 1 -> 2)" in log
    # the last rerun's result is the run folder's: the same defects as its survey layer
    import pyogrio

    assert len(result.defects) == pyogrio.read_info(out / "survey.gpkg", layer="defects")["features"]
