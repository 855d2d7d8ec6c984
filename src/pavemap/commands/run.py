"""``pavemap run`` (the whole pipeline on a sequence) and ``pavemap demo`` (synthetic, end to end)."""

from __future__ import annotations

import time
from pathlib import Path

import typer

from pavemap.errors import PavemapError

# The demo scene: nuScenes-like rig (6 cameras) on a shorter drive at quarter resolution,
# sized so synth + mesh + fusion + report finish in about 1.5-3 minutes on a 2-core CPU.
DEMO_FRAMES = 16
DEMO_SCALE = 0.25
DEMO_EPOCHS = 4
DEMO_RENDER_SCALE = 0.5  # of the already small demo images: enough optimizer steps in 4 epochs


def register(app: typer.Typer) -> None:
    @app.command()
    def run(
        seq: Path = typer.Argument(..., help="Sequence folder (see README: the sequence folder)."),
        out: Path = typer.Option(..., "--out", help="Run folder for all outputs."),
        config: str = typer.Option("nuscenes", help="Preset (nuscenes, kitti) or a YAML config file."),
        detector: str | None = typer.Option(None, help="sim, yolo or file (overrides the config)."),
        weights: Path | None = typer.Option(None, help="YOLO weights (.pt) for --detector yolo."),
        detections: Path | None = typer.Option(None, help="A detections file for --detector file."),
        device: str | None = typer.Option(None, help="auto, cpu, cuda (overrides the config)."),
        epochs: int | None = typer.Option(None, help="Mesh training epochs (overrides the config)."),
        overwrite: bool = typer.Option(False, help="Replace a run folder that holds another run."),
    ) -> None:
        """Run stage 1 (mesh), detection, filtering, fusion and all outputs on a sequence."""
        from pavemap.config import load_config
        from pavemap.pipeline import run as run_pipeline

        cfg = load_config(config)
        if detector is not None:
            cfg.detector.backend = detector
        if weights is not None:
            cfg.detector.backend = "yolo" if detector is None else cfg.detector.backend
            cfg.detector.weights = str(weights)
        if detections is not None:
            cfg.detector.backend = "file" if detector is None else cfg.detector.backend
            cfg.detector.file = str(detections)
        if cfg.detector.backend == "yolo" and cfg.detector.weights and not Path(cfg.detector.weights).is_file():
            raise PavemapError(
                f"weights file {cfg.detector.weights} not found; put a YOLO detection .pt there "
                "(e.g. models/pavemap-yolov8n-rdd2022-cn.pt) or train one with `pavemap train-detector`"
            )
        if device is not None:
            cfg.device = device
        if epochs is not None:
            cfg.mesh.epochs = epochs
        result = run_pipeline(seq, cfg, out, overwrite=overwrite)
        typer.echo(result.summary())
        typer.echo(f"outputs in {out}  (report: {out / 'report.html'})")

    @app.command()
    def demo(
        out: Path = typer.Option(Path("demo_out"), help="Folder for the synthetic scene and the run."),
        seed: int = typer.Option(0, help="Seed of the synthetic world and the simulated detector."),
        device: str = typer.Option("auto", help="auto, cpu or cuda."),
    ) -> None:
        """Synthesise a nuScenes-like drive, run everything, evaluate against the truth."""
        from pavemap.config import load_config
        from pavemap.pipeline import run as run_pipeline
        from pavemap.synth import synthesize

        t0 = time.perf_counter()
        seq_dir = out / "scene"
        if not (seq_dir / "sequence.json").is_file():
            typer.echo(f"synthesising a nuScenes-like scene ({DEMO_FRAMES} frames x 6 cameras, scale {DEMO_SCALE})")
            synthesize(seq_dir, preset="nuscenes-like", seed=seed, frames=DEMO_FRAMES, scale=DEMO_SCALE)
        from pavemap.synth import contact_sheet

        sheet = contact_sheet(seq_dir, out / "contact_sheet.png", n_frames=3)
        typer.echo(f"contact sheet of the scene: {sheet}")
        cfg = load_config("nuscenes")
        cfg.device = device
        cfg.detector.seed = seed
        cfg.mesh.epochs = DEMO_EPOCHS
        cfg.mesh.render_scale = DEMO_RENDER_SCALE
        result = run_pipeline(seq_dir, cfg, out / "run", overwrite=True)
        took = time.perf_counter() - t0
        typer.echo("")
        typer.echo(f"pavemap demo: {result.summary()}")
        typer.echo(f"time {took:.0f} s; report: {(out / 'run' / 'report.html').resolve()}")
