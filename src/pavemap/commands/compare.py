"""``pavemap compare RUN_A RUN_B --out DIR``: change between two surveys of the same road."""

from __future__ import annotations

from pathlib import Path

import typer


def register(app: typer.Typer) -> None:
    @app.command()
    def compare(
        run_a: Path = typer.Argument(..., help="Earlier survey: a run output folder (or its defects.geojson)."),
        run_b: Path = typer.Argument(..., help="Later survey: a run output folder (or its defects.geojson)."),
        out: Path = typer.Option(..., "--out", "-o", help="Folder for the changes layer, changes.png, changes.json."),
        match_m: float = typer.Option(0.5, "--match-m", help="Match defects whose centroids are this close (m); "
                                      "overlapping polygons always match."),
        grow_ratio: float = typer.Option(1.2, "--grow-ratio", help="A matched defect has grown when its area or "
                                         "severity rose by at least this factor."),
    ) -> None:
        """Classify defects as new, grown, unchanged or gone between two runs."""
        from pavemap.compare import compare_runs
        from pavemap.io.owned import undo_on_failure

        with undo_on_failure(out):  # a changes layer without changes.json would look like a result
            s = compare_runs(run_a, run_b, out, match_m=match_m, grow_ratio=grow_ratio)
        c = s["counts"]
        typer.echo(f"survey A {s['defects_a']} defects, survey B {s['defects_b']} defects "
                   f"({'lon/lat' if s['coordinates'] == 'lonlat' else 'local metres'})")
        typer.echo(f"new {c['new']}  grown {c['grown']}  unchanged {c['unchanged']}  gone {c['gone']}")
        for w in s["warnings"]:
            typer.secho(f"warning: {w}", fg=typer.colors.YELLOW, err=True)
        typer.echo(f"wrote {s['paths']['changes']}, {s['paths']['changes.png']}, {s['paths']['changes.json']}")
