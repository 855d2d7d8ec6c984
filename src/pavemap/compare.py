"""Change between two surveys of the same road: defects new, grown, unchanged and gone.

Both runs' ``defects.geojson`` are brought into one metric frame: run A's world frame. When both
runs carry a geo origin, B is moved through WGS84 (B world -> lon/lat -> A world), so two drives
with different local origins still line up; without geo origins both are taken to share one world
frame (as two synthetic surveys of one scene do).

Matching is one-to-one and greedy by centroid distance: a pair is allowed when the centroids are
within ``match_m`` or the polygons overlap (a long crack's centroid moves when it grows at one end).
A matched defect has *grown* when its area or its severity rose by at least ``grow_ratio`` times,
or its class became a more severe one (D00 < D10 < D20 < D40); otherwise it is *unchanged*.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import shapely

from pavemap.errors import PavemapError
from pavemap.export.geojson import DefectLayer, features_to_geojson
from pavemap.export.gis import CHANGES_GPKG, read_defect_layer, write_local_changes
from pavemap.geo.tangent import local_tangent, origin_to_dict
from pavemap.io.atomic import atomic_write_json
from pavemap.types import DEFECT_CODES

CHANGES = ("new", "grown", "unchanged", "gone")
CHANGE_COLOURS = {"new": "#d62728", "grown": "#ff7f0e", "unchanged": "#1f77b4", "gone": "#9467bd"}
_EPS = 1e-9


@dataclass
class _Defects:
    """One run's defects in the common frame. Arrays are (N,) unless noted."""

    geoms: list[object]
    centroids: np.ndarray  # (N, 2) float64 metres
    area: np.ndarray
    severity: np.ndarray  # NaN when unknown
    cls: np.ndarray  # int, -1 when unknown
    ids: list[object]
    props: list[dict]


def _defects_geojson(run: Path) -> Path:
    """A run folder's defects: ``defects.geojson`` (georeferenced) or ``survey.gpkg`` (local), or the file given."""
    from pavemap.export.gis import run_defects_path

    run = Path(run)
    if run.is_dir():
        p, _ = run_defects_path(run, "defects")
        if not p.is_file():
            raise PavemapError(f"{run}: no defects.geojson or survey.gpkg in this folder "
                               "(is it a pavemap run output folder?)")
        return p
    if run.is_file():
        return run
    raise PavemapError(f"{run}: no such run folder or GeoJSON file")


def _num(v: object, default: float = float("nan")) -> float:
    try:
        f = float(v)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        return default
    return f if np.isfinite(f) else default


def _cls_of(p: dict) -> int:
    if isinstance(p.get("cls"), int) and 0 <= p["cls"] < len(DEFECT_CODES):
        return int(p["cls"])
    for key in ("code", "name"):
        if p.get(key) in DEFECT_CODES:
            return DEFECT_CODES.index(p[key])
    return -1


def _collect(layer: DefectLayer, to_common=None) -> _Defects:
    geoms, cents, areas, sevs, clss, ids, props = [], [], [], [], [], [], []
    for g, p in zip(layer.geometries, layer.properties, strict=True):
        if g is not None and not g.is_empty and to_common is not None:
            g = to_common(g)
        if g is not None and not g.is_empty:
            c = g.centroid
            cxy = (c.x, c.y)
            area = float(g.area) if g.area > 0 else _num(p.get("area_m2"), 0.0)
        elif "x_m" in p and "y_m" in p and to_common is None:
            cxy = (_num(p["x_m"]), _num(p["y_m"]))
            area = _num(p.get("area_m2"), 0.0)
        else:
            continue  # a defect without a position cannot be compared
        geoms.append(g)
        cents.append(cxy)
        areas.append(area)
        # the paper's EMA severity: paper_severity since issue 16, severity in older files
        sevs.append(_num(next((p[k] for k in ("paper_severity", "severity", "severity_mean") if p.get(k) is not None),
                              None)))
        clss.append(_cls_of(p))
        ids.append(p.get("id"))
        props.append(p)
    return _Defects(geoms, np.asarray(cents, dtype=np.float64).reshape(-1, 2), np.asarray(areas, dtype=np.float64),
                    np.asarray(sevs, dtype=np.float64), np.asarray(clss, dtype=np.int64), ids, props)


def match_defects(a: _Defects, b: _Defects, match_m: float, by_class: bool = False) -> list[tuple[int, int, float]]:
    """Greedy one-to-one pairs (i in a, j in b, centroid distance), closest first.

    The same rule as the ground-truth evaluation (:func:`pavemap.evaluate.gt.match`). ``by_class``
    (the network register): pairs of the same class are made first, then the rest among what is left,
    so a defect the detector labelled differently on another drive still pairs, but never ahead of a
    same-class candidate.
    """
    from pavemap.evaluate.gt import match

    ga = [g if g is not None else shapely.Point() for g in a.geoms]
    gb = [g if g is not None else shapely.Point() for g in b.geoms]
    if not by_class:
        return match(ga, a.centroids, gb, b.centroids, match_m)

    def sub(ia: np.ndarray, ib: np.ndarray) -> list[tuple[int, int, float]]:
        found = match([ga[k] for k in ia], a.centroids[ia], [gb[k] for k in ib], b.centroids[ib], match_m)
        return [(int(ia[i]), int(ib[j]), d) for i, j, d in found]

    pairs: list[tuple[int, int, float]] = []
    for c in np.unique(a.cls):
        pairs += sub(np.flatnonzero(a.cls == c), np.flatnonzero(b.cls == c))
    rest_a = np.setdiff1d(np.arange(len(ga)), [p[0] for p in pairs]).astype(np.int64)
    rest_b = np.setdiff1d(np.arange(len(gb)), [p[1] for p in pairs]).astype(np.int64)
    pairs += sub(rest_a, rest_b)
    return sorted(pairs, key=lambda p: (p[2], p[0]))


def _classify(a: _Defects, b: _Defects, i: int, j: int, grow_ratio: float) -> tuple[str, list[str]]:
    reasons = []
    if b.area[j] >= grow_ratio * max(a.area[i], _EPS) and b.area[j] > a.area[i]:
        reasons.append("area")
    if np.isfinite(a.severity[i]) and np.isfinite(b.severity[j]) and \
            b.severity[j] >= grow_ratio * max(a.severity[i], _EPS) and b.severity[j] > a.severity[i]:
        reasons.append("severity")
    if a.cls[i] >= 0 and b.cls[j] > a.cls[i]:
        reasons.append("class")
    return ("grown" if reasons else "unchanged"), reasons


def _common_frame(la: DefectLayer, lb: DefectLayer) -> tuple[str, Callable | None, list[str]]:
    """The frame both layers are compared in: ``"lonlat"`` when both have geo origins (B's geometries then
    move into A's local frame, if their origins differ), else ``"local"`` world metres; (frame, B's
    geometry -> A's frame or None, warnings)."""
    warnings: list[str] = []
    to_common = None
    if la.geo_origin is not None and lb.geo_origin is not None:
        frame = "lonlat"
        if origin_to_dict(la.geo_origin) != origin_to_dict(lb.geo_origin):
            lt_a, lt_b = local_tangent(la.geo_origin), local_tangent(lb.geo_origin)

            def to_common(g: object) -> object:
                return lt_a.geometry_from_lonlat(lt_b.geometry_to_lonlat(g))
    else:
        frame = "local"
        if (la.geo_origin is None) != (lb.geo_origin is None):
            warnings.append("only one run has a geo origin; both were compared in their local world metres, "
                            "assuming the two runs share one world frame")
    return frame, to_common, warnings


def _change_records(A: _Defects, B: _Defects, pairs: list[tuple[int, int, float]],
                    grow_ratio: float) -> list[tuple[dict, int | None, int | None]]:
    """(record, index in A or None, index in B or None): the matched ``pairs`` classified, then B's
    unmatched defects (new), then A's (gone). A record holds change, geometry, id_a, id_b (and for a pair
    distance_m, reasons)."""
    records = []
    matched_a = {i for i, _, _ in pairs}
    matched_b = {j for _, j, _ in pairs}
    for i, j, d in pairs:
        change, reasons = _classify(A, B, i, j, grow_ratio)
        r = {"change": change, "geometry": B.geoms[j], "id_a": A.ids[i], "id_b": B.ids[j],
             "distance_m": round(d, 3), "reasons": reasons}
        records.append((r, i, j))
    records += [({"change": "new", "geometry": B.geoms[j], "id_a": None, "id_b": B.ids[j]}, None, j)
                for j in range(len(B.ids)) if j not in matched_b]
    records += [({"change": "gone", "geometry": A.geoms[i], "id_a": A.ids[i], "id_b": None}, i, None)
                for i in range(len(A.ids)) if i not in matched_a]
    return records


def _change_rows(A: _Defects, B: _Defects, records: list[tuple[dict, int | None, int | None]]
                 ) -> tuple[list, list[dict]]:
    """The records in output order (by change, then ids) as (geometries, property rows); each record's
    geometry moves into the first list (the figure then reads it from A or B)."""

    def code(d: _Defects, k: int | None) -> str | None:
        return DEFECT_CODES[d.cls[k]] if k is not None and d.cls[k] >= 0 else None

    geoms, pair_rows = [], []
    for n, (r, i, j) in enumerate(sorted(records, key=lambda t: (CHANGES.index(t[0]["change"]), str(t[0]["id_b"]),
                                                                   str(t[0]["id_a"])))):
        geoms.append(r.pop("geometry"))
        src = B if j is not None else A
        k = j if j is not None else i
        props = {
            "id": n + 1, "change": r["change"], "id_a": r["id_a"], "id_b": r["id_b"],
            "code": code(src, k), "code_a": code(A, i), "code_b": code(B, j),
            "area_a": None if i is None else round(float(A.area[i]), 4),
            "area_b": None if j is None else round(float(B.area[j]), 4),
            "severity_a": None if i is None or not np.isfinite(A.severity[i]) else round(float(A.severity[i]), 4),
            "severity_b": None if j is None or not np.isfinite(B.severity[j]) else round(float(B.severity[j]), 4),
            "distance_m": r.get("distance_m"), "reasons": r.get("reasons", []),
            "x_m": round(float(src.centroids[k, 0]), 3), "y_m": round(float(src.centroids[k, 1]), 3),
        }
        if i is not None and j is not None:
            props["area_ratio"] = round(float(B.area[j] / max(A.area[i], _EPS)), 3)
        pair_rows.append(props)
    return geoms, pair_rows


def compare_runs(run_a: str | os.PathLike, run_b: str | os.PathLike, out: str | os.PathLike,
                 match_m: float = 0.5, grow_ratio: float = 1.2) -> dict:
    """Compare survey A (earlier) with survey B (later); write the changes layer (``changes.geojson`` in lon/lat
    with geo origins, else ``changes.gpkg`` in the local engineering CRS), changes.png, changes.json.

    ``run_a``/``run_b``: run output folders (holding defects.geojson) or the GeoJSON files themselves.
    Returns the summary dict that is also written to ``changes.json``.
    """
    if not (np.isfinite(match_m) and match_m > 0):
        raise PavemapError(f"match_m must be a positive distance in metres, got {match_m}")
    if not (np.isfinite(grow_ratio) and grow_ratio >= 1.0):
        raise PavemapError(f"grow_ratio must be >= 1, got {grow_ratio}")
    pa, pb = _defects_geojson(Path(run_a)), _defects_geojson(Path(run_b))
    la, lb = read_defect_layer(pa), read_defect_layer(pb)
    frame, to_common, warnings = _common_frame(la, lb)
    A, B = _collect(la), _collect(lb, to_common)
    records = _change_records(A, B, match_defects(A, B, match_m), grow_ratio)
    geoms, pair_rows = _change_rows(A, B, records)
    counts = {c: sum(p["change"] == c for p in pair_rows) for c in CHANGES}
    out_dir = Path(out)
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise PavemapError(f"{out_dir}: cannot create the output folder ({e.strerror or e})") from None
    meta = {"format": "pavemap-changes/1", "run_a": str(pa), "run_b": str(pb)}
    if frame != "lonlat":
        meta["frame"] = "run A's local world frame x, y metres; not WGS84"
    fc = features_to_geojson(geoms, [dict(p) for p in pair_rows], la.geo_origin if frame == "lonlat" else None,
                             meta=meta)
    summary = {"run_a": str(pa), "run_b": str(pb), "defects_a": len(A.ids), "defects_b": len(B.ids),
               "counts": counts, "match_m": match_m, "grow_ratio": grow_ratio, "coordinates": frame,
               "warnings": warnings, "changes": pair_rows}
    layer = "changes.geojson" if frame == "lonlat" else CHANGES_GPKG
    try:
        if frame == "lonlat":
            atomic_write_json(out_dir / layer, fc, indent=None)
        else:
            write_local_changes(out_dir / layer, geoms, pair_rows)
        _changes_figure(out_dir / "changes.png", A, B, records, counts)
        atomic_write_json(out_dir / "changes.json", summary)
    except PermissionError as e:
        raise PavemapError(f"{out_dir}: cannot write the comparison ({e.strerror or e}: {e.filename})") from None
    summary["paths"] = {"changes": str(out_dir / layer), "changes.png": str(out_dir / "changes.png"),
                        "changes.json": str(out_dir / "changes.json")}
    return summary


def _changes_figure(path: Path, A: _Defects, B: _Defects, records: list, counts: dict) -> Path:
    """Map of the changes: A outlines dashed grey, B filled by change, gone in purple outline."""
    from matplotlib.collections import PatchCollection
    from matplotlib.patches import PathPatch, Rectangle

    from pavemap.export.figures import geometry_path, plt, save_figure

    allc = np.vstack([A.centroids, B.centroids]) if len(A.ids) + len(B.ids) else np.zeros((1, 2))
    span = np.ptp(allc, axis=0) + 4.0
    w = 12.0
    h = float(np.clip(w * span[1] / max(span[0], 1e-6), 3.5, 12.0))
    fig, ax = plt.subplots(figsize=(w, h + 1.2))
    outl = [PathPatch(p) for p in (geometry_path(g) for g in A.geoms if g is not None) if p is not None]
    if outl:
        ax.add_collection(PatchCollection(outl, facecolors="none", edgecolors="0.45", linewidths=1.0,
                                          linestyles="--", zorder=2))
    for r, i, j in records:
        g = r["geometry"] if "geometry" in r else (B.geoms[j] if j is not None else A.geoms[i])
        p = geometry_path(g) if g is not None else None
        col = CHANGE_COLOURS[r["change"]]
        cx, cy = (B.centroids[j] if j is not None else A.centroids[i])
        if p is not None:
            if r["change"] == "gone":
                ax.add_patch(PathPatch(p, fc="none", ec=col, lw=2.0, hatch="///", zorder=3))
            else:
                ax.add_patch(PathPatch(p, fc=col, ec="black", lw=0.8, alpha=0.75, zorder=3))
        # a marker keeps small defects visible at map scale
        ax.plot(cx, cy, "o", ms=7, mfc="none" if r["change"] == "gone" else col, mec=col, mew=1.5, zorder=4)
    ax.plot(allc[:, 0], allc[:, 1], alpha=0)  # make autoscale see every centroid
    ax.set_aspect("equal")
    ax.margins(0.05)
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.grid(alpha=0.25)
    handles = [Rectangle((0, 0), 1, 1, fc=CHANGE_COLOURS[c] if c != "gone" else "none", ec=CHANGE_COLOURS[c])
               for c in CHANGES] + [Rectangle((0, 0), 1, 1, fc="none", ec="0.45", ls="--")]
    labels = [f"{c} ({counts[c]})" for c in CHANGES] + ["survey A outline"]
    ax.legend(handles, labels, loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=9)
    ax.set_title(f"changes between surveys: {counts['new']} new, {counts['grown']} grown, "
                 f"{counts['unchanged']} unchanged, {counts['gone']} gone")
    return save_figure(fig, path)


__all__ = ["CHANGES", "compare_runs", "match_defects"]
