"""``pavemap register NETWORK``: (re)build the defect register of a network folder and print a summary."""

from __future__ import annotations

from pathlib import Path

import typer


def register(app: typer.Typer) -> None:
    @app.command(name="register")
    def register_cmd(
        network: Path = typer.Argument(..., help="A network folder written by `pavemap batch`."),
        grow_ratio: float = typer.Option(1.5, "--grow-ratio", help="A defect has grown when its area (or depth) "
                                         "rose by at least this factor since the previous survey that saw it."),
        floor_m: float = typer.Option(0.5, "--floor-m", help="Smallest merge distance (m); the tolerance grows "
                                      "with the drives' georeferencing residuals."),
        top: int = typer.Option(10, "--top", min=0, help="Print this many defects (new and grown first)."),
    ) -> None:
        """Merge every finished drive's defects into one record per physical defect (register.gpkg)."""
        from pavemap.network.batch import register_line
        from pavemap.network.register import STATUSES, build_register, read_register
        from pavemap.network.report import write_network_page

        s = build_register(network, grow_ratio=grow_ratio, floor_m=floor_m)
        write_network_page(network)
        typer.echo(register_line(s))
        typer.echo(f"surveys {', '.join(s['surveys'])}; drives {', '.join(s['drives'])}; CRS {s['crs']}")
        if s["left_out"]:
            typer.echo(f"left out (not finished): {', '.join(s['left_out'])}")
        rows = sorted(read_register(network), key=lambda r: (STATUSES.index(r["status"]), r["id"]))
        for r in rows[:top]:
            area = (f"area {r['area_prev_m2']:.2f} -> {r['area_last_m2']:.2f} m2" if r.get("area_prev_m2") is not None
                    else f"area {r['area_last_m2']:.2f} m2" if r.get("area_last_m2") is not None else "")
            typer.echo(f"  #{r['id']:<4} {r['code']:<4} {r['status']:<15} first {r['first_seen']} last "
                       f"{r['last_seen']} seen {r['sightings']}x  {area}")
        typer.echo(f"page {network / 'network.html'}")
