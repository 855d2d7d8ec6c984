"""The rest of a clip SfM cut: every stretch outside the part an import kept gets its own try.

SfM keeps the longest consistent part of a clip (:mod:`pavemap.sfm.parts`); a covered lens, a tunnel or a
wall of fog in the middle leaves a good stretch on each side. Each stretch of at least
``PartLimits.min_frames`` frames before or after the kept part is imported on its own, as a sequence of its
own under ``OUT/parts/frames-FIRST-LAST/`` (its own metric path: nothing ties its position to the main part's
across the gap, so it is not put in the same frame), and what its import kept splits the stretch again,
until no stretch long enough is left. A stretch SfM refuses keeps its ``sfm.json`` / ``sfm.png`` there.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

from pavemap.errors import PavemapError
from pavemap.sfm.parts import PartLimits
from pavemap.types import Sequence

PARTS_DIR = "parts"

#: (images of the stretch, destination folder, frame number of its first image) -> the imported sequence
ImportPart = Callable[[list[Path], Path, int], Sequence]


def part_folder(first: int, last: int) -> str:
    """``parts/frames-FIRST-LAST``, relative to the import's output folder."""
    return f"{PARTS_DIR}/frames-{first:06d}-{last:06d}"


def import_other_parts(images: list[Path], kept: tuple[int, int], out: Path, import_part: ImportPart,
                       min_frames: int | None = None, max_tries: int = 8) -> list[dict]:
    """Import every stretch of ``images`` (the whole clip, frame k = ``images[k]``) outside ``kept`` (first,
    last frame of the part the main import kept) of at least ``min_frames`` images. Returns one row per try,
    in frame order: ``frames`` [first, last] of the stretch, ``status`` "imported" (with ``folder``,
    ``kept`` [first, last] and ``frames_kept``) or "refused" (with ``reason``). ``max_tries`` bounds the SfM
    runs a clip cut into many pieces costs."""
    n_min = PartLimits().min_frames if min_frames is None else min_frames
    todo = [(0, kept[0] - 1), (kept[1] + 1, len(images) - 1)]
    rows: list[dict] = []
    while todo and len(rows) < max_tries:
        a, b = todo.pop(0)
        if b - a + 1 < n_min:
            continue
        dest = out / part_folder(a, b)
        try:
            seq = import_part(images[a:b + 1], dest, a)
        except PavemapError as e:
            rows.append({"frames": [a, b], "status": "refused", "reason": str(e), "folder": part_folder(a, b)})
            continue
        got = [f.index for f in seq.frames]
        lo, hi = min(got), max(got)
        rows.append({"frames": [a, b], "status": "imported", "folder": part_folder(a, b), "kept": [lo, hi],
                     "frames_kept": len(got)})
        todo += [(a, lo - 1), (hi + 1, b)]
    return sorted(rows, key=lambda r: r["frames"][0])


def imported_parts(report: dict) -> list[str]:
    """The folders (relative to the import's output) of the parts ``sfm.json``'s ``other_parts`` says were
    imported."""
    return [r["folder"] for r in report.get("other_parts") or [] if r.get("status") == "imported"]


__all__ = ["PARTS_DIR", "ImportPart", "import_other_parts", "imported_parts", "part_folder"]
