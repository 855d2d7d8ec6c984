"""The files of a run folder: stage results in, each file written once, atomically.

Stages return results and write nothing; these functions are the only writers of a run folder's
result files (``pavemap run`` through :func:`write_run`, ``pavemap fuse`` through
:func:`write_fusion_outputs`). ``metrics.json`` is written last: a folder holding it is complete.

Coordinates: ``defects.geojson`` and ``baseline_defects.geojson`` are WGS84 lon/lat when the
sequence has a geo origin, else local world metres, stated in their ``pavemap`` member together
with the origin; every feature also carries its centre in local metres (``x_m``, ``y_m``). Readers
(evaluation, ``pavemap compare``) bring geometries back to world metres through
:func:`pavemap.export.geojson.read_geojson`.
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


def write_npy(path: str | os.PathLike, a: np.ndarray) -> Path:
    """Save one array as ``.npy`` atomically."""
    with atomic_path(path) as tmp, open(tmp, "wb") as fh:
        np.save(fh, a)
    return Path(path)


def write_fusion_files(out_dir: str | os.PathLike, result: FusionResult,
                       geo_origin: GeoOrigin | None = None) -> dict[str, Path]:
    """Stage 3's files: defects + baseline GeoJSON, the maps (.npy + their grid), the detection records.

    ``defect_map.npy`` (H, W) float32 and ``defect_map_<code>.npy`` on the grid in ``defect_map.json``
    (``GridSpec.to_dict``, plus the vertex grid of ``vertex_prob.npy`` under ``surface``).
    """
    out = Path(out_dir)
    paths = {
        DEFECTS: write_geojson(out / DEFECTS, result.instances, geo_origin),
        BASELINE: write_geojson(out / BASELINE, result.baseline, geo_origin),
        "defect_map.npy": write_npy(out / "defect_map.npy", result.prob_map.astype(np.float32)),
    }
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


def write_fusion_outputs(out_dir: str | os.PathLike, result: FusionResult, geo_origin: GeoOrigin | None = None,
                         evaluation: dict | None = None, metrics: dict | None = None) -> dict[str, Path]:
    """The folder of ``pavemap fuse``: stage 3's files, ``eval.json`` (with an evaluation), ``metrics.json`` last."""
    out = Path(out_dir)
    paths = write_fusion_files(out, result, geo_origin)
    if evaluation is not None:
        paths[EVAL] = write_eval(out, evaluation)
    paths[METRICS] = atomic_write_json(out / METRICS, metrics if metrics is not None else result.metrics)
    return paths


def write_run(out_dir: str | os.PathLike, result: FusionResult, metrics: dict, *, seq: object | None = None,
              geo_origin: GeoOrigin | None = None, evaluation: dict | None = None, config: dict | None = None,
              output: object | None = None, bev_rgb: np.ndarray | None = None,
              bev_semantic: np.ndarray | None = None, mesh_grid: object | None = None,
              mesh_path: str | os.PathLike | None = None, progress: bool = True) -> dict[str, Path]:
    """Every result file of ``pavemap run``: stage 3's files, eval.json, the outputs people use, metrics.json.

    ``metrics['seconds']`` gains ``export`` and ``total`` (the sum of the stages) before
    ``metrics.json`` is written, last.
    """
    from pavemap.export import write_outputs

    t = time.perf_counter()
    out = Path(out_dir)
    paths = write_fusion_files(out, result, geo_origin)
    if evaluation is not None:
        paths[EVAL] = write_eval(out, evaluation)
    written = {**paths, METRICS: out / METRICS}  # listed in the report; metrics.json follows it
    paths.update(write_outputs(
        out, instances=result.instances, prob_map=result.prob_map, class_maps=result.class_maps, grid=result.grid,
        bev_rgb=bev_rgb, bev_semantic=bev_semantic, mesh_grid=mesh_grid, geo_origin=geo_origin, metrics=metrics,
        config=config, detections=result.detections, seq=seq, output=output, mesh_path=mesh_path,
        progress=progress, written=written,
    ))
    seconds = metrics.setdefault("seconds", {})
    seconds["export"] = round(time.perf_counter() - t, 3)
    seconds["total"] = round(sum(v for k, v in seconds.items() if k != "total"), 3)
    paths[METRICS] = atomic_write_json(out / METRICS, metrics)
    return paths


__all__ = ["write_eval", "write_fusion_files", "write_fusion_outputs", "write_npy", "write_run"]
