"""``pavemap weights list | verify | install FILE``: the weight files pavemap knows, where they are found,
whether each is the expected file (sha256), and adding one to the user's weight folder.

The registry and the checks are :mod:`pavemap.weights.registry`; this is only the command line.
"""

from __future__ import annotations

from pathlib import Path

import typer


def _size(n: int | None) -> str:
    return "-" if n is None else f"{n / 2**20:.1f} MiB"


def _list() -> None:
    """Each known weight file: where it is found, its size, sha256 and whether that is the expected one."""
    from pavemap.user_cache import install_dir, user_cache_dir
    from pavemap.weights.manage import weight_rows

    for r in weight_rows():
        state = {True: "ok", False: "MISMATCH", None: "required, MISSING" if r["required"] else "not installed"}
        typer.echo(f"{r['file']}  [{r['kind']}] {r['what']}")
        if r["path"] is None:
            typer.echo(f"  {state[None]} (expected sha256 {r['expected']})")
            continue
        typer.echo(f"  {state[r['ok']]:<8} {r['where']:<7} {_size(r['size']):>9}  sha256 {r['sha256']}  {r['path']}")
        if r["ok"] is False:
            typer.echo(f"  expected sha256 {r['expected']}")
    typer.echo(f"user weights folder: {install_dir()} (pavemap weights install FILE); cache: {user_cache_dir()}")


def _verify() -> None:
    """Exit status 1 naming the file when a known file's sha256 differs or the default detector is missing."""
    from pavemap.weights.manage import verify_problems, weight_rows

    rows = weight_rows()
    problems = verify_problems(rows)
    for p in problems:
        typer.secho(f"FAILED: {p}", fg=typer.colors.RED, err=True)
    if problems:
        raise typer.Exit(1)
    found = [r for r in rows if r["ok"]]
    typer.echo(f"ok: {len(found)} weight file(s) match their sha256 ({', '.join(str(r['path']) for r in found)})")


def register(app: typer.Typer) -> None:
    sub = typer.Typer(name="weights", help="List, verify (sha256) and install weight files.", no_args_is_help=True)

    @sub.command(name="list")
    def list_cmd() -> None:
        """Each known weight file: where it is found, size, sha256 and whether it matches the expected hash."""
        _list()

    @sub.command(name="verify")
    def verify_cmd() -> None:
        """Check the known weight files' sha256; exit status 1 naming the file on a mismatch or missing default."""
        _verify()

    @sub.command(name="install")
    def install_cmd(
        file: Path = typer.Argument(..., help="A YOLO detection checkpoint (.pt), or a known segmenter .pth."),
        force: bool = typer.Option(False, "--force", help="Replace a different installed file of the same name."),
    ) -> None:
        """Copy FILE into your weights folder (atomically) after checking it loads (a YOLO detection model)."""
        from pavemap.weights.manage import install_weights

        dest, summary = install_weights(file, force=force)
        typer.echo(f"installed {dest} ({summary})")
        typer.echo(f"use it with --weights {dest}" if dest.name != "pavemap-yolov5n-rdd2022.pt" else
                   "found by runs as the default detector when the packaged copy is missing")

    app.add_typer(sub)
