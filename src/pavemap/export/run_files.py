"""The files of a run folder: stage results in, each file written once, atomically.

Stages return results and write nothing; these functions are the only writers of a run folder's
result files (``pavemap run`` through :func:`write_run`, ``pavemap fuse`` through
:func:`write_fusion_outputs`). ``metrics.json`` is written last: a folder holding it is complete.

Coordinates: GeoJSON is WGS84 longitude/latitude only (RFC 7946), so ``defects.geojson`` and
``baseline_defects.geojson`` are written only when the sequence has a geo origin. ``survey.gpkg``
(:mod:`pavemap.export.gis`) is always written: in the drive's UTM zone (or ``output.crs``) with a geo
origin, else in an explicit local engineering CRS, so a run without a geo origin has no layer that
GIS tools read as EPSG:4326. Every record also carries its centre in local metres (``x_m``, ``y_m``).
Readers (evaluation, ``pavemap compare``) bring geometries back to world metres through
:func:`pavemap.export.gis.read_defect_layer` (GeoJSON or GeoPackage).
"""

from __future__ import annotations

import json
import os
import time
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from pavemap.export.geojson import write_geojson
from pavemap.io.atomic import atomic_path, atomic_write_json, atomic_write_text
from pavemap.types import DEFECT_CODES, GeoOrigin

if TYPE_CHECKING:
    from pavemap.fuse import FusionResult

DEFECTS = "defects.geojson"
BASELINE = "baseline_defects.geojson"
DETECTIONS_MAPPED = "detections_mapped.jsonl"
MAP_GRID = "defect_map.json"
METRICS = "metrics.json"
EVAL = "eval.json"
SEGMENTS_CSV = "segments.csv"  # road segments with their PCI-like index (pavemap.maintain.segments)
SEGMENTS_GEOJSON = "segments.geojson"


def write_npy(path: str | os.PathLike, a: np.ndarray) -> Path:
    """Save one array as ``.npy`` atomically."""
    with atomic_path(path) as tmp, open(tmp, "wb") as fh:
        np.save(fh, a)
    return Path(path)


def surveyed_area(seq: object | None, result: FusionResult, surface: object | None = None
                  ) -> tuple[np.ndarray | None, object | None]:
    """The surveyed cells of the maps' grid (H, W) bool and their outline (world metres); (None, None)
    without a sequence (everything counts as surveyed then)."""
    if seq is None or not getattr(seq, "frames", None):
        return None, None
    from pavemap.geo.coverage import coarse_coverage, coverage_mask, coverage_polygon

    coarse, g = coarse_coverage(seq, result.grid, surface)
    return coverage_mask(seq, result.grid, surface), coverage_polygon(coarse, g)


def write_fusion_files(out_dir: str | os.PathLike, result: FusionResult,
                       geo_origin: GeoOrigin | None = None, *, seq: object | None = None,
                       surveyed: object | None = None, output: object | None = None) -> dict[str, Path]:
    """Stage 3's files: the defect layers, the maps (.npy + their grid), the detection records.

    Layers: ``survey.gpkg`` always, defects + baseline GeoJSON with a geo origin (module docstring);
    the road segments (``result.segments``) as ``segments.csv`` always, ``segments.geojson`` with a geo origin;
    ``output`` (OutputConfig or dict) gives ``crs``, ``extra_formats`` and ``vehicle``.
    ``defect_map.npy`` (H, W) float32 and ``defect_map_<code>.npy`` on the grid in ``defect_map.json``
    (``GridSpec.to_dict``, plus the vertex grid of ``vertex_prob.npy`` under ``surface``).
    """
    from pavemap.export.gis import write_gis
    from pavemap.export.segments import write_segments_csv, write_segments_geojson

    out = Path(out_dir)
    paths: dict[str, Path] = {}
    segments = list(getattr(result, "segments", None) or [])
    if geo_origin is not None:
        paths[DEFECTS] = write_geojson(out / DEFECTS, result.instances, geo_origin)
        paths[BASELINE] = write_geojson(out / BASELINE, result.baseline, geo_origin)
        paths[SEGMENTS_GEOJSON] = write_segments_geojson(out / SEGMENTS_GEOJSON, segments, geo_origin)
    paths[SEGMENTS_CSV] = write_segments_csv(out / SEGMENTS_CSV, segments)  # always, like survey.gpkg
    paths.update(write_gis(out, result.instances, baseline=result.baseline, geo_origin=geo_origin,
                           crs=_opt(output, "crs", "auto"), seq=seq, surveyed=surveyed,
                           formats=tuple(_opt(output, "extra_formats", ())), vehicle=_opt(output, "vehicle", ""),
                           segments=segments))
    paths["defect_map.npy"] = write_npy(out / "defect_map.npy", result.prob_map.astype(np.float32))
    for k, code in enumerate(DEFECT_CODES):
        name = f"defect_map_{code}.npy"
        paths[name] = write_npy(out / name, result.class_maps[k].astype(np.float32))
    paths["vertex_prob.npy"] = write_npy(out / "vertex_prob.npy", result.vertex_prob)
    paths[MAP_GRID] = atomic_write_json(out / MAP_GRID, {
        **result.grid.to_dict(), "surface": result.surface_grid.to_dict(),
        "note": "cell [r, c] centre at (x0 + c*res, y0 + r*res)"})
    paths[DETECTIONS_MAPPED] = atomic_write_text(
        out / DETECTIONS_MAPPED, "".join(json.dumps(r, allow_nan=False) + "\n" for r in result.detections))
    return paths


def write_eval(out_dir: str | os.PathLike, evaluation: dict) -> Path:
    """``eval.json``: the ground-truth scores of a run (``pavemap eval`` on a finished folder)."""
    return atomic_write_json(Path(out_dir) / EVAL, evaluation)


def _opt(output: object | None, name: str, default):  # noqa: ANN001, ANN202
    if output is None:
        return default
    return output.get(name, default) if isinstance(output, dict) else getattr(output, name, default)


def write_fusion_outputs(out_dir: str | os.PathLike, result: FusionResult, geo_origin: GeoOrigin | None = None,
                         evaluation: dict | None = None, metrics: dict | None = None, *, seq: object | None = None,
                         surface: object | None = None, output: object | None = None) -> dict[str, Path]:
    """The folder of ``pavemap fuse``: stage 3's files, the map GeoTIFF and CSV, ``eval.json`` (with an
    evaluation), ``metrics.json`` last. ``seq`` and ``surface`` give the trajectory and surveyed area."""
    from pavemap.export.evidence import write_evidence
    from pavemap.export.geotiff import write_geotiff
    from pavemap.export.tables import write_csv

    out = Path(out_dir)
    valid, area = surveyed_area(seq, result, surface)
    # evidence first: the layers and the CSV carry each defect's photo path (or why there is none)
    evidence = write_evidence(out, result.instances, result.detections, seq)  # type: ignore[arg-type]
    paths = write_fusion_files(out, result, geo_origin, seq=seq, surveyed=area, output=output)
    paths.update(evidence)
    paths["defects.csv"] = write_csv(out / "defects.csv", result.instances, geo_origin)
    paths["defect_map.tif"] = write_geotiff(out / "defect_map.tif", result.prob_map, result.class_maps, result.grid,
                                            geo_origin, crs=_opt(output, "crs", "auto"), valid=valid,
                                            name=getattr(seq, "name", ""))
    if evaluation is not None:
        paths[EVAL] = write_eval(out, evaluation)
    paths[METRICS] = atomic_write_json(out / METRICS, metrics if metrics is not None else result.metrics)
    return paths


def write_run(out_dir: str | os.PathLike, result: FusionResult, metrics: dict, *, seq: object | None = None,
              geo_origin: GeoOrigin | None = None, evaluation: dict | None = None, config: dict | None = None,
              output: object | None = None, bev_rgb: np.ndarray | None = None,
              bev_semantic: np.ndarray | None = None, mesh_grid: object | None = None,
              mesh_path: str | os.PathLike | None = None, progress: bool = True,
              surface: object | None = None) -> dict[str, Path]:
    """Every result file of ``pavemap run``: stage 3's files, eval.json, the outputs people use, metrics.json.

    ``metrics['seconds']`` gains ``export`` and ``total`` (the sum of the stages) before
    ``metrics.json`` is written, last. ``surface`` (the road HeightField) places the surveyed area.
    """
    from pavemap.export.evidence import write_evidence
    from pavemap.export.outputs import write_outputs

    t = time.perf_counter()
    out = Path(out_dir)
    valid, area = surveyed_area(seq, result, surface)
    # evidence first: the layers, the CSV and the report carry each defect's photo (or why there is none)
    evidence = write_evidence(out, result.instances, result.detections, seq)  # type: ignore[arg-type]
    paths = write_fusion_files(out, result, geo_origin, seq=seq, surveyed=area, output=output)
    paths.update(evidence)
    if evaluation is not None:
        paths[EVAL] = write_eval(out, evaluation)
    written = {**paths, METRICS: out / METRICS}  # listed in the report; metrics.json follows it
    paths.update(write_outputs(
        out, instances=result.instances, prob_map=result.prob_map, class_maps=result.class_maps, grid=result.grid,
        bev_rgb=bev_rgb, bev_semantic=bev_semantic, mesh_grid=mesh_grid, geo_origin=geo_origin, metrics=metrics,
        config=config, detections=result.detections, seq=seq, output=output, mesh_path=mesh_path,
        progress=progress, written=written, valid=valid, segments=getattr(result, "segments", None),
    ))
    seconds = metrics.setdefault("seconds", {})
    seconds["export"] = round(time.perf_counter() - t, 3)
    seconds["total"] = round(sum(v for k, v in seconds.items() if k != "total"), 3)
    paths[METRICS] = atomic_write_json(out / METRICS, metrics)
    return paths


__all__ = ["surveyed_area", "write_eval", "write_fusion_files", "write_fusion_outputs", "write_npy", "write_run"]
