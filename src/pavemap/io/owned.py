"""Output folders pavemap owns: claimed with a marker file, and only what pavemap wrote is ever deleted.

Every folder a command creates (a run folder, a synthetic or imported sequence folder) holds the
marker ``.pavemap-owner.json``: what kind of folder it is and the list of files pavemap wrote there
(the manifest, relative paths). ``--overwrite`` replaces only such a folder, and deletes only the
files in its manifest (and pavemap's own ``.partial-`` temporaries); anything a person put there is
kept and reported. A folder without the marker is never touched; an output folder equal to, or
inside, one of the command's input folders is refused before anything is written.

The manifest is written by :meth:`OutputFolder.record` when the command ends (finished or failed),
from the files that are new or changed since the folder was claimed, plus the earlier entries still
there. A process killed before that leaves its files unlisted: they are then kept, never deleted by
mistake. A command may claim a folder at once with the marker (``early=True``) or, when it has a claim
file of its own (a run's ``run.json``), write the marker only at the end, so every file of a run
folder is written once per run.
"""

from __future__ import annotations

import contextlib
import json
import os
import re
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

from pavemap.errors import PavemapError
from pavemap.io.atomic import atomic_write_json
from pavemap.io.lock import LOCK_FILE, locked

MARKER = ".pavemap-owner.json"
FORMAT = "pavemap-owner/1"
#: The temporary names of pavemap's atomic writers (:mod:`pavemap.io.atomic`, the synthesiser).
PARTIAL = re.compile(r"^\..+\.partial-\d+")


def _resolved(p: str | os.PathLike) -> Path:
    return Path(p).expanduser().resolve()


def check_outside_inputs(out: str | os.PathLike, inputs: Iterable[str | os.PathLike | None],
                         option: str = "--out") -> None:
    """Refuse an output folder that is one of the input folders or lies inside one.

    ``inputs`` are folders (or files: their folder counts only when the output is that very path).
    """
    o = _resolved(out)
    for inp in inputs:
        if inp is None:
            continue
        i = _resolved(inp)
        if o == i:
            raise PavemapError(f"{out}: {option} is the input {inp}; choose a separate output folder")
        if i.is_dir() and i in o.parents:
            raise PavemapError(f"{out}: {option} lies inside the input folder {inp}; choose a folder outside it")


def read_owner(folder: str | os.PathLike) -> dict | None:
    """The marker of a folder pavemap wrote, or None (no marker, or a file that is not pavemap's)."""
    p = Path(folder) / MARKER
    try:
        d = json.loads(p.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    if not isinstance(d, dict) or d.get("format") != FORMAT or not isinstance(d.get("files", []), list):
        return None
    return d


def _walk(folder: Path) -> dict[str, tuple[int, int]]:
    """``{relative path: (size, mtime_ns)}`` of the regular files under ``folder`` (links not followed)."""
    out: dict[str, tuple[int, int]] = {}
    for dirpath, dirnames, filenames in os.walk(folder):
        for name in filenames:
            if name == LOCK_FILE:  # the lock of a process writing the folder: bookkeeping, not an output
                continue
            p = Path(dirpath) / name
            try:
                st = p.lstat()
            except OSError:
                continue
            out[p.relative_to(folder).as_posix()] = (st.st_size, st.st_mtime_ns)
        dirnames[:] = [d for d in dirnames if not (Path(dirpath) / d).is_symlink()]
    return out


def _inside(folder: Path, rel: str) -> Path | None:
    """``folder / rel`` when it stays inside ``folder`` (a manifest entry cannot point elsewhere)."""
    if not isinstance(rel, str) or not rel or Path(rel).is_absolute() or ".." in Path(rel).parts:
        return None
    return folder / rel


def remove_owned(folder: str | os.PathLike, owner: dict) -> list[str]:
    """Delete the files of ``owner``'s manifest (and pavemap's temporaries) under ``folder``, then the
    folders this emptied. Returns the relative paths of what is left (files pavemap did not write)."""
    folder = Path(folder)
    emptied: set[Path] = set()
    targets = [p for p in (_inside(folder, r) for r in owner.get("files", [])) if p is not None]
    targets += [folder / r for r in _walk(folder) if PARTIAL.match(Path(r).name)]
    for p in targets:
        if p.is_symlink() or p.is_file():
            p.unlink()
            emptied.update(q for q in p.parents if folder in q.parents)
    (folder / MARKER).unlink(missing_ok=True)
    for d in sorted(emptied, key=lambda q: len(q.parts), reverse=True):
        with contextlib.suppress(OSError):  # not empty: holds someone else's files
            d.rmdir()
    return sorted(_walk(folder)) if folder.is_dir() else []


@dataclass
class OutputFolder:
    """A claimed output folder. ``record()`` adds what was written since the claim to the manifest."""

    path: Path
    kind: str
    info: dict = field(default_factory=dict)
    before: dict[str, tuple[int, int]] = field(default_factory=dict)
    files: set[str] = field(default_factory=set)

    def written(self) -> list[str]:
        """Relative paths of the files new or changed since the claim (the marker itself excluded)."""
        now = _walk(self.path)
        return sorted(r for r, st in now.items() if r != MARKER and self.before.get(r) != st)

    def record(self, status: str = "complete") -> None:
        """Write the marker with the manifest: earlier entries still present plus what was written since."""
        now = _walk(self.path)
        self.files = {r for r in self.files if r in now} | set(self.written())
        atomic_write_json(self.path / MARKER, {"format": FORMAT, "kind": self.kind, "status": status,
                                               **self.info, "files": sorted(self.files)}, indent=1)

    def remove_own(self, rel: str) -> None:
        """Delete ``rel`` when pavemap wrote it (listed in the manifest): e.g. the completion marker of an
        earlier run, before a rerun that might fail."""
        if rel in self.files:
            (self.path / rel).unlink(missing_ok=True)
            self.files.discard(rel)

    def discard(self, keep: Callable[[str], bool]) -> list[str]:
        """Delete the files written since the claim for which ``keep(rel)`` is False (what a failed command
        must not leave looking complete). Returns what was deleted."""
        gone = []
        for rel in self.written():
            if not keep(rel):
                (self.path / rel).unlink(missing_ok=True)
                gone.append(rel)
        return gone


def check_replaceable(out: str | os.PathLike, kind: str, overwrite: bool,
                      inputs: Iterable[str | os.PathLike | None] = ()) -> bool:
    """For a command that builds its folder under a temporary name and renames it onto ``out`` (the
    synthesiser): whether ``out`` exists and may be replaced as a whole. Raises PavemapError when ``out``
    is an input or inside one, holds something without ``overwrite``, was not written by pavemap, or holds
    files pavemap did not write (they would be lost)."""
    out = Path(out)
    check_outside_inputs(out, inputs)
    if not out.exists() and not out.is_symlink():
        return False
    if not out.is_dir() or out.is_symlink():
        raise PavemapError(f"{out}: exists and is not a folder; choose another --out")
    if not any(p.name != LOCK_FILE for p in out.iterdir()):
        return True
    owner = read_owner(out)
    if owner is None:
        raise PavemapError(f"{out}: folder is not empty and was not written by pavemap (no {MARKER}); "
                           + ("--overwrite only replaces a folder pavemap wrote; " if overwrite else "")
                           + "choose a new or empty folder")
    if not overwrite:
        raise PavemapError(f"{out}: already exists (a pavemap {owner.get('kind', 'folder')}); choose another --out "
                           "or pass --overwrite")
    listed = {r for r in owner.get("files", []) if isinstance(r, str)}
    foreign = [r for r in _walk(out) if r != MARKER and r not in listed and not PARTIAL.match(Path(r).name)]
    if foreign:
        raise PavemapError(f"{out}: holds {len(foreign)} file(s) pavemap did not write ({', '.join(foreign[:3])}"
                           f"{', ...' if len(foreign) > 3 else ''}); move them away or choose another --out")
    return True


def mark_written(folder: str | os.PathLike, kind: str, info: dict | None = None) -> None:
    """Write the marker of a folder a command just built in full: every file in it is pavemap's."""
    folder = Path(folder)
    files = sorted(r for r in _walk(folder) if r != MARKER)
    atomic_write_json(folder / MARKER, {"format": FORMAT, "kind": kind, "status": "complete", **(info or {}),
                                        "files": files}, indent=1)


def note_written(path: str | os.PathLike) -> None:
    """Add a file pavemap just wrote into a sequence folder it owns (e.g. ``detections.jsonl`` by
    ``pavemap detect``) to that folder's manifest, so that ``--overwrite`` may replace it later."""
    path = Path(path)
    for folder in list(path.parents)[:3]:  # the sequence folder, or truth/ … inside it
        owner = read_owner(folder)
        if owner is None:
            continue
        rel = path.relative_to(folder).as_posix()
        if owner.get("kind") == "sequence" and rel not in owner.get("files", []):
            owner["files"] = sorted([*owner.get("files", []), rel])
            atomic_write_json(folder / MARKER, owner, indent=1)
        return


@contextlib.contextmanager
def undo_on_failure(out: str | os.PathLike, keep: tuple[str, ...] = ()) -> Iterator[None]:
    """For a command writing several files into a folder it does not claim: when the body fails, delete
    the files it *created* there (files that existed before are left alone), except names in ``keep``
    (e.g. a checkpoint to resume from; an entry ending in ``/`` keeps a sub-folder, e.g. the finished
    segments of a long drive), so a half-written result does not look complete."""
    out = Path(out)
    before = set(_walk(out)) if out.is_dir() else set()
    try:
        yield
    except BaseException:
        with contextlib.suppress(OSError):
            for rel in set(_walk(out)) - before if out.is_dir() else ():
                if Path(rel).name not in keep and not any(k.endswith("/") and rel.startswith(k) for k in keep):
                    (out / rel).unlink(missing_ok=True)
        raise


@contextlib.contextmanager
def writing(out: str | os.PathLike, kind: str, overwrite: bool = False,
            inputs: Iterable[str | os.PathLike | None] = (), info: dict | None = None,
            same: Callable[[dict], bool] | None = None, legacy: Callable[[Path], dict | None] | None = None,
            early: bool = True, keep_on_failure: Callable[[str], bool] | None = None) -> Iterator[OutputFolder]:
    """Claim ``out`` (:func:`claim`) for the body of a ``with``; when the body fails, delete what it wrote
    (a half-written folder must not look complete) except the diagnosis files ``keep_on_failure(rel)`` names,
    then record the manifest either way. The folder is locked for the body (:mod:`pavemap.io.lock`): a second
    process writing it stops with an error."""
    check_outside_inputs(out, inputs)  # before the lock creates the folder
    with locked(out):
        folder = claim(out, kind, overwrite, inputs, info, same, legacy, early)
        try:
            yield folder
        except BaseException:
            with contextlib.suppress(OSError):  # a read-only or full disk: the original error matters
                folder.discard(keep_on_failure or (lambda rel: False))
                folder.record("failed")
            raise
        folder.record()


def claim(out: str | os.PathLike, kind: str, overwrite: bool, inputs: Iterable[str | os.PathLike | None] = (),
          info: dict | None = None, same: Callable[[dict], bool] | None = None,
          legacy: Callable[[Path], dict | None] | None = None, early: bool = True) -> OutputFolder:
    """Make ``out`` an output folder of ``kind`` and return it, or raise PavemapError saying why not.

    - ``out`` equal to or inside an input folder: refused.
    - missing or empty: created and claimed.
    - holding pavemap's marker and ``same(marker)`` true (a rerun of the same job): kept, to resume.
    - holding pavemap's marker otherwise: refused, unless ``overwrite``: then pavemap's files are
      deleted (:func:`remove_owned`); files a person added are kept and listed in a warning.
    - holding anything else: refused, with or without ``overwrite``.

    ``legacy(out)`` recognises a folder by another claim file (returns a marker dict). The folder must be
    writable: a probe file is written and removed. ``early``: write the marker now (else only at ``record``).
    """
    out = Path(out)
    check_outside_inputs(out, inputs)
    try:
        exists = out.exists()
        if exists and not out.is_dir():
            raise PavemapError(f"{out}: exists and is not a folder")
        busy = exists and any(p.name != LOCK_FILE for p in out.iterdir())
    except OSError as e:
        raise PavemapError(f"{out}: cannot be read ({e.strerror or e})") from None
    owner = read_owner(out) if busy else None
    if busy and owner is None and legacy is not None:
        owner = legacy(out)
    kept: list[str] = []
    files: set[str] = set()
    if busy and owner is None:
        raise PavemapError(f"{out}: folder is not empty and was not written by pavemap (no {MARKER}); "
                           + ("--overwrite only replaces a folder pavemap wrote; " if overwrite else "")
                           + "choose a new or empty folder")
    if owner is not None and owner.get("status") == "failed" and not owner.get("files"):
        kept = remove_owned(out, owner)  # a failed job that left nothing but its marker: free to reuse
        owner = None
    if owner is not None:
        if same is not None and same(owner):
            files = {r for r in owner.get("files", []) if isinstance(r, str)}
            kind = str(owner.get("kind", kind))  # e.g. fuse outputs added to a run folder: still a run
        elif not overwrite:
            of = f" (of {owner['source']})" if owner.get("source") else ""
            what = f"another {owner.get('kind', 'folder')}" if same else f"a pavemap {owner.get('kind', 'folder')}"
            raise PavemapError(f"{out}: holds {what}{of}; choose another --out or pass --overwrite (which deletes "
                               "only the files pavemap wrote there)")
        else:
            kept = remove_owned(out, owner)
    try:
        out.mkdir(parents=True, exist_ok=True)
        probe = out / f".write-test-{os.getpid()}"
        probe.write_text("")
        probe.unlink()
    except OSError as e:
        raise PavemapError(f"{out}: cannot write here ({e.strerror or e})") from None
    folder = OutputFolder(out, kind, dict(info or {}), _walk(out), files)
    if kept:
        folder.info["kept"] = kept[:20]
    if early:
        folder.record()
    return folder


__all__ = ["MARKER", "OutputFolder", "check_outside_inputs", "check_replaceable", "claim", "mark_written",
           "note_written", "read_owner", "remove_owned", "undo_on_failure", "writing"]
