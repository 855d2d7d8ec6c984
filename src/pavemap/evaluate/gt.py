"""Ground-truth evaluation of a fusion run against synthetic truth (SPEC §5, DESIGN "Evaluation protocol").

Matching rule (one-to-one, greedy): every (prediction, truth) pair whose centroids are within
``match_dist_m`` (0.5 m) **or** whose polygons overlap is a candidate; candidates are taken in
order of increasing centroid distance, each prediction and each truth defect used at most once.

- precision = matched predictions / predictions (a prediction matched to any true defect is
  correct, visible or not);
- recall = matched *visible* truth defects / visible truth defects, where a truth defect is
  visible when the simulated detector produced true detections of it in at least 2 distinct
  frames (fusion with n_min >= 2 cannot map the others);
- per class the same with class-aware pairs (prediction class = truth class);
- localisation error = centroid distance of matched pairs (median, 90th percentile);
- fp_removed = share of off-road false-positive detections that the filter removed;
  tp_lost = share of true detections the filter removed (confidence or road filter);
- the single-frame baseline (each filtered detection mapped alone) is scored the same way.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

import numpy as np
import shapely
from shapely.strtree import STRtree

from pavemap.errors import PavemapError, SequenceError
from pavemap.export.geojson import DefectLayer, read_geojson
from pavemap.types import DEFECT_CODES

MATCH_DIST_M = 0.5
RULE = ("one-to-one greedy by centroid distance; a pair is allowed when centroids are within "
        f"{MATCH_DIST_M} m or the polygons overlap; recall counts truth defects with true detections "
        "in >= 2 frames")


def load_truth(seq_root: str | os.PathLike) -> list[dict]:
    """truth/defects.geojson -> [{"id", "cls", "polygon"}] (world metres)."""
    f = Path(seq_root) / "truth" / "defects.geojson"
    if not f.is_file():
        raise SequenceError(f, "ground truth not found (only synthetic sequences have truth/defects.geojson)")
    layer = _read_layer(f)
    out = []
    for k, (geom, p) in enumerate(zip(layer.geometries, layer.properties, strict=True)):
        if geom is None or geom.is_empty:
            raise SequenceError(f, f"feature {k} has no polygon")
        out.append({"id": p.get("id", k), "cls": _cls(p, f, k), "polygon": geom})
    return out


def _read_layer(path: Path, name: str = "defects") -> DefectLayer:
    """A defects GeoJSON (any pavemap writer, local or lon/lat) or GeoPackage layer ``name`` with its
    geometries in world metres."""
    from pavemap.export.gis import read_defect_layer

    try:
        layer = read_geojson(path) if path.suffix.lower() != ".gpkg" else read_defect_layer(path, name)
    except PavemapError as e:
        raise SequenceError(path, str(e).removeprefix(f"{path}: ")) from None
    if layer.coordinates == "lonlat" and layer.meta.get("geo_origin") is None and len(layer):
        # lon/lat without the origin it was written with cannot be brought back to this run's metres
        raise SequenceError(path, "lon/lat coordinates without a pavemap.geo_origin; cannot score in world metres")
    return layer


def _cls(p: dict, path: Path, k: int) -> int:
    try:
        c = int(p["cls"])
    except (KeyError, TypeError, ValueError):
        raise SequenceError(path, f"feature {k}: needs an integer 'cls' property") from None
    if not 0 <= c < len(DEFECT_CODES):
        raise SequenceError(path, f"feature {k}: cls {c} outside 0..{len(DEFECT_CODES) - 1}")
    return c


def match(pred_polys: list, pred_xy: np.ndarray, gt_polys: list, gt_xy: np.ndarray,
          match_dist_m: float = MATCH_DIST_M) -> list[tuple[int, int, float]]:
    """One-to-one greedy matching (see module doc). Returns (pred index, truth index, distance m)."""
    if len(pred_polys) == 0 or len(gt_polys) == 0:
        return []
    tree = STRtree(gt_polys)
    pi, gi = tree.query(np.asarray(pred_polys, dtype=object), predicate="intersects")
    # Centroid pairs: a small prediction next to (not on) a thin crack still counts.
    gtree = STRtree(shapely.points(gt_xy))
    ci, cg = gtree.query(shapely.points(pred_xy), predicate="dwithin", distance=match_dist_m)
    pairs = np.unique(np.concatenate([np.stack([pi, gi], 1), np.stack([ci, cg], 1)]), axis=0)
    d = np.linalg.norm(pred_xy[pairs[:, 0]] - gt_xy[pairs[:, 1]], axis=1)
    order = np.argsort(d, kind="stable")
    used_p: set[int] = set()
    used_g: set[int] = set()
    out = []
    for k in order:  # pairs are few (local candidates only); the greedy pass is inherently sequential
        p, g = int(pairs[k, 0]), int(pairs[k, 1])
        if p in used_p or g in used_g:
            continue
        used_p.add(p)
        used_g.add(g)
        out.append((p, g, float(d[k])))
    return out


def _prf(tp_p: int, n_p: int, tp_g: int, n_g: int) -> dict:
    prec = tp_p / n_p if n_p else 0.0
    rec = tp_g / n_g if n_g else 0.0
    f1 = 2 * prec * rec / (prec + rec) if prec + rec > 0 else 0.0
    return {"precision": prec, "recall": rec, "f1": f1, "predicted": n_p, "truth": n_g}


def score_instances(preds: list[dict], truth: list[dict], visible: set | None,
                    match_dist_m: float = MATCH_DIST_M) -> dict:
    """Scores of predictions [{"cls", "polygon", "centroid"}] against truth [{"id", "cls", "polygon"}]."""
    pred_polys = [p["polygon"] for p in preds]
    pred_xy = np.array([p["centroid"] for p in preds], dtype=np.float64).reshape(-1, 2)
    gt_polys = [t["polygon"] for t in truth]
    gt_xy = np.array([[c.x, c.y] for c in (t["polygon"].centroid for t in truth)], dtype=np.float64).reshape(-1, 2)
    vis = np.array([visible is None or t["id"] in visible for t in truth], dtype=bool)
    pairs = match(pred_polys, pred_xy, gt_polys, gt_xy, match_dist_m)
    errors = np.array([d for _, _, d in pairs])
    res = _prf(len(pairs), len(preds), sum(1 for _, g, _ in pairs if vis[g]), int(vis.sum()))
    res["matched"] = len(pairs)
    res["median_error_m"] = float(np.median(errors)) if len(errors) else None
    res["p90_error_m"] = float(np.percentile(errors, 90)) if len(errors) else None
    res["class_accuracy"] = (sum(1 for p, g, _ in pairs if preds[p]["cls"] == truth[g]["cls"]) / len(pairs)
                             if pairs else None)
    # Extent: area ratio and principal length error of matched pairs.
    if pairs:
        ratios = [preds[p]["polygon"].area / max(truth[g]["polygon"].area, 1e-9) for p, g, _ in pairs]
        res["median_area_ratio"] = float(np.median(ratios))
    else:
        res["median_area_ratio"] = None
    per_class = {}
    for c, code in enumerate(DEFECT_CODES):
        pk = [i for i, p in enumerate(preds) if p["cls"] == c]
        gk = [i for i, t in enumerate(truth) if t["cls"] == c]
        sub = match([pred_polys[i] for i in pk], pred_xy[pk], [gt_polys[i] for i in gk], gt_xy[gk], match_dist_m)
        per_class[code] = _prf(len(sub), len(pk), sum(1 for _, g, _ in sub if vis[gk[g]]), int(vis[gk].sum()))
    res["per_class"] = per_class
    return res


def detection_scores(records: list[dict], truth_lines: list[dict]) -> dict:
    """fp_removed / tp_lost from per-detection filter records aligned with the truth side file."""
    offroad = [r for r, t in zip(records, truth_lines, strict=True) if t.get("offroad") and not t.get("true")]
    true = [r for r, t in zip(records, truth_lines, strict=True) if t.get("true")]
    true_valid = [r for r in true if r["reason"] in ("kept", "low_conf", "off_road")]
    return {
        "offroad_fp_detections": len(offroad),
        "fp_removed": sum(1 for r in offroad if not r["kept"]) / len(offroad) if offroad else None,
        "fp_removed_by_road_filter": (sum(1 for r in offroad if r["reason"] == "off_road") / len(offroad)
                                      if offroad else None),
        "true_detections": len(true),
        "tp_lost": sum(1 for r in true_valid if not r["kept"]) / len(true_valid) if true_valid else None,
        "tp_lost_by_road_filter": (sum(1 for r in true_valid if r["reason"] == "off_road") / len(true_valid)
                                   if true_valid else None),
        "true_mapped": sum(1 for r in true if r.get("mapped")) / len(true) if true else None,
    }


def visible_defects(records: list[dict], truth_lines: list[dict], min_frames: int = 2) -> set:
    """Truth defect ids with true detections in at least ``min_frames`` distinct frames (any conf)."""
    frames: dict[Any, set] = {}
    for r, t in zip(records, truth_lines, strict=True):
        if t.get("true") and t.get("defect_id") is not None:
            frames.setdefault(t["defect_id"], set()).add(r["frame"])
    return {k for k, v in frames.items() if len(v) >= min_frames}


def _read_jsonl(path: Path) -> list[dict]:
    try:
        return [json.loads(line) for line in path.read_text(encoding="utf-8").splitlines() if line.strip()]
    except (OSError, json.JSONDecodeError) as e:
        raise SequenceError(path, f"cannot read JSON lines ({e})") from None


def _read_instances(path: Path, name: str = "defects") -> list[dict]:
    """Predictions of a run folder's defects GeoJSON: cls, polygon and centre in world metres.

    The centre is the ``x_m``, ``y_m`` properties (always local metres, exact to the mm); the
    polygon comes back from lon/lat through the geo origin the file states.
    """
    if not path.is_file():
        return []
    layer = _read_layer(path, name)
    out = []
    for k, (poly, p) in enumerate(zip(layer.geometries, layer.properties, strict=True)):
        if poly is None or poly.is_empty:
            continue
        if p.get("x_m") is not None and p.get("y_m") is not None:
            cen = (float(p["x_m"]), float(p["y_m"]))
        else:
            cen = (poly.centroid.x, poly.centroid.y)
        out.append({"cls": _cls(p, path, k), "polygon": poly, "centroid": cen})
    return out


def _truth_lines(seq_root: Path, run_dir: Path | None, n: int) -> tuple[list[dict] | None, str]:
    cands = ([run_dir / "truth" / "detections_truth.jsonl", run_dir / "detections_truth.jsonl"] if run_dir else [])
    cands.append(seq_root / "truth" / "detections_truth.jsonl")
    for c in cands:
        if c.is_file():
            lines = _read_jsonl(c)
            if len(lines) == n:
                return lines, str(c)
            return None, f"{c} has {len(lines)} lines but the run has {n} detections (not aligned)"
    return None, "no truth/detections_truth.jsonl (detections not from the simulated detector)"


def evaluate(result_or_run_dir: Any, seq_root: str | os.PathLike, match_dist_m: float = MATCH_DIST_M) -> dict:
    """Score a FusionResult or a run folder (``pavemap run`` or ``pavemap fuse``) against ``seq_root``'s truth.

    Returns the content of ``eval.json``: precision, recall, f1, median_error_m, p90_error_m,
    msr, fp_removed, tp_lost, per_class, baseline (the single-frame baseline's scores), rule.
    """
    seq_root = Path(seq_root)
    truth = load_truth(seq_root)
    run_dir = None
    if isinstance(result_or_run_dir, str | os.PathLike):
        run_dir = Path(result_or_run_dir)
        if not (run_dir / "detections_mapped.jsonl").is_file():
            raise PavemapError(f"{run_dir}: not a run folder (no detections_mapped.jsonl; "
                               "written by `pavemap run` or `pavemap fuse`)")
        from pavemap.export.gis import run_defects_path

        preds = _read_instances(*run_defects_path(run_dir, "defects"))  # GeoJSON, or survey.gpkg without geo
        base = _read_instances(*run_defects_path(run_dir, "baseline_defects"))
        records = _read_jsonl(run_dir / "detections_mapped.jsonl")
        mf = run_dir / "metrics.json"
        metrics = json.loads(mf.read_text(encoding="utf-8")) if mf.is_file() else {}
    else:
        r = result_or_run_dir
        preds = [{"cls": i.cls, "polygon": i.polygon, "centroid": i.centroid} for i in r.instances]
        base = [{"cls": i.cls, "polygon": i.polygon, "centroid": i.centroid} for i in r.baseline]
        records, metrics = r.detections, r.metrics
    lines, source = _truth_lines(seq_root, run_dir, len(records))
    visible = visible_defects(records, lines) if lines is not None else None
    out: dict[str, Any] = {"rule": RULE, "match_dist_m": match_dist_m}
    fused = score_instances(preds, truth, visible, match_dist_m)
    out.update({k: fused[k] for k in ("precision", "recall", "f1", "median_error_m", "p90_error_m")})
    out["msr"] = metrics.get("msr")
    det = detection_scores(records, lines) if lines is not None else {}
    out["fp_removed"] = det.get("fp_removed")
    out["tp_lost"] = det.get("tp_lost")
    out.update({k: v for k, v in fused.items() if k not in out})
    out["detections"] = det
    out["truth_detections_source"] = source
    out["truth_defects"] = len(truth)
    out["visible_defects"] = len(visible) if visible is not None else len(truth)
    out["baseline"] = score_instances(base, truth, visible, match_dist_m)
    return out
