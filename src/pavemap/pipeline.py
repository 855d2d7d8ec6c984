"""End to end: stage 1 (mesh) -> detection -> filter -> fusion -> evaluation -> outputs.

Stages 1 and 2a keep their results in the run folder (``mesh/``, ``detections.jsonl``) and leave
a stamp ``.stages/<stage>.json`` holding the hash of their inputs and config; a rerun skips a
stage whose stamp matches, so an interrupted run resumes where it stopped and a changed setting
redoes only what depends on it. The filter, fusion and evaluation are cheap and return results
in memory; :func:`pavemap.export.run_files.write_run` then writes every result file once.
The pipeline itself writes only the folder's bookkeeping: ``run.json``, ``config.yaml``,
``run.log`` and the stamps.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import shutil
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from pavemap.config import RunConfig, dump_config
from pavemap.detect.config import DetectorConfig, FilterConfig
from pavemap.errors import PavemapError
from pavemap.geometry.grid import GridSpec
from pavemap.io.atomic import atomic_write_json, atomic_write_text
from pavemap.io.sequence import DETECTIONS_FILE, SEQUENCE_FILE, read_detections, read_sequence
from pavemap.types import DefectInstance, Detection, GeoOrigin, Sequence

if TYPE_CHECKING:  # torch loads when a stage runs, not on import
    from pavemap.fuse import FusionConfig, FusionResult

RUN_FILE = "run.json"
STAGES = ("mesh", "detect", "fuse", "evaluate", "export")
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

    def to_geojson(self) -> dict:
        """The defects as written to ``defects.geojson`` (lon/lat when the sequence has a geo origin)."""
        from pavemap.export.geojson import instances_to_geojson

        return instances_to_geojson(self.defects, self.geo_origin)

    def to_dataframe(self):  # noqa: ANN201 - pandas is optional
        from pavemap.export.tables import to_dataframe

        return to_dataframe(self.defects, self.geo_origin)

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
        return ", ".join(parts)


# ---------------------------------------------------------------------------- hashing


def _hash_sequence(seq: Sequence) -> str:
    h = hashlib.sha256()
    assert seq.root is not None
    h.update((seq.root / SEQUENCE_FILE).read_bytes())
    for rel in ("truth/height.npy", "truth/defects.geojson"):
        p = seq.root / rel
        if p.is_file():
            h.update(p.read_bytes())
    # Image contents are not hashed (too slow for long drives); size + mtime catch edits.
    for f in seq.frames:
        for v in f.views.values():
            for rel in (v.image, v.semantics, v.depth):
                if rel:
                    st = (seq.root / rel).stat()
                    h.update(f"{rel}:{st.st_size}:{st.st_mtime_ns}".encode())
    return h.hexdigest()[:16]


def _hash(*parts: object) -> str:
    return hashlib.sha256(json.dumps(parts, sort_keys=True, default=str).encode()).hexdigest()[:16]


def _file_hash(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()[:16] if path.is_file() else "none"


class _Stages:
    def __init__(self, out: Path, force: bool = False):
        self.dir = out / ".stages"
        self.dir.mkdir(parents=True, exist_ok=True)
        self.force = force

    def done(self, name: str, key: str) -> bool:
        p = self.dir / f"{name}.json"
        if self.force or not p.is_file():
            return False
        try:
            return json.loads(p.read_text())["key"] == key
        except (json.JSONDecodeError, KeyError):
            return False

    def mark(self, name: str, key: str, seconds: float) -> None:
        atomic_write_json(self.dir / f"{name}.json", {"key": key, "seconds": seconds, "finished": time.time()})

    def seconds(self, name: str) -> float | None:
        p = self.dir / f"{name}.json"
        return json.loads(p.read_text()).get("seconds") if p.is_file() else None

    def invalidate_after(self, name: str) -> None:
        for later in STAGES[STAGES.index(name) + 1 :]:
            (self.dir / f"{later}.json").unlink(missing_ok=True)


def _prepare_out(out: Path, seq: Sequence, overwrite: bool) -> None:
    """Refuse a folder that holds something else; claim it with run.json."""
    if out.exists() and not out.is_dir():
        raise PavemapError(f"{out}: exists and is not a folder")
    marker = out / RUN_FILE
    if out.is_dir() and any(out.iterdir()):
        same = False
        if marker.is_file():
            try:
                prev = json.loads(marker.read_text())
            except json.JSONDecodeError:
                prev = {}
            same = prev.get("sequence") == str(seq.root.resolve()) if seq.root else False
            if not same and not overwrite:
                raise PavemapError(
                    f"{out}: holds another run (of {prev.get('sequence', '?')}); "
                    "choose another --out or pass --overwrite"
                )
        elif not overwrite:
            raise PavemapError(
                f"{out}: folder is not empty and holds no pavemap run; choose another --out or pass --overwrite"
            )
        if overwrite and not same:
            shutil.rmtree(out)
    try:
        out.mkdir(parents=True, exist_ok=True)
        probe = out / ".write-test"
        probe.write_text("")
        probe.unlink()
    except OSError as e:
        raise PavemapError(f"{out}: cannot write the run folder ({e.strerror or e})") from None
    atomic_write_json(marker, {"format": "pavemap-run/1", "sequence": str(seq.root.resolve()), "name": seq.name})


def _setup_log(out: Path) -> logging.Handler:
    handler = logging.FileHandler(out / "run.log", encoding="utf-8")
    handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(message)s"))
    log.addHandler(handler)
    log.setLevel(logging.INFO)
    return handler


# ---------------------------------------------------------------------------- stages


def _detect(seq: Sequence, d: DetectorConfig, device: str, out: Path) -> Path:
    """Stage 2a with a resolved backend (:func:`pavemap.detect.backends.resolve_backend`) -> detections.jsonl."""
    det_path = out / DETECTIONS_FILE
    if d.backend == "sim":
        from pavemap.synth.simdetector import detect_sequence as sim_detect

        sim_detect(seq, seed=d.seed, out=det_path)
    elif d.backend == "yolo":
        from pavemap.detect.yolo import detect_sequence as yolo_detect

        assert d.weights is not None  # resolve_backend sets them
        yolo_detect(
            seq, weights=Path(d.weights), out=det_path, imgsz=d.imgsz, conf=d.conf, device=device,
            batch=d.batch, class_map=Path(d.class_map) if d.class_map else None,
        )
    else:  # file
        src = Path(d.file) if d.file else (seq.root / DETECTIONS_FILE if seq.root else None)
        if src is None or not src.exists():
            raise PavemapError(f"detector.backend is file but {src} does not exist (give --detections FILE)")
        from pavemap.detect.sources import load_detections
        from pavemap.io.sequence import write_detections

        write_detections(det_path, load_detections(src, seq))
    return det_path


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
) -> RunResult:
    """Run the whole pipeline on a sequence folder and write every output into ``out_dir``.

    Without ``config`` the preset that fits the rig is used (:func:`pavemap.config.preset_for`);
    ``detector.backend: auto`` becomes ``sim`` on a synthetic sequence, else the shipped YOLO weights.
    Both choices are logged and returned in ``RunResult.preset`` / ``RunResult.detector``.

    >>> result = pavemap.run("my_seq", pavemap.load_config("nuscenes"), "runs/my_seq")  # doctest: +SKIP
    """
    from pavemap.config import preset_config, preset_for
    from pavemap.detect.backends import resolve_backend
    from pavemap.device import resolve_device

    if not isinstance(seq, Sequence):
        seq = read_sequence(seq)
    if config is None:
        name, why = preset_for(seq)
        cfg, preset_note = preset_config(name), f"{name} ({why})"
    else:
        cfg, preset_note = config, f"{config.preset} (given)"
    cfg.validate()
    device = str(resolve_device(cfg.device))
    detector, why = resolve_backend(cfg.detector, seq)  # a missing input stops here, before any stage
    out = Path(out_dir) if out_dir is not None else Path("runs") / seq.name
    _prepare_out(out, seq, overwrite)
    handler = _setup_log(out)
    try:
        log.info("preset %s", preset_note)
        log.info("detector %s (%s)", detector.backend, why)
        result = _run(seq, cfg, detector, device, out, progress)
        result.preset, result.detector = preset_note, f"{detector.backend} ({why})"
        return result
    finally:
        log.removeHandler(handler)
        handler.close()


def _run(seq: Sequence, cfg: RunConfig, detector: DetectorConfig, device: str, out: Path,
         progress: bool) -> RunResult:
    import dataclasses

    stages = _Stages(out)
    atomic_write_text(out / "config.yaml", dump_config(cfg))
    seq_key = _hash_sequence(seq)
    log.info("run %s on %s (device %s)", seq.name, seq.root, device)
    timings: dict[str, float] = {}

    mesh_dir = out / "mesh"
    mesh, timings["mesh"] = _mesh_stage(seq, cfg, device, seq_key, stages, mesh_dir, progress)

    # Stage 2a: detection.
    det_src = _file_hash(Path(detector.weights)) if detector.weights else None
    key = _hash(seq_key, dataclasses.asdict(detector), det_src,
                _file_hash(Path(detector.file)) if detector.file else None)
    t = time.perf_counter()
    if stages.done("detect", key) and (out / DETECTIONS_FILE).is_file():
        log.info("detect: up to date")
        timings["detect"] = stages.seconds("detect") or 0.0
    else:
        stages.invalidate_after("detect")
        log.info("detect: backend %s", detector.backend)
        _detect(seq, detector, device, out)
        timings["detect"] = time.perf_counter() - t
        stages.mark("detect", key, timings["detect"])
    detections = read_detections(out / DETECTIONS_FILE)

    # Stages 2b + 3: filter, then fusion (cheap: always redone, so the result is in memory).
    t = time.perf_counter()
    result = filter_and_fuse(seq, detections, mesh.surface, cfg.filter, cfg.fusion, mesh=mesh, progress=progress)
    timings["fuse"] = time.perf_counter() - t
    stages.mark("fuse", _hash(key, dataclasses.asdict(cfg.filter), dataclasses.asdict(cfg.fusion)), timings["fuse"])
    log.info("fuse: %d detections in, %d defects", len(detections), len(result.instances))

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
    mesh_metrics_file = mesh_dir / "metrics.json"
    if mesh_metrics_file.is_file():
        metrics["mesh"] = json.loads(mesh_metrics_file.read_text())
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
    )


def _mesh_stage(seq: Sequence, cfg: RunConfig, device: str, seq_key: str, stages: _Stages, mesh_dir: Path,
                progress: bool) -> tuple[object, float]:
    """Stage 1: the road mesh, reused when its stamp matches. Returns (RoadMesh, seconds)."""
    import dataclasses

    from pavemap.mesh import load_mesh, reconstruct

    mesh_cfg = dataclasses.replace(cfg.mesh, device=device) if hasattr(cfg.mesh, "device") else cfg.mesh
    key = _hash(seq_key, dataclasses.asdict(mesh_cfg))
    if stages.done("mesh", key) and (mesh_dir / "metrics.json").is_file():
        log.info("mesh: up to date, reusing %s", mesh_dir)
        return load_mesh(mesh_dir), stages.seconds("mesh") or 0.0
    t = time.perf_counter()
    stages.invalidate_after("mesh")
    log.info("mesh: reconstructing")
    mesh, _ = reconstruct(seq, mesh_dir, mesh_cfg, progress=progress)
    seconds = time.perf_counter() - t
    stages.mark("mesh", key, seconds)
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
    )
