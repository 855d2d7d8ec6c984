"""``pavemap batch MANIFEST.yaml --out NETWORK``: every drive of a network survey as a task on dask."""

from __future__ import annotations

from pathlib import Path

import typer


def register(app: typer.Typer) -> None:
    @app.command()
    def batch(
        manifest: Path = typer.Argument(..., help="YAML manifest: drives: [{path: SEQ, date: YYYY-MM-DD, name: N, "
                                        "vehicle: V}, ...] (paths relative to the manifest)."),
        out: Path = typer.Option(..., "--out", "-o", help="Network folder: drives/<name>/ run folders, "
                                 "network.json, register.gpkg, network.html."),
        scheduler: str | None = typer.Option(None, "--scheduler", help="Address of a running dask scheduler "
                                             "(tcp://HOST:8786), or 'serial' for one drive after another here. "
                                             "Default: a LocalCluster on this machine."),
        workers: int | None = typer.Option(None, "--workers", min=1, help="LocalCluster worker processes "
                                           "(default: the cores); one thread each."),
        memory_limit: str = typer.Option("auto", "--memory-limit", help="Memory per LocalCluster worker "
                                         "(e.g. 4GB; auto: the machine's memory / workers)."),
        retries: int = typer.Option(2, "--retries", min=0, help="Times a failed drive is tried again (also "
                                    "when its worker dies)."),
        no_register: bool = typer.Option(False, "--no-register", help="Process the drives, do not build the "
                                         "register."),
        worker_start: str = typer.Option("forkserver", "--worker-start", help="How LocalCluster workers start: "
                                         "forkserver (forked from one interpreter that has imported what a "
                                         "drive needs; spawn where the platform has none) or spawn."),
    ) -> None:
        """Run many drives in parallel (drives already done are not redone), then build the defect register."""
        from pavemap.network.batch import run_batch  # light: run_batch starts the workers' server at its top

        s = run_batch(manifest, out, scheduler=scheduler, workers=workers, memory_limit=memory_limit,
                      retries=retries, register=not no_register, echo=typer.echo, worker_start=worker_start)
        done = sum(e["status"] == "done" for e in s["drives"])
        typer.echo(f"{done} of {len(s['drives'])} drives done in {s.get('batch_seconds', 0):.1f} s; "
                   f"status {out / 'network.json'}, page {out / 'network.html'}")
        if s["failed"]:
            typer.secho(f"failed: {', '.join(s['failed'])} (see network.json; a rerun retries only these)",
                        fg=typer.colors.RED, err=True)
            raise typer.Exit(1)
