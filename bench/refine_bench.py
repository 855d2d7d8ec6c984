"""Photometric refinement benchmark (issue 47): the synthetic drives without depth, with and without
``mesh.refine``, and surfaces shifted by a known offset, refined.

Per preset: height bias and RMSE over observed vertices and all vertices vs the truth, held-out PSNR, stage-1
seconds, the consistency self-check's offset, for the closed form and the closed form + refinement; then the
true surface shifted by -10, -5, +5, +10 cm and the bias after the refinement. Writes
``bench/results/refine.json`` with the commit, date and load.

``--parts`` picks what to measure (the others keep their figures from the file, each part with its own
commit and date): ``synthetic`` (the above), ``f1`` (whole ``pavemap run`` on the presets' drives with and
without the refinement: defect F1, precision, recall, stage-1 seconds), ``real`` (the real KITTI sample and the
two nuScenes clips, imported once into ``--data``/real: the refinement's offset, the consistency check,
the camera height above the surface, held-out PSNR, seconds; see :mod:`refine_real`), ``error_parts`` (where the
closed form's height error lies: near kerbs and by their side, by distance from the path, by spatial scale, and
with the truth's road / off-road sides at the kerbs; :mod:`refine_error_parts`), ``relief_rounds`` (the closed form
on three drives per preset with 2 / 4 / 8 robust rounds in the kerb refit: what chose ``refit_iterations``).

    python bench/refine_bench.py [--data DIR] [--presets kitti-like,nuscenes-like] [--parts synthetic,f1,real]
                                 [--real-data DIR]
"""

from __future__ import annotations

import json
import os
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "src"))

from common import bench_parser, git_commit, machine_entry, write_results  # noqa: E402
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
    cfg = closed_form_cfg(preset)
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
    from pavemap.mesh.epoch import posed as _posed
    from pavemap.mesh.refine_run import refine_offset
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
    from pavemap.mesh.epoch import posed as _posed
    from pavemap.mesh.refine import pool_images
    from pavemap.mesh.refine_solve import refine_heights
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


def f1_runs(seq_dir: Path, preset: str, work: Path) -> dict:
    """Whole ``pavemap run`` (the preset's config, CPU, simulated detector) on the drive, without and with
    ``mesh.refine``: defect F1, precision, recall against the truth and the seconds per stage."""
    import shutil
    import tempfile

    import pavemap

    out = {}
    for refine in (False, True):
        cfg = pavemap.load_config({"kitti-like": "kitti", "nuscenes-like": "nuscenes"}[preset])
        cfg.device, cfg.mesh.refine, cfg.mesh.consistency_check = "cpu", refine, refine
        run_dir = Path(tempfile.mkdtemp(prefix=f"refine-f1-{preset}-", dir=work))
        try:
            res = pavemap.run(seq_dir, cfg, run_dir / "run", progress=False)
            ev, m = res.evaluation or {}, res.metrics
            out["refined" if refine else "closed_form"] = {
                "f1": ev.get("f1"), "precision": ev.get("precision"), "recall": ev.get("recall"),
                "matched": ev.get("matched"), "truth": ev.get("truth"), "stage_seconds": m.get("seconds"),
                "refine": m.get("mesh", {}).get("refine"), "consistency": m.get("mesh", {}).get("consistency")}
        finally:
            shutil.rmtree(run_dir)
        print(preset, "refine" if refine else "closed form", json.dumps(out["refined" if refine else "closed_form"]),
              flush=True)
    return out


def closed_form_cfg(preset: str) -> MeshConfig:
    """The preset's stage-1 config as the bench runs it: its render scale, CPU, one thread, no resume."""
    cfg = MeshConfig.preset(SETTINGS[preset]["mesh_preset"])
    cfg.render_scale = SETTINGS[preset]["render_scale"]
    cfg.device, cfg.resume, cfg.threads = "cpu", False, 1
    return cfg


def closed_form_error_parts(seq_dir: Path, preset: str) -> dict:
    """Where the closed form's error lies on the drive (:mod:`refine_error_parts`)."""
    from refine_error_parts import error_parts, truth_sides

    seq = read_sequence(seq_dir)
    cfg = closed_form_cfg(preset)
    mesh, _ = reconstruct(seq, None, cfg, progress=False)
    out = error_parts(mesh, seq)
    mesh, _ = truth_sides(seq, cfg)
    parts = error_parts(mesh, seq)
    out["with_truth_kerb_sides"] = {k: parts[k] for k in ("bias_m", "rmse_m", "kerb_sides")}
    return out


def synthetic(seq_dir: Path, preset: str) -> dict:
    """The closed form and the refinement on the drive, surfaces shifted by OFFSETS, the Gauss-Newton relief."""
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
    return entry


def main() -> None:
    ap = bench_parser(__doc__, "kitti-like,nuscenes-like", RESULTS)
    ap.add_argument("--parts", default="synthetic",
                    help="comma-separated: synthetic, f1, real, error_parts, relief_rounds")
    ap.add_argument("--real-data", type=Path, default=ROOT.parent / "shared" / "data",
                    help="folder of kitti-odometry-sample/, nuscenes-front-clip/, nuscenes-front-clip-2/")
    a = ap.parse_args()
    parts = set(a.parts.split(","))
    known = {"synthetic", "f1", "real", "error_parts", "relief_rounds"}
    if parts - known:
        raise SystemExit(f"--parts: unknown {sorted(parts - known)}")
    torch.set_num_threads(1)
    commit = git_commit()
    stamp = {**machine_entry(), "commit": commit}
    results = json.loads(a.results.read_text()) if a.results.is_file() else {}
    results["targets"] = TARGETS
    if "real" in parts:
        from refine_real import real_samples

        results["real"] = {**stamp, "samples": real_samples(a.real_data, a.data / "real")}
        results["real"]["load_avg"] = os.getloadavg()
        write_results(a.results, results)
    for preset in a.presets.split(",") if parts & {"synthetic", "f1", "error_parts", "relief_rounds"} else ():
        seq_dir = bench_drive(a.data, preset, "none", "cpu")
        if "synthetic" in parts:
            results.update(stamp)  # the top-level commit and date are the synthetic part's
            results.setdefault("presets", {})[preset] = {**synthetic(seq_dir, preset), "load_avg": os.getloadavg()}
        if "error_parts" in parts:
            results.setdefault("error_parts", {})[preset] = {**stamp, **closed_form_error_parts(seq_dir, preset)}
            print(preset, json.dumps(results["error_parts"][preset]), flush=True)
        if "relief_rounds" in parts:
            from refine_error_parts import relief_rounds

            drives = relief_rounds(a.data, preset, closed_form_cfg(preset))
            results.setdefault("relief_rounds", {})[preset] = {**stamp, "drives": drives, "load_avg": os.getloadavg()}
        if "f1" in parts:
            results.setdefault("f1", {})[preset] = {**stamp, **f1_runs(seq_dir, preset, a.data),
                                                    "load_avg": os.getloadavg()}
        write_results(a.results, results)


if __name__ == "__main__":
    main()
