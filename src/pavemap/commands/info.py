"""``pavemap info SEQ``: summary of a sequence folder and its validation result.

``info`` validates more than the reader does: every image is decoded in full (a truncated PNG
fails here, not in the middle of a run), semantic maps must hold the sequence's class ids and
depth maps plausible millimetre values. Problems are listed (file, JSON path, problem) and the
exit status is 1; a sequence that cannot be read at all is an error (exit status 2).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import typer

from pavemap.errors import SequenceError
from pavemap.io.sequence import DETECTIONS_FILE, SEQUENCE_FILE, sequence_from_dict, validate_sequence
from pavemap.types import Sequence

MAX_SHOWN = 20


def _invalid(lines: list[str]) -> None:
    typer.secho(f"INVALID: {len(lines)} problem(s)", fg=typer.colors.RED)
    for line in lines[:MAX_SHOWN]:
        typer.echo(f"  {line}")
    if len(lines) > MAX_SHOWN:
        typer.echo(f"  ... and {len(lines) - MAX_SHOWN} more")
    raise typer.Exit(1)


def _read(seq: Path) -> Sequence:
    """The sequence, or the list of its schema problems and exit status 1."""
    from pavemap.io.schema import check_sequence, load_json
    from pavemap.io.sequence import read_sequence

    file = seq / SEQUENCE_FILE
    try:
        present = file.is_file()
    except (OSError, ValueError):
        present = False
    if not present:
        read_sequence(seq, validate=False)  # raises the reader's one-line error (exit status 2)
    try:
        d = load_json(file)
    except SequenceError as e:
        _invalid([str(e)])
    issues = check_sequence(d, limit=200)
    if issues:
        _invalid([f"{file}: {i}" for i in issues])
    try:
        return sequence_from_dict(d, seq)
    except SequenceError as e:
        _invalid([str(e)])
    raise AssertionError("unreachable")


def _summary(seq: Path, s: Sequence) -> None:
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
    n_sem = sum(1 for f in s.frames for v in f.views.values() if v.semantics)
    layers = {
        "semantics": "yes" if n_sem == views else ("no" if n_sem == 0 else f"{n_sem} of {views} views"),
        "depth": "yes" if any(v.depth for f in s.frames for v in f.views.values()) else "no",
        "detections": "yes" if (seq / DETECTIONS_FILE).is_file() else "no",
        "truth": "yes" if (seq / "truth" / "defects.geojson").is_file() else "no",
    }
    typer.echo("layers     " + ", ".join(f"{k}: {v}" for k, v in layers.items()))
    from pavemap.geo.attach import describe

    # the georeferencing record (source, fixes, residual RMS, scale, lever arm, warnings) says how far to trust it
    typer.echo("geo        " + describe(s).replace("\n", "\n           "))
    r = (s.geo_origin.georef or {}) if s.geo_origin is not None else {}
    if r.get("lever_arm_m"):
        typer.echo(f"           GPS lever arm {r['lever_arm_m']} m (x forward, y left, z up)")
    if n_sem == 0:
        typer.secho("warning: no semantic maps: stage 1 reconstructs from RGB only and the road filter uses the "
                    "mesh footprint (every box on the mapped road area counts as road)", fg=typer.colors.YELLOW,
                    err=True)


def register(app: typer.Typer) -> None:
    @app.command()
    def info(seq: Path = typer.Argument(..., help="Sequence folder (holds sequence.json).")) -> None:
        """Print a summary of a sequence folder and validate it (decodes every image)."""
        s = _read(seq)
        _summary(seq, s)
        problems = validate_sequence(s, deep=True, max_problems=200)
        if problems:
            _invalid([str(p) for p in problems])
        typer.secho("valid", fg=typer.colors.GREEN)
