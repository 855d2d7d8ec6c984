"""Reading a user's detections: JSONL (SPEC §6) or YOLO txt files, one per image.

YOLO txt lines are ``cls cx cy w h [conf]`` normalised to the image size (ultralytics
``save_txt``/``save_conf`` output). A folder of them is matched to the sequence's views by
image file name: ``DIR/<camera>/<image stem>.txt`` or, with a single camera,
``DIR/<image stem>.txt``. Class ids are taken as RDD2022 ids (0 D00, 1 D10, 2 D20, 3 D40);
unknown ids and other unusable values are left for the filter to skip and count.
"""

from __future__ import annotations

import logging
import os
from pathlib import Path

from pavemap.errors import PavemapError
from pavemap.io.sequence import SequenceError, read_detections
from pavemap.types import Detection, Sequence

log = logging.getLogger("pavemap")


def read_yolo_txt(path: str | os.PathLike, frame: int, camera: str, width: int, height: int) -> list[Detection]:
    """Parse one YOLO txt file into pixel-box detections of view (frame, camera).

    A missing ``conf`` column means 1.0. Malformed lines raise SequenceError naming file and line.
    """
    path = Path(path)
    dets: list[Detection] = []
    try:
        lines = path.read_text(encoding="utf-8").splitlines()
    except OSError as e:
        raise SequenceError(path, f"cannot read YOLO labels ({e})") from None
    except UnicodeDecodeError as e:
        raise SequenceError(path, f"is not UTF-8 text (byte 0x{e.object[e.start]:02x} at offset {e.start})") from None
    for ln, line in enumerate(lines, 1):
        parts = line.split()
        if not parts:
            continue
        if len(parts) not in (5, 6):
            raise SequenceError(path, f"line {ln}: expected 'cls cx cy w h [conf]', got {len(parts)} fields")
        try:
            cls_f = float(parts[0])
            cx, cy, w, h = (float(x) for x in parts[1:5])
            conf = float(parts[5]) if len(parts) == 6 else 1.0
        except ValueError:
            raise SequenceError(path, f"line {ln}: non-numeric field in {line.strip()!r}") from None
        cls = int(cls_f) if cls_f.is_integer() else -1  # a fractional class id is unknown
        box = ((cx - w / 2) * width, (cy - h / 2) * height, (cx + w / 2) * width, (cy + h / 2) * height)
        dets.append(Detection(frame, camera, box, cls, conf))
    return dets


def read_yolo_dir(root: str | os.PathLike, seq: Sequence) -> list[Detection]:
    """All YOLO txt files under ``root`` matched to the views of ``seq`` (frame order, then camera)."""
    root = Path(root)
    single = len(seq.cameras) == 1
    dets: list[Detection] = []
    used: set[Path] = set()
    for f in seq.frames:
        for cam, v in f.views.items():
            stem = Path(v.image).stem
            candidates = [root / cam / f"{stem}.txt"] + ([root / f"{stem}.txt"] if single else [])
            for c in candidates:
                if c.is_file():
                    cam_info = seq.cameras[cam]
                    dets.extend(read_yolo_txt(c, f.index, cam, cam_info.width, cam_info.height))
                    used.add(c.resolve())
                    break
    unmatched = [p for p in root.rglob("*.txt") if p.resolve() not in used]
    if unmatched:
        log.warning("%d YOLO label file(s) match no view of the sequence and were skipped; first: %s",
                    len(unmatched), ", ".join(str(p) for p in unmatched[:3]))
    if not used:
        raise PavemapError(
            f"{root}: no YOLO label file matches a view (expected {root}/<camera>/<image stem>.txt"
            + (f" or {root}/<image stem>.txt" if single else "") + ")"
        )
    return dets


def detections_model(path: str | os.PathLike) -> str | None:
    """The ``model`` (sha256 of the weights) every line of a detections JSONL names, or None: YOLO txt files, an
    empty file, lines without it or naming different models (``pavemap detect`` writes it; other tools may not)."""
    import json

    path = Path(path)
    if not path.is_file() or path.suffix == ".txt":
        return None
    models: set[str | None] = set()
    with path.open(encoding="utf-8", errors="replace") as f:
        for line in f:
            if not line.strip():
                continue
            try:
                rec = json.loads(line)
            except (ValueError, RecursionError):
                return None  # load_detections names the bad line
            m = rec.get("model") if isinstance(rec, dict) else None
            models.add(m if isinstance(m, str) else None)
            if len(models) > 1:
                return None
    return next(iter(models)) if models else None


def load_detections(path: str | os.PathLike, seq: Sequence | None = None) -> list[Detection]:
    """Detections from a JSONL file (SPEC §6), a folder of YOLO txt files, or one YOLO txt file.

    A single txt file is accepted only when the sequence has exactly one view in total
    (otherwise it is ambiguous which view it belongs to; give the folder).
    """
    path = Path(path)
    if not path.exists():
        raise PavemapError(f"{path}: detections file or folder not found")
    if path.is_dir():
        if seq is None:
            raise PavemapError(f"{path}: reading a folder of YOLO txt files needs the sequence")
        return read_yolo_dir(path, seq)
    if path.suffix == ".txt":
        views = [(f.index, c) for f in (seq.frames if seq else []) for c in f.views]
        if seq is None or len(views) != 1:
            raise PavemapError(f"{path}: a single YOLO txt file is ambiguous; give the folder of txt files")
        frame, cam = views[0]
        c = seq.cameras[cam]
        return read_yolo_txt(path, frame, cam, c.width, c.height)
    return read_detections(path)
