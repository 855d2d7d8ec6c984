"""End to end: stage 1 (mesh) -> detection -> filter -> fusion -> evaluation -> outputs.

Stages 1 and 2a keep their results in the run folder (``mesh/``, ``detections.jsonl``) and leave
a stamp ``.stages/<stage>.json`` holding the hash of their inputs and config; a rerun skips a
stage whose stamp matches, so an interrupted run resumes where it stopped and a changed setting
redoes only what depends on it (:mod:`pavemap.run_folder`: the stamps, the hashes, why a stage is
redone). The filter, fusion and evaluation are cheap and return results in memory;
:func:`pavemap.export.run_files.write_run` then writes every result file once. The pipeline itself
writes only the folder's bookkeeping: ``run.json``, ``config.yaml``, ``run.log``, the stamps and, at
the end, the ownership marker ``.pavemap-owner.json`` listing every file pavemap wrote there (what
``--overwrite`` may delete, :mod:`pavemap.io.owned`). A run that fails deletes the result files it
wrote and keeps what a rerun resumes from.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import logging
import os
import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from pavemap.config import RunConfig, dump_config
from pavemap.detect.config import DetectorConfig, FilterConfig
from pavemap.errors import PavemapError
from pavemap.geometry.grid import GridSpec
from pavemap.io.atomic import atomic_write_text
from pavemap.io.hashes import hash_parts, hash_sequence
from pavemap.io.sequence import DETECTIONS_FILE, read_detections, read_sequence
from pavemap.run_folder import (
    RUN_FILE,
    STAGES,
    Stages,
    detect_parts,
    keep_on_failure,
    mesh_parts,
    prepare_out,
    why_changed,
)
from pavemap.types import DefectInstance, Detection, GeoOrigin, Sequence

if TYPE_CHECKING:  # torch loads when a stage runs, not on import
    from pavemap.fuse import FusionConfig, FusionResult

__all__ = ["RUN_FILE", "STAGES", "RunResult", "filter_and_fuse", "run"]
log = logging.getLogger("pavemap")


@dataclass
class RunResult:
    """What a run produced: defects, maps and metrics (see ``out_dir`` for the files)."""

    out_dir: Path
    defects: list[DefectInstance]
    prob_map: np.ndarray  # (H, W) float32 total defect probability
    class_maps: np.ndarray  # (4, H, W) float32 per class
    grid: GridSpec  # the maps' grid
    metrics: dict
    evaluation: dict | None = None
    files: dict[str, Path] = field(default_factory=dict)
    geo_origin: GeoOrigin | None = None
    preset: str = ""  # the preset the run started from, and why (when chosen from the rig)
    detector: str = ""  # the backend that ran, and why (``auto`` resolved)
    warnings: list[str] = field(default_factory=list)  # the run's warnings (also in run.log)
    segments: list = field(default_factory=list)  # road segments with their PCI-like index (pavemap.maintain)

    def to_geojson(self) -> dict:
        """The defects as written to ``defects.geojson``: WGS84 lon/lat (RFC 7946); PavemapError without a
        geo origin (local metres would be read as degrees; use :meth:`to_dataframe` or ``survey.gpkg``)."""
        from pavemap.export.frames import defects_geojson

        return defects_geojson(self.defects, self.geo_origin)

    def to_dataframe(self, crs: str | None = None):  # noqa: ANN201 - geopandas / pandas are optional
        """A geopandas GeoDataFrame of the defects when geopandas is installed (EPSG:4326 with a geo origin,
        ``crs="auto"`` for the UTM zone; the local engineering CRS without one), else pandas, else dicts."""
        from pavemap.export.frames import defects_frame

        return defects_frame(self.defects, self.geo_origin, crs)

    def summary(self) -> str:
        by = {}
        for d in self.defects:
            by[d.code] = by.get(d.code, 0) + 1
        parts = [f"{len(self.defects)} defects"] + [f"{k} {v}" for k, v in sorted(by.items())]
        if self.evaluation:
            e = self.evaluation
            parts.append(f"F1 {e['f1']:.2f} (P {e['precision']:.2f}, R {e['recall']:.2f})")
            if e.get("median_error_m") is not None:
                parts.append(f"median error {e['median_error_m']:.2f} m")
        geometry = self.metrics.get("geometry") or {}
        return ", ".join(parts) + "".join(f"\nwarning: {w}" for w in geometry.get("warnings") or [])


def _setup_log(out: Path) -> logging.Handler:
    from pavemap.preflight import QuietFileHandler

    handler = QuietFileHandler(out / "run.log", encoding="utf-8")
    handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(message)s"))
    log.addHandler(handler)
    log.setLevel(logging.INFO)
    return handler


# ---------------------------------------------------------------------------- stages


def _detect(seq: Sequence, d: DetectorConfig, device: str, out: Path, progress: bool = True) -> Path:
    """Stage 2a with a resolved backend (:func:`pavemap.detect.backends.resolve_backend`) -> detections.jsonl."""
    det_path = out / DETECTIONS_FILE
    if d.backend == "sim":
        from pavemap.synth.simdetector import SimDetectorConfig
        from pavemap.synth.simdetector import detect_sequence as sim_detect

        sim_detect(seq, seed=d.seed, out=det_path, config=SimDetectorConfig(paint_share=d.paint_fp),
                   progress=progress)
    elif d.backend == "yolo":
        from pavemap.detect.yolo import detect_sequence as yolo_detect

        assert d.weights is not None  # resolve_backend sets them
        yolo_detect(
            seq, weights=Path(d.weights), out=det_path, imgsz=d.imgsz, conf=d.conf, device=device,
            batch=d.batch, class_map=Path(d.class_map) if d.class_map else None, progress=progress,
        )
    else:  # file
        src = Path(d.file) if d.file else (seq.root / DETECTIONS_FILE if seq.root else None)
        if src is None or not src.exists():
            raise PavemapError(f"detector.backend is file but {src} does not exist (give --detections FILE)")
        from pavemap.detect.sources import load_detections
        from pavemap.io.sequence import write_detections

        write_detections(det_path, load_detections(src, seq))
    return det_path


def skipped_text(metrics: dict) -> str:
    """The detections the filter did not use, with counts by reason, in one line ('' when all were used).

    ``metrics`` is a FusionResult's: ``invalid_by_reason`` (unusable: unknown frame or camera, bad box,
    unknown class, bad confidence, outside the image), ``below_conf`` and ``filtered_detections`` (off road).
    """
    n_in = int(metrics.get("input_detections", 0))
    invalid = {k: v for k, v in (metrics.get("invalid_by_reason") or {}).items() if v}
    low, off = int(metrics.get("below_conf", 0)), int(metrics.get("filtered_detections", 0))
    if not (invalid or low or off):
        return ""
    parts = []
    if invalid:
        parts.append(f"{sum(invalid.values())} unusable (" + ", ".join(f"{k.replace('_', ' ')} {v}"
                                                                     for k, v in sorted(invalid.items())) + ")")
    if low:
        parts.append(f"{low} below filter.tau_conf")
    if off:
        parts.append(f"{off} off the road (filter.tau_road)")
    return f"skipped {sum(invalid.values()) + low + off} of {n_in} detections: " + ", ".join(parts)


def filter_and_fuse(seq: Sequence, detections: list[Detection], surface, filter_config: FilterConfig,  # noqa: ANN001
                    fusion_config: FusionConfig, mesh: object | None = None, progress: bool = True) -> FusionResult:
    """Stage 2b then stage 3: the road filter (:mod:`pavemap.detect`), then fusion (:mod:`pavemap.fuse`).

    ``surface`` is a HeightField; ``mesh`` (optional) supplies the mesh road mask. Returns a FusionResult.
    """
    import torch

    from pavemap.detect.filter import filter_detections
    from pavemap.fuse import fuse

    with torch.no_grad():
        filtered = filter_detections(seq, detections, filter_config, mesh=mesh)
        return fuse(seq, filtered, surface, fusion_config, progress=progress)


def run(
    seq: Sequence | str | os.PathLike,
    config: RunConfig | None = None,
    out_dir: str | os.PathLike | None = None,
    overwrite: bool = False,
    progress: bool = True,
    segmenter: str = "auto",
    segmenter_weights: str | os.PathLike | None = None,
) -> RunResult:
    """Run the whole pipeline on a sequence folder and write every output into ``out_dir``.

    Without ``config`` the preset that fits the rig is used (:func:`pavemap.config.preset_for`);
    ``detector.backend: auto`` becomes ``sim`` on a synthetic sequence, else the shipped YOLO weights.
    Both choices are logged and returned in ``RunResult.preset`` / ``RunResult.detector``.
    A drive without semantic maps is labelled by ``segmenter`` (:func:`pavemap.segment.auto.semantics_for_run`:
    ``auto`` = ESPNet when its weights are found, into ``out_dir/semantics``); what was used is in
    ``RunResult.metrics["semantics"]``.

    Before any stage every frame's files are decoded in full (a damaged frame is a SequenceError, or dropped with
    a warning when ``config.skip_bad_frames``) and yolo weights checked; ``out_dir`` is locked for the run (a
    second process stops with PavemapError naming this one); a write the disk refuses is one PavemapError naming
    the folder (:mod:`pavemap.preflight`, docs/faults.md).

    >>> result = pavemap.run("my_seq", pavemap.load_config("nuscenes"), "runs/my_seq")  # doctest: +SKIP
    """
    from pavemap.config import preset_config, preset_for
    from pavemap.detect.backends import detector_model, resolve_backend, resolved_filter
    from pavemap.device import resolve_device

    if not isinstance(seq, Sequence):
        seq = read_sequence(seq, validate=not (config is not None and config.skip_bad_frames))
    if config is None:
        name, why = preset_for(seq)
        cfg, preset_note = preset_config(name), f"{name} ({why})"
    else:
        cfg, preset_note = config, f"{config.preset} (given)"
    cfg.validate()
    from pavemap.geo.crs import output_crs

    output_crs(seq.geo_origin, cfg.output.crs)  # a CRS the sequence cannot have fails before any stage
    device = str(resolve_device(cfg.device))
    detector, why = resolve_backend(cfg.detector, seq)  # a missing input stops here, before any stage
    if detector.backend == "file":  # so does a malformed detections file
        from pavemap.detect.sources import load_detections

        load_detections(detector.file or seq.root / DETECTIONS_FILE, seq)  # type: ignore[operator]
    filt, tau_note = resolved_filter(cfg.filter, cfg.preset, detector_model(detector, seq))  # its operating point
    cfg, why = dataclasses.replace(cfg, filter=filt), f"{why}; {tau_note}"
    from pavemap.io.lock import locked
    from pavemap.io.owned import check_outside_inputs
    from pavemap.preflight import check_frames, check_weights

    check_weights(detector.weights if detector.backend == "yolo" else None)  # a truncated download: not after stage 1
    seq = check_frames(seq, cfg.skip_bad_frames)  # every image decoded in full, as `pavemap info` does
    out = Path(out_dir) if out_dir is not None else Path("runs") / seq.name
    check_outside_inputs(out, (seq.root, detector.file))  # before the lock creates the folder
    with locked(out):  # a second process writing this folder stops here, naming this one
        return _run_claimed(seq, cfg, detector, why, preset_note, device, out, overwrite, progress,
                            segmenter, segmenter_weights)


def _run_claimed(seq: Sequence, cfg: RunConfig, detector: DetectorConfig, why: str, preset_note: str, device: str,
                 out: Path, overwrite: bool, progress: bool, segmenter: str,
                 segmenter_weights: str | os.PathLike | None) -> RunResult:
    """:func:`run` in the locked folder ``out``: claim it, then the stages; on failure what this attempt
    wrote is deleted (what a rerun resumes from is kept) and a refused write is worded as one line."""
    from pavemap.preflight import write_failure

    folder = prepare_out(out, seq, overwrite, inputs=(detector.file,))
    handler, seen = _setup_log(out), _WarningList()
    log.addHandler(seen)
    try:
        log.info("preset %s", preset_note)
        log.info("detector %s (%s)", detector.backend, why)
        if folder.info.get("kept"):
            log.warning("--overwrite kept %d file(s) in %s that pavemap did not write: %s", len(folder.info["kept"]),
                        out, ", ".join(folder.info["kept"][:5]))
        from pavemap.segment.auto import semantics_for_run

        seq, semantics = semantics_for_run(seq, segmenter, segmenter_weights, device, out, cfg.mesh.camera_height)
        log.info("semantics: %s", semantics)
        result = _run(seq, cfg, detector, device, out, progress, semantics)
        result.preset, result.detector = preset_note, f"{detector.backend} ({why})"
        result.warnings = seen.messages
        folder.record("complete")
        return result
    except BaseException as e:  # an interrupt too: what this attempt wrote must not look complete
        with contextlib.suppress(OSError):  # a read-only or full disk: the original error is what matters
            gone = folder.discard(keep_on_failure)
            log.error("failed (%s: %s); removed %d unfinished result file(s); rerun to resume",
                      type(e).__name__, e, len(gone))
            folder.record("failed")
        worded = write_failure(e, out)
        if worded is not None:
            raise worded from None
        raise
    finally:
        for h in (handler, seen):
            log.removeHandler(h)
        handler.close()


class _WarningList(logging.Handler):
    """Collects the run's warnings for the console (they are in run.log as well)."""

    def __init__(self) -> None:
        super().__init__(logging.WARNING)
        self.messages: list[str] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.messages.append(record.getMessage())


def _run(seq: Sequence, cfg: RunConfig, detector: DetectorConfig, device: str, out: Path,
         progress: bool, semantics: str = "") -> RunResult:
    stages = Stages(out)
    atomic_write_text(out / "config.yaml", dump_config(cfg))
    seq_key = hash_sequence(seq)
    log.info("run %s on %s (device %s)", seq.name, seq.root, device)
    timings: dict[str, float] = {}

    mesh_dir = out / "mesh"
    mesh, timings["mesh"] = _mesh_stage(seq, cfg, device, seq_key, stages, mesh_dir, progress)
    key, timings["detect"] = _detect_stage(seq, detector, device, seq_key, stages, out, progress)
    detections = read_detections(out / DETECTIONS_FILE)

    # Stages 2b + 3: filter, then fusion (cheap: always redone, so the result is in memory).
    t = time.perf_counter()
    result = filter_and_fuse(seq, detections, mesh.surface, cfg.filter, cfg.fusion, mesh=mesh, progress=progress)
    from pavemap.mesh.geometry import mark_observed

    mark_observed(result.instances, mesh)  # a defect on ground no view observed says so (issue 12)
    from pavemap.maintain import assess, load_policy, summary
    from pavemap.maintain.assessment import survey_inputs

    m = cfg.maintenance  # what to repair first (issue 16): measures, severity, urgency, road segments
    seen = survey_inputs(seq, detector.backend, result.metrics, load_policy(m.policy), detector.imgsz,
                         cfg.filter.tau_conf)  # what the survey could see: segments "not assessed" (issue 41)
    result.segments = assess(result.instances, seq, mesh.surface, result.instance_labels, mesh.observed,
                             policy=m.policy, segment_m=m.segment_m, lane_width_m=m.lane_width_m,
                             samples=mesh.samples, floor_sweep=m.floor_sweep, **seen)
    result.metrics["maintenance"] = summary(result.instances, result.segments, seen["check"])
    timings["fuse"] = time.perf_counter() - t
    stages.mark("fuse", hash_parts(key, dataclasses.asdict(cfg.filter), dataclasses.asdict(cfg.fusion)),
                timings["fuse"])
    log.info("fuse: %d detections in, %d defects", len(detections), len(result.instances))
    skipped = skipped_text(result.metrics)
    if skipped:
        log.info("%s", skipped)

    # Evaluation against synthetic truth, when the sequence has it.
    evaluation = None
    if seq.root is not None and (seq.root / "truth" / "defects.geojson").is_file():
        from pavemap.evaluate import evaluate

        t = time.perf_counter()
        evaluation = evaluate(result, seq.root)
        timings["evaluate"] = time.perf_counter() - t

    metrics = dict(result.metrics)
    metrics["seconds"] = {k: round(v, 3) for k, v in timings.items()}
    metrics["detector"] = detector.backend
    metrics["semantics"] = semantics
    mesh_metrics_file = mesh_dir / "metrics.json"
    if mesh_metrics_file.is_file():
        metrics["mesh"] = json.loads(mesh_metrics_file.read_text())
        geometry = metrics["mesh"].get("geometry") or {}
        if geometry:  # the surface's self-check, up front (issue 12)
            metrics["geometry"] = {k: geometry.get(k) for k in ("trustworthy", "source", "warnings")}
    if evaluation is not None:
        metrics["evaluation"] = evaluation

    files = _export(seq, cfg, out, mesh, mesh_dir, result, metrics, evaluation, progress)
    log.info("done in %.1f s", metrics["seconds"]["total"])
    return RunResult(
        out_dir=out,
        defects=result.instances,
        prob_map=result.prob_map,
        class_maps=result.class_maps,
        grid=result.grid,
        metrics=metrics,
        evaluation=evaluation,
        files=files,
        geo_origin=seq.geo_origin,
        segments=result.segments,
    )


def _detect_stage(seq: Sequence, detector: DetectorConfig, device: str, seq_key: str, stages: Stages,
                  out: Path, progress: bool = True) -> tuple[str, float]:
    """Stage 2a: ``detections.jsonl``, reused when its stamp matches. Returns (stage key, seconds)."""
    parts = detect_parts(seq_key, detector, device, seq)
    key = hash_parts(parts)
    if stages.done("detect", key) and (out / DETECTIONS_FILE).is_file():
        log.info("detect: up to date")
        return key, stages.seconds("detect") or 0.0
    t = time.perf_counter()
    stages.invalidate_after("detect")
    log.info("detect: backend %s (%s)", detector.backend, why_changed(stages.parts("detect"), parts))
    stages.start("detect", key, parts)
    _detect(seq, detector, device, out, progress)
    seconds = time.perf_counter() - t
    stages.mark("detect", key, seconds, parts)
    return key, seconds


def _mesh_stage(seq: Sequence, cfg: RunConfig, device: str, seq_key: str, stages: Stages, mesh_dir: Path,
                progress: bool) -> tuple[object, float]:
    """Stage 1: the road mesh, reused when its stamp matches. Returns (RoadMesh, seconds).

    An interrupted stage resumes from ``mesh/checkpoint.pt`` only when it was started with the same key:
    a checkpoint of other inputs or settings (fewer epochs, another seed, other learning rates …) would
    give a mesh no uninterrupted run gives, so it is deleted and the stage starts afresh.
    """
    from pavemap.mesh import load_mesh, reconstruct
    from pavemap.mesh.checkpoint import CHECKPOINT

    mesh_cfg = dataclasses.replace(cfg.mesh, device=device) if hasattr(cfg.mesh, "device") else cfg.mesh
    parts = mesh_parts(seq_key, mesh_cfg)
    key = hash_parts(parts)
    if stages.done("mesh", key) and (mesh_dir / "metrics.json").is_file():
        log.info("mesh: up to date, reusing %s", mesh_dir)
        return load_mesh(mesh_dir), stages.seconds("mesh") or 0.0
    t = time.perf_counter()
    stages.invalidate_after("detect")  # what uses the mesh; detection does not
    why = why_changed(stages.parts("mesh"), parts)
    checkpoint = mesh_dir / CHECKPOINT
    if checkpoint.is_file() and stages.started_key("mesh") == key and mesh_cfg.resume:
        log.info("mesh: resuming the interrupted stage from %s (same inputs and settings)", checkpoint)
    else:
        if checkpoint.is_file():
            checkpoint.unlink()
            log.info("mesh: checkpoint discarded, it belongs to other inputs or settings (%s)", why)
        log.info("mesh: reconstructing (%s)", why)
    stages.start("mesh", key, parts)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        mesh, _ = reconstruct(seq, mesh_dir, mesh_cfg, progress=progress)
    for w in caught:
        log.warning("mesh: %s", w.message)
    seconds = time.perf_counter() - t
    stages.mark("mesh", key, seconds, parts)
    return mesh, seconds


def _export(seq, cfg, out, mesh, mesh_dir, result, metrics, evaluation, progress) -> dict[str, Path]:  # noqa: ANN001
    from pavemap.export.run_files import write_run
    from pavemap.fuse.core import surface_grid
    from pavemap.mesh import bev_rasters

    bev = bev_rasters(mesh, seq.classes)
    return write_run(
        out, result, metrics, seq=seq, geo_origin=seq.geo_origin, evaluation=evaluation, config=cfg.to_dict(),
        output=cfg.output, bev_rgb=bev["rgb"], bev_semantic=bev["semantic_rgb"],
        mesh_grid=surface_grid(mesh.surface), mesh_path=mesh_dir / "mesh.ply", progress=progress,
        surface=mesh.surface,
    )
