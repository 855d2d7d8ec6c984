"""Defect instances as an RFC 7946 GeoJSON FeatureCollection.

Two coordinate modes:
- ``lonlat``: WGS84 longitude, latitude (RFC 7946 proper) when the sequence has a geo origin;
- ``local``: world x, y metres (SPEC §0) otherwise. RFC 7946 removed the ``crs`` member, so we
  do not write one; the frame is stated in a ``pavemap`` foreign member (RFC 7946 §6.1), which
  also carries the geo origin so a reader can go back to world metres exactly.

Exterior rings are counter-clockwise and holes clockwise (RFC 7946 §3.1.6 right-hand rule).
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import shapely
from shapely.geometry import MultiPolygon, Polygon, shape
from shapely.geometry.polygon import orient

from pavemap.errors import PavemapError
from pavemap.geo.tangent import local_tangent, origin_from_dict, origin_to_dict
from pavemap.io.atomic import atomic_write_json
from pavemap.types import DEFECT_CODES, DEFECT_NAMES, DefectInstance, GeoOrigin

FORMAT = "pavemap-defects/1"
# 1e-8 degree is about 1 mm, like 1e-3 m: well below the 0.1 m mesh resolution
LONLAT_DECIMALS = 8
METRE_DECIMALS = 3
# The one property schema of a defect, in every GeoJSON and CSV pavemap writes (docs/guide/outputs.md, "Defect schema").
# (name, type, unit, meaning); the synthetic truth carries the subset it knows (id, cls, code, name,
# area_m2, length_m, x_m, y_m) plus its own generator fields.
PROPERTY_SCHEMA: tuple[tuple[str, str, str, str], ...] = (
    ("id", "int", "", "defect number within the file, from 1 (truth: from 0)"),
    ("cls", "int", "", "class index 0 D00, 1 D10, 2 D20, 3 D40 (majority vote of its observations)"),
    ("code", "str", "", "RDD2022 class code: D00, D10, D20 or D40"),
    ("name", "str", "", "readable class name (longitudinal crack, transverse crack, alligator crack, pothole)"),
    ("paper_severity", "float", "0-1", "the paper's EMA severity (mean of class weights over the defect's "
     "vertices; for the paper metrics, not the maintenance severity_level)"),
    ("paper_severity_max", "float", "0-1", "largest vertex EMA severity"),
    ("confidence", "float", "0-1", "highest detector confidence among its observations"),
    ("observations", "int", "count", "distinct detections fused into it"),
    ("probability", "float", "0-1", "peak fused defect probability P of its vertices"),
    ("area_m2", "float", "m²", "area on the road: potholes (D40) and alligator cracking (D20) the measured size, "
     "weighted median over its detections of the box footprint on the road x pi/4 (a box bounds its defect; a "
     "pothole or patch fills about the inscribed ellipse); elsewhere the fused vertices' area (mapped_area_m2)"),
    ("length_m", "float", "m", "longest extent (principal axis) of the polygon"),
    ("priority", "str", "", "urgency by the maintenance policy: repair now / schedule / monitor "
     "(unassessed before pavemap.maintain runs); sort by priority_rank"),
    ("x_m", "float", "m", "centre x in the local world frame (SPEC §0), exact in every file"),
    ("y_m", "float", "m", "centre y in the local world frame"),
    ("lon", "float", "degree", "centre WGS84 longitude (only with a geo origin)"),
    ("lat", "float", "degree", "centre WGS84 latitude (only with a geo origin)"),
    ("observed", "bool", "", "its centre lies where the mesh height was measured (a ground point or depth sample "
     "within 2 m; false: the road carried along from where it was, the position less certain; absent with a mesh "
     "without the observed layer)"),
    ("texture_contested", "bool", "", "its centre lies where the BEV texture may hold a vehicle (views disagree "
     "with the texture there, bev_contested.npy): a detection may have fired on a vehicle; check its photo; "
     "absent with a mesh without the texture check)"),
    # maintenance measures (issue 16, pavemap.maintain); absent where not assessed
    ("severity_level", "str", "", "low / medium / high by the maintenance policy (pavemap.maintain.policy)"),
    ("certainty", "str", "", "confirmed / probable / single sighting (probability and observation count)"),
    ("priority_rank", "int", "", "1 = most urgent; sorting by it sorts by urgency"),
    ("urgency_score", "float", "", "the policy's urgency score (severity x class x lane position x size)"),
    ("chainage_m", "float", "m", "distance along the driven route from its first frame to the defect's centre"),
    ("offset_m", "float", "m", "signed lateral offset of the centre from the route (+ left of travel)"),
    ("lane_position", "str", "", "wheel path / lane centre / edge (from the offset and the lane width)"),
    ("segment", "int", "", "road segment id (pavemap.maintain.segments), from 1 along the route"),
    ("depth_max_mm", "float", "mm", "pothole: deepest point below the local road plane (null: not measurable)"),
    ("depth_mean_mm", "float", "mm", "pothole: mean depth over its footprint (null: not measurable)"),
    ("volume_l", "float", "litre", "pothole: volume below the local road plane (null: not measurable)"),
    ("depth_sigma_mm", "float", "mm", "pothole: 1-sigma uncertainty of the depth (plane fit and mesh residual)"),
    ("measurable", "bool", "", "whether the surface under the defect was observed well enough to measure it"),
    ("measure_note", "str", "", "why a measure is missing (e.g. unobserved ground, at the mesh edge)"),
    ("mapped_area_m2", "float", "m²", "area of the fused vertices (vertices x cell area), i.e. of the polygon"),
    ("crack_length_m", "float", "m", "crack: weighted median over its detections of the footprint's longer "
     "mid-line on the road (skeleton_length_m where no detection gave a footprint)"),
    ("skeleton_length_m", "float", "m", "crack: length along the skeleton of the fused vertices"),
    ("size_views", "int", "count", "detections whose ground footprint measured the size (area_m2, crack_length_m)"),
    ("orientation_deg", "float", "degree", "crack: angle between the crack and the route (0 along, 90 across)"),
    ("orientation_ok", "bool", "", "crack: whether the orientation agrees with the class (D00 along, D10 across)"),
    ("evidence", "str", "", "relative path of the best view's crop with the box drawn (evidence/<id>.jpg)"),
    ("evidence_note", "str", "", "why there is no evidence photo"),
)
PROPERTY_KEYS = tuple(name for name, *_ in PROPERTY_SCHEMA[:12])


def _num(v: object, nd: int = 4) -> float | None:
    """A JSON-safe rounded float (None for NaN/inf)."""
    f = float(v)  # type: ignore[arg-type]
    return round(f, nd) if math.isfinite(f) else None


def instance_properties(inst: DefectInstance, geo_origin: GeoOrigin | None = None) -> dict:
    """The flat property record of one instance (also the CSV row and the report's table row)."""
    cx, cy = float(inst.centroid[0]), float(inst.centroid[1])
    props: dict = {
        "id": int(inst.id),
        "cls": int(inst.cls),
        "code": inst.code,
        "name": inst.name,
        "paper_severity": _num(inst.severity_mean),
        "paper_severity_max": _num(inst.severity_max),
        "confidence": _num(inst.confidence),
        "observations": int(inst.observations),
        "probability": _num(inst.probability),
        "area_m2": _num(inst.area_m2),
        "length_m": _num(inst.length_m, 3),
        "priority": str(inst.priority),
        "x_m": _num(cx, METRE_DECIMALS),
        "y_m": _num(cy, METRE_DECIMALS),
    }
    if geo_origin is not None:
        lon, lat = local_tangent(geo_origin).to_lonlat(np.array([cx]), np.array([cy]))
        props["lon"] = _num(lon[0], LONLAT_DECIMALS + 1)
        props["lat"] = _num(lat[0], LONLAT_DECIMALS + 1)
    # stage-specific extras (e.g. matched truth id) pass through when JSON-simple and not clashing
    for k, v in (inst.extra or {}).items():
        if k in props:
            continue
        if isinstance(v, (bool, int, str)) or v is None:
            props[k] = v
        elif isinstance(v, (float, np.floating)):
            props[k] = _num(v)
        elif isinstance(v, np.integer):
            props[k] = int(v)
    return props


def _ring(coords: np.ndarray, nd: int) -> list[list[float]] | None:
    """(N, 2) closed ring -> rounded positions without repeated points; None when degenerate."""
    r = np.round(np.asarray(coords, dtype=np.float64)[:, :2], nd)
    keep = np.ones(len(r), dtype=bool)
    keep[1:] = np.any(r[1:] != r[:-1], axis=1)
    r = r[keep]
    if len(r) and np.any(r[0] != r[-1]):
        r = np.vstack([r, r[:1]])
    if len(r) < 4:
        return None
    return r.tolist()


def _polygons(geom: object) -> list[Polygon]:
    if geom is None or getattr(geom, "is_empty", True):
        return []
    if isinstance(geom, Polygon):
        return [geom]
    if isinstance(geom, MultiPolygon):
        return list(geom.geoms)
    if hasattr(geom, "geoms"):  # GeometryCollection: keep its areal parts
        return [p for g in geom.geoms for p in _polygons(g)]
    return []


def geometry_to_geojson(geom: object, nd: int) -> dict | None:
    """A shapely (Multi)Polygon -> a GeoJSON geometry dict with RFC 7946 winding, rounded to ``nd``."""
    polys = []
    for p in _polygons(geom):
        p = orient(p, sign=1.0)  # exterior CCW, interiors CW
        ext = _ring(np.asarray(p.exterior.coords), nd)
        if ext is None:
            continue
        holes = [h for h in (_ring(np.asarray(i.coords), nd) for i in p.interiors) if h is not None]
        polys.append([ext, *holes])
    if not polys:
        return None
    if len(polys) == 1:
        return {"type": "Polygon", "coordinates": polys[0]}
    return {"type": "MultiPolygon", "coordinates": polys}


def _bbox(features: list[dict]) -> list[float] | None:
    pts = [np.asarray(ring, dtype=np.float64)
           for f in features if f["geometry"] is not None
           for poly in ([f["geometry"]["coordinates"]] if f["geometry"]["type"] == "Polygon"
                        else f["geometry"]["coordinates"])
           for ring in poly]
    if not pts:
        return None
    a = np.vstack(pts)
    return [float(a[:, 0].min()), float(a[:, 1].min()), float(a[:, 0].max()), float(a[:, 1].max())]


def features_to_geojson(geometries: list[object], properties: list[dict], geo_origin: GeoOrigin | None = None,
                        ids: list[int] | None = None, meta: dict | None = None) -> dict:
    """The codec: shapely geometries in world metres + property dicts -> an RFC 7946 FeatureCollection.

    With ``geo_origin`` the coordinates are WGS84 lon/lat (RFC 7946 proper); without one they stay
    local world metres, stated in the ``pavemap`` member (``coordinates: local``). Every GeoJSON the
    project writes (run defects, baseline, synthetic truth, survey changes) goes through here;
    ``meta`` adds to (or overrides, e.g. ``format``) the ``pavemap`` member.
    """
    lt = local_tangent(geo_origin) if geo_origin is not None else None
    nd = LONLAT_DECIMALS if lt is not None else METRE_DECIMALS
    features = []
    for k, (geom, props) in enumerate(zip(geometries, properties, strict=True)):
        if lt is not None and geom is not None and not geom.is_empty:
            geom = lt.geometry_to_lonlat(geom)
        features.append({
            "type": "Feature",
            "id": int(ids[k]) if ids is not None else int(props.get("id", k)),
            "geometry": geometry_to_geojson(geom, nd),
            "properties": props,
        })
    fc: dict = {"type": "FeatureCollection"}
    bbox = _bbox(features)
    if bbox is not None:
        fc["bbox"] = [round(b, nd) for b in bbox]
    fc["pavemap"] = {
        "format": FORMAT,
        "coordinates": "lonlat" if lt is not None else "local",
        "frame": ("WGS84 longitude, latitude (degrees)" if lt is not None else
                  "local world frame x, y in metres (SPEC §0); not WGS84"),
        "units": "degree" if lt is not None else "metre",
        "geo_origin": origin_to_dict(geo_origin),
        "count": len(features),
        "codes": {c: DEFECT_NAMES[c] for c in DEFECT_CODES},
        **(meta or {}),
    }
    fc["features"] = features
    return fc


def instances_to_geojson(instances: list[DefectInstance], geo_origin: GeoOrigin | None = None) -> dict:
    """RFC 7946 FeatureCollection dict of ``instances`` (lon/lat when ``geo_origin`` is given)."""
    return features_to_geojson([inst.polygon for inst in instances],
                               [instance_properties(inst, geo_origin) for inst in instances], geo_origin)


def write_geojson(path: str | os.PathLike, instances: list[DefectInstance],
                  geo_origin: GeoOrigin | None = None) -> Path:
    """Write ``defects.geojson`` atomically; returns its path."""
    return atomic_write_json(path, instances_to_geojson(instances, geo_origin), indent=None)


@dataclass
class DefectLayer:
    """A defects.geojson read back: geometries in world metres plus their properties."""

    path: Path
    geometries: list[object]  # shapely geometries, world x, y metres (may be None)
    properties: list[dict]
    geo_origin: GeoOrigin | None = None
    coordinates: str = "local"  # "local" | "lonlat" as written in the file
    meta: dict = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.properties)


def _origin_for_lonlat(features: list, p: Path) -> GeoOrigin | None:
    pts = []
    for f in features:
        g = f.get("geometry") if isinstance(f, dict) else None
        if g:
            try:
                pts.append(np.asarray(shape(g).bounds, dtype=np.float64).reshape(2, 2))
            except (ValueError, TypeError, AttributeError, KeyError, shapely.errors.GEOSException):
                continue
    if not pts:
        return None
    a = np.vstack(pts)
    lon, lat = (a.min(0) + a.max(0)) / 2
    return origin_from_dict({"lat": float(lat), "lon": float(lon)}, where=f"{p}: coordinates")


def read_geojson(path: str | os.PathLike) -> DefectLayer:
    """Read a pavemap defects GeoJSON (or any Polygon FeatureCollection) back into world metres.

    A file without a ``pavemap`` member is taken as local metres (like ``truth/defects.geojson``).
    A lon/lat file without an origin gets one at its bounding-box centre (heading 90, x east).
    """
    p = Path(path)
    from pavemap.errors import SequenceError
    from pavemap.io.schema import load_json  # the one JSON reader of user files: duplicate keys refused

    if not p.exists():
        raise PavemapError(f"{p}: file not found")
    try:
        doc = load_json(p)
    except SequenceError as e:
        raise PavemapError(str(e)) from None
    if not isinstance(doc, dict) or doc.get("type") != "FeatureCollection" or not isinstance(
            doc.get("features"), list):
        raise PavemapError(f"{p}: not a GeoJSON FeatureCollection")
    meta = doc.get("pavemap") if isinstance(doc.get("pavemap"), dict) else {}
    origin = origin_from_dict(meta.get("geo_origin"), where=f"{p}: pavemap.geo_origin")
    mode = meta.get("coordinates", "lonlat" if origin is not None else "local")
    if mode not in ("local", "lonlat"):
        raise PavemapError(f"{p}: pavemap.coordinates must be 'local' or 'lonlat', got {mode!r}")
    if mode == "lonlat" and origin is None:
        # lon/lat without an origin (e.g. edited in a GIS): use the bbox centre, x east, y north
        origin = _origin_for_lonlat(doc["features"], p)
    lt = local_tangent(origin) if (origin is not None and mode == "lonlat") else None
    geoms, props = [], []
    for i, f in enumerate(doc["features"]):
        if not isinstance(f, dict) or f.get("type") != "Feature":
            raise PavemapError(f"{p}: feature {i} is not a GeoJSON Feature")
        g = f.get("geometry")
        try:
            geom = shape(g) if g else None
        except (ValueError, TypeError, AttributeError, KeyError, shapely.errors.GEOSException) as e:
            raise PavemapError(f"{p}: feature {i} has an invalid geometry ({e})") from None
        if geom is not None and lt is not None:
            geom = lt.geometry_from_lonlat(geom)
        if geom is not None and not geom.is_valid:
            geom = shapely.make_valid(geom)
        geoms.append(geom)
        pr = dict(f.get("properties") or {})
        pr.setdefault("id", f.get("id", i))
        props.append(pr)
    return DefectLayer(p, geoms, props, origin, mode, dict(meta))


__all__ = ["FORMAT", "PROPERTY_KEYS", "PROPERTY_SCHEMA", "DefectLayer", "features_to_geojson", "geometry_to_geojson",
           "instance_properties", "instances_to_geojson", "read_geojson", "write_geojson"]
