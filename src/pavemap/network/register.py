"""The defect register of a road network: one record per physical defect across drives and surveys.

``NETWORK/register.gpkg`` (GeoPackage 1.3, opens in QGIS), all layers in one CRS: the UTM zone of
the earliest drive's geo origin (WGS84 / UTM, metres), so areas and distances read in metres:

- ``observations``: every defect instance of every finished drive (its run's record, see
  :data:`pavemap.export.geojson.PROPERTY_SCHEMA`) with ``drive``, ``date``, ``vehicle``, its number in
  the drive (``instance_id``) and the physical defect it was merged into (``defect_id``);
- ``defects``: the physical defects: class, first and last survey it was seen in, sightings, the drives,
  area and depth in its previous and its last survey, their change, and ``status``;
- ``drives``: one line per drive (its trajectory) with date, vehicle, defects and georeferencing residual;
- ``segments``: the drives' condition segments, when their runs wrote them (issue 16);
- ``layer_styles``: QGIS styles (:mod:`pavemap.export.qgis_style`): defects by status, observations by
  urgency (both labelled with the class code), drives as lines, segments by condition index.

Merging: drives are taken in date order (then name); each drive's instances are matched one-to-one to
the register's defects (their latest sighting) by :func:`pavemap.compare.match_defects` with
``by_class``: same class first, then the rest; a pair needs centroids within the tolerance or
overlapping polygons. Tolerance: ``max(floor_m, 2 x hypot(drive residual, largest residual so far))``,
the residual being the georeferencing RMS of the drive's GPS fit (none for an exact origin: the floor).

Status, against the last survey (date) whose drives covered the defect (the ``survey`` layer's area):
*new* first seen in that survey; *grown* seen in it and its area or depth rose by ``grow_ratio``
times since the previous survey that saw it; *unchanged* seen, not grown; *not seen again* not seen in it.
"""

from __future__ import annotations

import datetime as dt
import os
import time
from collections import Counter
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import shapely
from pyproj import CRS, Transformer

from pavemap.errors import PavemapError
from pavemap.export.geojson import PROPERTY_SCHEMA
from pavemap.io.atomic import atomic_path, atomic_write_json

REGISTER_GPKG = "register.gpkg"
REGISTER_JSON = "register.json"
FLOOR_M = 0.5  # the evaluation's and `pavemap compare`'s match distance
RESIDUAL_K = 2.0
GROW_RATIO = 1.5
STATUSES = ("new", "grown", "unchanged", "not seen again")


@dataclass
class DriveDefects:
    """One finished drive's defects in the register CRS."""

    name: str
    date: str
    vehicle: str
    defects: object  # compare._Defects
    rms_m: float  # georeferencing residual (0: exact origin)
    coverage: object | None  # shapely, register CRS
    trajectory: object | None  # shapely LineString, register CRS


def no_origin_message(names: list[str]) -> str:
    return (f"drive(s) {', '.join(names)} have no geo origin: the register merges defects of different drives "
            "by their position on the Earth, so every drive needs one (import with GPS, or give --geo-origin). "
            "These drives are still batch-processed: their runs are in NETWORK/drives/")


def _survey_record(gpkg: Path, to_reg: Transformer) -> tuple[float, object | None]:
    """(georeferencing RMS, surveyed area in the register CRS) from the run's ``survey`` layer."""
    import pyogrio

    meta, _, geoms, values = pyogrio.raw.read(gpkg, layer="survey")
    rec = {n: v[0] for n, v in zip(meta["fields"], values, strict=True)}
    rms = float(rec.get("georef_rms_m", np.nan))
    area = shapely.from_wkb(geoms[0]) if len(geoms) and geoms[0] is not None else None
    if area is not None:
        area = _reproject(area, CRS.from_user_input(meta["crs"]), to_reg)
    return (rms if np.isfinite(rms) else 0.0), area


def _reproject(geom: object, src: CRS, to_reg: Transformer) -> object:
    """A geometry in ``src`` -> the register CRS (through WGS84)."""
    to_ll = Transformer.from_crs(src, "EPSG:4326", always_xy=True)

    def f(c: np.ndarray) -> np.ndarray:
        lon, lat = to_ll.transform(c[:, 0], c[:, 1])
        return np.column_stack(to_reg.transform(lon, lat))

    return shapely.transform(geom, f)


def _trajectory(gpkg: Path, to_reg: Transformer) -> object | None:
    import warnings

    import pyogrio

    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # GDAL reads the M values as Z: only x, y are used
            meta, _, geoms, _ = pyogrio.raw.read(gpkg, layer="trajectory")
    except Exception:  # noqa: BLE001 - a run without a trajectory layer: no line on the map
        return None
    if not len(geoms) or geoms[0] is None:
        return None
    line = shapely.force_2d(shapely.from_wkb(geoms[0]))
    return _reproject(line, CRS.from_user_input(meta["crs"]), to_reg)


def load_drive(net: Path, entry: dict, reg_crs: CRS | None) -> tuple[DriveDefects, CRS]:
    """A finished drive's defects in the register CRS (``reg_crs`` None: this drive's UTM zone)."""
    from pavemap.compare import _collect
    from pavemap.export.gis import SURVEY_GPKG, read_defect_layer
    from pavemap.geo.crs import output_crs
    from pavemap.geo.tangent import local_tangent

    gpkg = net / entry["run"] / SURVEY_GPKG
    layer = read_defect_layer(gpkg)
    if layer.geo_origin is None:
        raise PavemapError(no_origin_message([entry["name"]]))
    reg_crs = reg_crs or output_crs(layer.geo_origin, "auto")
    to_reg = Transformer.from_crs("EPSG:4326", reg_crs, always_xy=True)
    lt = local_tangent(layer.geo_origin)

    def world_to_reg(g: object) -> object:
        def f(c: np.ndarray) -> np.ndarray:
            lon, lat = lt.to_lonlat(c[:, 0], c[:, 1])
            return np.column_stack(to_reg.transform(lon, lat))

        return shapely.transform(g, f)

    rms, coverage = _survey_record(gpkg, to_reg)
    drive = DriveDefects(entry["name"], entry["date"], entry.get("vehicle", ""), _collect(layer, world_to_reg),
                         rms, coverage, _trajectory(gpkg, to_reg))
    return drive, reg_crs


@dataclass
class _Register:
    """The physical defects while drives are merged in: latest sighting's geometry, centroid, class."""

    geoms: list
    centroids: list
    cls: list
    sightings: list  # per defect: [(drive index, instance index)]

    def as_defects(self) -> object:
        from pavemap.compare import _Defects

        n = len(self.geoms)
        return _Defects(list(self.geoms), np.asarray(self.centroids, dtype=np.float64).reshape(-1, 2),
                        np.zeros(n), np.full(n, np.nan), np.asarray(self.cls, dtype=np.int64).reshape(-1),
                        list(range(n)), [{} for _ in range(n)])


def merge(drives: list[DriveDefects], floor_m: float = FLOOR_M) -> tuple[list[list[tuple[int, int]]], dict]:
    """Merge the drives' instances (drives in date order) into physical defects.

    Returns the sightings of each physical defect ([(drive index, instance index)], in merge order)
    and the tolerance used for each drive (m).
    """
    from pavemap.compare import match_defects

    reg = _Register([], [], [], [])
    tolerance: dict[str, float] = {}
    rms_so_far = 0.0
    for di, d in enumerate(drives):
        tol = max(floor_m, RESIDUAL_K * float(np.hypot(d.rms_m, rms_so_far)))
        tolerance[d.name] = round(tol, 3)
        D = d.defects
        pairs = match_defects(reg.as_defects(), D, tol, by_class=True)  # type: ignore[arg-type]
        matched = set()
        for i, j, _ in pairs:
            reg.sightings[i].append((di, j))
            reg.geoms[i], reg.centroids[i], reg.cls[i] = D.geoms[j], D.centroids[j], int(D.cls[j])
            matched.add(j)
        for j in range(len(D.ids)):
            if j not in matched:
                reg.geoms.append(D.geoms[j])
                reg.centroids.append(D.centroids[j])
                reg.cls.append(int(D.cls[j]))
                reg.sightings.append([(di, j)])
        rms_so_far = max(rms_so_far, d.rms_m)
    return reg.sightings, tolerance


def _num(v: object) -> float:
    try:
        f = float(v)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        return float("nan")
    return f if np.isfinite(f) else float("nan")


def _r(v: float, nd: int = 4) -> float | None:
    return round(float(v), nd) if np.isfinite(v) else None


def _covered(drives: list[DriveDefects], floor_m: float) -> dict[str, object | None]:
    """Per survey date, the area its drives covered (buffered by the floor); None: a drive without one
    (taken as covering everything)."""
    out: dict[str, object | None] = {}
    for date in sorted({d.date for d in drives}):
        areas = [d.coverage for d in drives if d.date == date]
        out[date] = None if any(a is None for a in areas) else shapely.union_all(areas).buffer(floor_m)
    return out


def _status(by_date: dict[str, list[tuple[int, int]]], covering: list[str], drives: list[DriveDefects],
            grow_ratio: float) -> dict:
    """Status and growth of one physical defect from its sightings grouped by survey date."""
    seen = sorted(by_date)
    last_cov = covering[-1]

    def mean(date: str, what: str) -> float:
        if what == "area":
            vals = [drives[di].defects.area[j] for di, j in by_date[date]]  # type: ignore[attr-defined]
        else:
            vals = [_num(drives[di].defects.props[j].get("depth_max_mm")) for di, j in by_date[date]]  # type: ignore[attr-defined]
        vals = [v for v in vals if np.isfinite(v)]
        return float(np.mean(vals)) if vals else float("nan")

    last = last_cov if last_cov in by_date else seen[-1]
    earlier = [d for d in seen if d < last]
    prev = earlier[-1] if earlier else None
    a1, d1 = mean(last, "area"), mean(last, "depth")
    a0, d0 = (mean(prev, "area"), mean(prev, "depth")) if prev else (float("nan"), float("nan"))
    reasons = []
    if np.isfinite(a0) and a1 > a0 and a1 >= grow_ratio * max(a0, 1e-9):
        reasons.append("area")
    if np.isfinite(d0) and np.isfinite(d1) and d1 > d0 and d1 >= grow_ratio * max(d0, 1e-9):
        reasons.append("depth")
    if last_cov not in by_date:
        status = "not seen again"
    elif prev is None:
        status = "new"
    else:
        status = "grown" if reasons else "unchanged"
    return {"status": status, "reasons": "; ".join(reasons) if status == "grown" else "",
            "last_survey": last_cov, "previous_seen": prev or "",
            "area_prev_m2": _r(a0), "area_last_m2": _r(a1), "area_ratio": _r(a1 / a0, 3) if prev and a0 > 0 else None,
            "depth_prev_mm": _r(d0, 1), "depth_last_mm": _r(d1, 1),
            "depth_change_mm": _r(d1 - d0, 1) if np.isfinite(d0) and np.isfinite(d1) else None}


def defect_records(drives: list[DriveDefects], sightings: list[list[tuple[int, int]]], grow_ratio: float,
                   floor_m: float, to_ll: Transformer) -> tuple[list, list[dict]]:
    """(geometries, records) of the ``defects`` layer: one per physical defect."""
    from pavemap.types import DEFECT_CODES, DEFECT_NAMES

    cover = _covered(drives, floor_m)
    geoms, recs = [], []
    for pid, s in enumerate(sightings):
        by_date: dict[str, list[tuple[int, int]]] = {}
        for di, j in s:
            by_date.setdefault(drives[di].date, []).append((di, j))
        di, j = s[-1]
        D = drives[di].defects
        pt = shapely.Point(*D.centroids[j])  # type: ignore[attr-defined]
        covering = [d for d, area in cover.items() if d in by_date or area is None or area.contains(pt)]
        last_dates = by_date[max(by_date)]
        votes = Counter(int(drives[a].defects.cls[b]) for a, b in last_dates)  # type: ignore[attr-defined]
        cls = max(votes, key=lambda c: (votes[c], c))  # a tie goes to the more severe class
        code = DEFECT_CODES[cls] if 0 <= cls < len(DEFECT_CODES) else ""
        lon, lat = to_ll.transform(pt.x, pt.y)
        rec = {"id": pid + 1, "cls": cls, "code": code, "name": DEFECT_NAMES.get(code, ""),
               **_status(by_date, covering, drives, grow_ratio),
               "first_seen": min(by_date), "last_seen": max(by_date), "surveys_seen": len(by_date),
               "sightings": len(s), "drives": ", ".join(sorted({drives[a].name for a, _ in s})),
               "x": round(pt.x, 3), "y": round(pt.y, 3), "lon": round(float(lon), 9), "lat": round(float(lat), 9)}
        geoms.append(D.geoms[j])  # type: ignore[attr-defined]
        recs.append(rec)
    return geoms, recs


DEFECT_SCHEMA = [("id", "int"), ("cls", "int"), ("code", "str"), ("name", "str"), ("status", "str"),
                 ("reasons", "str"), ("first_seen", "str"), ("last_seen", "str"), ("last_survey", "str"),
                 ("previous_seen", "str"), ("surveys_seen", "int"), ("sightings", "int"), ("drives", "str"),
                 ("area_prev_m2", "float"), ("area_last_m2", "float"), ("area_ratio", "float"),
                 ("depth_prev_mm", "float"), ("depth_last_mm", "float"), ("depth_change_mm", "float"),
                 ("x", "float"), ("y", "float"), ("lon", "float"), ("lat", "float")]
OBSERVATION_SCHEMA = [("drive", "str"), ("date", "str"), ("vehicle", "str"), ("defect_id", "int"),
                      ("instance_id", "int")] + [(n, t) for n, t, *_ in PROPERTY_SCHEMA if n != "id"]
DRIVE_SCHEMA = [("name", "str"), ("date", "str"), ("vehicle", "str"), ("defects", "int"),
                ("georef_rms_m", "float"), ("tolerance_m", "float")]


def _segments(net: Path, entries: list[dict], reg_crs: CRS) -> tuple[list, list[str], list[np.ndarray]] | None:
    """The drives' ``segments`` layers (issue 16) as one layer in the register CRS, with drive and date
    columns; None when no run wrote one."""
    import pyogrio

    from pavemap.export.gis import SURVEY_GPKG

    to_reg = Transformer.from_crs("EPSG:4326", reg_crs, always_xy=True)
    geoms: list = []
    names: list[str] | None = None
    cols: list[list[np.ndarray]] = []
    for e in entries:
        gpkg = net / e["run"] / SURVEY_GPKG
        try:
            meta, _, g, values = pyogrio.raw.read(gpkg, layer="segments")
        except Exception:  # noqa: BLE001 - a run without segments (issue 16 not run there)
            continue
        fields = [str(f) for f in meta["fields"]]
        if names is not None and fields != names:
            continue  # another pavemap version's columns: not mixed into one table
        names = fields
        src = CRS.from_user_input(meta["crs"])
        geoms += [None if w is None else _reproject(shapely.from_wkb(w), src, to_reg) for w in g]
        n = len(g)
        cols.append([np.array([e["name"]] * n, dtype=object), np.array([e["date"]] * n, dtype=object), *values])
    if names is None or not geoms:
        return None
    data = [np.concatenate([c[k] for c in cols]) for k in range(len(names) + 2)]
    return geoms, ["drive", "date", *names], data


def write_register(path: Path, crs: CRS, observations: tuple[list, list[dict]], defects: tuple[list, list[dict]],
                   drives: tuple[list, list[dict]], segments: tuple | None) -> Path:
    """Write ``register.gpkg`` (atomically: a reader never sees half a register)."""
    import pyogrio.raw

    from pavemap.export.gis import _GPKG_OPTIONS, _multi, _write_layer
    from pavemap.export.qgis_style import register_styles, write_layer_styles

    with atomic_path(path) as tmp:
        _write_layer(tmp, "GPKG", "defects", [_multi(g) for g in defects[0]], defects[1], crs, "MultiPolygon",
                     DEFECT_SCHEMA, dataset_options=_GPKG_OPTIONS)
        _write_layer(tmp, "GPKG", "observations", [_multi(g) for g in observations[0]], observations[1], crs,
                     "MultiPolygon", OBSERVATION_SCHEMA)
        _write_layer(tmp, "GPKG", "drives", drives[0], drives[1], crs, "LineString", DRIVE_SCHEMA)
        if segments is not None:
            geoms, names, data = segments
            wkb = np.array([None if g is None else shapely.to_wkb(g) for g in geoms], dtype=object)
            kinds = {shapely.get_type_id(g) for g in geoms if g is not None}
            gtype = "Unknown" if len(kinds) != 1 else shapely.from_wkb(wkb[[w is not None for w in wkb]][0]).geom_type
            pyogrio.raw.write(tmp, wkb, data, names, layer="segments", driver="GPKG", geometry_type=gtype,
                              crs=crs.to_wkt())
        write_layer_styles(tmp, register_styles())
    return path


def build_register(net: str | os.PathLike, grow_ratio: float = GROW_RATIO, floor_m: float = FLOOR_M) -> dict:
    """Build ``NETWORK/register.gpkg`` and ``register.json`` from the finished drives of ``network.json``.

    PavemapError when a finished drive has no geo origin (:func:`no_origin_message`) or none finished.
    Returns the summary (also in ``register.json``).
    """
    from pavemap.geo.crs import crs_label
    from pavemap.network.folder import read_network

    if not (np.isfinite(grow_ratio) and grow_ratio >= 1.0):
        raise PavemapError(f"grow_ratio must be >= 1, got {grow_ratio}")
    if not (np.isfinite(floor_m) and floor_m > 0):
        raise PavemapError(f"the tolerance floor must be a positive distance in metres, got {floor_m}")
    t = time.perf_counter()
    net = Path(net)
    status = read_network(net)
    entries = sorted((e for e in status["drives"] if e.get("status") == "done"), key=lambda e: (e["date"], e["name"]))
    if not entries:
        raise PavemapError(f"{net}: no finished drive to build a register from (see {net / 'network.json'})")
    missing = [e["name"] for e in entries if e.get("geo_origin") is False]
    if missing:
        raise PavemapError(no_origin_message(missing))
    drives: list[DriveDefects] = []
    reg_crs = None
    for e in entries:
        d, reg_crs = load_drive(net, e, reg_crs)
        drives.append(d)
    assert reg_crs is not None
    sightings, tolerance = merge(drives, floor_m)
    to_ll = Transformer.from_crs(reg_crs, "EPSG:4326", always_xy=True)
    defects = defect_records(drives, sightings, grow_ratio, floor_m, to_ll)
    owner = {s: pid + 1 for pid, ss in enumerate(sightings) for s in ss}
    obs_geoms, obs_recs = [], []
    for di, d in enumerate(drives):
        D = d.defects
        for j, p in enumerate(D.props):  # type: ignore[attr-defined]
            obs_geoms.append(D.geoms[j])  # type: ignore[attr-defined]
            obs_recs.append({**{k: v for k, v in p.items() if k != "id"}, "drive": d.name, "date": d.date,
                             "vehicle": d.vehicle, "defect_id": owner[(di, j)], "instance_id": p.get("id")})
    drive_recs = [{"name": d.name, "date": d.date, "vehicle": d.vehicle, "defects": len(d.defects.ids),  # type: ignore[attr-defined]
                   "georef_rms_m": d.rms_m, "tolerance_m": tolerance[d.name]} for d in drives]
    path = write_register(net / REGISTER_GPKG, reg_crs, (obs_geoms, obs_recs), defects,
                          ([d.trajectory for d in drives], drive_recs), _segments(net, entries, reg_crs))
    counts = Counter(r["status"] for r in defects[1])
    summary = {"path": str(path), "crs": crs_label(reg_crs), "observations": len(obs_recs),
               "defects": len(defects[1]), "status_counts": {s: counts.get(s, 0) for s in STATUSES},
               "surveys": sorted({d.date for d in drives}), "drives": [d.name for d in drives],
               "left_out": [e["name"] for e in status["drives"] if e.get("status") != "done"],
               "tolerance_m": tolerance, "floor_m": floor_m, "grow_ratio": grow_ratio,
               "built_utc": dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),
               "seconds": round(time.perf_counter() - t, 3)}
    atomic_write_json(net / REGISTER_JSON, summary)
    return summary


def read_register(net: str | os.PathLike, layer: str = "defects") -> list[dict]:
    """The records of a register layer (no geometry), e.g. for the summary and the page."""
    import pyogrio

    from pavemap.export.gis import _plain

    p = Path(net) / REGISTER_GPKG
    if not p.is_file():
        raise PavemapError(f"{net}: no {REGISTER_GPKG}; run `pavemap register {net}` to build it")
    meta, _, _, values = pyogrio.raw.read(p, layer=layer, read_geometry=False)
    return [{n: _plain(v[k]) for n, v in zip(meta["fields"], values, strict=True)} for k in range(len(values[0]) if
                                                                                             values else 0)]


__all__ = ["FLOOR_M", "GROW_RATIO", "REGISTER_GPKG", "REGISTER_JSON", "STATUSES", "build_register", "load_drive",
           "merge",
           "no_origin_message", "read_register"]
