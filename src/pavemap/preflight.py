"""What a run checks before its first long stage, and how a failed write is worded.

- Every frame's files are decoded in full up front by the code ``pavemap info`` uses
  (:func:`pavemap.io.sequence.validate_sequence` with ``deep``): a truncated or corrupt JPEG is an error
  naming the file, not a half-grey frame that stage 1 trains on (libjpeg only prints "Premature end of
  JPEG file" and decodes the rest as grey). ``skip_bad_frames`` drops such frames with a warning instead.
- Detector weights must be a PyTorch file (a zip archive or a pickle), not a truncated download.
- A write that fails (disk full, quota, read-only, permission) becomes one line naming the folder and the
  cause; ``torch.save`` reports a full disk as a RuntimeError ("unexpected pos", "file write failed"),
  which is worded the same.
"""

from __future__ import annotations

import contextlib
import dataclasses
import errno
import logging
import os
import shutil
import warnings
import zipfile
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

from PIL import ImageFile

from pavemap.errors import TORCH_WRITE_FAILED, PavemapError, SequenceError
from pavemap.io.sequence import Problem, validate_sequence
from pavemap.types import Sequence

log = logging.getLogger("pavemap")

#: Frames per task of the up-front decode (threads: PIL and OpenCV decode outside the GIL).
CHUNK = 16
#: Errnos of a write the environment refused, with their words.
WRITE_ERRNOS = {errno.ENOSPC: "no space left on device", errno.EDQUOT: "disk quota exceeded",
                errno.EROFS: "read-only file system", errno.EACCES: "permission denied",
                errno.EPERM: "operation not permitted"}


def frame_problems(seq: Sequence, threads: int | None = None) -> list[Problem]:
    """Every problem of every frame's files, each image decoded in full (``pavemap info``'s check), in frame
    order; problems of the whole sequence (``detections.jsonl``) last. A truncated image is a problem even
    where a library was told to load truncated images."""
    chunks = [dataclasses.replace(seq, frames=seq.frames[i:i + CHUNK]) for i in range(0, len(seq.frames), CHUNK)]
    threads = threads or min(8, os.cpu_count() or 1)
    old, ImageFile.LOAD_TRUNCATED_IMAGES = ImageFile.LOAD_TRUNCATED_IMAGES, False
    try:
        with ThreadPoolExecutor(threads) as pool:
            parts = list(pool.map(lambda c: validate_sequence(c, deep=True, max_problems=10**9, detections=False),
                                  chunks))
    finally:
        ImageFile.LOAD_TRUNCATED_IMAGES = old
    whole = [p for p in validate_sequence(dataclasses.replace(seq, frames=[]), max_problems=5)]
    return [p for part in parts for p in part] + whole


def check_frames(seq: Sequence, skip_bad: bool = False) -> Sequence:
    """``seq`` when every frame's files decode and fit; else SequenceError naming the first bad files, or with
    ``skip_bad`` a copy without the bad frames and a warning listing them (an error when none is left)."""
    problems = frame_problems(seq)
    if not problems:
        return seq
    whole = [p for p in problems if p.frame is None]
    if whole or not skip_bad:
        first = (whole or problems)[0]
        rest = len(problems) - 1
        more = f"; and {rest} more problem(s)" if rest else ""
        hint = "" if whole else " (run `pavemap info` for the list; --skip-bad-frames makes a map without them)"
        raise SequenceError(first.file, first.message + more + hint)
    bad: dict[int, Problem] = {}
    for p in problems:
        bad.setdefault(p.frame, p)  # type: ignore[arg-type]
    kept = [f for f in seq.frames if f.index not in bad]
    if not kept:
        raise SequenceError(problems[0].file, f"{problems[0].message}; every frame has a damaged file, none left")
    listed = ", ".join(f"frame {i} ({p.file}: {p.message})" for i, p in list(bad.items())[:5])
    warnings.warn(f"--skip-bad-frames: skipped {len(bad)} of {len(seq.frames)} frame(s) with damaged files: {listed}"
                  + (f" and {len(bad) - 5} more" if len(bad) > 5 else ""), stacklevel=2)
    return dataclasses.replace(seq, frames=kept)


def check_weights(path: str | os.PathLike | None) -> None:
    """PavemapError when ``path`` is not a PyTorch weights file: a zip archive (``torch.save``) or a pickle.
    Cheap (the header and the zip directory), so a truncated download stops a run before stage 1."""
    if path is None:
        return
    p = Path(path)
    try:
        with p.open("rb") as f:
            head = f.read(2)
        ok = zipfile.is_zipfile(p) or head[:1] == b"\x80"  # a pickle starts with PROTO
    except OSError as e:
        raise PavemapError(f"{p}: cannot read the weights ({e.strerror or e})") from None
    if not ok:
        raise PavemapError(f"{p}: not loadable as PyTorch weights (neither a torch.save zip archive nor a pickle: "
                           "a truncated download or another format?)")


def write_failure(e: BaseException, folder: str | os.PathLike) -> PavemapError | None:
    """One line for a write into ``folder`` the environment refused (disk full, quota, read-only, permission),
    or None when ``e`` is something else. A rerun after freeing space resumes."""
    folder = Path(folder)
    if isinstance(e, OSError) and e.errno in WRITE_ERRNOS:
        words = WRITE_ERRNOS[e.errno]
        where = f" (writing {e.filename})" if e.filename else ""
        return PavemapError(f"{folder}: {words}{where}; {_remedy(e.errno, folder)}")
    if isinstance(e, RuntimeError) and any(s in str(e) for s in TORCH_WRITE_FAILED):
        free = _free_mb(folder)
        said = f" ({free:.0f} MB free)" if free is not None else ""
        return PavemapError(f"{folder}: a checkpoint write failed, no space left on device?{said}; "
                            f"{_remedy(errno.ENOSPC, folder)}")
    return None


def _remedy(code: int | None, folder: Path) -> str:
    if code in (errno.ENOSPC, errno.EDQUOT):
        return "free some space (or choose --out on another disk), then rerun: it resumes where it stopped"
    return f"choose a writable --out (not {folder})"


def _free_mb(folder: Path) -> float | None:
    for p in (folder, *folder.parents):
        with contextlib.suppress(OSError):
            return shutil.disk_usage(p).free / 2**20
    return None


class QuietFileHandler(logging.FileHandler):
    """``run.log``: a log line that cannot be written (the disk that failed the run is full) is dropped, not
    printed with a traceback; the error itself reaches the user."""

    def handleError(self, record: logging.LogRecord) -> None:  # noqa: N802 - logging's name
        pass


__all__ = ["QuietFileHandler", "check_frames", "check_weights", "frame_problems", "write_failure"]
