"""Defects as a table: ``defects.csv`` and a DataFrame (pandas optional, never required)."""

from __future__ import annotations

import csv
import io
import os
from pathlib import Path

from pavemap.export.geojson import PROPERTY_SCHEMA, instance_properties
from pavemap.io.atomic import atomic_write_text
from pavemap.maintain.policy import PRIORITIES
from pavemap.types import UNASSESSED, DefectInstance, GeoOrigin

# What a road engineer reads first: which defect, how urgent, what, how bad, how big, where.
_LEAD = ("id", "priority", "priority_rank", "code", "name", "severity_level", "area_m2", "length_m",
         "crack_length_m", "depth_max_mm", "chainage_m")
GEO_COLUMNS = ("lat", "lon")
#: every other key of the defect schema follows, in schema order (so the CSV cannot drift from it)
CSV_COLUMNS = _LEAD + tuple(n for n, *_ in PROPERTY_SCHEMA if n not in _LEAD and n not in GEO_COLUMNS)
#: urgency order of the priority texts (0 = most urgent); sort by ``priority_rank`` within one
PRIORITY_RANK = {**{p: k for k, p in enumerate(PRIORITIES)}, UNASSESSED: len(PRIORITIES)}


def columns(geo: bool) -> tuple[str, ...]:
    """The CSV columns; with a geo origin lat/lon follow the chainage."""
    if not geo:
        return CSV_COLUMNS
    k = len(_LEAD)
    return CSV_COLUMNS[:k] + GEO_COLUMNS + CSV_COLUMNS[k:]


def records(instances: list[DefectInstance], geo_origin: GeoOrigin | None = None) -> list[dict]:
    """One flat dict per instance with the CSV columns (plus lat/lon with a geo origin), in id order."""
    cols = columns(geo_origin is not None)
    out = []
    for inst in sorted(instances, key=lambda i: i.id):
        p = instance_properties(inst, geo_origin)
        out.append({c: p.get(c) for c in cols})
    return out


def to_csv_text(instances: list[DefectInstance], geo_origin: GeoOrigin | None = None) -> str:
    cols = columns(geo_origin is not None)
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
    cols = list(columns(geo_origin is not None))
    return pd.DataFrame(rows, columns=cols)


__all__ = ["CSV_COLUMNS", "GEO_COLUMNS", "PRIORITY_RANK", "columns", "records", "to_csv_text", "to_dataframe",
           "write_csv"]
