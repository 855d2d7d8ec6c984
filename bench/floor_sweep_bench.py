"""Pothole depth without depth (issue 16): the floor sweep (maintain.floor_sweep) -> bench/results/floor_sweep.json.

The maintenance bench's drives (bench/maintenance_bench.py: kitti-like 40 frames at 10 Hz, nuScenes-like 14
frames at 2 Hz, more defects than the presets), synthesized without depth at the images' full size (1241 x 376,
1600 x 900) and, for kitti-like, at the bench's half size. Three rows per drive:

- ``method``: the sweep on the true surface and the true pothole outlines (the measuring method alone): per
  pothole the deepest point (the 0.99 quantile of the samples' depths below the ring plane, as the maintenance
  stage reads them) against the truth's ``depth_max_m``, or why it was not measured;
- ``flat_road``: pothole-sized disks (0.3 m radius) of plain road (no defect within 0.7 m, the true surface
  within 12 mm of a plane over 1.8 m) 3-8 m from each frame's camera: the depth the sweep reads where there is
  none (the same quantile);
- ``run``: ``pavemap.run`` without depth and the maintenance stage with ``floor_sweep`` on and off, matched to
  the truth as the maintenance bench does: the depth errors, how many were measured and why not, severity
  agreement.

    python bench/floor_sweep_bench.py [--data DIR] [--presets kitti-like nuscenes-like]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "src"))
sys.path.insert(0, str(Path(__file__).parent))

from common import machine_entry, write_results  # noqa: E402
from maintenance_bench import DRIVES, WORLD, compare, map_and_measure, summarise  # noqa: E402

RESULTS = ROOT / "bench" / "results" / "floor_sweep.json"
SIZES = {"kitti-like": (1.0, 0.5), "nuscenes-like": (1.0,)}


def _stats(errors: list[float]) -> dict:
    a = np.abs(np.asarray(errors, float))
    return {"n": len(a), "median_abs_mm": round(float(np.median(a)), 1) if len(a) else None,
            "p90_abs_mm": round(float(np.percentile(a, 90)), 1) if len(a) else None,
            "max_abs_mm": round(float(a.max()), 1) if len(a) else None,
            "signed_median_mm": round(float(np.median(errors)), 1) if len(a) else None}


def _deepest_mm(pts: np.ndarray, poly, surface) -> float:  # noqa: ANN001
    from pavemap.maintain.floor_sweep import FloorSweepConfig, _road_plane

    p0, n = _road_plane(poly, surface, FloorSweepConfig())
    return float(np.quantile((p0 - pts) @ n, 0.99)) * 1000.0


def method_row(seq_dir: Path) -> dict:
    from shapely.geometry import shape

    from pavemap.io.sequence import read_sequence
    from pavemap.io.truth import read_truth_height
    from pavemap.maintain.floor_sweep import floor_samples

    seq, surface = read_sequence(seq_dir), read_truth_height(seq_dir)
    feats = json.loads((seq_dir / "truth" / "defects.geojson").read_text())["features"]
    rows, errors, why_not = [], [], {}
    for f in feats:
        p = f["properties"]
        if p["cls"] != 3:
            continue
        poly = shape(f["geometry"])
        pts, why = floor_samples(seq, [poly], surface)
        if why[0] is not None:
            key = why[0].split(":")[0]
            why_not[key] = why_not.get(key, 0) + 1
            rows.append({"id": p["id"], "truth_mm": round(1000 * p["depth_max_m"], 1), "why_not": why[0]})
            continue
        d = _deepest_mm(pts, poly, surface)
        errors.append(d - 1000 * p["depth_max_m"])
        rows.append({"id": p["id"], "truth_mm": round(1000 * p["depth_max_m"], 1), "measured_mm": round(d, 1),
                     "cells": len(pts)})
    return {**_stats(errors), "potholes": len(rows), "not_measured": why_not, "rows": rows}


def flat_road_row(seq_dir: Path) -> dict:
    import torch
    from shapely.geometry import Point, shape

    from pavemap.io.sequence import read_sequence
    from pavemap.io.truth import read_truth_height
    from pavemap.maintain.floor_sweep import floor_samples

    seq, surface = read_sequence(seq_dir), read_truth_height(seq_dir)
    feats = json.loads((seq_dir / "truth" / "defects.geojson").read_text())["features"]
    defects = [shape(f["geometry"]).buffer(0.7) for f in feats]
    cam = "CAM_FRONT"
    readings, tried = [], 0
    for fr in seq.frames:
        T = np.asarray(fr.views[cam].T_world_cam)
        fwd = T[:3, 2] / np.linalg.norm(T[:2, 2])
        left = np.array([-fwd[1], fwd[0], 0.0])
        for ahead, side in ((8.0, 0.0), (8.0, 1.0), (8.0, -1.0), (3.0, 3.0), (3.0, -3.0), (6.0, 3.0), (6.0, -3.0)):
            c = T[:3, 3] + ahead * fwd + side * left
            disk = Point(c[0], c[1]).buffer(0.3)
            if any(disk.intersects(d) for d in defects):
                continue
            g = np.stack(np.meshgrid(np.linspace(c[0] - 0.9, c[0] + 0.9, 37),
                                     np.linspace(c[1] - 0.9, c[1] + 0.9, 37)), -1).reshape(-1, 2)
            z, inside = surface.height_at(torch.from_numpy(g).float())
            A = np.c_[np.ones(len(g)), g - c[:2]]
            if not inside.all() or np.abs(z.numpy() - A @ np.linalg.lstsq(A, z.numpy(), rcond=None)[0]).max() > 0.012:
                continue
            tried += 1
            pts, why = floor_samples(seq, [disk], surface)
            if why[0] is None and len(pts) >= 5:
                readings.append(_deepest_mm(pts, disk, surface))
    return {**_stats(readings), "disks": tried, "measured": len(readings)}


def run_rows(seq_dir: Path, data: Path, name: str, preset: str) -> dict:
    out = {}
    for on in (False, True):
        t = time.perf_counter()
        inst, on_truth, _, secs = map_and_measure(seq_dir, data / f"run-{name}", preset, "cpu", floor_sweep=on)
        s = summarise(compare(inst, on_truth, seq_dir)["rows"])
        out["floor_sweep" if on else "area_fallback"] = {
            k: s[k] for k in ("potholes_matched", "potholes_measured", "not_measurable", "depth_abs_err_mm",
                              "depth_signed_err_mm_median", "severity_pairs", "severity_agreement")} | {
            "seconds": {**secs, "total": round(time.perf_counter() - t, 1)}}
    return out


def main() -> None:
    from pavemap.synth import synthesize

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--presets", nargs="+", default=list(SIZES))
    ap.add_argument("--data", type=Path, default=Path(os.environ.get("PAVEMAP_BENCH_DATA", "/tmp/pavemap-bench"))
                    / "floor-sweep")
    ap.add_argument("--results", type=Path, default=RESULTS)
    a = ap.parse_args()
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True, cwd=ROOT
                            ).stdout.strip()
    out = {"benchmark": "pothole depth without depth: the floor sweep vs synthetic truth (issue 16)",
           **machine_entry(), "commit": commit,
           "uptime_start": subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip(),
           "targets_mm": {"median": 10.0, "p90": 20.0}, "drives": {}}
    for preset in a.presets:
        for scale in SIZES[preset]:
            name = f"{preset}-x{scale:g}"
            seq_dir = a.data / name
            if not (seq_dir / "sequence.json").is_file():
                synthesize(seq_dir, preset, seed=0, depth="none", progress=False,
                           **{**DRIVES[preset], "scale": scale}, **WORLD)
            row = {"scale": scale, "method": method_row(seq_dir)}
            if scale == 1.0:
                row["flat_road"] = flat_road_row(seq_dir)
                row["run"] = run_rows(seq_dir, a.data, name, preset)
            out["drives"][name] = row
            print(name, json.dumps({k: ({kk: vv for kk, vv in v.items() if kk != "rows"} if isinstance(v, dict)
                                        else v) for k, v in row.items()}), flush=True)
    out["uptime_end"] = subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip()
    write_results(a.results, out)


if __name__ == "__main__":
    main()
