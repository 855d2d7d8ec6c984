"""``pavemap reconstruct SEQ --out DIR``: stage 1, the differentiable BEV road mesh."""

from __future__ import annotations

import dataclasses
import warnings
from pathlib import Path

import typer

from pavemap.commands import options as opt


def register(app: typer.Typer) -> None:
    @app.command()
    def reconstruct(
        seq: Path = typer.Argument(..., help="Sequence folder."),
        out: Path = typer.Option(..., "--out", "-o", help="Output folder (mesh.ply, BEV rasters, metrics.json)."),
        config: str | None = opt.CONFIG,
        sets: list[str] | None = opt.SET,
        epochs: int | None = opt.EPOCHS,
        device: str | None = opt.DEVICE,
        seed: int | None = typer.Option(None, help="Random seed (= --set mesh.seed=N)."),
        resume: bool | None = typer.Option(None, "--resume/--no-resume", help="Continue from OUT/checkpoint.pt "
                                           "when it matches (= --set mesh.resume=...). Default: the config's, on."),
        pose_refine: bool | None = typer.Option(
            None, "--pose-refine/--no-pose-refine", help="Refine a small SE(3) correction per frame (= --set "
            "mesh.pose_refine=...; mesh.pose_per, mesh.pose_prior_deg, mesh.pose_prior_m tune it). Default: off."),
    ) -> None:
        """Reconstruct the road surface mesh (height, colour, semantics) from a sequence."""
        from pavemap.io.owned import undo_on_failure
        from pavemap.io.sequence import read_sequence
        from pavemap.mesh import reconstruct as run
        from pavemap.mesh.checkpoint import CHECKPOINT
        from pavemap.mesh.tiles import SEGMENTS_DIR

        s = read_sequence(seq)
        rc = opt.resolve_config(s, config, sets, {"device": device, "mesh.epochs": epochs, "mesh.seed": seed,
                                                  "mesh.resume": resume, "mesh.pose_refine": pose_refine})
        cfg = dataclasses.replace(rc.mesh, device=rc.device)
        keep = (CHECKPOINT, f"{SEGMENTS_DIR}/")  # what a stopped run resumes from
        with warnings.catch_warnings(record=True) as caught, undo_on_failure(out, keep=keep):
            warnings.simplefilter("always")
            _, m = run(s, out, cfg, progress=True)
        for w in caught:
            typer.secho(f"warning: {w.message}", fg=typer.colors.YELLOW, err=True)

        def fmt(v: object, spec: str) -> str:
            return "n/a" if v is None else format(v, spec)

        share = m.get("heldout_textured_share")
        on = "" if share is None else f" on the {100 * share:.0f} % of held-out road the training views textured"
        typer.echo(
            f"mesh: {m['vertices']} vertices, {m['faces']} faces; PSNR {fmt(m['psnr'], '.2f')} dB{on}, "
            f"semantic acc {fmt(m['sem_acc'], '.3f')}, height RMSE {fmt(m.get('height_rmse'), '.3f')} m, "
            f"{m['seconds']:.0f} s on {m['device']} -> {out}"
        )
