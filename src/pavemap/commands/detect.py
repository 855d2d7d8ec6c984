"""``pavemap detect SEQ [--detector auto|sim|yolo|file]``: write ``detections.jsonl`` for a sequence."""

from __future__ import annotations

from pathlib import Path

import typer

from pavemap.commands import options as opt


def register(app: typer.Typer) -> None:
    @app.command()
    def detect(
        seq: Path = typer.Argument(..., help="Sequence folder."),
        out: Path | None = typer.Option(None, "--out", "-o", help="Output JSONL (default SEQ/detections.jsonl)."),
        config: str | None = opt.CONFIG,
        sets: list[str] | None = opt.SET,
        detector: opt.Detector | None = opt.DETECTOR,
        weights: Path | None = opt.WEIGHTS,
        detections: Path | None = opt.DETECTIONS,
        seed: int | None = typer.Option(None, help="sim: random seed (= --set detector.seed=N)."),
        device: str | None = opt.DEVICE,
    ) -> None:
        """Detect road defects in every view of a sequence -> detections.jsonl.

        YOLO settings go through --set: detector.imgsz, detector.conf, detector.batch, detector.class_map.
        """
        from pavemap.io.sequence import DETECTIONS_FILE, read_sequence

        s = read_sequence(seq)
        rc = opt.resolve_config(s, config, sets, {**opt.detector_shortcuts(detector, weights, detections),
                                                  "detector.seed": seed, "device": device})
        d = opt.announce_detector(rc, s)
        out_path = out if out is not None else seq / DETECTIONS_FILE
        if d.backend == "sim":
            from pavemap.synth.simdetector import SimDetectorConfig
            from pavemap.synth.simdetector import detect_sequence as sim_detect

            n = sim_detect(s, seed=d.seed, out=out_path, config=SimDetectorConfig(paint_share=d.paint_fp))
        elif d.backend == "yolo":
            from pavemap.detect.yolo import detect_sequence as yolo_detect

            n = yolo_detect(
                s, weights=Path(d.weights), out=out_path, imgsz=d.imgsz, conf=d.conf, device=rc.device,
                batch=d.batch, class_map=Path(d.class_map) if d.class_map else None,
            )
        else:
            from pavemap.detect.sources import load_detections
            from pavemap.io.sequence import write_detections

            dets = load_detections(Path(d.file) if d.file else seq / DETECTIONS_FILE, s)
            write_detections(out_path, dets)
            n = len(dets)
        typer.echo(f"{n} detections -> {out_path}")
