"""``pavemap run`` (the whole pipeline on a sequence) and ``pavemap demo`` (synthetic, end to end)."""

from __future__ import annotations

import time
from pathlib import Path

import typer

from pavemap.commands import options as opt

# The demo scene: nuScenes-like rig (6 cameras) on a shorter drive at quarter resolution,
# sized so synth + mesh + fusion + report finish in well under a minute on a 2-core CPU (20 s at docs/history's commit).
DEMO_FRAMES = 16
DEMO_SCALE = 0.25
DEMO_RENDER_SCALE = 0.5  # of the already small demo images: enough pixels per vertex for the bakes


def register(app: typer.Typer) -> None:
    @app.command()
    def run(
        seq: Path = typer.Argument(..., help="Sequence folder (see docs/guide/sequence-folder.md)."),
        out: Path = typer.Option(..., "--out", "-o", help="Run folder for all outputs."),
        config: str | None = opt.CONFIG,
        sets: list[str] | None = opt.SET,
        detector: opt.Detector | None = opt.DETECTOR,
        weights: Path | None = opt.WEIGHTS,
        detections: Path | None = opt.DETECTIONS,
        device: str | None = opt.DEVICE,
        epochs: int | None = opt.EPOCHS,
        crs: str | None = opt.CRS,
        segmenter: str = typer.Option("auto", "--segmenter", help="For a drive without semantic maps: auto (ESPNet "
                                      "when its weights are found, else run without; said on the console), espnet, "
                                      "espnetv2 or none. Labels go to OUT/semantics. See docs/segmenter.md."),
        segmenter_weights: Path | None = typer.Option(None, "--segmenter-weights", help="The segmenter's weight "
                                                      "file (default: looked up, see docs/segmenter.md)."),
        overwrite: bool = typer.Option(False, help="Replace a run folder that holds another pavemap run (deletes "
                                       "only the files pavemap wrote there)."),
        skip_bad_frames: bool = typer.Option(False, "--skip-bad-frames", help="Drop frames whose image or layer "
                                             "files are damaged (truncated, corrupt, missing) with a warning listing "
                                             "them, instead of stopping (= --set skip_bad_frames=true)."),
    ) -> None:
        """Run stage 1 (mesh), detection, filtering, fusion and all outputs on a sequence."""
        from pavemap.io.sequence import read_sequence
        from pavemap.pipeline import run as run_pipeline

        s = read_sequence(seq, validate=False)  # the run checks every file in full (damaged frames: see above)
        cfg = opt.resolve_config(s, config, sets, {**opt.detector_shortcuts(detector, weights, detections),
                                                "device": device, "mesh.epochs": epochs,
                                                "output.crs": crs, "skip_bad_frames": skip_bad_frames or None})
        opt.announce_detector(cfg, s, threshold=True)
        result = run_pipeline(s, cfg, out, overwrite=overwrite, segmenter=segmenter,
                              segmenter_weights=segmenter_weights)
        report(result)
        typer.echo(f"outputs in {out}  (report: {out / 'report.html'})")

    @app.command()
    def demo(
        out: Path = typer.Option(Path("demo_out"), help="Folder for the synthetic scene and the run."),
        seed: int = typer.Option(0, help="Seed of the synthetic world and the simulated detector."),
        device: str | None = opt.DEVICE,
        sets: list[str] | None = opt.SET,
    ) -> None:
        """Synthesise a nuScenes-like drive, run everything, evaluate against the truth."""
        from pavemap.io.sequence import read_sequence
        from pavemap.pipeline import run as run_pipeline
        from pavemap.synth import synthesize

        t0 = time.perf_counter()
        seq_dir = out / "scene"
        if not (seq_dir / "sequence.json").is_file():
            typer.echo(f"synthesising a nuScenes-like scene ({DEMO_FRAMES} frames x 6 cameras, scale {DEMO_SCALE})")
            # no depth layer: the monocular case users have; the geometry comes from the images (issue 12)
            synthesize(seq_dir, preset="nuscenes-like", seed=seed, frames=DEMO_FRAMES, scale=DEMO_SCALE, depth="none")
        from pavemap.synth import contact_sheet

        sheet = contact_sheet(seq_dir, out / "contact_sheet.png", n_frames=3)
        typer.echo(f"contact sheet of the scene: {sheet}")
        s = read_sequence(seq_dir)
        cfg = opt.resolve_config(s, "nuscenes", sets, {"device": device, "detector.seed": seed,
                                                   "mesh.render_scale": DEMO_RENDER_SCALE})
        opt.announce_detector(cfg, s, threshold=True)
        result = run_pipeline(s, cfg, out / "run", overwrite=True)
        took = time.perf_counter() - t0
        typer.echo("")
        report(result, prefix="pavemap demo: ")
        typer.echo(f"time {took:.0f} s; report: {(out / 'run' / 'report.html').resolve()}")


def report(result: object, prefix: str = "") -> None:
    """The console summary of a run: its warnings, the detections not used (counts by reason), the result."""
    from pavemap.pipeline import skipped_text

    summary = result.summary()  # type: ignore[attr-defined]
    semantics = getattr(result, "metrics", {}).get("semantics")
    if semantics:
        typer.echo(f"semantics: {semantics}")
    for w in getattr(result, "warnings", []):
        if w.removeprefix("mesh: ") not in summary:  # the summary repeats the geometry check's own
            typer.secho(f"warning: {w}", fg=typer.colors.YELLOW, err=True)
    skipped = skipped_text(getattr(result, "metrics", {}))
    if skipped:
        typer.echo(skipped)
    typer.echo(prefix + summary)
