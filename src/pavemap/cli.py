"""The ``pavemap`` command line: one thin command per step.

Each area registers its commands from ``pavemap.commands.<area>`` (a ``register(app)``
function), so the CLI stays a thin layer over the stage functions. Shared options live in
:mod:`pavemap.commands.options`. A user error (:class:`PavemapError`, :class:`SequenceError`, a
missing file, a write that fails: read-only, disk full) ends the command with one ``error: ...`` line
naming the file, and exit status 2.
"""

from __future__ import annotations

import errno
import importlib
import importlib.util
import re
import sys
import warnings
from collections.abc import Sequence
from typing import Any

import typer
from typer.core import TyperGroup

from pavemap.errors import TORCH_WRITE_FAILED, PavemapError, SequenceError
from pavemap.shutdown import prepare_quick_exit
from pavemap.version import __version__

USER_ERRORS = (SequenceError, PavemapError, OSError)  # what ends a command with one line, exit status 2
#: How a failed read or write is worded, by errno (the rest: the system's own words).
_OS_WORDS = {
    errno.ENOSPC: "no space left on device",
    errno.EROFS: "read-only file system",
    errno.EACCES: "permission denied",
    errno.EPERM: "operation not permitted",
    errno.EDQUOT: "disk quota exceeded",
    errno.ENAMETOOLONG: "file name too long",
    errno.EIO: "input/output error (a failing disk or a lost network mount?)",
}


def os_error_text(e: OSError) -> str:
    """One line for a failed read or write: the path and what went wrong (``no space left on device``)."""
    words = _OS_WORDS.get(e.errno or -1) or e.strerror or str(e)
    path = e.filename if e.filename is not None else getattr(e, "filename2", None)
    if e.errno in (errno.ENOSPC, errno.EDQUOT):
        return f"{words} while writing {path}" if path else f"{words} (a write failed)"
    return f"{path}: {words}" if path else words
_PAIR = re.compile(r"[A-Za-z_]\w*\.[A-Za-z_]\w*=")


def expand_set_args(args: Sequence[str]) -> list[str]:
    """``--set a.b=1 c.d=2`` → ``--set a.b=1 --set c.d=2``: pairs after a ``--set`` value belong to it."""
    out: list[str] = []
    in_set = False
    i = 0
    while i < len(args):
        a = args[i]
        if a in ("--set", "-s") and i + 1 < len(args):
            out += [a, args[i + 1]]
            in_set, i = True, i + 2
            continue
        if a == "--":
            out += args[i:]
            break
        if a.startswith("--set="):
            in_set = True
        elif in_set and _PAIR.match(a):
            out += ["--set", a]
            i += 1
            continue
        else:
            in_set = False
        out.append(a)
        i += 1
    return out


class _PavemapGroup(TyperGroup):
    """Expands ``--set`` pairs and turns user errors into one line and exit status 2."""

    def main(self, args: Sequence[str] | None = None, *rest: Any, **kwargs: Any) -> Any:
        return super().main(expand_set_args(sys.argv[1:] if args is None else list(args)), *rest, **kwargs)

    def invoke(self, ctx: Any) -> Any:
        try:
            return super().invoke(ctx)
        except (SequenceError, PavemapError) as e:
            _fail(str(e))
        except OSError as e:  # a missing file, a read-only folder, a full disk: the environment, not a bug
            _fail(os_error_text(e))
        except RuntimeError as e:  # torch.save's words for a short write (a full disk): one line, no traceback
            if not any(w in str(e) for w in TORCH_WRITE_FAILED):
                raise
            _fail(f"a write failed, no space left on device? ({str(e).splitlines()[0][:120]}); free some space, "
                  "then rerun: a run resumes where it stopped")
        except MemoryError:
            _fail("out of memory; use smaller settings (e.g. mesh.render_scale, mesh.pixels_per_step, a coarser "
                  "mesh.resolution) or a machine with more memory")
        except KeyboardInterrupt:
            typer.secho("interrupted; a rerun resumes where the run stopped", fg=typer.colors.RED, err=True)
            raise typer.Exit(130) from None


def _fail(message: str) -> None:
    typer.secho(f"error: {message}", fg=typer.colors.RED, err=True)
    raise typer.Exit(2) from None


app = typer.Typer(
    name="pavemap",
    cls=_PavemapGroup,
    help="Map road defects in 3D from driving video: BEV road mesh, detection, filtering and fusion.",
    no_args_is_help=True,
    add_completion=True,
    pretty_exceptions_enable=False,
)


def _version(value: bool) -> None:
    if value:
        typer.echo(f"pavemap {__version__}")
        raise typer.Exit()


@app.callback()
def _root(
    version: bool = typer.Option(False, "--version", "-V", callback=_version, is_eager=True,
                                 help="Print the version and exit."),
) -> None:
    """pavemap: road defect mapping. Run `pavemap demo` for a full example on synthetic data."""


COMMAND_MODULES = ("info", "synth", "detect", "reconstruct", "fuse", "imports", "train", "run", "compare", "config",
                   "batch", "register", "weights")

for _name in COMMAND_MODULES:
    _mod = f"pavemap.commands.{_name}"
    if importlib.util.find_spec(_mod) is not None:
        importlib.import_module(_mod).register(app)


def _show_warning(message: Warning | str, category: type[Warning], filename: str, lineno: int,
                  file: Any = None, line: str | None = None) -> None:
    """A warning on the command line: one line, without the source file and line a library user gets."""
    typer.secho(f"warning: {message}", fg=typer.colors.YELLOW, err=True)


def main() -> None:
    warnings.showwarning = _show_warning
    try:
        app()
    finally:
        prepare_quick_exit()


if __name__ == "__main__":
    main()
