"""``pavemap reconstruct SEQ --out DIR``: stage 1, the differentiable BEV road mesh."""

from __future__ import annotations

import warnings
from pathlib import Path

import typer

from pavemap.errors import PavemapError


def register(app: typer.Typer) -> None:
    @app.command()
    def reconstruct(
        seq: Path = typer.Argument(..., help="Sequence folder."),
        out: Path = typer.Option(..., "--out", help="Output folder (mesh.ply, BEV rasters, metrics.json)."),
        epochs: int | None = typer.Option(None, help="Training epochs (default 7)."),
        device: str = typer.Option("auto", help="auto, cpu or cuda."),
        preset: str = typer.Option("nuscenes", help="nuscenes (crop 7 m, L=5) or kitti (crop 5 m, L=4)."),
        render_scale: float | None = typer.Option(None, help="Training image scale (speed/accuracy)."),
        resume: bool = typer.Option(True, help="Continue from OUT/checkpoint.pt when it matches."),
        pose_refine: bool = typer.Option(False, help="Refine a small SE(3) correction per view: Gauss-Newton "
                                         "alignment to the baked texture and depth, then joint Adam steps."),
        pose_per: str = typer.Option("frame", help="With --pose-refine: one correction per frame (the rig moves "
                                     "as one) or per view (each camera on its own)."),
        pose_prior_deg: float = typer.Option(0.3, help="With --pose-refine: accuracy of the raw rotations (deg)."),
        pose_prior_m: float = typer.Option(0.2, help="With --pose-refine: accuracy of the raw positions (m)."),
        seed: int = typer.Option(0, help="Random seed."),
    ) -> None:
        """Reconstruct the road surface mesh (height, colour, semantics) from a sequence."""
        from pavemap.io.sequence import read_sequence
        from pavemap.mesh import MeshConfig
        from pavemap.mesh import reconstruct as run

        s = read_sequence(seq)
        cfg = MeshConfig.preset(preset)
        cfg.device, cfg.resume, cfg.pose_refine, cfg.seed = device, resume, pose_refine, seed
        cfg.pose_prior_deg, cfg.pose_prior_m, cfg.pose_per = pose_prior_deg, pose_prior_m, pose_per
        if epochs is not None:
            if epochs < 0:
                raise PavemapError("--epochs must be >= 0")
            cfg.epochs = epochs
        if render_scale is not None:
            cfg.render_scale = render_scale
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            _, m = run(s, out, cfg, progress=True)
        for w in caught:
            typer.secho(f"warning: {w.message}", fg=typer.colors.YELLOW, err=True)

        def fmt(v: object, spec: str) -> str:
            return "n/a" if v is None else format(v, spec)

        typer.echo(
            f"mesh: {m['vertices']} vertices, {m['faces']} faces; PSNR {fmt(m['psnr'], '.2f')} dB, "
            f"semantic acc {fmt(m['sem_acc'], '.3f')}, height RMSE {fmt(m.get('height_rmse'), '.3f')} m, "
            f"{m['seconds']:.0f} s on {m['device']} -> {out}"
        )
