"""An OS lock on an output folder while a process writes it, so two runs never write one folder.

The lock is ``fcntl.flock`` on the file ``.pavemap-lock`` in the folder, which holds the owner's pid,
host, start time and command (JSON) for the message a second process shows. The kernel releases a
``flock`` when its process ends, however it ends: a lock file left by a killed process is free to take,
and is taken over with a warning naming the process that left it. A second process finds the lock
held and stops with a :class:`~pavemap.errors.PavemapError` naming the holder (the CLI: exit status 2).

The lock is per process and re-entrant: a run that calls another writer of the same folder (``fuse``
into its run folder) does not lock itself out. The lock file is pavemap's bookkeeping, not an output:
the manifest (:mod:`pavemap.io.owned`) neither lists nor counts it, and it is removed on release.
"""

from __future__ import annotations

import contextlib
import datetime as dt
import errno
import json
import os
import socket
import sys
import warnings
from collections.abc import Iterator
from pathlib import Path

from pavemap.errors import PavemapError

LOCK_FILE = ".pavemap-lock"
#: Folders this process holds: resolved path -> (fd, depth of nesting).
_HELD: dict[Path, list[int]] = {}


def _holder_text(d: dict) -> str:
    """``pavemap process 1234 on host box (`pavemap run`, since 2024-05-01 10:02:03)`` from a lock file's record."""
    what = f"`{d['command']}`, " if d.get("command") else ""
    return (f"pavemap process {d.get('pid', '?')} on host {d.get('host', '?')} "
            f"({what}since {d.get('started', '?')})")


def _read(fd: int) -> dict:
    try:
        os.lseek(fd, 0, os.SEEK_SET)
        d = json.loads(os.read(fd, 65536).decode("utf-8", "replace") or "{}")
    except (OSError, ValueError):
        return {}
    return d if isinstance(d, dict) else {}


def _command() -> str:
    args = [os.path.basename(sys.argv[0]) if sys.argv else "python", *sys.argv[1:3]]
    return " ".join(a for a in args if a)[:80]


def _open_locked(path: Path, option: str) -> int:
    """An fd of ``path`` holding its exclusive flock; PavemapError when another process holds it."""
    import fcntl

    while True:
        fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as e:
            holder = _read(fd)
            os.close(fd)
            if e.errno not in (errno.EAGAIN, errno.EWOULDBLOCK, errno.EACCES):
                raise
            raise PavemapError(f"{path.parent}: in use by {_holder_text(holder)}; wait for it to finish, or "
                               f"choose another {option}") from None
        # a process releasing the lock unlinks the file: holding a lock on a name-less inode would not stop a
        # third process that creates the file anew, so take the lock on what the name points to now
        try:
            same = os.path.samestat(os.fstat(fd), os.stat(path))
        except FileNotFoundError:
            same = False
        if same:
            return fd
        os.close(fd)


def acquire(folder: str | os.PathLike, option: str = "--out") -> None:
    """Lock ``folder`` (created when missing) for this process; PavemapError naming the holder when another
    live process has it. A lock file left by a process that ended is taken over with a warning."""
    folder = Path(folder)
    key = folder.resolve()
    if key in _HELD:
        _HELD[key][1] += 1
        return
    if folder.exists() and not folder.is_dir():
        raise PavemapError(f"{folder}: exists and is not a folder; choose another {option}")
    try:
        folder.mkdir(parents=True, exist_ok=True)
        fd = _open_locked(folder / LOCK_FILE, option)
    except PavemapError:
        raise
    except OSError as e:  # a read-only or full disk: the caller's check of the folder words it
        raise PavemapError(f"{folder}: cannot write here ({e.strerror or e})") from None
    before = _read(fd)
    if before.get("pid") is not None and (before.get("pid"), before.get("host")) != (os.getpid(), socket.gethostname()):
        warnings.warn(f"{folder}: took over the lock left by {_holder_text(before)}, which no longer holds it "
                      "(killed or crashed); a rerun resumes from what it finished", stacklevel=2)
    record = {"pid": os.getpid(), "host": socket.gethostname(),
              "started": dt.datetime.now().astimezone().isoformat(timespec="seconds"), "command": _command()}
    with contextlib.suppress(OSError):  # a full disk: the lock holds without its record
        os.ftruncate(fd, 0)
        os.pwrite(fd, json.dumps(record).encode(), 0)
    _HELD[key] = [fd, 1]


def release(folder: str | os.PathLike) -> None:
    """Undo one :func:`acquire` of ``folder``; the last one removes the lock file and drops the lock."""
    key = Path(folder).resolve()
    held = _HELD.get(key)
    if held is None:
        return
    held[1] -= 1
    if held[1] > 0:
        return
    del _HELD[key]
    with contextlib.suppress(OSError):  # unlinked while still locked: no other process can hold it meanwhile
        (key / LOCK_FILE).unlink()
    os.close(held[0])


@contextlib.contextmanager
def locked(folder: str | os.PathLike, option: str = "--out") -> Iterator[None]:
    """``with locked(out):`` hold the folder's lock (:func:`acquire`) for the body."""
    acquire(folder, option)
    try:
        yield
    finally:
        release(folder)


def holds(folder: str | os.PathLike) -> bool:
    """Whether this process holds ``folder``'s lock."""
    return Path(folder).resolve() in _HELD


__all__ = ["LOCK_FILE", "acquire", "holds", "locked", "release"]
