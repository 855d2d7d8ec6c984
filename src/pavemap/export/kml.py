"""Defects and the drive as KML / KMZ (OGC KML 2.2; always WGS84 longitude, latitude).

Written as plain XML rather than through GDAL's LIBKML driver, which cannot add a second layer to
a KMZ it has written: one document, a ``defects`` folder (a Placemark per defect: MultiGeometry of
its polygons, styled by class, the defect schema as ExtendedData) and a ``trajectory`` folder.
"""

from __future__ import annotations

import os
import zipfile
from pathlib import Path
from xml.sax.saxutils import escape

import numpy as np

from pavemap.export.geojson import LONLAT_DECIMALS, _polygons, instance_properties
from pavemap.geo.tangent import local_tangent
from pavemap.io.atomic import atomic_path, atomic_write_text
from pavemap.palette import DEFECT_HEX
from pavemap.types import DEFECT_CODES, DefectInstance, GeoOrigin, Sequence


def _abgr(hex_rgb: str, alpha: int) -> str:
    h = hex_rgb.lstrip("#")
    return f"{alpha:02x}{h[4:6]}{h[2:4]}{h[0:2]}"


def _coords(xy: np.ndarray, lt) -> str:  # noqa: ANN001
    lon, lat = lt.to_lonlat(xy[:, 0], xy[:, 1])
    return " ".join(f"{a:.{LONLAT_DECIMALS}f},{b:.{LONLAT_DECIMALS}f}" for a, b in zip(lon, lat, strict=True))


def _polygon_xml(poly: object, lt) -> str:  # noqa: ANN001
    def ring(tag: str, c: object) -> str:
        return (f"<{tag}><LinearRing><coordinates>{_coords(np.asarray(c.coords), lt)}</coordinates>"
                f"</LinearRing></{tag}>")

    inner = "".join(ring("innerBoundaryIs", r) for r in poly.interiors)  # type: ignore[attr-defined]
    return f"<Polygon>{ring('outerBoundaryIs', poly.exterior)}{inner}</Polygon>"  # type: ignore[attr-defined]


def kml_text(instances: list[DefectInstance], geo_origin: GeoOrigin, seq: Sequence | None = None,
             title: str = "pavemap survey") -> str:
    """The KML document of the defects (and the drive when ``seq`` is given)."""
    lt = local_tangent(geo_origin)
    styles = "".join(
        f'<Style id="{c}"><LineStyle><color>{_abgr(DEFECT_HEX[c], 255)}</color><width>2</width></LineStyle>'
        f"<PolyStyle><color>{_abgr(DEFECT_HEX[c], 128)}</color></PolyStyle></Style>" for c in DEFECT_CODES)
    marks = []
    for inst in instances:
        polys = _polygons(inst.polygon)
        if not polys:
            continue
        props = instance_properties(inst, geo_origin)
        data = "".join(f'<Data name="{escape(k)}"><value>{escape(str(v))}</value></Data>'
                       for k, v in props.items() if v is not None)
        geom = "".join(_polygon_xml(p, lt) for p in polys)
        level = props.get("severity_level")  # urgency first, then how bad (when assessed)
        what = f"{escape(inst.priority)}" + (f", {escape(str(level))} severity" if level else "")
        marks.append(f"<Placemark><name>{inst.code} #{inst.id}</name><description>{escape(inst.name)}: "
                     f"{what}</description><styleUrl>#{inst.code}</styleUrl>"
                     f"<ExtendedData>{data}</ExtendedData><MultiGeometry>{geom}</MultiGeometry></Placemark>")
    track = ""
    if seq is not None and len(seq.frames) > 1:
        track = (f"<Folder><name>trajectory</name><Placemark><name>{escape(seq.name)}</name><LineString>"
                 f"<tessellate>1</tessellate><coordinates>{_coords(seq.trajectory()[:, :2], lt)}</coordinates>"
                 "</LineString></Placemark></Folder>")
    return ('<?xml version="1.0" encoding="UTF-8"?>\n<kml xmlns="http://www.opengis.net/kml/2.2"><Document>'
            f"<name>{escape(title)}</name>{styles}<Folder><name>defects</name>{''.join(marks)}</Folder>"
            f"{track}</Document></kml>\n")


def write_kml(path: str | os.PathLike, instances: list[DefectInstance], geo_origin: GeoOrigin,
              seq: Sequence | None = None) -> Path:
    """``.kml`` (text) or ``.kmz`` (zipped ``doc.kml``), atomically."""
    p = Path(path)
    title = f"pavemap survey — {seq.name}" if seq is not None else "pavemap survey"
    text = kml_text(instances, geo_origin, seq, title)
    if p.suffix.lower() != ".kmz":
        return atomic_write_text(p, text)
    with atomic_path(p) as tmp, zipfile.ZipFile(tmp, "w", zipfile.ZIP_DEFLATED) as z:
        z.writestr("doc.kml", text)
    return p


__all__ = ["kml_text", "write_kml"]
