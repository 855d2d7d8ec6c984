"""Pothole depth without depth (issue 16): the floor sweep (maintain.floor_sweep) -> bench/results/floor_sweep.json.

The maintenance bench's drives (bench/maintenance_bench.py: kitti-like 40 frames at 10 Hz, nuScenes-like 14
frames at 2 Hz, more defects than the presets), synthesized without depth at the images' full size (1241 x 376,
1600 x 900) and, for kitti-like, at the bench's half size. Rows per drive:

- ``method``: the sweep on the true surface and the true pothole outlines (the measuring method alone): per
  pothole the deepest point (the 0.99 quantile of the samples' depths below the ring plane, as the maintenance
  stage reads them) against the truth's ``depth_max_m``, or why it was not measured;
- ``flat_road``: pothole-sized disks (0.3 m radius) of plain road (no defect within 0.7 m, the true surface
  within 12 mm of a plane over 1.8 m) 3-8 m from each frame's camera: the depth the sweep reads where there is
  none (the same quantile);
- ``run``: ``pavemap.run`` without depth and the maintenance stage with ``floor_sweep`` on and off, matched to
  the truth as the maintenance bench does: the depth errors, how many were measured and why not, severity
  agreement;
- ``visibility`` (true outlines) and ``run.outlines_seen`` (the outlines the run swept): what the views the sweep
  picks can see of each pothole's floor on the true surface (ray marching), with and without the near-rim rule
  (``FloorSweepConfig.max_hidden_share``): the share all see, and how far the deepest point all see lies above
  the truth's deepest.

    python bench/floor_sweep_bench.py [--data DIR] [--presets kitti-like nuscenes-like]
        [--real kitti SEQ MESH --real nuscenes-clip SEQ MESH]

``--real``: plain-road disks on a real drive (``real_road_row``); SEQ from ``pavemap import``, MESH from
``pavemap reconstruct`` (the README's "Real KITTI sample" and "Real nuScenes clip" give both commands).
"""

from __future__ import annotations

import argparse
import json
import os
import re
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "src"))
sys.path.insert(0, str(Path(__file__).parent))

from common import git_commit, machine_entry, write_results  # noqa: E402
from maintenance_bench import DRIVES, WORLD, compare, map_and_measure, summarise  # noqa: E402

RESULTS = ROOT / "bench" / "results" / "floor_sweep.json"
SIZES = {"kitti-like": (1.0, 0.5), "nuscenes-like": (1.0,)}


def _stats(errors: list[float]) -> dict:
    a = np.abs(np.asarray(errors, float))
    return {"n": len(a), "median_abs_mm": round(float(np.median(a)), 1) if len(a) else None,
            "p90_abs_mm": round(float(np.percentile(a, 90)), 1) if len(a) else None,
            "max_abs_mm": round(float(a.max()), 1) if len(a) else None,
            "signed_median_mm": round(float(np.median(errors)), 1) if len(a) else None}


def _reason(why: str) -> str:
    """A reason without its figures, for counting."""
    return re.sub(r" from \d+ of its \d+ views.*", "", why.split(":")[0])


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
            key = _reason(why[0])
            why_not[key] = why_not.get(key, 0) + 1
            rows.append({"id": p["id"], "truth_mm": round(1000 * p["depth_max_m"], 1), "why_not": why[0]})
            continue
        d = _deepest_mm(pts, poly, surface)
        errors.append(d - 1000 * p["depth_max_m"])
        rows.append({"id": p["id"], "truth_mm": round(1000 * p["depth_max_m"], 1), "measured_mm": round(d, 1),
                     "cells": len(pts)})
    return {**_stats(errors), "potholes": len(rows), "not_measured": why_not, "rows": rows}


def _visible(camera: np.ndarray, pts: np.ndarray, surface) -> np.ndarray:  # noqa: ANN001
    """(N,) bool: the ray from ``camera`` (3,) toward each surface point (N, 3) meets the true surface first at that
    point (within 2 mm of height), not on a rim or wall before it (the project's ray / height-field march)."""
    import torch

    from pavemap.geometry.heightfield import intersect_rays

    d = pts - camera[None]
    dist = np.linalg.norm(d, axis=1)
    dt = surface.heights.dtype
    hit = intersect_rays(surface, torch.from_numpy(np.repeat(camera[None], len(pts), 0)).to(dt),
                         torch.from_numpy(d / dist[:, None]).to(dt), max_dist=float(dist.max()) + 0.5)
    slack = 0.002 / np.maximum(np.abs(d[:, 2]) / dist, 1e-3)  # 2 mm of height, along a grazing ray
    return hit.hit.numpy() & (hit.lam.double().numpy() >= dist - slack)


def _floor_seen(seq, surface, outline, truth: dict) -> dict | None:  # noqa: ANN001
    """What the views the sweep picks for ``outline`` (world polygon) can see of a true pothole's floor (``truth``:
    a GeoJSON feature of ``truth/defects.geojson``), on the true ``surface``: for the views it would pick without
    the near-rim rule (at least two, else None), each one's share of the floor (2 cm grid), the share all see, the
    deepest point all see, the reference sees, and the views the rule keeps all see."""
    import torch
    from shapely import contains_xy
    from shapely.geometry import shape

    from pavemap.maintain.floor_sweep import FloorSweepConfig, _hidden_share, _partners, _road_plane, _views_seeing

    cfg = FloorSweepConfig()
    views = [v for f in seq.frames for v in f.views.values()]
    centres = np.array([np.asarray(v.T_world_cam)[:3, 3] for v in views])
    plane = _road_plane(outline, surface, cfg)
    seen_by = [] if plane is None else _views_seeing(seq, views, centres, outline, plane[0], cfg)
    near = _partners(seen_by, plane[0], cfg) if seen_by else []
    if len(near) < 2:
        return None
    poly = shape(truth["geometry"])
    x0, y0, x1, y1 = poly.bounds
    X, Y = (a.ravel() for a in np.meshgrid(np.arange(x0, x1, 0.02), np.arange(y0, y1, 0.02)))
    inside = contains_xy(poly, X, Y)
    xy = np.stack([X[inside], Y[inside]], 1)
    pts = np.c_[xy, surface.height_at(torch.from_numpy(xy).to(surface.heights.dtype))[0].numpy().astype(np.float64)]
    depth = (plane[0] - pts) @ plane[1] * 1000.0
    seen = np.stack([_visible(np.asarray(v.T_world_cam)[:3, 3], pts, surface) for v in near])
    shares = [_hidden_share(v, outline, plane, cfg.hidden_depth_m) for v in near]
    kept = np.array(shares) <= cfg.max_hidden_share

    def deepest(mask: np.ndarray) -> float | None:
        return round(float(depth[mask].max()), 1) if mask.any() else None
    return {"id": truth["properties"]["id"], "truth_mm": round(1000 * truth["properties"]["depth_max_m"], 1),
            "ranges_m": [round(float(np.linalg.norm(np.asarray(v.T_world_cam)[:3, 3] - plane[0])), 1) for v in near],
            "hidden_share_5cm": [round(x, 2) for x in shares],
            "seen_by_each": [round(float(m.mean()), 2) for m in seen],
            "seen_by_all": round(float(seen.all(0).mean()), 2), "deepest_seen_by_all_mm": deepest(seen.all(0)),
            "deepest_seen_by_reference_mm": deepest(seen[0]), "views_kept": int(kept.sum()),
            "deepest_seen_by_kept_mm": deepest(seen[kept].all(0)) if kept.any() else None}


def _seen_summary(rows: list[dict]) -> dict:
    """Medians over the potholes with three views or more: the share of the floor all see, and how far the deepest
    point all see (and the views the near-rim rule keeps see) lies above the truth's (mm)."""
    three = [r for r in rows if len(r["ranges_m"]) >= 3]

    def short(key: str) -> float | None:
        v = [r["truth_mm"] - r[key] for r in three if r[key] is not None]
        return round(float(np.median(v)), 1) if v else None
    return {"potholes_with_2_or_more_views": len(rows), "with_3_or_more": len(three),
            "median_seen_by_all": round(float(np.median([r["seen_by_all"] for r in three])), 2) if three else None,
            "median_short_deepest_seen_by_all_mm": short("deepest_seen_by_all_mm"),
            "median_short_deepest_seen_by_kept_mm": short("deepest_seen_by_kept_mm"), "rows": rows}


def visibility_row(seq_dir: Path) -> dict:
    """:func:`_floor_seen` for each true pothole on its true outline (the truth decides what a view can see)."""
    from shapely.geometry import shape

    from pavemap.io.sequence import read_sequence
    from pavemap.io.truth import read_truth_height

    seq, surface = read_sequence(seq_dir), read_truth_height(seq_dir)
    feats = [f for f in json.loads((seq_dir / "truth" / "defects.geojson").read_text())["features"]
             if f["properties"]["cls"] == 3]
    rows = [_floor_seen(seq, surface, shape(f["geometry"]), f) for f in feats]
    return _seen_summary([r for r in rows if r is not None])


def _run_outlines_seen(seq_dir: Path, outlines: list) -> dict:
    """:func:`_floor_seen` for the outlines a run swept, each matched to the true pothole it overlaps most (the
    first outline of each; one that overlaps none is counted as ``unmatched``)."""
    from shapely.geometry import shape

    from pavemap.io.sequence import read_sequence
    from pavemap.io.truth import read_truth_height

    seq, surface = read_sequence(seq_dir), read_truth_height(seq_dir)
    feats = [f for f in json.loads((seq_dir / "truth" / "defects.geojson").read_text())["features"]
             if f["properties"]["cls"] == 3]
    rows, matched, unmatched = [], set(), 0
    for o in outlines:
        area, k = max(((o.intersection(shape(f["geometry"])).area, k) for k, f in enumerate(feats)),
                      default=(0.0, -1))
        if area <= 0:
            unmatched += 1
            continue
        if k in matched:
            continue
        matched.add(k)
        row = _floor_seen(seq, surface, o, feats[k])
        if row is not None:
            rows.append(row)
    return {**_seen_summary(rows), "unmatched": unmatched}


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


def real_road_row(seq_dir: Path, mesh_dir: Path) -> dict:
    """Real frames have no truth, but plain road has no depth: 0.3 m disks 5-9 m ahead of every third frame's first
    camera (1.5 m aside, or straight ahead at 9 m), on a stage-1 mesh's surface: why each was not measured, and
    the depth the sweep reads on the measured ones (the maintenance stage's quantile)."""
    from shapely.geometry import Point

    from pavemap.io.sequence import read_sequence
    from pavemap.maintain.floor_sweep import floor_sets
    from pavemap.mesh import load_mesh

    seq, surface = read_sequence(seq_dir), load_mesh(mesh_dir).surface
    cam = sorted(seq.cameras)[0]
    disks = []
    for fr in seq.frames[::3]:
        if cam not in fr.views:
            continue
        T = np.asarray(fr.views[cam].T_world_cam)
        fwd = T[:3, 2] / np.linalg.norm(T[:2, 2])
        left = np.array([-fwd[1], fwd[0], 0.0])
        for ahead, side in ((5.0, 1.5), (5.0, -1.5), (7.0, 1.5), (7.0, -1.5), (9.0, 0.0)):
            c = T[:3, 3] + ahead * fwd + side * left
            disks.append(Point(c[0], c[1]).buffer(0.3))
    why_not, readings = {}, []
    for pts, why, plane in floor_sets(seq, disks, surface):
        if why is None and len(pts) >= 5:
            readings.append(float(np.quantile((plane[0] - pts) @ plane[1], 0.99)) * 1000.0)
            continue
        key = _reason(why or "fewer than 5 cells")
        why_not[key] = why_not.get(key, 0) + 1
    return {**_stats(readings), "disks": len(disks), "image_size": [seq.cameras[cam].width, seq.cameras[cam].height],
            "not_measured": why_not}


def run_rows(seq_dir: Path, data: Path, name: str, preset: str) -> dict:
    import pavemap.maintain.floor_sweep as sweep

    out, swept = {}, []
    sweep_sets = sweep.floor_sets

    def keep_outlines(seq, polygons, surface, cfg=None):  # noqa: ANN001, ANN202
        swept.extend(polygons)
        return sweep_sets(seq, polygons, surface, cfg)
    for on in (False, True):
        t = time.perf_counter()
        if on:  # what the maintenance stage sweeps: the outlines, for the visibility rows
            sweep.floor_sets = keep_outlines
        try:
            inst, on_truth, _, secs = map_and_measure(seq_dir, data / f"run-{name}", preset, "cpu", floor_sweep=on)
        finally:
            sweep.floor_sets = sweep_sets
        s = summarise(compare(inst, on_truth, seq_dir)["rows"])
        out["floor_sweep" if on else "area_fallback"] = {
            k: s[k] for k in ("potholes_matched", "potholes_measured", "not_measurable", "depth_abs_err_mm",
                              "depth_signed_err_mm_median", "severity_pairs", "severity_agreement")} | {
            "seconds": {**secs, "total": round(time.perf_counter() - t, 1)}}
    out["outlines_seen"] = _run_outlines_seen(seq_dir, swept)
    return out


def main() -> None:
    from pavemap.synth import synthesize

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--presets", nargs="*", default=list(SIZES))
    ap.add_argument("--real", nargs=3, action="append", default=[], metavar=("NAME", "SEQUENCE", "MESH"),
                    help="a real sequence (pavemap import), its stage-1 mesh (pavemap reconstruct): plain-road disks")
    ap.add_argument("--data", type=Path, default=Path(os.environ.get("PAVEMAP_BENCH_DATA", "/tmp/pavemap-bench"))
                    / "floor-sweep")
    ap.add_argument("--results", type=Path, default=RESULTS)
    a = ap.parse_args()
    commit = git_commit()
    out = {"benchmark": "pothole depth without depth: the floor sweep vs synthetic truth (issue 16)",
           **machine_entry(), "commit": commit,
           "uptime_start": subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip(),
           "targets_mm": {"median": 10.0, "p90": 20.0}, "drives": {}}
    for name, seq_dir, mesh_dir in a.real:  # first: a wrong path ends the bench before the synthetic drives
        out.setdefault("real", {})[name] = real_road_row(Path(seq_dir), Path(mesh_dir))
        print(name, json.dumps(out["real"][name]), flush=True)
    for preset in a.presets:
        for scale in SIZES[preset]:
            name = f"{preset}-x{scale:g}"
            seq_dir = a.data / name
            if not (seq_dir / "sequence.json").is_file():
                synthesize(seq_dir, preset, seed=0, depth="none", progress=False,
                           **{**DRIVES[preset], "scale": scale}, **WORLD)
            row = {"scale": scale, "method": method_row(seq_dir), "visibility": visibility_row(seq_dir)}
            if scale == 1.0:
                row["flat_road"] = flat_road_row(seq_dir)
                row["run"] = run_rows(seq_dir, a.data, name, preset)
            out["drives"][name] = row
            print(name, json.dumps({k: ({kk: vv for kk, vv in v.items() if kk != "rows"} if isinstance(v, dict)
                                        else v) for k, v in row.items()}), flush=True)
    out["uptime_end"] = subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip()
    write_results(a.results, out)


if __name__ == "__main__":
    from pavemap.errors import PavemapError, SequenceError

    try:
        main()
    except (PavemapError, SequenceError) as e:  # a folder that is not a sequence or a mesh: its path, no traceback
        sys.exit(f"floor_sweep_bench: {e}")
