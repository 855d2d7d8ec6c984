"""``pavemap info SEQ``: summary of a sequence folder and its validation result."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import typer

from pavemap.io.sequence import DETECTIONS_FILE, read_sequence, validate_sequence


def register(app: typer.Typer) -> None:
    @app.command()
    def info(seq: Path = typer.Argument(..., help="Sequence folder (holds sequence.json).")) -> None:
        """Print a summary of a sequence folder and validate it."""
        s = read_sequence(seq, validate=False)
        traj = s.trajectory()
        length = float(np.linalg.norm(np.diff(traj[:, :2], axis=0), axis=1).sum()) if len(traj) > 1 else 0.0
        views = sum(len(f.views) for f in s.frames)
        typer.echo(f"sequence   {s.name}  ({seq})")
        typer.echo(f"frames     {len(s.frames)} (indices {s.frames[0].index}..{s.frames[-1].index}), views {views}")
        for name, c in s.cameras.items():
            typer.echo(f"camera     {name}: {c.width}x{c.height}, fx={c.K[0, 0]:.1f}")
        typer.echo(f"trajectory {length:.1f} m")
        road = ", ".join(c.name for c in s.classes if c.road) or "none"
        movable = ", ".join(c.name for c in s.classes if c.movable) or "none"
        typer.echo(f"classes    {len(s.classes)}; road: {road}; movable: {movable}")
        layers = {
            "semantics": any(v.semantics for f in s.frames for v in f.views.values()),
            "depth": any(v.depth for f in s.frames for v in f.views.values()),
            "detections": (seq / DETECTIONS_FILE).is_file(),
            "truth": (seq / "truth" / "defects.geojson").is_file(),
        }
        typer.echo("layers     " + ", ".join(f"{k}: {'yes' if v else 'no'}" for k, v in layers.items()))
        geo = s.geo_origin
        typer.echo(f"geo origin {'none' if geo is None else f'{geo.lat:.6f}, {geo.lon:.6f}'}")
        problems = validate_sequence(s)
        if problems:
            typer.secho(f"INVALID: {len(problems)} problem(s)", fg=typer.colors.RED)
            for p in problems[:20]:
                typer.echo(f"  {p}")
            raise typer.Exit(1)
        typer.secho("valid", fg=typer.colors.GREEN)
