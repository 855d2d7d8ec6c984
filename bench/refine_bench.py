"""Photometric refinement benchmark (issue 47): the synthetic drives without depth, with and without
``mesh.refine``, and surfaces shifted by a known offset, refined.

Per preset: height bias and RMSE over observed vertices and all vertices vs the truth, held-out PSNR, stage-1
seconds, the consistency self-check's offset, for the closed form and the closed form + refinement; then the
true surface shifted by -10, -5, +5, +10 cm and the bias after the refinement. Writes
``bench/results/refine.json`` with the commit, date and load.

``--real``: instead, the real samples as a user runs them (``pavemap import``, then ``pavemap reconstruct``
with its defaults and the self-check ``mesh.consistency_check=true``, with and without ``mesh.refine=true``):
the KITTI sample (51 grey frames, true poses, corridor semantics) and both nuScenes clips (``import folder
--poses sfm --fps 2``, the segmenter's semantics). No truth surface there: the refinement's offset, the
check's reading, the camera height stage 1 used and found, the held-out PSNR over the textured road and the
seconds (key ``real``).

    python bench/refine_bench.py [--data DIR] [--presets kitti-like,nuscenes-like] [--real]
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "src"))

from common import bench_parser, machine_entry, write_results  # noqa: E402
from mesh_bench import SETTINGS, bench_drive, height_bias  # noqa: E402
from pavemap.io.sequence import read_sequence  # noqa: E402
from pavemap.mesh import MeshConfig, reconstruct  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "bench" / "results" / "refine.json"
OFFSETS = (-0.10, -0.05, 0.05, 0.10)
TARGETS = {"shifted_10cm_bias_after_m": 0.01, "closed_form_bias_m": 0.01, "rmse_reduction": 0.30,
           "time_vs_closed_form": 2.0}


def run(seq_dir: Path, preset: str, refine: bool) -> dict:
    """Stage 1 on the drive, closed form (+ the refinement); the consistency check on in both."""
    seq = read_sequence(seq_dir)
    cfg = MeshConfig.preset(SETTINGS[preset]["mesh_preset"])
    cfg.render_scale = SETTINGS[preset]["render_scale"]
    cfg.device, cfg.resume, cfg.threads = "cpu", False, 1
    cfg.refine, cfg.consistency_check = refine, True
    t = time.perf_counter()
    mesh, m = reconstruct(seq, None, cfg, progress=False)
    total = time.perf_counter() - t
    return {"seconds_total": round(total, 1), "seconds_check": m["consistency"]["seconds"],
            "seconds_without_check": round(total - m["consistency"]["seconds"], 1),
            "psnr_db": round(m["psnr"], 3), **height_bias(None, mesh, seq), "consistency": m["consistency"],
            "refine": m.get("refine")}


def shifted(seq_dir: Path, preset: str) -> list[dict]:
    """The true surface shifted by each of OFFSETS, refined: the bias before and after."""
    from pavemap.mesh.refine_run import refine_offset
    from pavemap.mesh.train import _posed
    from refine_diag import setup

    fit, run_, zt, _ = setup(seq_dir, SETTINGS[preset]["mesh_preset"])
    rows = []
    for off in OFFSETS:
        with torch.no_grad():
            fit.model.z_base.copy_(zt + off)
        t = time.perf_counter()
        r = refine_offset(fit.model, fit.pool, _posed(fit), fit.cfg)
        err = fit.model.current_heights().double().cpu() - zt.double()
        rows.append({"offset_m": off, "bias_after_m": round(float(err.mean()), 4),
                     "seconds": round(time.perf_counter() - t, 1), "moved_m": r["offset_m"]})
        print(json.dumps(rows[-1]), flush=True)
    return rows


def relief(seq_dir: Path, preset: str) -> dict:
    """The Gauss-Newton levels of :func:`pavemap.mesh.refine_solve.refine_heights` (offset and tilt, then control
    grids of 2 m and 1 m) on the closed-form surface (before the kerb refit): height error before and after."""
    from pavemap.mesh.refine import pool_images
    from pavemap.mesh.refine_solve import refine_heights
    from pavemap.mesh.train import _posed
    from refine_diag import setup

    fit, run_, zt, zc = setup(seq_dir, SETTINGS[preset]["mesh_preset"])
    rgb, mask = pool_images(fit.pool)
    t = time.perf_counter()
    z, log = refine_heights(rgb, mask, fit.pool.K, _posed(fit), torch.from_numpy(run_.data.grid.vertex_xy()), zc,
                            fit.cfg.resolution, fit.cfg.max_dist)
    secs = time.perf_counter() - t

    def err(h: torch.Tensor) -> dict:
        e = h.double() - zt.double()
        return {"bias_m": round(float(e.mean()), 4), "rmse_m": round(float(e.pow(2).mean().sqrt()), 4)}

    return {"before": err(zc), "after": err(z), "seconds": round(secs, 1), "levels": log}


SHARED = ROOT.parent / "shared" / "data"
REAL_IMPORTS = {
    "kitti-sample": ["import", "kitti", str(SHARED / "kitti-odometry-sample"), "--sequence", "90", "--camera", "0",
                     "--no-lidar"],
    "nuscenes-clip-1": ["import", "folder", str(SHARED / "nuscenes-front-clip" / "images"), "--cameras",
                        str(SHARED / "nuscenes-front-clip" / "cameras.json"), "--poses", "sfm", "--fps", "2"],
    "nuscenes-clip-2": ["import", "folder", str(SHARED / "nuscenes-front-clip-2" / "images"), "--cameras",
                        str(SHARED / "nuscenes-front-clip-2" / "cameras.json"), "--poses", "sfm", "--fps", "2"],
}


def f1(seq_dir: Path, preset: str) -> dict:
    """Defect F1 of ``pavemap.run`` on the bench drive (simulated detections, ``detector.backend=file``), closed
    form against closed form + refinement: the refinement must not cost defects."""
    import pavemap
    from pavemap.config import load_config
    from pavemap.synth import detect_sequence

    seq = read_sequence(seq_dir)
    if not (seq_dir / "detections.jsonl").is_file():
        detect_sequence(seq, seed=0, progress=False)
    out = {}
    for label, refine in (("closed_form", False), ("refined", True)):
        cfg = load_config(SETTINGS[preset]["mesh_preset"])
        cfg.device, cfg.detector.backend = "cpu", "file"
        cfg.mesh.render_scale, cfg.mesh.refine = SETTINGS[preset]["render_scale"], refine
        cfg.output.figures = cfg.output.report = False
        t = time.perf_counter()
        r = pavemap.run(read_sequence(seq_dir), cfg, seq_dir.parent / f"refine-f1-{preset}-{label}", overwrite=True,
                        progress=False)
        e = r.evaluation or {}
        out[label] = {"f1": e.get("f1"), "precision": e.get("precision"), "recall": e.get("recall"),
                      "defects": len(r.defects), "seconds": round(time.perf_counter() - t, 1)}
        print(preset, label, json.dumps(out[label]), flush=True)
    return out


def real(data: Path) -> dict:
    """Each real sample imported once (kept under ``data``), reconstructed with and without the refinement."""
    cli = [sys.executable, "-c", "import sys; from pavemap.cli import main; sys.exit(main())"]
    out: dict = {}
    for name, args in REAL_IMPORTS.items():
        seq = data / f"real-{name}"
        if not (seq / "sequence.json").is_file():
            subprocess.run(cli + args + ["--out", str(seq), "--overwrite"], check=True, capture_output=True)
        rows = {}
        for label, sets in (("closed_form", ["mesh.consistency_check=true"]),
                            ("refined", ["mesh.refine=true", "mesh.consistency_check=true"])):
            mesh = data / f"real-{name}-{label}"
            shutil.rmtree(mesh, ignore_errors=True)  # the bench's own output of an earlier run
            t = time.perf_counter()
            subprocess.run(cli + ["reconstruct", str(seq), "--out", str(mesh)]
                           + [x for s in sets for x in ("--set", s)], check=True, capture_output=True)
            m = json.loads((mesh / "metrics.json").read_text())
            cam = (m.get("geometry") or {}).get("camera_height") or {}
            rows[label] = {"seconds": round(time.perf_counter() - t, 1), "psnr_db": m.get("psnr"),
                           "heldout_textured_share": m.get("heldout_textured_share"),
                           "camera_height_used_m": cam.get("used_m"), "camera_height_found_m": cam.get("found_m"),
                           "camera_height_prior_m": cam.get("prior_m"), "refine": m.get("refine"),
                           "consistency": m.get("consistency")}
            print(name, label, json.dumps(rows[label]), flush=True)
        out[name] = {**rows, "load_avg": os.getloadavg()}
    return out


def main() -> None:
    ap = bench_parser(__doc__, "kitti-like,nuscenes-like", RESULTS)
    ap.add_argument("--real", action="store_true", help="the real samples only (key 'real')")
    ap.add_argument("--f1", action="store_true", help="defect F1 with and without the refinement only (key 'f1')")
    a = ap.parse_args()
    if a.f1:
        results = json.loads(a.results.read_text()) if a.results.is_file() else {}
        commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True,
                                text=True).stdout.strip()
        results["f1"] = {**machine_entry(), "commit": commit,
                         **{p: f1(bench_drive(a.data, p, "none", "cpu"), p) for p in a.presets.split(",")}}
        write_results(a.results, results)
        return
    if a.real:
        results = json.loads(a.results.read_text()) if a.results.is_file() else {}
        commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True,
                                text=True).stdout.strip()
        results["real"] = {**machine_entry(), "commit": commit, "samples": real(a.data)}
        write_results(a.results, results)
        return
    torch.set_num_threads(1)
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True,
                            text=True).stdout.strip()
    old = json.loads(a.results.read_text()) if a.results.is_file() else {}
    results = {"targets": TARGETS, **machine_entry(), "commit": commit, "presets": {},
               **({"diagnosis": old["diagnosis"]} if "diagnosis" in old else {})}  # bench/refine_diag.py's
    for preset in a.presets.split(","):
        seq_dir = bench_drive(a.data, preset, "none", "cpu")
        entry = {"closed_form": run(seq_dir, preset, False)}
        print(preset, json.dumps(entry["closed_form"]), flush=True)
        entry["refined"] = run(seq_dir, preset, True)
        # the load of a shared machine moves whole runs by 2-4x: the refinement's own seconds against the closed form's
        closed = entry["closed_form"]["seconds_without_check"]
        entry["time_ratio_refine"] = round((closed + entry["refined"]["refine"]["seconds"]) / max(closed, 1e-9), 2)
        print(preset, json.dumps(entry["refined"]), flush=True)
        entry["shifted"] = shifted(seq_dir, preset)
        entry["relief_gauss_newton"] = relief(seq_dir, preset)
        print(preset, json.dumps(entry["relief_gauss_newton"]), flush=True)
        entry["load_avg"] = os.getloadavg()
        results["presets"][preset] = entry
        write_results(a.results, results)


if __name__ == "__main__":
    main()
