"""End to end: stage 1 (mesh) -> detection -> filter + fusion -> evaluation -> outputs.

Each stage writes into the run folder and leaves a stamp ``.stages/<stage>.json`` holding
the hash of its inputs and config; a rerun skips a stage whose stamp matches, so an
interrupted run resumes where it stopped and a changed setting redoes only what depends
on it.
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

import numpy as np

from pavemap.config import RunConfig, dump_config
from pavemap.errors import PavemapError
from pavemap.io.atomic import atomic_write_json, atomic_write_text
from pavemap.io.sequence import DETECTIONS_FILE, SEQUENCE_FILE, read_detections, read_sequence
from pavemap.types import DefectInstance, Sequence

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
    grid: dict  # x0, y0, res, shape of the maps
    metrics: dict
    evaluation: dict | None = None
    files: dict[str, Path] = field(default_factory=dict)

    def to_geojson(self) -> dict:
        from pavemap.export.geojson import instances_to_geojson

        return instances_to_geojson(self.defects)

    def to_dataframe(self):  # noqa: ANN201 - pandas is optional
        from pavemap.export.tables import to_dataframe

        return to_dataframe(self.defects)

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


def resolve_device(device: str) -> str:
    import torch

    if device == "auto":
        return "cuda" if torch.cuda.is_available() else "cpu"
    if device.startswith("cuda") and not torch.cuda.is_available():
        raise PavemapError(f"--device {device}: CUDA is not available on this machine (use auto or cpu)")
    if device not in ("cpu",) and not device.startswith("cuda"):
        raise PavemapError(f"--device must be auto, cpu, cuda or cuda:N, got {device!r}")
    return device


# ---------------------------------------------------------------------------- stages


def _detect(seq: Sequence, cfg: RunConfig, out: Path) -> Path:
    det_path = out / DETECTIONS_FILE
    d = cfg.detector
    if d.backend == "sim":
        from pavemap.synth.simdetector import detect_sequence as sim_detect

        sim_detect(seq, seed=d.seed, out=det_path)
    elif d.backend == "yolo":
        if not d.weights:
            raise PavemapError("detector.backend is yolo but no weights were given (--weights PATH.pt)")
        from pavemap.detect.yolo import detect_sequence as yolo_detect

        yolo_detect(
            seq, weights=Path(d.weights), out=det_path, imgsz=d.imgsz, conf=d.conf, device=cfg.device,
            batch=d.batch, class_map=Path(d.class_map) if d.class_map else None,
        )
    else:  # file
        src = Path(d.file) if d.file else (seq.root / DETECTIONS_FILE if seq.root else None)
        if src is None or not src.exists():
            raise PavemapError(f"detector.backend is file but {src} does not exist (give --detections FILE)")
        from pavemap.detect.sources import load_detections

        dets = load_detections(src, seq)
        from pavemap.io.sequence import write_detections

        write_detections(det_path, dets)
    return det_path


def run(
    seq: Sequence | str | os.PathLike,
    config: RunConfig | None = None,
    out_dir: str | os.PathLike | None = None,
    overwrite: bool = False,
    progress: bool = True,
) -> RunResult:
    """Run the whole pipeline on a sequence folder and write every output into ``out_dir``.

    >>> result = pavemap.run("my_seq", pavemap.load_config("nuscenes"), "runs/my_seq")  # doctest: +SKIP
    """
    from pavemap.config import preset_config

    if not isinstance(seq, Sequence):
        seq = read_sequence(seq)
    cfg = config if config is not None else preset_config("nuscenes")
    device = resolve_device(cfg.device)
    out = Path(out_dir) if out_dir is not None else Path("runs") / seq.name
    _prepare_out(out, seq, overwrite)
    handler = _setup_log(out)
    try:
        return _run(seq, cfg, device, out, progress)
    finally:
        log.removeHandler(handler)
        handler.close()


def _run(seq: Sequence, cfg: RunConfig, device: str, out: Path, progress: bool) -> RunResult:
    import dataclasses

    import torch

    from pavemap.fuse import fuse, write_fusion
    from pavemap.mesh import load_mesh, reconstruct

    stages = _Stages(out)
    atomic_write_text(out / "config.yaml", dump_config(cfg))
    seq_key = _hash_sequence(seq)
    log.info("run %s on %s (device %s)", seq.name, seq.root, device)
    timings: dict[str, float] = {}

    # Stage 1: the road mesh.
    mesh_dir = out / "mesh"
    mesh_cfg = dataclasses.replace(cfg.mesh, device=device) if hasattr(cfg.mesh, "device") else cfg.mesh
    key = _hash(seq_key, dataclasses.asdict(mesh_cfg))
    t = time.perf_counter()
    if stages.done("mesh", key) and (mesh_dir / "metrics.json").is_file():
        log.info("mesh: up to date, reusing %s", mesh_dir)
        mesh = load_mesh(mesh_dir)
        timings["mesh"] = stages.seconds("mesh") or 0.0
    else:
        stages.invalidate_after("mesh")
        log.info("mesh: reconstructing")
        mesh, _ = reconstruct(seq, mesh_dir, mesh_cfg, progress=progress)
        timings["mesh"] = time.perf_counter() - t
        stages.mark("mesh", key, timings["mesh"])

    # Stage 2a: detection.
    det_cfg = dataclasses.asdict(cfg.detector)
    det_src = _file_hash(Path(cfg.detector.weights)) if cfg.detector.weights else None
    key = _hash(seq_key, det_cfg, det_src, _file_hash(Path(cfg.detector.file)) if cfg.detector.file else None)
    t = time.perf_counter()
    if stages.done("detect", key) and (out / DETECTIONS_FILE).is_file():
        log.info("detect: up to date")
        timings["detect"] = stages.seconds("detect") or 0.0
    else:
        stages.invalidate_after("detect")
        log.info("detect: backend %s", cfg.detector.backend)
        _detect(seq, cfg, out)
        timings["detect"] = time.perf_counter() - t
        stages.mark("detect", key, timings["detect"])
    detections = read_detections(out / DETECTIONS_FILE)

    # Stages 2b + 3: filter and fusion (cheap: always redone, so its result is in memory).
    t = time.perf_counter()
    with torch.no_grad():
        result = fuse(seq, detections, mesh.surface, cfg.fusion, mesh=mesh, progress=progress)
    write_fusion(result, out)
    timings["fuse"] = time.perf_counter() - t
    stages.mark("fuse", _hash(key, dataclasses.asdict(cfg.fusion)), timings["fuse"])
    log.info("fuse: %d detections in, %d defects", len(detections), len(result.instances))

    # Evaluation against synthetic truth, when the sequence has it.
    evaluation = None
    if seq.root is not None and (seq.root / "truth" / "defects.geojson").is_file():
        from pavemap.evaluate import evaluate

        t = time.perf_counter()
        evaluation = evaluate(out, seq.root)
        atomic_write_json(out / "eval.json", evaluation)
        timings["evaluate"] = time.perf_counter() - t

    metrics = dict(result.metrics)
    metrics["seconds"] = {k: round(v, 3) for k, v in timings.items()}
    mesh_metrics_file = mesh_dir / "metrics.json"
    if mesh_metrics_file.is_file():
        metrics["mesh"] = json.loads(mesh_metrics_file.read_text())
    if evaluation is not None:
        metrics["evaluation"] = evaluation

    # Outputs people use.
    t = time.perf_counter()
    files = _export(seq, cfg, out, mesh, mesh_dir, result, metrics)
    timings["export"] = time.perf_counter() - t
    metrics["seconds"]["export"] = round(timings["export"], 3)
    metrics["seconds"]["total"] = round(sum(timings.values()), 3)
    atomic_write_json(out / "metrics.json", metrics)
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
    )


def _export(seq, cfg, out, mesh, mesh_dir, result, metrics) -> dict[str, Path]:  # noqa: ANN001
    from pavemap.export import write_outputs
    from pavemap.mesh import bev_rasters

    bev = bev_rasters(mesh, seq.classes)
    s = mesh.surface
    mesh_grid = {"x0": s.x0, "y0": s.y0, "res": s.res, "shape": list(s.heights.shape)}
    return write_outputs(
        out,
        instances=result.instances,
        prob_map=result.prob_map,
        class_maps=result.class_maps,
        grid=result.grid,
        bev_rgb=bev["rgb"],
        bev_semantic=bev["semantic_rgb"],
        mesh_grid=mesh_grid,
        geo_origin=seq.geo_origin,
        metrics=metrics,
        config=cfg.to_dict(),
        detections=result.detections,
        seq=seq,
        output=cfg.output,
        mesh_path=mesh_dir / "mesh.ply",
    )
