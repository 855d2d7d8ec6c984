"""Stage 3 driver: associate -> accumulate -> probability -> instances and BEV maps.

``fuse`` is a pure function of the sequence, stage 2's filter result, a surface and the config;
it writes nothing (the run folder's files are written by :mod:`pavemap.export`). The surface is
anything with the HeightField interface (reconstructed mesh, synthetic truth, a plane), see
:mod:`pavemap.geometry`.
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections import Counter
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np
import shapely
import torch

from pavemap.device import resolve_device
from pavemap.fuse.accumulate import accumulate, probability
from pavemap.fuse.associate import associate_detections
from pavemap.fuse.config import FusionConfig
from pavemap.fuse.footprint import detection_footprints, instance_outlines, instance_sizes
from pavemap.fuse.instances import build_instances
from pavemap.fuse.maps import bev_grid, splat
from pavemap.geometry.grid import GridSpec
from pavemap.types import DEFECT_CODES, UNASSESSED, DefectInstance, Detection, Sequence

# Filter outcomes that are not "unusable input" (every other reason counts as invalid).
_FILTER_OUTCOMES = ("kept", "low_conf", "off_road", "paint", "ego")  # paint / ego: pavemap.detect.paint


class Filtered(Protocol):
    """What fusion needs of stage 2's result (:class:`pavemap.detect.filter.FilterResult`)."""

    kept: list[Detection]
    records: list[dict]
    config: object
    mask_used: str
    mask_fallbacks: dict[str, int]
    seconds: float


@dataclass
class FusionResult:
    """Everything stage 3 produced.

    prob_map (H, W) float32 and class_maps (4, H, W) float32 on ``grid`` (rows go +y);
    vertex_prob (ny, nx) float32 on ``surface_grid``; detections: one record per input detection
    (filter reason, r_road, mapped, distance_m, hit_xyz, vertices, instance); baseline: the
    single-frame baseline instances (every mapped detection alone, no fusion) for the evaluation.
    """

    instances: list[DefectInstance]
    grid: GridSpec
    prob_map: np.ndarray
    class_maps: np.ndarray
    vertex_prob: np.ndarray
    detections: list[dict]
    metrics: dict
    surface_grid: GridSpec
    baseline: list[DefectInstance] = field(default_factory=list)
    observed_vertices: np.ndarray | None = None  # (M,) int64 sorted flat ids j*nx+i of the observed vertices
    vertex_counts: np.ndarray | None = None  # (M, 4) int32 per-class observations of those vertices
    vertex_severity: np.ndarray | None = None  # (M,) float64 their EMA severity
    instance_labels: np.ndarray | None = None  # (ny, nx) int32 on surface_grid: instance id, 0 = none
    segments: list = field(default_factory=list)  # pavemap.maintain road segments, once assessed


def surface_grid(surface) -> GridSpec:  # noqa: ANN001
    """The vertex grid of a HeightField-like surface."""
    grid = getattr(surface, "grid", None)
    if isinstance(grid, GridSpec):
        return grid
    return GridSpec(surface.x0, surface.y0, surface.res, surface.nx, surface.ny)


def _device(config: FusionConfig, surface) -> torch.device:  # noqa: ANN001
    return surface.heights.device if config.device == "auto" else resolve_device(config.device)


def fuse(seq: Sequence, filtered: Filtered, surface, config: FusionConfig,  # noqa: ANN001
         progress: bool = True) -> FusionResult:
    """Map and fuse stage 2's kept detections onto ``surface`` (a HeightField) -> instances, maps, metrics."""
    from tqdm import tqdm

    config.validate()
    t0 = time.perf_counter()
    steps = tqdm(total=4, desc="fuse", unit="step", disable=not progress, leave=False)
    kept = filtered.kept
    records = [dict(r) for r in filtered.records]  # fusion adds its fields to copies
    kept_idx = np.array([r["index"] for r in records if r["kept"]], dtype=np.int64)
    dev = _device(config, surface)
    if surface.heights.device != dev:
        surface = surface.to(dev)
    grid_v = surface_grid(surface)
    with torch.no_grad():
        asc = associate_detections(seq, kept, surface, config)
        steps.update()
        t_assoc = time.perf_counter() - t0
        acc, obs_t, p_obs, pc_obs = _accumulate(seq, kept, kept_idx, asc, grid_v, config, dev)
        steps.update()

    V = grid_v.nx * grid_v.ny
    ny, nx = grid_v.shape
    valid = surface.valid.reshape(-1).cpu().numpy()
    obs_all = obs_t.cpu().numpy()
    keep_obs = valid[obs_all]  # associations only pick valid vertices; kept explicit for safety
    obs = obs_all[keep_obs]
    counts = acc.counts.cpu().numpy()[keep_obs]
    sev = acc.sev.cpu().numpy()[keep_obs]
    p_obs_np = p_obs.cpu().numpy()[keep_obs]
    pc_obs_np = pc_obs.cpu().numpy()[keep_obs]
    nobs_obs = counts.sum(1)
    p_dense = np.zeros(V, dtype=np.float32)
    if config.prob == "sigmoid":
        p_dense[valid] = 0.5  # the paper's form: sigma(0) = 0.5 on every unobserved vertex
    p_dense[obs] = p_obs_np
    defect = nobs_obs >= config.n_min
    pair_det = asc.det.cpu().numpy()
    pair_vid = asc.vid.cpu().numpy()
    instances, labels = build_instances(
        (ny, nx), obs, defect, p_obs_np, counts, sev, acc.conf.cpu().numpy()[keep_obs], pair_det, pair_vid,
        grid_v.x0, grid_v.y0, grid_v.res, min_obs=config.min_instance_obs, merge_gap_m=config.merge_gap_m,
        crack_join_m=config.crack_join_m,
    )
    steps.update()

    grid = bev_grid(grid_v, config.splat_res)
    jj, ii = np.divmod(obs, nx)
    xy = np.stack([grid_v.x0 + ii * grid_v.res, grid_v.y0 + jj * grid_v.res], 1)
    # Only observed vertices carry P > 0 (in the sigmoid form the 0.5 floor is left out of the map,
    # so the map stays readable: the erratum the default fixes).
    values = np.concatenate([p_obs_np[None], pc_obs_np.T], 0)
    maps = splat(values, xy, grid_v.res, grid, config.splat_sigma)
    steps.update()
    steps.close()

    inst_of, hits, ground_px = _detection_records(seq, kept, kept_idx, records, asc, labels, pair_det, pair_vid)
    fp_area, fp_length, _, fp_quads = detection_footprints(seq, kept, hits)
    instance_sizes(instances, inst_of, fp_area, fp_length, ground_px)
    instance_outlines(instances, inst_of, fp_quads, ground_px)
    if config.centroid == "detections":
        _centroids_from_detections(instances, inst_of, hits, ground_px)
    baseline = baseline_instances(kept, pair_det, pair_vid, grid_v.x0, grid_v.y0, grid_v.res, nx,
                                  severity_weights=config.severity_weights)
    metrics = paper_metrics(records, defect, int(valid.sum()), nobs_obs, sev, instances, config, filtered)
    metrics["seconds"] = {"filter": round(filtered.seconds, 3), "associate": round(t_assoc, 3),
                          "total": round(filtered.seconds + time.perf_counter() - t0, 3)}
    metrics["surface"] = {**grid_v.to_dict(), "valid_vertices": int(valid.sum())}
    return FusionResult(
        instances=instances, grid=grid, prob_map=maps[0], class_maps=maps[1:],
        vertex_prob=p_dense.reshape(ny, nx), detections=records, metrics=metrics, surface_grid=grid_v,
        baseline=baseline, observed_vertices=obs, vertex_counts=counts, vertex_severity=sev,
        instance_labels=labels.astype(np.int32, copy=False),
    )


def _accumulate(seq: Sequence, kept: list[Detection], kept_idx: np.ndarray, asc, grid_v: GridSpec,  # noqa: ANN001
                config: FusionConfig, dev: torch.device):  # noqa: ANN202
    """Accumulators of the observed vertices, their flat ids and probabilities (total, per class)."""
    # Application order for the EMA: frame order of the sequence, then input order.
    frame_rank = {f.index: r for r, f in enumerate(seq.frames)}
    n = len(kept)
    fr = np.array([frame_rank[d.frame] for d in kept], dtype=np.int64)
    order_np = np.lexsort((kept_idx, fr)) if n else np.zeros(0, dtype=np.int64)
    order = torch.empty(n, dtype=torch.long, device=dev)
    order[torch.as_tensor(order_np, device=dev)] = torch.arange(n, device=dev)
    cls = torch.tensor([d.cls for d in kept], dtype=torch.long, device=dev)
    conf = torch.tensor([d.conf for d in kept], dtype=torch.float64, device=dev)
    acc = accumulate(asc.det, asc.vid, order, cls, conf, config.alpha, config.severity_weights)
    # Probabilities on the observed vertices only; every other vertex has P = 0 (tanh form).
    p_obs, pc_obs = probability(acc, config.prob)
    return acc, acc.seen, p_obs, pc_obs


def _detection_records(seq: Sequence, kept: list[Detection], kept_idx: np.ndarray, records: list[dict], asc,  # noqa: ANN001
                       labels: np.ndarray, pair_det: np.ndarray, pair_vid: np.ndarray
                       ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Add fusion's fields to the per-detection records.

    Returns, per kept detection: instance id (K,) int64 (0 = none), surface point (K, 3) float64
    (nan on a miss) and the road metres one image row spans there (K,) float64.
    """
    n = len(kept)
    mapped = asc.mapped.cpu().numpy()
    dist = asc.distance.cpu().numpy()
    hits = asc.hit.cpu().numpy()
    ground_px = ground_pixel_size(seq, kept, hits)
    nvert = np.bincount(pair_det, minlength=n) if n else np.zeros(0, np.int64)
    lab_flat = labels.reshape(-1)
    inst_of = instance_of_detections(pair_det, lab_flat[pair_vid] if len(pair_vid) else pair_vid, n)
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
    return inst_of, hits, ground_px


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
            centroid=(float(cx[t]), float(cy[t])), priority=UNASSESSED,
            extra={"detection": k, "vertices": int(cnt[t])},
        ))
    return out


def paper_metrics(records: list[dict], defect: np.ndarray, n_valid: int, nobs: np.ndarray, sev: np.ndarray,
                  instances: list[DefectInstance], config: FusionConfig, filtered: Filtered) -> dict:
    """SPEC §4 statistics plus the bad-input counts.

    total = detections passing sanitising and the confidence threshold (what the paper's detector
    outputs); filtered = removed by the road filter; FR = filtered / total; ORP = 1 - FR;
    valid = kept; MSR = mapped / valid; coverage = defect vertices / valid vertices.
    ``defect``, ``nobs``, ``sev`` are given on the observed vertices only; ``n_valid`` counts all valid ones.
    """
    reasons = Counter(r["reason"] for r in records)
    invalid = {k: v for k, v in sorted(reasons.items()) if k not in _FILTER_OUTCOMES}
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
        "on_paint": reasons.get("paint", 0),  # on-road boxes lane paint spans (filter.tau_paint)
        "on_ego": reasons.get("ego", 0),  # boxes on the camera's ego mask (the bonnet)
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
        "mask": filtered.mask_used,
        "mask_fallbacks": dict(filtered.mask_fallbacks),
        "config": {"filter": _plain(filtered.config), "fusion": _plain(config)},
    }


def _plain(cfg: object) -> dict:
    """A config dataclass as a JSON-ready dict (tuples as lists)."""
    d = dataclasses.asdict(cfg) if dataclasses.is_dataclass(cfg) else dict(vars(cfg))
    return {k: (list(v) if isinstance(v, tuple) else v) for k, v in d.items()}
