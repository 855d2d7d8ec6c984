"""Which detector a run uses: ``auto`` resolved against the sequence, and the shipped YOLO weights.

``auto`` means the simulated detector where the sequence carries synthetic ground truth
(``truth/defects.geojson``: the simulator draws its detections from it), and the shipped YOLO
weights everywhere else (an imported drive has no truth to simulate from).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

from pavemap.detect.config import DetectorConfig
from pavemap.errors import PavemapError
from pavemap.types import Sequence
from pavemap.weights.registry import SHIPPED_WEIGHTS, candidates, known

TRUTH_DEFECTS = "truth/defects.geojson"


def weights_candidates() -> list[Path]:
    """Where the shipped weights are looked for: inside the installed package, then the user's weight folders
    (:func:`pavemap.weights.registry.candidates`)."""
    entry = known(SHIPPED_WEIGHTS)
    assert entry is not None
    return [p for _, p in candidates(entry)]


def shipped_weights() -> Path:
    """The shipped RDD2022 YOLO weights; a PavemapError saying where to put them when missing."""
    cands = weights_candidates()
    for p in cands:
        if p.is_file():
            return p
    raise PavemapError(
        f"{SHIPPED_WEIGHTS}: the shipped YOLO weights are missing (looked in {', '.join(str(p) for p in cands)}); "
        "reinstall pavemap, `pavemap weights install FILE.pt`, pass --weights PATH.pt, or train one with "
        "`pavemap train-detector`"
    )


def has_truth(seq: Sequence) -> bool:
    """True when the sequence is synthetic: it carries ``truth/defects.geojson``."""
    return seq.root is not None and (seq.root / TRUTH_DEFECTS).is_file()


def resolve_backend(config: DetectorConfig, seq: Sequence) -> tuple[DetectorConfig, str]:
    """A copy of ``config`` with a concrete backend (and yolo weights), and one line saying why.

    ``sim`` on a sequence without synthetic truth is a PavemapError naming what to use instead.
    """
    config.validate()
    backend = config.backend
    if backend == "auto":
        if has_truth(seq):
            backend, why = "sim", f"the sequence has synthetic truth ({TRUTH_DEFECTS})"
        else:
            backend, why = "yolo", f"the sequence has no {TRUTH_DEFECTS}, so the shipped YOLO weights"
    else:
        why = "asked for in the config"
    if backend == "sim" and not has_truth(seq):
        raise PavemapError(
            f"{seq.root / TRUTH_DEFECTS if seq.root else TRUTH_DEFECTS}: not found; the simulated detector needs "
            "synthetic truth (pavemap synth); use --detector yolo (shipped weights) or --detector file"
        )
    if backend == "sim" and not all(v.semantics for f in seq.frames for v in f.views.values()):
        raise PavemapError(f"{seq.root}: the simulated detector needs the semantic map of every view; use "
                           "--detector yolo or --detector file")
    weights = config.weights
    if backend == "yolo":
        if weights is None:
            weights = str(shipped_weights())
        elif not Path(weights).is_file():
            raise PavemapError(
                f"{weights}: weights file not found; put a YOLO detection .pt there "
                f"(e.g. {SHIPPED_WEIGHTS}) or train one with `pavemap train-detector`"
            )
        why += f" ({weights})"
    if backend == "file" and config.file is not None and not Path(config.file).exists():
        raise PavemapError(f"{config.file}: detections file not found (detector.file)")
    return dataclasses.replace(config, backend=backend, weights=weights), why


__all__ = ["SHIPPED_WEIGHTS", "has_truth", "resolve_backend", "shipped_weights", "weights_candidates"]
