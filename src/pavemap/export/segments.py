"""The maintenance segments as files: ``segments.csv`` (always) and ``segments.geojson`` (georeferenced runs).

The records and the CSV text are :mod:`pavemap.maintain.segments`'; writing them is the export's.
"""

from __future__ import annotations

import os
from pathlib import Path

from pavemap.maintain.segments import Segment, segment_records, segments_csv_text


def write_segments_csv(path: str | os.PathLike, segments: list[Segment]) -> Path:
    """Write ``segments.csv`` atomically; returns its path."""
    from pavemap.io.atomic import atomic_write_text

    return atomic_write_text(path, segments_csv_text(segments))


def write_segments_geojson(path: str | os.PathLike, segments: list[Segment], geo_origin: object) -> Path:
    """``segments.geojson``: the corridors as WGS84 polygons with the segment records (georeferenced runs only)."""
    from pavemap.export.geojson import features_to_geojson
    from pavemap.io.atomic import atomic_write_json

    fc = features_to_geojson([s.polygon for s in segments], segment_records(segments), geo_origin,  # type: ignore[arg-type]
                             ids=[s.id for s in segments],
                             meta={"format": "pavemap-segments/1", "count": len(segments),
                                   "index": "PCI-like, not a certified ASTM D6433 survey"})
    return atomic_write_json(path, fc, indent=None)


__all__ = ["write_segments_csv", "write_segments_geojson"]
