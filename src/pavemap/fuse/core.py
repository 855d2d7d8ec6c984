"""Stage 3 driver: filter -> associate -> accumulate -> probability -> instances and BEV maps.

``fuse`` is a pure function of the sequence, the detections, a surface and the config; files
are written by ``write_fusion``. The surface is anything with the HeightField interface
(reconstructed mesh, synthetic truth, a plane), see :mod:`pavemap.geometry`.
"""

from __future__ import annotations

import logging
import math
import time
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import shapely
import torch

from pavemap.detect.filter import INVALID_REASONS, filter_detections
from pavemap.fuse.accumulate import Accumulators, accumulate, probability
from pavemap.fuse.associate import Association, associate_footprint, associate_hit, associate_ray, rays_through
from pavemap.fuse.config import FusionConfig
from pavemap.fuse.instances import build_instances, priority
from pavemap.fuse.maps import bev_grid, splat
from pavemap.types import DEFECT_CODES, NUM_DEFECT_CLASSES, DefectInstance, Detection, Sequence

log = logging.getLogger("pavemap")


@dataclass
class FusionResult:
    """Everything stage 3 produced.

    prob_map (H, W) float32 and class_maps (4, H, W) float32 on ``grid`` (x0, y0 = centre of
    cell [0, 0], res, shape [H, W]; row = y); vertex_prob (ny, nx) float32 on the surface grid;
    detections: one record per input detection (filter reason, r_road, mapped, distance_m,
    hit_xyz, vertices, instance); baseline: the single-frame baseline instances (every mapped
    detection alone, no fusion) for the evaluation.
    """

    instances: list[DefectInstance]
    grid: dict
    prob_map: np.ndarray
    class_maps: np.ndarray
    vertex_prob: np.ndarray
    detections: list[dict]
    metrics: dict
    baseline: list[DefectInstance] = field(default_factory=list)
    surface_grid: dict = field(default_factory=dict)
    vertex_counts: np.ndarray | None = None  # (ny, nx, 4) int32 per-class observations
    vertex_severity: np.ndarray | None = None  # (ny, nx) float64 EMA severity


def _device(config: FusionConfig, surface) -> torch.device:  # noqa: ANN001
    if config.device == "auto":
        return surface.heights.device
    if config.device.startswith("cuda") and not torch.cuda.is_available():
        log.warning("fusion device %s is not available; using the CPU", config.device)
        return torch.device("cpu")
    return torch.device(config.device)


def associate_detections(seq: Sequence, dets: list[Detection], surface, config: FusionConfig) -> Association:  # noqa: ANN001
    """Run the configured association mode for (already filtered) detections on ``surface``."""
    dev = surface.heights.device
    n = len(dets)
    frames = seq.frame_by_index()
    K = torch.tensor(np.array([seq.cameras[d.camera].K for d in dets]).reshape(n, 3, 3), dtype=torch.float64,
                     device=dev)
    T = torch.tensor(np.array([frames[d.frame].views[d.camera].T_world_cam for d in dets]).reshape(n, 4, 4),
                     dtype=torch.float64, device=dev)
    boxes = torch.tensor(np.array([d.box for d in dets], dtype=np.float64).reshape(n, 4), device=dev)
    conf = torch.tensor([d.conf for d in dets], dtype=torch.float64, device=dev)
    if config.association == "footprint":
        return associate_footprint(surface, boxes, K, T, config)
    centre = torch.stack([(boxes[:, 0] + boxes[:, 2]) / 2, (boxes[:, 1] + boxes[:, 3]) / 2], 1)
    o, d = rays_through(K, T, centre)
    if config.association == "ray":
        return associate_ray(surface, o, d, conf, config)
    return associate_hit(surface, o, d, config, boxes=boxes, K=K, T=T)


def fuse(
    seq: Sequence, detections: list[Detection], surface, config: FusionConfig,  # noqa: ANN001
    mesh: object | None = None, progress: bool = True,
) -> FusionResult:
    """Filter, map and fuse detections onto ``surface`` (a HeightField) -> instances, maps, metrics."""
    from tqdm import tqdm

    config.validate()
    t0 = time.perf_counter()
    steps = tqdm(total=5, desc="fuse", unit="step", disable=not progress, leave=False)
    fstats: dict = {}
    kept, records = filter_detections(seq, detections, config, mesh=mesh, stats=fstats)
    kept_idx = np.array([r["index"] for r in records if r["kept"]], dtype=np.int64)
    steps.update()
    t_filter = time.perf_counter() - t0

    dev = _device(config, surface)
    if surface.heights.device != dev:
        surface = surface.to(dev)
    with torch.no_grad():
        t1 = time.perf_counter()
        asc = associate_detections(seq, kept, surface, config)
        steps.update()
        t_assoc = time.perf_counter() - t1
        # Application order for the EMA: frame order of the sequence, then input order.
        frame_rank = {f.index: r for r, f in enumerate(seq.frames)}
        n = len(kept)
        fr = np.array([frame_rank[d.frame] for d in kept], dtype=np.int64)
        order_np = np.lexsort((kept_idx, fr)) if n else np.zeros(0, dtype=np.int64)
        order = torch.empty(n, dtype=torch.long, device=dev)
        order[torch.as_tensor(order_np, device=dev)] = torch.arange(n, device=dev)
        cls = torch.tensor([d.cls for d in kept], dtype=torch.long, device=dev)
        conf = torch.tensor([d.conf for d in kept], dtype=torch.float64, device=dev)
        ny, nx = surface.ny, surface.nx
        acc = accumulate(ny * nx, asc.det, asc.vid, order, cls, conf, config.alpha, config.severity_weights)
        # Probabilities on the observed vertices only; every other vertex has P = 0 (tanh form).
        obs_t = acc.seen if acc.seen is not None else torch.nonzero(acc.n > 0).squeeze(1)
        p_obs, pc_obs = probability(Accumulators(acc.counts[obs_t], acc.sev[obs_t], acc.conf[obs_t]), config.prob)
        steps.update()

    V = ny * nx
    valid = surface.valid.reshape(-1).cpu().numpy()
    counts = acc.counts.cpu().numpy()
    sev = acc.sev.cpu().numpy()
    conf_v = acc.conf.cpu().numpy()
    obs_all = obs_t.cpu().numpy()
    keep_obs = valid[obs_all]  # associations only pick valid vertices; kept explicit for safety
    obs = obs_all[keep_obs]
    p_obs_np = p_obs.cpu().numpy()[keep_obs]
    pc_obs_np = pc_obs.cpu().numpy()[keep_obs]
    nobs_obs = counts[obs].sum(1)
    p_dense = np.zeros(V, dtype=np.float32)
    if config.prob == "sigmoid":
        p_dense[valid] = 0.5  # the paper's form: sigma(0) = 0.5 on every unobserved vertex
    p_dense[obs] = p_obs_np
    defect = np.zeros(V, dtype=bool)
    defect[obs] = nobs_obs >= config.n_min
    pair_det = asc.det.cpu().numpy()
    pair_vid = asc.vid.cpu().numpy()
    instances, labels = build_instances(
        defect.reshape(ny, nx), p_dense.reshape(ny, nx), counts.reshape(ny, nx, NUM_DEFECT_CLASSES),
        sev.reshape(ny, nx), conf_v.reshape(ny, nx), pair_det, pair_vid,
        surface.x0, surface.y0, surface.res, min_obs=config.min_instance_obs, merge_gap_m=config.merge_gap_m,
    )
    steps.update()

    grid = bev_grid(surface.x0, surface.y0, surface.res, nx, ny, config.splat_res)
    jj, ii = np.divmod(obs, nx)
    xy = np.stack([surface.x0 + ii * surface.res, surface.y0 + jj * surface.res], 1)
    # Only observed vertices carry P > 0 (in the sigmoid form the 0.5 floor is left out of the map,
    # so the map stays readable: the erratum the default fixes).
    values = np.concatenate([p_obs_np[None], pc_obs_np.T], 0)
    maps = splat(values, xy, surface.res, grid, config.splat_sigma)
    steps.update()
    steps.close()

    # Per-detection records.
    mapped = asc.mapped.cpu().numpy()
    dist = asc.distance.cpu().numpy()
    hits = asc.hit.cpu().numpy()
    ground_px = ground_pixel_size(seq, kept, hits)
    nvert = np.bincount(pair_det, minlength=n) if n else np.zeros(0, np.int64)
    lab_flat = labels.reshape(-1)
    inst_of = instance_of_detections(pair_det, lab_flat[pair_vid] if len(pair_vid) else pair_vid, n)
    if config.centroid == "detections":
        _centroids_from_detections(instances, inst_of, hits, ground_px)
    for r in records:
        r.update(mapped=False, distance_m=None, hit_xyz=None, vertices=0, instance=None)
    for k, i in enumerate(kept_idx):
        rec = records[i]
        rec["mapped"] = bool(mapped[k])
        rec["distance_m"] = None if not math.isfinite(dist[k]) else round(float(dist[k]), 4)
        rec["hit_xyz"] = None if not np.all(np.isfinite(hits[k])) else [round(float(v), 3) for v in hits[k]]
        rec["vertices"] = int(nvert[k])
        rec["ground_px_m"] = None if not np.isfinite(ground_px[k]) else round(float(ground_px[k]), 4)
        rec["instance"] = int(inst_of[k]) if inst_of[k] > 0 else None

    baseline = baseline_instances(kept, pair_det, pair_vid, surface.x0, surface.y0, surface.res, nx,
                                  severity_weights=config.severity_weights)
    metrics = paper_metrics(records, defect[obs], int(valid.sum()), nobs_obs, sev[obs], instances, config, fstats)
    metrics["seconds"] = {"filter": round(t_filter, 3), "associate": round(t_assoc, 3),
                          "total": round(time.perf_counter() - t0, 3)}
    metrics["surface"] = {"x0": surface.x0, "y0": surface.y0, "res": surface.res, "shape": [ny, nx],
                          "valid_vertices": int(valid.sum())}
    return FusionResult(
        instances=instances, grid=grid, prob_map=maps[0], class_maps=maps[1:],
        vertex_prob=p_dense.reshape(ny, nx),
        detections=records, metrics=metrics, baseline=baseline,
        surface_grid={"x0": surface.x0, "y0": surface.y0, "res": surface.res, "shape": [ny, nx]},
        vertex_counts=counts.reshape(ny, nx, NUM_DEFECT_CLASSES),
        vertex_severity=sev.reshape(ny, nx),
    )


def instance_of_detections(pair_det: np.ndarray, pair_label: np.ndarray, n: int) -> np.ndarray:
    """(n,) instance id (0 = none) of each detection: the instance holding most of its vertices."""
    out = np.zeros(n, dtype=np.int64)
    m = pair_label > 0
    if not m.any():
        return out
    k = int(pair_label.max()) + 1
    keys, cnt = np.unique(pair_det[m].astype(np.int64) * k + pair_label[m], return_counts=True)
    det, lab = np.divmod(keys, k)
    order = np.lexsort((-cnt, det))  # per detection, the largest count first
    det, lab = det[order], lab[order]
    first = np.r_[True, det[1:] != det[:-1]]
    out[det[first]] = lab[first]
    return out


def ground_pixel_size(seq: Sequence, dets: list[Detection], points: np.ndarray) -> np.ndarray:
    """(N,) metres of road one image row spans at each detection's surface point (nan without one).

    ``(range / f) / sin(grazing angle)``: a far, grazing view localises a box edge to metres,
    a near one to centimetres.
    """
    if not dets:
        return np.zeros(0)
    frames = seq.frame_by_index()
    o = np.array([frames[d.frame].views[d.camera].T_world_cam[:3, 3] for d in dets])
    f = np.array([seq.cameras[d.camera].K[1, 1] for d in dets])
    v = points - o
    rng = np.linalg.norm(v, axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        sin_g = np.abs(v[:, 2]) / rng
        return (rng / f) / np.maximum(sin_g, 0.02)


def _centroids_from_detections(instances: list[DefectInstance], inst_of: np.ndarray, points: np.ndarray,
                               ground_px: np.ndarray) -> None:
    """Set each instance's centroid to the weighted mean surface point of its detections.

    Every detection is one estimate of the defect's centre, with an error that grows with the
    road length one pixel spans there (``ground_px``): weights ``1 / ground_px^2`` (inverse
    variance) let near views dominate far, grazing ones. The vertex union's centroid follows the
    shape of the overlap of the detections' disks instead; it stays in ``extra``.
    """
    ok = (inst_of > 0) & np.isfinite(points).all(1) & np.isfinite(ground_px) & (ground_px > 0)
    if not instances or not ok.any():
        return
    k = len(instances) + 1
    w = 1.0 / ground_px[ok] ** 2
    cnt = np.bincount(inst_of[ok], w, minlength=k)
    sx = np.bincount(inst_of[ok], w * points[ok, 0], minlength=k)
    sy = np.bincount(inst_of[ok], w * points[ok, 1], minlength=k)
    for inst in instances:
        inst.extra["vertex_centroid"] = [round(c, 3) for c in inst.centroid]
        if cnt[inst.id] > 0:
            inst.centroid = (float(sx[inst.id] / cnt[inst.id]), float(sy[inst.id] / cnt[inst.id]))


def baseline_instances(kept: list[Detection], pair_det: np.ndarray, pair_vid: np.ndarray, x0: float, y0: float,
                       res: float, nx: int, severity_weights: tuple[float, ...] = (0.3, 0.4, 0.7, 1.0)
                       ) -> list[DefectInstance]:
    """Single-frame baseline: each mapped detection alone is an instance.

    Its polygon is the bounding rectangle of its vertices' cells (rectangles keep this cheap for
    tens of thousands of detections), its centroid the mean of its vertices.
    """
    if len(pair_det) == 0:
        return []
    jj, ii = np.divmod(pair_vid, nx)
    x, y = x0 + ii * res, y0 + jj * res
    ids, inv, cnt = np.unique(pair_det, return_inverse=True, return_counts=True)
    m = len(ids)
    lo_x = np.full(m, np.inf)
    lo_y = np.full(m, np.inf)
    hi_x = np.full(m, -np.inf)
    hi_y = np.full(m, -np.inf)
    np.minimum.at(lo_x, inv, x)
    np.minimum.at(lo_y, inv, y)
    np.maximum.at(hi_x, inv, x)
    np.maximum.at(hi_y, inv, y)
    h = res / 2
    polys = shapely.box(lo_x - h, lo_y - h, hi_x + h, hi_y + h)
    area = (hi_x - lo_x + res) * (hi_y - lo_y + res)
    cx = np.bincount(inv, x) / cnt
    cy = np.bincount(inv, y) / cnt
    out = []
    for t, k in enumerate(ids.tolist()):
        d = kept[k]
        sev = float(severity_weights[d.cls])
        out.append(DefectInstance(
            id=t + 1, cls=int(d.cls), polygon=polys[t], severity_mean=sev, severity_max=sev,
            confidence=float(d.conf), observations=1, probability=float(d.conf),
            area_m2=float(area[t]), length_m=float(max(hi_x[t] - lo_x[t], hi_y[t] - lo_y[t]) + res),
            centroid=(float(cx[t]), float(cy[t])), priority=priority(float(d.conf)),
            extra={"detection": k, "vertices": int(cnt[t])},
        ))
    return out


def paper_metrics(records: list[dict], defect: np.ndarray, n_valid: int, nobs: np.ndarray, sev: np.ndarray,
                  instances: list[DefectInstance], config: FusionConfig, fstats: dict) -> dict:
    """SPEC §4 statistics plus the bad-input counts.

    total = detections passing sanitising and the confidence threshold (what the paper's detector
    outputs); filtered = removed by the road filter; FR = filtered / total; ORP = 1 - FR;
    valid = kept; MSR = mapped / valid; coverage = defect vertices / valid vertices.
    ``defect``, ``nobs``, ``sev`` are given on the observed vertices only; ``n_valid`` counts all valid ones.
    """
    reasons = Counter(r["reason"] for r in records)
    invalid = {k: reasons.get(k, 0) for k in INVALID_REASONS if reasons.get(k, 0)}
    kept = [r for r in records if r["kept"]]
    total = len(kept) + reasons.get("off_road", 0)
    mapped = [r for r in kept if r["mapped"]]
    dists = [r["distance_m"] for r in mapped if r["distance_m"] is not None]
    nd = int(defect.sum())
    fr = reasons.get("off_road", 0) / total if total else 0.0
    return {
        "input_detections": len(records),
        "invalid_detections": sum(invalid.values()),
        "invalid_by_reason": invalid,
        "below_conf": reasons.get("low_conf", 0),
        "total_detections": total,
        "filtered_detections": reasons.get("off_road", 0),
        "valid_detections": len(kept),
        "mapped_detections": len(mapped),
        "filter_rate": fr,
        "on_road_precision": 1.0 - fr if total else 0.0,
        "msr": len(mapped) / len(kept) if kept else 0.0,
        "coverage": nd / max(n_valid, 1),
        "defect_vertices": nd,
        "obs_per_vertex": float(nobs[defect].mean()) if nd else 0.0,
        "mean_severity": float(sev[defect].mean()) if nd else 0.0,
        "avg_distance_m": float(np.mean(dists)) if dists else None,
        "instances": len(instances),
        "instances_by_class": {c: sum(1 for i in instances if i.cls == k) for k, c in enumerate(DEFECT_CODES)},
        "association": config.association,
        "mask": fstats.get("mask_used", config.mask),
        "mask_fallbacks": fstats.get("mask_fallbacks", {}),
        "config": {k: (list(v) if isinstance(v, tuple) else v) for k, v in vars(config).items()},
    }


def instances_to_features(instances: list[DefectInstance]) -> dict:
    """GeoJSON FeatureCollection in local world metres (x, y), one feature per instance."""
    feats = []
    for inst in instances:
        feats.append({
            "type": "Feature",
            "geometry": shapely.geometry.mapping(inst.polygon),
            "properties": {
                "id": inst.id, "cls": inst.cls, "name": inst.code, "type": inst.name,
                "severity_mean": round(inst.severity_mean, 4), "severity_max": round(inst.severity_max, 4),
                "confidence": round(inst.confidence, 4), "observations": inst.observations,
                "probability": round(inst.probability, 4), "area_m2": round(inst.area_m2, 4),
                "length_m": round(inst.length_m, 3), "centroid": [round(c, 3) for c in inst.centroid],
                "priority": inst.priority, **{k: v for k, v in inst.extra.items()},
            },
        })
    return {"type": "FeatureCollection", "crs_note": "local world metres (x, y), pavemap", "features": feats}


def write_fusion(result: FusionResult, out_dir: Path) -> None:
    """defects.geojson (local metres), baseline_defects.geojson, defect_map.npy (+ .json grid),
    defect_map_<code>.npy, vertex_prob.npy, metrics.json, detections_mapped.jsonl - all atomically."""
    import json

    from pavemap.io.atomic import atomic_path, atomic_write_json, atomic_write_text

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    atomic_write_json(out / "defects.geojson", instances_to_features(result.instances), indent=None)
    atomic_write_json(out / "baseline_defects.geojson", instances_to_features(result.baseline), indent=None)

    def save(name: str, a: np.ndarray) -> None:
        with atomic_path(out / name) as tmp, open(tmp, "wb") as fh:
            np.save(fh, a)

    save("defect_map.npy", result.prob_map.astype(np.float32))
    for k, code in enumerate(DEFECT_CODES):
        save(f"defect_map_{code}.npy", result.class_maps[k].astype(np.float32))
    save("vertex_prob.npy", result.vertex_prob)
    atomic_write_json(out / "defect_map.json", {**result.grid, "surface": result.surface_grid,
                                                "note": "cell [r, c] centre at (x0 + c*res, y0 + r*res)"})
    atomic_write_json(out / "metrics.json", result.metrics)
    atomic_write_text(out / "detections_mapped.jsonl",
                      "".join(json.dumps(r, allow_nan=False) + "\n" for r in result.detections))
