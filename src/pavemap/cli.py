"""The ``pavemap`` command line: one thin command per step.

Each area registers its commands from ``pavemap.commands.<area>`` (a ``register(app)``
function), so the CLI stays a thin layer over the stage functions.
"""

from __future__ import annotations

import importlib
import importlib.util
import sys

import typer

from pavemap.errors import PavemapError, SequenceError

app = typer.Typer(
    name="pavemap",
    help="Map road defects in 3D from driving video: BEV road mesh, detection, filtering and fusion.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)



@app.callback()
def _root() -> None:
    """pavemap: road defect mapping. Run `pavemap demo` for a full example on synthetic data."""


COMMAND_MODULES = ("info", "synth", "detect", "reconstruct", "fuse", "imports", "train", "run", "compare")

for _name in COMMAND_MODULES:
    _mod = f"pavemap.commands.{_name}"
    if importlib.util.find_spec(_mod) is not None:
        importlib.import_module(_mod).register(app)


def main() -> None:
    try:
        app()
    except (SequenceError, PavemapError, FileNotFoundError, FileExistsError, PermissionError) as e:
        typer.secho(f"error: {e}", fg=typer.colors.RED, err=True)
        sys.exit(2)


if __name__ == "__main__":
    main()
