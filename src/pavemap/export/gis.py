"""GIS layers of a run: ``survey.gpkg`` (always), ``defects.fgb`` and ``survey.kml`` / ``.kmz`` on request.

``survey.gpkg`` (GeoPackage 1.3, written through GDAL by pyogrio) holds:

- ``defects``: one MultiPolygon per defect (always Multi, so the layer has one geometry type) with
  the defect schema of :data:`pavemap.export.geojson.PROPERTY_SCHEMA`;
- ``defect_points``: the same records as points at the defects' centres (what a city's pothole
  programme takes);
- ``trajectory``: the drive as one LineString ZM: Z the height (altitude with a geo origin), M the
  frame timestamp in seconds (Unix time when the frames carry absolute times), plus start/end fields;
- ``survey``: one record with the date, vehicle, cameras, software version, CRS, geo origin and the
  georeferencing residual; its geometry is the surveyed area (:mod:`pavemap.geo.coverage`);
- ``baseline_defects``: the single-frame baseline (every mapped detection alone; for evaluation);
- ``segments``: the road segments of chainage with their PCI-like condition index
  (:data:`pavemap.maintain.segments.SEGMENT_SCHEMA`), when the run was assessed;
- ``layer_styles``: the QGIS styles of these layers (:mod:`pavemap.export.qgis_style`): the file opens in
  QGIS with defects coloured by urgency and labelled with their code, segments by condition index.

CRS: with a geo origin the drive's UTM zone (or ``--crs``); without one the local engineering CRS
of :func:`pavemap.geo.crs.local_crs`, so no layer of a run without a geo origin reads as EPSG:4326.
FlatGeobuf (``defects.fgb``) uses the same CRS; KML (:mod:`pavemap.export.kml`) is WGS84 by
definition, so it is written only with a geo origin. :func:`read_defect_layer` brings any of them back to world metres.
"""

from __future__ import annotations

import datetime as dt
import logging
import os
import struct
from pathlib import Path

import numpy as np
import shapely
from pyproj import CRS, Transformer
from shapely.geometry import MultiPolygon, Point

from pavemap.errors import PavemapError
from pavemap.export.geojson import PROPERTY_SCHEMA, DefectLayer, _polygons, instance_properties
from pavemap.export.kml import write_kml
from pavemap.export.qgis_style import survey_styles, write_layer_styles
from pavemap.geo.crs import crs_label, local_crs, output_crs
from pavemap.geo.tangent import WGS84, _apply, local_tangent, origin_from_dict
from pavemap.io.atomic import atomic_path
from pavemap.types import DefectInstance, GeoOrigin, Sequence

log = logging.getLogger("pavemap")

SURVEY_GPKG = "survey.gpkg"
DEFECTS_FGB = "defects.fgb"
EXTRA_FORMATS = ("fgb", "kml", "kmz")
_DTYPES = {"int": np.int64, "float": np.float64, "str": object, "bool": bool}
_GPKG_OPTIONS = {"VERSION": "1.3"}  # 1.4 (GDAL >= 3.7's default) draws a warning from GDAL 3.6


def _schema(geo: bool) -> list[tuple[str, str]]:
    return [(n, t) for n, t, *_ in PROPERTY_SCHEMA if geo or n not in ("lon", "lat")]


def _fields(records: list[dict], schema: list[tuple[str, str]]
            ) -> tuple[list[np.ndarray], list[str], list[np.ndarray | None]]:
    """Field arrays, names and null masks (bool fields only: true / false / null, e.g. ``measurable``)."""
    data, masks = [], []
    for name, typ in schema:
        vals = [r.get(name) for r in records]
        mask = None
        if typ == "float":  # None is NULL (a NaN float stays NaN)
            data.append(np.array([np.nan if v is None else float(v) for v in vals], dtype=np.float64))
            mask = np.array([v is None for v in vals], dtype=bool)
        elif typ == "int":
            data.append(np.array([-1 if v is None else int(v) for v in vals], dtype=np.int64))
            mask = np.array([v is None for v in vals], dtype=bool)
        elif typ == "bool":
            data.append(np.array([bool(v) for v in vals], dtype=bool))
            mask = np.array([v is None for v in vals], dtype=bool)
        else:
            data.append(np.array(["" if v is None else str(v) for v in vals], dtype=object))
        masks.append(mask)
    return data, [n for n, _ in schema], masks


class _Projector:
    """World x, y metres -> the output CRS (through lon/lat with a geo origin; identity without)."""

    def __init__(self, origin: GeoOrigin | None, crs: CRS, wgs84: bool = False) -> None:
        self.lt = local_tangent(origin) if origin is not None else None
        self.tr = None if (self.lt is None or wgs84) else Transformer.from_crs(WGS84, crs, always_xy=True)

    def xy(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        if self.lt is None:
            return np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64)
        lon, lat = self.lt.to_lonlat(x, y)
        if self.tr is None:
            return lon, lat
        return _apply(self.tr, lon, lat)

    def geometry(self, geom: object) -> object:
        def apply(c: np.ndarray) -> np.ndarray:
            return np.column_stack(self.xy(c[:, 0], c[:, 1]))

        return shapely.transform(geom, apply)


def _multi(geom: object) -> MultiPolygon | None:
    polys = _polygons(geom)
    return MultiPolygon(polys) if polys else None


def _wkb(geoms: list[object | None]) -> np.ndarray:
    return np.array([None if g is None else shapely.to_wkb(g) for g in geoms], dtype=object)


def _linestring_zm(x: np.ndarray, y: np.ndarray, z: np.ndarray, m: np.ndarray) -> bytes:
    """ISO WKB LineString ZM (type 3002); shapely 2.0 cannot make M coordinates."""
    pts = np.column_stack([x, y, z, m]).astype("<f8")
    return struct.pack("<BII", 1, 3002, len(pts)) + pts.tobytes()


def _time_text(t: float, absolute: bool) -> str:
    if absolute:
        return dt.datetime.fromtimestamp(t, dt.UTC).isoformat(timespec="milliseconds")
    return f"{t:.3f} s"


def trajectory_layer(seq: Sequence, proj: _Projector, origin: GeoOrigin | None) -> tuple[bytes, dict]:
    """The drive as LineString ZM (M = frame time) and its fields."""
    traj = seq.trajectory()
    t = np.array([f.timestamp for f in seq.frames], dtype=np.float64)
    x, y = proj.xy(traj[:, 0], traj[:, 1])
    z = traj[:, 2] + (float(origin.alt) if origin is not None else 0.0)
    absolute = bool(len(t)) and float(t[0]) > 1e8
    length = float(np.sum(np.linalg.norm(np.diff(traj[:, :2], axis=0), axis=1))) if len(traj) > 1 else 0.0
    fields = {"sequence": seq.name, "frames": len(seq.frames), "start_time": _time_text(t[0], absolute),
              "end_time": _time_text(t[-1], absolute), "duration_s": float(t[-1] - t[0]), "length_m": length,
              "m_values": "frame timestamp, s" + (" (Unix time, UTC)" if absolute else " (relative)")}
    if len(x) == 1:  # a LineString needs two points
        x, y, z, t = (np.repeat(a, 2) for a in (x, y, z, t))
    return _linestring_zm(x, y, z, t), fields


def survey_record(seq: Sequence | None, origin: GeoOrigin | None, crs: CRS, n_defects: int,
                  vehicle: str = "") -> dict:
    """The ``survey`` layer's one record (plain values)."""
    from pavemap.version import __version__

    r = (origin.georef if origin is not None else None) or {}
    t0 = seq.frames[0].timestamp if seq is not None and seq.frames else None
    date = dt.datetime.fromtimestamp(t0, dt.UTC).date().isoformat() if t0 is not None and t0 > 1e8 else ""
    cams = ", ".join(f"{c.name} {c.width}x{c.height}" for c in seq.cameras.values()) if seq is not None else ""
    return {
        "sequence": seq.name if seq is not None else "", "date": date, "vehicle": vehicle, "cameras": cams,
        "software": f"pavemap {__version__}", "processed_utc": dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),
        "crs": crs_label(crs), "defects": int(n_defects),
        "georeferenced": origin is not None,
        "origin_lat": np.nan if origin is None else float(origin.lat),
        "origin_lon": np.nan if origin is None else float(origin.lon),
        "origin_alt": np.nan if origin is None else float(origin.alt),
        "origin_heading_deg": np.nan if origin is None else float(origin.heading_deg),
        "georef_source": str(r.get("source", "")),
        "georef_fixes": int(r.get("fixes", 0) or 0), "georef_inliers": int(r.get("inliers", 0) or 0),
        "georef_rms_m": float(r["rms_m"]) if r.get("rms_m") is not None else np.nan,
        "georef_scale": float(r.get("scale_applied", 1.0) or 1.0),
        "georef_warnings": "; ".join(r.get("warnings", [])),
    }


def _write_layer(path: Path, driver: str, layer: str, geoms: list, records: dict | list[dict], crs: CRS | None,
                 geometry_type: str, schema: list[tuple[str, str]] | None = None, **kw: object) -> None:
    import pyogrio.raw

    if isinstance(records, dict):  # one record of plain values
        schema = [(k, "str" if isinstance(v, str) else "int" if isinstance(v, bool | int) else "float")
                  for k, v in records.items()]
        records = [{k: (int(v) if isinstance(v, bool) else v) for k, v in records.items()}]
    data, names, masks = _fields(records, schema or [])
    if any(m is not None for m in masks):
        kw["field_mask"] = masks
    pyogrio.raw.write(path, _wkb(geoms) if geometry_type != "Measured 3D LineString" else
                      np.array(geoms, dtype=object), data, names, layer=layer, driver=driver,
                      geometry_type=geometry_type, crs=crs.to_wkt() if crs is not None else None, **kw)


def write_gis(out_dir: str | os.PathLike, instances: list[DefectInstance], *, baseline: list[DefectInstance] | None
              = None, geo_origin: GeoOrigin | None = None, crs: str = "auto", seq: Sequence | None = None,
              surveyed: object | None = None, formats: tuple[str, ...] = (), vehicle: str = "",
              segments: list | None = None) -> dict[str, Path]:
    """Write ``survey.gpkg`` (and ``defects.fgb``, ``survey.kml``/``.kmz`` for ``formats``); returns {name: path}.

    ``surveyed``: the surveyed area, a shapely geometry in world metres (the ``survey`` layer's geometry).
    ``segments``: road segments (:mod:`pavemap.maintain.segments`), the ``segments`` layer when given.
    """
    unknown = sorted(set(formats) - set(EXTRA_FORMATS))
    if unknown:
        raise PavemapError(f"output.extra_formats: unknown {unknown}; choose from {', '.join(EXTRA_FORMATS)}")
    out = Path(out_dir)
    target = output_crs(geo_origin, crs, seq.name if seq is not None else "")
    proj = _Projector(geo_origin, target)
    schema = _schema(geo_origin is not None)

    def records(items: list[DefectInstance]) -> list[dict]:
        return [instance_properties(i, geo_origin) for i in items]

    def polys(items: list[DefectInstance], p: _Projector) -> list:
        return [None if (m := _multi(i.polygon)) is None else p.geometry(m) for i in items]

    def points(items: list[DefectInstance], p: _Projector) -> list:
        return [Point(*(float(v[0]) for v in p.xy(np.array([i.centroid[0]]), np.array([i.centroid[1]]))))
                for i in items]

    paths: dict[str, Path] = {}
    with atomic_path(out / SURVEY_GPKG) as tmp:
        opts = {"dataset_options": _GPKG_OPTIONS}
        _write_layer(tmp, "GPKG", "defects", polys(instances, proj), records(instances), target, "MultiPolygon",
                     schema, **opts)
        _write_layer(tmp, "GPKG", "defect_points", points(instances, proj), records(instances), target, "Point",
                     schema)
        if seq is not None and seq.frames:
            wkb, fields = trajectory_layer(seq, proj, geo_origin)
            _write_layer(tmp, "GPKG", "trajectory", [wkb], fields, target, "Measured 3D LineString")
        area = _multi(surveyed) if surveyed is not None else None
        _write_layer(tmp, "GPKG", "survey", [None if area is None else proj.geometry(area)],
                     survey_record(seq, geo_origin, target, len(instances), vehicle), target, "MultiPolygon")
        _write_layer(tmp, "GPKG", "baseline_defects", polys(baseline or [], proj), records(baseline or []), target,
                     "MultiPolygon", schema)
        if segments is not None:
            from pavemap.maintain.segments import SEGMENT_SCHEMA

            _write_layer(tmp, "GPKG", "segments", [None if (m := _multi(g.polygon)) is None else proj.geometry(m)
                                                   for g in segments], [g.record() for g in segments], target,
                         "MultiPolygon", [(n, t) for n, t, *_ in SEGMENT_SCHEMA])
        write_layer_styles(tmp, survey_styles())  # into the temporary file: it appears styled, at once
    paths[SURVEY_GPKG] = out / SURVEY_GPKG
    if "fgb" in formats:
        with atomic_path(out / DEFECTS_FGB) as tmp:
            _write_layer(tmp, "FlatGeobuf", "defects", polys(instances, proj), records(instances), target,
                         "MultiPolygon", schema)
        paths[DEFECTS_FGB] = out / DEFECTS_FGB
    for kind in ("kml", "kmz"):
        if kind not in formats:
            continue
        if geo_origin is None:
            log.warning("survey.%s not written: KML is longitude/latitude and this run has no geo origin", kind)
            continue
        name = f"survey.{kind}"
        write_kml(out / name, instances, geo_origin, seq)
        paths[name] = out / name
    return paths


CHANGES_GPKG = "changes.gpkg"
_CHANGE_SCHEMA = [("id", "int"), ("change", "str"), ("id_a", "int"), ("id_b", "int"), ("code", "str"),
                  ("code_a", "str"), ("code_b", "str"), ("area_a", "float"), ("area_b", "float"),
                  ("severity_a", "float"), ("severity_b", "float"), ("distance_m", "float"), ("reasons", "str"),
                  ("area_ratio", "float"), ("x_m", "float"), ("y_m", "float")]


def write_local_changes(path: str | os.PathLike, geoms: list, rows: list[dict]) -> Path:
    """A comparison without a geo origin: layer ``changes`` in the local engineering CRS (GeoJSON would be
    read as lon/lat). ``geoms`` in world metres; a missing id (new / gone) is written as -1."""
    recs = [{**r, "reasons": "; ".join(r.get("reasons") or [])} for r in rows]
    out = Path(path)
    with atomic_path(out) as tmp:
        _write_layer(tmp, "GPKG", "changes", [_multi(g) for g in geoms], recs, local_crs("changes"), "MultiPolygon",
                     _CHANGE_SCHEMA, dataset_options=_GPKG_OPTIONS)
    return out


# ---------------------------------------------------------------------------- reading back


def _origin_of(path: Path) -> GeoOrigin | None:
    import pyogrio

    try:
        meta, _, _, values = pyogrio.raw.read(path, layer="survey", read_geometry=False)
    except Exception:  # noqa: BLE001 - a file without a survey layer has no origin to give
        return None
    names = list(meta["fields"])
    rec = {n: v[0] for n, v in zip(names, values, strict=True)}
    if not rec.get("georeferenced"):
        return None
    return origin_from_dict({"lat": rec["origin_lat"], "lon": rec["origin_lon"], "alt": rec["origin_alt"],
                             "heading_deg": rec["origin_heading_deg"]}, where=f"{path}: survey layer")


def read_defect_layer(path: str | os.PathLike, layer: str = "defects") -> DefectLayer:
    """A defects layer of a GeoPackage / FlatGeobuf (or a GeoJSON) back in world metres.

    Georeferenced files are brought back through the geo origin of their ``survey`` layer; a
    FlatGeobuf in a projected CRS needs the ``survey.gpkg`` beside it.
    """
    import pyogrio

    from pavemap.export.geojson import read_geojson

    p = Path(path)
    if p.suffix.lower() in (".geojson", ".json"):
        return read_geojson(p)
    if not p.is_file():
        raise PavemapError(f"{p}: file not found")
    try:
        meta, _, geoms, values = pyogrio.raw.read(p, layer=layer)
    except Exception as e:  # noqa: BLE001 - GDAL's errors: name the file and layer
        raise PavemapError(f"{p}: cannot read layer {layer!r} ({e})") from None
    crs = CRS.from_user_input(meta["crs"]) if meta.get("crs") else None
    origin = _origin_of(p if p.suffix.lower() == ".gpkg" else p.with_name(SURVEY_GPKG))
    back = None
    if crs is not None and not crs.is_engineering:
        if origin is None:
            raise PavemapError(f"{p}: layer {layer!r} is in {crs.name} but no geo origin was found (survey layer)")
        to_ll = Transformer.from_crs(crs, WGS84, always_xy=True)
        lt = local_tangent(origin)

        def back(c: np.ndarray) -> np.ndarray:
            lon, lat = to_ll.transform(c[:, 0], c[:, 1])
            return np.column_stack(lt.from_lonlat(np.asarray(lon), np.asarray(lat)))

    out_geoms, props = [], []
    for k, wkb in enumerate(geoms):
        g = shapely.from_wkb(wkb) if wkb is not None else None
        if g is not None and back is not None:
            g = shapely.transform(g, back)
        out_geoms.append(g)
        props.append({n: _plain(v[k]) for n, v in zip(meta["fields"], values, strict=True)})
    mode = "local" if back is None else "lonlat"
    return DefectLayer(p, out_geoms, props, origin, mode, {"crs": crs.name if crs else None, "layer": layer})


def _plain(v: object) -> object:
    if isinstance(v, np.integer):
        return int(v)
    if isinstance(v, np.floating):
        return None if np.isnan(v) else float(v)
    return v


def run_defects_path(run_dir: str | os.PathLike, which: str = "defects") -> tuple[Path, str]:
    """Where a run folder keeps its ``defects`` / ``baseline_defects``: the lon/lat GeoJSON of a
    georeferenced run, else the GeoPackage layer. Returns (path, layer); the path may not exist."""
    run = Path(run_dir)
    gj = run / f"{which}.geojson"
    if gj.is_file():
        return gj, which
    gpkg = run / SURVEY_GPKG
    return (gpkg, which) if gpkg.is_file() else (gj, which)


__all__ = ["DEFECTS_FGB", "EXTRA_FORMATS", "SURVEY_GPKG", "read_defect_layer", "run_defects_path",
           "survey_record", "trajectory_layer", "write_gis"]
