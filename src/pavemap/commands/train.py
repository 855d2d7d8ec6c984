"""``pavemap train-detector DATA.yaml``: train a YOLO road-defect detector (ultralytics, offline)."""

from __future__ import annotations

from pathlib import Path

import typer

from pavemap.commands.options import DEVICE_HELP


def register(app: typer.Typer) -> None:
    @app.command("train-detector")
    def train_detector_cmd(
        data: Path = typer.Argument(..., help="ultralytics dataset yaml (path, train, val, names D00/D10/D20/D40)."),
        model: str = typer.Option("yolov5n.yaml", help="Model yaml (random init, no download) or a local .pt."),
        init_from: Path | None = typer.Option(
            None, "--init-from",
            help="A YOLOv5 COCO checkpoint (e.g. ultralytics' yolov5n.pt) whose backbone and neck start --model.",
        ),
        epochs: int = typer.Option(100, help="Epochs (ignored when --hours is given)."),
        hours: float | None = typer.Option(None, help="Wall-time budget; ultralytics fits the epochs to it."),
        imgsz: int = typer.Option(640, help="Training image size."),
        batch: int = typer.Option(16, help="Images per batch."),
        device: str = typer.Option("auto", help=f"{DEVICE_HELP}."),
        workers: int = typer.Option(8, help="Data loader workers."),
        project: Path = typer.Option(Path("runs/detect"), help="Output folder of runs."),
        name: str = typer.Option("train", help="Run name (a subfolder of --project)."),
        resume: Path | None = typer.Option(None, help="Continue a run from its weights/last.pt."),
        out: Path | None = typer.Option(None, help="Copy the best weights here when done."),
    ) -> None:
        """Train a YOLO detector on RDD2022 or your own data (ultralytics, fully offline)."""
        import shutil

        from pavemap.detect.yolo import train_detector

        if init_from is not None:
            if not model.endswith((".yaml", ".yml")):
                raise typer.BadParameter(f"--init-from starts a model yaml (e.g. yolov5n.yaml), not {model}")
            from pavemap.detect.pretrained import coco_start_checkpoint

            model = str(coco_start_checkpoint(init_from, project / name / "coco_start.pt", model_yaml=model))
            typer.echo(f"COCO start from {init_from} -> {model}")
        best = train_detector(
            data, model=model, epochs=epochs, imgsz=imgsz, device=device, batch=batch, project=project,
            name=name, time_hours=hours, workers=workers, resume=resume,
        )
        if out is not None:
            out.parent.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(best, out)
            best = out
        typer.echo(f"best weights -> {best}")
