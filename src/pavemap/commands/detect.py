"""``pavemap detect SEQ --backend sim|yolo``: write ``detections.jsonl`` for a sequence."""

from __future__ import annotations

from pathlib import Path

import typer

from pavemap.errors import PavemapError


def register(app: typer.Typer) -> None:
    @app.command()
    def detect(
        seq: Path = typer.Argument(..., help="Sequence folder."),
        backend: str = typer.Option("sim", help="sim (synthetic truth, simulated noise) or yolo (ultralytics)."),
        out: Path | None = typer.Option(None, help="Output JSONL (default SEQ/detections.jsonl)."),
        seed: int = typer.Option(0, help="sim: random seed."),
        weights: Path | None = typer.Option(None, help="yolo: detection weights file (.pt)."),
        imgsz: int = typer.Option(640, help="yolo: inference image size."),
        conf: float = typer.Option(0.05, help="yolo: minimum confidence kept."),
        device: str = typer.Option("auto", help="yolo: auto, cpu, cuda or cuda:N."),
        batch: int = typer.Option(8, help="yolo: images per batch."),
        class_map: Path | None = typer.Option(None, help="yolo: YAML map of model class names to D00..D40 or 'drop'."),
    ) -> None:
        """Detect road defects in every view of a sequence."""
        from pavemap.io.sequence import DETECTIONS_FILE, read_sequence

        s = read_sequence(seq)
        out_path = out if out is not None else seq / DETECTIONS_FILE
        if backend == "sim":
            from pavemap.synth.simdetector import detect_sequence as sim_detect

            n = sim_detect(s, seed=seed, out=out_path)
        elif backend == "yolo":
            if weights is None:
                raise PavemapError("--backend yolo needs --weights PATH to a YOLO detection .pt file")
            from pavemap.detect.yolo import detect_sequence as yolo_detect

            n = yolo_detect(
                s, weights=weights, out=out_path, imgsz=imgsz, conf=conf, device=device, batch=batch,
                class_map=class_map,
            )
        else:
            raise PavemapError(f"unknown backend {backend!r}; choose sim or yolo")
        typer.echo(f"{n} detections -> {out_path}")
