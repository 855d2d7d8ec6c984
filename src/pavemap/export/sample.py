"""A small, plausible set of export inputs (road BEV, defects, maps) for tests and previews.

Not a simulator of the method: it only draws a straight road with lane markings and a few
defect shapes so the export layer can be exercised and looked at without running the pipeline.
"""

from __future__ import annotations

import math

import numpy as np
from shapely import affinity
from shapely.geometry import Point, Polygon, box

from pavemap.geometry.chainage import route_polyline
from pavemap.geometry.grid import GridSpec
from pavemap.maintain import UNASSESSED, assess_instances
from pavemap.types import DEFECT_CODES, DefectInstance, GeoOrigin

W_SEV = (0.3, 0.4, 0.7, 1.0)


def defect_shape(cls: int, cx: float, cy: float, rng: np.random.Generator, scale: float = 1.0) -> Polygon:
    """A polygon typical of class ``cls`` centred near (cx, cy) (metres)."""
    ang = float(rng.uniform(-15, 15))
    if cls == 0:  # longitudinal crack: long and thin along x
        g = box(-1.2 * scale, -0.08, 1.2 * scale, 0.08)
    elif cls == 1:  # transverse crack: across the road
        g = box(-0.08, -0.9 * scale, 0.08, 0.9 * scale)
    elif cls == 2:  # alligator: blotchy area
        t = np.linspace(0, 2 * np.pi, 14, endpoint=False)
        r = (0.7 + 0.25 * rng.random(14)) * scale
        g = Polygon(np.column_stack([1.3 * r * np.cos(t), r * np.sin(t)]))
    else:  # pothole: round
        g = Point(0, 0).buffer(0.35 * scale, quad_segs=6)
    return affinity.translate(affinity.rotate(g, ang, origin=(0, 0)), cx, cy)


def sample_inputs(n: int = 12, seed: int = 0, geo: bool = False, heading_deg: float = 90.0,
                  length_m: float = 60.0, width_m: float = 14.0, res: float = 0.1, layout: str = "strip") -> dict:
    """Keyword arguments for ``write_outputs`` (minus ``out_dir``) describing ``n`` defects on a road.

    ``layout``: "strip" (a straight road ``length_m`` x ``width_m``) or "crossing" (a 70 x 60 m
    crossroads, cells outside the trajectory crop left black as in a real BEV).
    Returns a dict with instances, prob_map (H, W) float32, class_maps (4, H, W) float32, grid,
    bev_rgb/bev_semantic (ny, nx, 3) uint8, mesh_grid, geo_origin, metrics, config, detections, trajectory.
    """
    if layout not in ("strip", "crossing"):
        raise ValueError(f"layout must be 'strip' or 'crossing', got {layout!r}")
    rng = np.random.default_rng(seed)
    if layout == "crossing":
        length_m, x0, y0, height_m = 70.0, -5.0, -30.0, 60.0
    else:
        x0, y0, height_m = -5.0, -width_m / 2, width_m
    nx, ny = int(round(length_m / res)) + 1, int(round(height_m / res)) + 1
    grid = GridSpec(x0, y0, res, nx, ny)
    X, Y = grid.centres()  # (ny, nx)

    # road BEV: asphalt texture, lane markings, verges outside the carriageway
    half = 5.5 if layout == "crossing" else width_m / 2 - 1.5
    xc = 30.0  # the crossing road's centre line (x)
    along = np.abs(Y) < half
    across = (np.abs(X - xc) < half) if layout == "crossing" else np.zeros_like(along)
    road = along | across
    tex = rng.normal(0, 1, (ny, nx)).astype(np.float32)
    tex = 0.6 * tex + 0.4 * np.roll(tex, 1, axis=1)
    base = 96 + 9 * tex + 6 * np.sin(X / 7.0) + 4 * np.cos(Y / 5.0)
    rgb = np.stack([base, base + 2, base + 5], axis=-1)
    verge = ~road
    rgb[verge] = np.stack([70 + 12 * tex, 98 + 14 * tex, 52 + 8 * tex], axis=-1)[verge]
    in_box = np.abs(X - xc) < half + 1 if layout == "crossing" else np.zeros_like(along)
    centre = (np.abs(Y) < 0.08) & ((X % 6.0) < 3.0) & ~in_box
    edge = along & (np.abs(np.abs(Y) - (half - 0.3)) < 0.08) & ~in_box
    if layout == "crossing":
        in_box_y = np.abs(Y) < half + 1
        centre |= (np.abs(X - xc) < 0.08) & ((Y % 6.0) < 3.0) & ~in_box_y
        edge |= across & (np.abs(np.abs(X - xc) - (half - 0.3)) < 0.08) & ~in_box_y
        zebra = across & (np.abs(np.abs(Y) - (half + 2.2)) < 1.5) & ((X % 1.0) < 0.5) & (np.abs(X - xc) < half - 0.6)
        edge |= zebra
    rgb[centre | edge] = 228
    sem = np.zeros((ny, nx, 3), np.float32)
    sem[road] = (128, 64, 128)
    sem[verge] = (107, 142, 35)
    sem[centre | edge] = (255, 255, 255)
    if layout == "crossing":
        crop = (np.abs(Y) < half + 3.5) | (np.abs(X - xc) < half + 3.5)
        rgb[~crop] = 0
        sem[~crop] = 0

    instances = []
    prob = np.zeros((ny, nx), np.float32)
    per_class = np.zeros((4, ny, nx), np.float32)
    if layout == "crossing":
        on_cross = rng.random(n) < 0.4
        t = rng.uniform(2, 62, n)
        cxs = np.where(on_cross, xc + rng.uniform(-half + 1.5, half - 1.5, n), rng.uniform(-2, 62, n))
        cys = np.where(on_cross, t - 31, rng.uniform(-half + 1.5, half - 1.5, n))
    else:
        cxs = np.sort(rng.uniform(2, length_m - 10, n))
        cys = rng.uniform(-width_m / 2 + 2.5, width_m / 2 - 2.5, n)
    for i in range(n):
        cls = int(rng.integers(0, 4)) if i >= 4 else i % 4
        cx, cy = float(cxs[i]), float(cys[i])
        poly = defect_shape(cls, cx, cy, rng, scale=float(rng.uniform(0.7, 1.3)))
        obs = int(rng.integers(2, 9))
        sev_mean = W_SEV[cls] * float(rng.uniform(0.35, 0.9))
        p = float(np.tanh(sev_mean * math.log(1 + obs) / 2) * 1.6)
        p = float(min(p, 0.98))
        minx, miny, maxx, maxy = poly.bounds
        length = max(maxx - minx, maxy - miny)
        instances.append(DefectInstance(
            id=i + 1, cls=cls, polygon=poly, severity_mean=sev_mean, severity_max=min(1.0, sev_mean * 1.4),
            confidence=float(rng.uniform(0.3, 0.9)), observations=obs, probability=p, area_m2=float(poly.area),
            length_m=float(length), centroid=(poly.centroid.x, poly.centroid.y), priority=UNASSESSED))
        # darken the road where the defect is and splat its probability
        inside = (X - cx) ** 2 + (Y - cy) ** 2 < (length / 2 + 0.2) ** 2
        blob = np.exp(-((X - cx) ** 2 + (Y - cy) ** 2) / (2 * (0.3 + length / 4) ** 2)).astype(np.float32) * p
        prob = np.maximum(prob, blob)
        per_class[cls] = np.maximum(per_class[cls], blob)
        from shapely import contains_xy

        mask = inside & contains_xy(poly, X, Y)
        rgb[mask] *= 0.45 if cls != 3 else 0.3
    bev_rgb = np.clip(rgb, 0, 255).astype(np.uint8)
    bev_sem = sem.astype(np.uint8)
    detections = []
    for f in range(6):
        for _k in range(4):
            kept = bool(rng.random() > 0.3)
            x1, y1 = float(rng.uniform(100, 1300)), float(rng.uniform(500, 800))
            detections.append({
                "frame": f, "camera": "CAM_FRONT", "box": [x1, y1, x1 + float(rng.uniform(60, 200)),
                                                            y1 + float(rng.uniform(30, 80))],
                "cls": int(rng.integers(0, 4)), "conf": float(rng.uniform(0.05, 0.9)), "kept": kept,
                "reason": None if kept else "off road (R_road 0.12 < 0.5)", "r_road": 0.9 if kept else 0.12,
                "mapped": kept and bool(rng.random() > 0.2)})
    total = len(detections)
    kept = sum(d["kept"] for d in detections)
    metrics = {
        "paper": {"filter_rate": 1 - kept / total, "orp": kept / total,
                  "msr": sum(d["mapped"] for d in detections) / max(kept, 1), "coverage": 0.0016,
                  "obs_per_vertex": 2.5, "severity": 0.16, "avg_distance_m": 0.12},
        "eval": {"precision": 0.9, "recall": 0.85, "f1": 0.874, "loc_error_m": 0.11},
        "timing": {"mesh_s": 31.2, "detect_s": 2.1, "fuse_s": 1.4, "export_s": 2.0, "total_s": 36.7},
    }
    config = {"preset": "nuscenes", "mesh": {"resolution": res, "crop_m": 7.0, "epochs": 7},
              "detect": {"backend": "sim", "tau_conf": 0.05, "tau_road": 0.5},
              "fuse": {"mode": "hit", "alpha": 0.3, "n_min": 2, "w_sev": {c: w for c, w in
                                                                           zip(DEFECT_CODES, W_SEV, strict=True)}}}
    origin = GeoOrigin(lat=52.5200, lon=13.4050, alt=34.0, heading_deg=heading_deg) if geo else None
    if layout == "crossing":
        a = np.column_stack([np.linspace(-3, xc - 2.5, 15), np.full(15, -2.5)])
        th = np.linspace(0, np.pi / 2, 9)[1:-1]  # a left turn of radius 5 m into the northbound lane
        b = np.column_stack([xc - 2.5 + 5 * np.sin(th), 2.5 - 5 * np.cos(th)])
        c = np.column_stack([np.full(12, xc + 2.5), np.linspace(3, 28, 12)])
        traj = np.vstack([a, b, c])
    else:
        traj = np.column_stack([np.linspace(0, length_m - 8, 20), np.full(20, -1.8)])
    assess_instances(instances, route_polyline(traj))  # severity level, certainty, urgency as a run has them
    return {"instances": instances, "prob_map": prob, "class_maps": per_class, "grid": grid, "bev_rgb": bev_rgb,
            "bev_semantic": bev_sem, "mesh_grid": grid, "geo_origin": origin, "metrics": metrics,
            "config": config, "detections": detections, "trajectory": traj}


__all__ = ["defect_shape", "sample_inputs"]
