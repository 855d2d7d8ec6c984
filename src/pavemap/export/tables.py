"""Defects as a table: ``defects.csv`` and a DataFrame (pandas optional, never required)."""

from __future__ import annotations

import csv
import io
import os
from pathlib import Path

from pavemap.export.geojson import instance_properties
from pavemap.io.atomic import atomic_write_text
from pavemap.types import DefectInstance, GeoOrigin

CSV_COLUMNS = ("id", "code", "name", "cls", "priority", "severity", "severity_max", "confidence",
               "observations", "probability", "area_m2", "length_m", "x_m", "y_m")
GEO_COLUMNS = ("lon", "lat")
PRIORITY_RANK = {"repair now": 0, "inspect": 1, "no action": 2}


def records(instances: list[DefectInstance], geo_origin: GeoOrigin | None = None) -> list[dict]:
    """One flat dict per instance with the CSV columns (plus lon/lat with a geo origin), in id order."""
    cols = CSV_COLUMNS + (GEO_COLUMNS if geo_origin is not None else ())
    out = []
    for inst in sorted(instances, key=lambda i: i.id):
        p = instance_properties(inst, geo_origin)
        out.append({c: p.get(c) for c in cols})
    return out


def to_csv_text(instances: list[DefectInstance], geo_origin: GeoOrigin | None = None) -> str:
    cols = CSV_COLUMNS + (GEO_COLUMNS if geo_origin is not None else ())
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=list(cols), lineterminator="\n")
    w.writeheader()
    for r in records(instances, geo_origin):
        w.writerow({k: ("" if v is None else v) for k, v in r.items()})
    return buf.getvalue()


def write_csv(path: str | os.PathLike, instances: list[DefectInstance], geo_origin: GeoOrigin | None = None) -> Path:
    """Write ``defects.csv`` atomically (header only when there are no defects)."""
    return atomic_write_text(path, to_csv_text(instances, geo_origin))


def to_dataframe(instances: list[DefectInstance], geo_origin: GeoOrigin | None = None):
    """A pandas DataFrame of the defects when pandas is installed, else the list of row dicts."""
    rows = records(instances, geo_origin)
    try:
        import pandas as pd
    except ImportError:
        return rows
    cols = list(CSV_COLUMNS + (GEO_COLUMNS if geo_origin is not None else ()))
    return pd.DataFrame(rows, columns=cols)


__all__ = ["CSV_COLUMNS", "GEO_COLUMNS", "PRIORITY_RANK", "records", "to_csv_text", "to_dataframe", "write_csv"]
