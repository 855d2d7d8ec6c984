"""The run folder's bookkeeping: who owns it, which stages are done, and why a stage is redone.

A stage leaves a stamp ``.stages/<stage>.json`` when it finishes and ``.stages/<stage>.started.json``
when it begins, each holding the *parts* its result depends on (the sequence's hash, the config
fields that change the result, the files it reads, the pavemap code: :func:`code_version`) and their hash,
the key.
A rerun reuses a finished stage whose key matches; an interrupted stage resumes from its
checkpoint only when the started stamp matches, so the result is the one an uninterrupted run
gives; otherwise the stage is redone and the log says which parts changed.
"""

from __future__ import annotations

import dataclasses
import json
import time
from pathlib import Path

from pavemap.detect.config import DetectorConfig
from pavemap.errors import PavemapError
from pavemap.io.atomic import atomic_write_json
from pavemap.io.hashes import path_hash
from pavemap.io.owned import PARTIAL, OutputFolder, claim
from pavemap.io.sequence import DETECTIONS_FILE
from pavemap.types import Sequence
from pavemap.version import code_version

RUN_FILE = "run.json"
STAGES = ("mesh", "detect", "fuse", "evaluate", "export")
#: Written last by the export: a run folder holding it is complete.
COMPLETE = "metrics.json"
#: What a failed run keeps (what a rerun resumes from, and the log saying what failed); the rest of
#: what it wrote is deleted so that nothing looks complete.
RESUMABLE = ("mesh/", ".stages/", DETECTIONS_FILE, "run.log", "config.yaml", RUN_FILE)
#: Mesh config fields that do not change the mesh (``resume`` only says whether a checkpoint may be used).
MESH_NOT_RESULT = ("resume",)


def mesh_parts(seq_key: str, mesh_cfg: object) -> dict:
    """What stage 1's result depends on: the sequence, every result-changing mesh field, the version."""
    cfg = {k: v for k, v in dataclasses.asdict(mesh_cfg).items() if k not in MESH_NOT_RESULT}  # type: ignore[call-overload]
    return {"sequence": seq_key, "config": cfg, "version": code_version()}


def detect_parts(seq_key: str, detector: DetectorConfig, device: str, seq: Sequence) -> dict:
    """What stage 2a's result depends on: the sequence, the detector section, the files it reads
    (weights, class map, the detections file or folder: ``SEQ/detections.jsonl`` when none is named),
    the device (yolo only: other backends run on the CPU) and the version."""
    source = None
    if detector.backend == "file":
        source = detector.file if detector.file else (seq.root / DETECTIONS_FILE if seq.root else None)
    return {"sequence": seq_key, "config": dataclasses.asdict(detector), "version": code_version(),
            "weights": path_hash(detector.weights) if detector.backend == "yolo" else None,
            "class_map": path_hash(detector.class_map) if detector.backend == "yolo" else None,
            "source": path_hash(source), "device": device if detector.backend == "yolo" else None}


def why_changed(old: dict | None, new: dict) -> str:
    """What differs between the parts of an earlier stamp and now, in words (fields named)."""
    if not old:
        return "no earlier result"
    said = []
    for k in sorted(set(old) | set(new)):
        a, b = old.get(k), new.get(k)
        if a == b:
            continue
        if isinstance(a, dict) and isinstance(b, dict):
            fields = [f"{f} {a.get(f)!r} -> {b.get(f)!r}" for f in sorted(set(a) | set(b)) if a.get(f) != b.get(f)]
            said.append(f"{k}: " + ", ".join(fields[:6]) + (" ..." if len(fields) > 6 else ""))
        else:
            said.append(f"{k} changed")
    return "; ".join(said) or "the stamp is from an older pavemap"


# ---------------------------------------------------------------------------- stamps


class Stages:
    """The stamps under ``OUT/.stages``."""

    def __init__(self, out: Path, force: bool = False):
        self.dir = out / ".stages"
        self.dir.mkdir(parents=True, exist_ok=True)
        self.force = force

    def _read(self, name: str) -> dict | None:
        try:
            d = json.loads((self.dir / f"{name}.json").read_text())
        except (OSError, ValueError):
            return None
        return d if isinstance(d, dict) else None

    def done(self, name: str, key: str) -> bool:
        d = None if self.force else self._read(name)
        return d is not None and d.get("key") == key

    def parts(self, name: str) -> dict | None:
        """The parts of the stage's last stamp: the finished one, else the started one."""
        d = self._read(name) or self._read(f"{name}.started")
        return d.get("parts") if d else None

    def started_key(self, name: str) -> str | None:
        d = self._read(f"{name}.started")
        return d.get("key") if d else None

    def start(self, name: str, key: str, parts: dict) -> None:
        (self.dir / f"{name}.json").unlink(missing_ok=True)
        atomic_write_json(self.dir / f"{name}.started.json", {"key": key, "parts": parts, "started": time.time()})

    def mark(self, name: str, key: str, seconds: float, parts: dict | None = None) -> None:
        atomic_write_json(self.dir / f"{name}.json", {"key": key, "parts": parts, "seconds": seconds,
                                                      "finished": time.time()})

    def seconds(self, name: str) -> float | None:
        d = self._read(name)
        return d.get("seconds") if d else None

    def invalidate_after(self, name: str) -> None:
        for later in STAGES[STAGES.index(name) + 1:]:
            (self.dir / f"{later}.json").unlink(missing_ok=True)
            (self.dir / f"{later}.started.json").unlink(missing_ok=True)


# ---------------------------------------------------------------------------- the folder


def legacy_run(out: Path) -> dict | None:
    """A run folder claimed by ``run.json`` (format pavemap-run/1) without the marker: a run that was killed
    before its end, or one written before the marker existed. Its files are not known, so an overwrite
    deletes none of them."""
    try:
        d = json.loads((out / RUN_FILE).read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    if not isinstance(d, dict) or d.get("format") != "pavemap-run/1":
        return None
    return {"kind": "run", "source": d.get("sequence"), "files": []}


def prepare_out(out: Path, seq: Sequence, overwrite: bool, inputs: tuple = ()) -> OutputFolder:
    """Claim ``out`` for a run of ``seq`` (:func:`pavemap.io.owned.claim`): a rerun of the same sequence
    resumes; another run is replaced only with ``overwrite``; a folder pavemap did not write, or one inside
    an input, is refused. Stale temporaries and the previous completion marker are removed, so an
    interrupted rerun never looks complete."""
    if seq.root is None:
        raise PavemapError("pavemap.run needs a sequence read from a folder (seq.root is None)")
    source = str(seq.root.resolve())
    folder = claim(out, "run", overwrite, inputs=(seq.root, *inputs), info={"source": source},
                   same=lambda o: o.get("kind") == "run" and o.get("source") == source, legacy=legacy_run,
                   early=False)
    folder.remove_own(COMPLETE)
    for rel in folder.before:  # temporaries of a killed run (pavemap's by their name)
        if PARTIAL.match(Path(rel).name):
            (out / rel).unlink(missing_ok=True)
    # run.json claims the folder while the run goes on; the marker with the manifest follows at the end
    atomic_write_json(out / RUN_FILE, {"format": "pavemap-run/1", "sequence": source, "name": seq.name})
    return folder


def keep_on_failure(rel: str) -> bool:
    """Whether a failed run keeps the file ``rel`` (see RESUMABLE)."""
    return any(rel == k or (k.endswith("/") and rel.startswith(k)) for k in RESUMABLE)


__all__ = ["COMPLETE", "RUN_FILE", "STAGES", "Stages", "detect_parts", "keep_on_failure", "legacy_run", "mesh_parts",
           "prepare_out", "why_changed"]
