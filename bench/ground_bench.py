"""Ground points from images alone (issue 12): triangulated ground points and the camera height they give.

Synthetic drives without depth (truth: ``truth/height.npy`` + ``height.json``) and the real KITTI sample
(51 grey frames, true poses, no LiDAR; KITTI's camera height is about 1.65 m). Writes
``bench/results/ground.json``. Times are wall seconds on the bench machine (see ``machine``).

    python bench/ground_bench.py [--data /tmp/pavemap-ground] [--quick]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "src"))

from common import machine_entry, write_results  # noqa: E402
from pavemap.geometry.grid import GridSpec  # noqa: E402
from pavemap.geometry.triangulate import local_ground, sample_grid  # noqa: E402
from pavemap.io.sequence import read_sequence  # noqa: E402
from pavemap.mesh.geometry import check_surface
from pavemap.mesh.ground_points import (  # noqa: E402
    GroundConfig,
    estimate_camera_height,
    find_ground_points,
)

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "bench" / "results" / "ground.json"
KITTI_SAMPLE = Path("/work/shared/data/kitti-odometry-sample")
DRIVES = {  # name: (preset, seed, frames)
    "nuscenes-like": ("nuscenes-like", 7, None),
    "kitti-like": ("kitti-like", 23, 60),
}
TARGETS = {"camera_height_abs_err_m": 0.02, "kitti_real_camera_height_m": [1.60, 1.70]}


def ensure_data(data: Path) -> dict[str, Path]:
    paths = {}
    for name, (preset, seed, frames) in DRIVES.items():
        p = data / name
        if not (p / "sequence.json").is_file():
            from pavemap.synth import synthesize

            synthesize(p, preset, seed=seed, frames=frames, depth="none", progress=False)
        paths[name] = p
    p = data / "kitti-real"
    if not (p / "sequence.json").is_file() and KITTI_SAMPLE.is_dir():
        from pavemap.ingest.kitti import import_kitti

        import_kitti(KITTI_SAMPLE, "90", p, camera=0, lidar=False)
    if (p / "sequence.json").is_file():
        paths["kitti-real"] = p
    return paths


def _robust(r: np.ndarray) -> dict:
    r = r[np.isfinite(r)]
    if len(r) == 0:
        return {"n": 0}
    return {"n": int(len(r)), "median_m": round(float(np.median(r)), 4),
            "robust_rms_m": round(float(1.4826 * np.median(np.abs(r))), 4),
            "p90_abs_m": round(float(np.quantile(np.abs(r), 0.9)), 4),
            "outliers_gt_10cm": round(float(np.mean(np.abs(r) > 0.1)), 4)}


def run_one(seq, cfg: GroundConfig, truth: tuple[GridSpec, np.ndarray] | None) -> dict:
    t = time.perf_counter()
    gp = find_ground_points(seq, cfg)
    t_points = time.perf_counter() - t
    est = estimate_camera_height(seq, gp)
    t_total = time.perf_counter() - t
    out = {"points": len(gp), "observable": gp.observable, "reason": gp.reason,
           "views_per_point": np.bincount(gp.n_views).tolist() if len(gp) else [],
           "angle_deg_median": round(float(np.median(gp.angle_deg)), 2) if len(gp) else None,
           "time_points_s": round(t_points, 1), "time_total_s": round(t_total, 1),
           "pairs": gp.stats.get("pairs"), "cameras": {}}
    errs = []
    for name, e in est.items():
        c = {"found_m": round(e.median, 4), "spread_m": round(e.spread, 4), "stderr_m": round(e.stderr, 4),
             "frames": e.n_centres}
        if truth is not None:
            C = np.array([f.views[name].T_world_cam[:3, 3] for f in seq.frames if name in f.views])
            true = float(np.median(C[:, 2] - sample_grid(*truth, C[:, :2])))
            c.update(true_m=round(true, 4), error_m=round(e.median - true, 4))
            errs.append(abs(e.median - true))
        out["cameras"][name] = c
    if truth is not None and len(gp):
        out["height_error"] = _robust(gp.points[:, 2] - sample_grid(*truth, gp.points[:, :2]))
        out["camera_height_abs_err_max_m"] = round(float(np.max(errs)), 4)
        out["camera_height_abs_err_median_m"] = round(float(np.median(errs)), 4)
        ok, bad = check_surface(gp, *truth), check_surface(gp, *truth, offset=0.3)
        out["self_check"] = {"truth_flagged": ok.flagged, "truth_median_m": round(ok.median, 4),
                             "truth_robust_rms_m": round(ok.robust_rms, 4),
                             "shift_0.3_flagged": bad.flagged, "shift_0.3_median_m": round(bad.median, 4)}
    if truth is None and gp.observable:
        out["plane_residuals"] = plane_residuals(seq, gp)
    return out


def plane_residuals(seq, gp, radius: float = 4.0) -> dict:
    """Residuals of the points within ``radius`` of each camera to that camera's robust local plane."""
    name = next(iter(seq.cameras))
    C = np.array([f.views[name].T_world_cam[:3, 3] for f in seq.frames])
    lg = local_ground(gp.points, C, radius=radius)
    res = []
    for c, h0, (a, b) in zip(C, lg.h0, lg.slope, strict=True):
        if not np.isfinite(h0):
            continue
        near = np.linalg.norm(gp.points[:, :2] - c[:2], axis=1) <= radius
        p = gp.points[near]
        res.append(p[:, 2] - (h0 + a * (p[:, 0] - c[0]) + b * (p[:, 1] - c[1])))
    r = np.concatenate(res) if res else np.zeros(0)
    out = _robust(r)
    out["local_plane_sigma_median_m"] = round(float(np.nanmedian(lg.sigma)), 4)
    out["slope_median"] = np.round(np.nanmedian(np.abs(lg.slope), axis=0), 4).tolist()
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=Path("/tmp/pavemap-ground"))
    ap.add_argument("--quick", action="store_true", help="defaults only, no ablations")
    ap.add_argument("--results", type=Path, default=RESULTS)
    args = ap.parse_args()
    paths = ensure_data(args.data)
    variants = {  # name: (drives, config changes); the defaults first
        "default": (list(paths), {}),
        "no_semantics": (["nuscenes-like", "kitti-like"], {"use_semantics": False}),
        "prior_2.0m": (["nuscenes-like", "kitti-like"], {"prior_height": 2.0}),
        "no_neighbour_filter": (["kitti-like", "nuscenes-like"], {"neighbour_m": 0.0}),
        "no_sharpness_test": (["kitti-like"], {"min_drop": 0.0}),
        "min_views_3": (["kitti-like"], {"min_views": 3}),
        "scale_0.5": (["kitti-like", "kitti-real"], {"scale": 0.5}),
        "corridor_3m": (["kitti-real"], {"corridor_m": 3.0}),
    }
    if args.quick:
        variants = {"default": variants["default"]}
    results: dict = {"machine": machine_entry(), "targets": TARGETS, "defaults": dataclasses.asdict(GroundConfig()),
                     "runs": {}}
    for vname, (drives, change) in variants.items():
        for d in drives:
            if d not in paths:
                continue
            seq = read_sequence(paths[d])
            truth = None
            if (paths[d] / "truth" / "height.npy").is_file():
                grid = GridSpec.from_dict(json.loads((paths[d] / "truth" / "height.json").read_text()))
                truth = (grid, np.load(paths[d] / "truth" / "height.npy").astype(np.float64))
            r = run_one(seq, dataclasses.replace(GroundConfig(), **change), truth)
            results["runs"].setdefault(vname, {})[d] = r
            he = r.get("height_error", {})
            print(f"{vname:20s} {d:14s} points {r['points']:6d}  err med {he.get('median_m')} "
                  f"rRMS {he.get('robust_rms_m')} p90 {he.get('p90_abs_m')}  cam "
                  f"{ {k: (v['found_m'], v.get('true_m')) for k, v in r['cameras'].items()} }  "
                  f"{r['time_total_s']} s", flush=True)
    write_results(args.results, results)


if __name__ == "__main__":
    main()
