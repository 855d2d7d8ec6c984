"""``pavemap config [SEQ] [--config] [--set ...]``: print the resolved config, i.e. every field ``--set`` accepts."""

from __future__ import annotations

from pathlib import Path

import typer

from pavemap.commands.options import CONFIG, SET, resolve_config


def register(app: typer.Typer) -> None:
    @app.command("config")
    def config_cmd(
        seq: Path | None = typer.Argument(None, help="Sequence folder: pick the preset from its rig."),
        config: str | None = CONFIG,
        sets: list[str] | None = SET,
    ) -> None:
        """Print the resolved config as YAML (the preset, a YAML file and --set overrides applied)."""
        from pavemap.config import dump_config
        from pavemap.io.sequence import read_sequence

        s = read_sequence(seq) if seq is not None else None
        typer.echo(dump_config(resolve_config(s, config, sets)), nl=False)
