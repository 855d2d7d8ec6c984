"""Outputs people use: GeoJSON, GeoTIFF, CSV, figures and the self-contained HTML report.

``export`` is the only writer of a run folder's result files: :func:`write_run` (``pavemap run``)
and :func:`write_fusion_outputs` (``pavemap fuse``) write each file once; ``write_outputs`` writes
the outputs people use (and is usable alone, as is each writer).
Every file is written under a temporary name and renamed, so a partial file never looks complete;
``report.html`` is written last.
"""

from __future__ import annotations

from pavemap.export.geojson import instances_to_geojson, read_geojson, write_geojson
from pavemap.export.outputs import write_outputs, write_png
from pavemap.export.run_files import write_fusion_outputs, write_run
from pavemap.export.tables import to_dataframe, write_csv


def __getattr__(name: str):
    # lazy re-exports of the heavy writers (matplotlib / rasterio)
    if name == "write_geotiff":
        from pavemap.export.geotiff import write_geotiff

        return write_geotiff
    if name == "write_report":
        from pavemap.export.report import write_report

        return write_report
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


__all__ = ["instances_to_geojson", "read_geojson", "to_dataframe", "write_csv", "write_fusion_outputs",
           "write_geojson", "write_geotiff", "write_outputs", "write_png", "write_report", "write_run"]
