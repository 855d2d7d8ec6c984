"""Which detector a run uses: ``auto`` resolved against the sequence, and the shipped YOLO weights.

``auto`` means the simulated detector where the sequence carries synthetic ground truth
(``truth/defects.geojson``: the simulator draws its detections from it), and the shipped YOLO
weights everywhere else (an imported drive has no truth to simulate from).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

from pavemap.detect.config import PAPER_TAU_CONF, DetectorConfig, FilterConfig
from pavemap.errors import PavemapError
from pavemap.io.sequence import DETECTIONS_FILE
from pavemap.types import Sequence
from pavemap.weights.registry import SHIPPED_WEIGHTS, by_sha256, candidates, known, sha256_of

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


def detector_model(detector: DetectorConfig, seq: Sequence) -> str | None:
    """The sha256 of the model behind a resolved detector's boxes, or None (the simulated detector; a detections
    file that does not name its model): yolo weights are hashed, a file gives its lines' ``model``."""
    if detector.backend == "yolo" and detector.weights is not None:
        return sha256_of(detector.weights)
    if detector.backend == "file":
        from pavemap.detect.sources import detections_model

        path = Path(detector.file) if detector.file else (seq.root / DETECTIONS_FILE if seq.root else None)
        return detections_model(path) if path is not None else None
    return None


def resolve_tau_conf(tau_conf: float | None, preset: str, model_sha256: str | None) -> tuple[float, str]:
    """The confidence threshold of a run, and one line saying why.

    A number given in the config wins. Else (None) the detector's operating point: the measured one of weights
    the registry knows by hash (:attr:`pavemap.weights.registry.KnownWeights.tau_conf`), else the paper's for
    the preset (:data:`pavemap.detect.config.PAPER_TAU_CONF`: the simulated detector is calibrated to it; other
    weights have not been measured by pavemap).
    """
    if tau_conf is not None:
        return float(tau_conf), "set in the config"
    if preset not in PAPER_TAU_CONF:
        raise PavemapError(f"unknown preset {preset!r}; choose one of {', '.join(PAPER_TAU_CONF)}")
    entry = by_sha256(model_sha256) if model_sha256 else None
    if entry is not None and entry.tau_conf is not None:
        return entry.tau_conf, (f"the measured operating point of {entry.file} (docs/guide/detector.md; "
                                "--set filter.tau_conf=... to change)")
    paper = PAPER_TAU_CONF[preset]
    if model_sha256 is None:
        return paper, f"the paper's for the {preset} preset"
    return paper, (f"the paper's for the {preset} preset: these weights' operating point is not measured "
                   "(bench/detector_thresholds.py measures it; --set filter.tau_conf=... to change)")


def resolved_filter(filter_config: FilterConfig, preset: str, model_sha256: str | None) -> tuple[FilterConfig, str]:
    """A copy of ``filter_config`` with ``tau_conf`` resolved for the model behind the boxes (:func:`detector_model`;
    None for the simulated detector), and one line saying which threshold and why."""
    tau, why = resolve_tau_conf(filter_config.tau_conf, preset, model_sha256)
    return dataclasses.replace(filter_config, tau_conf=tau), f"filter.tau_conf {tau:g} ({why})"


__all__ = ["SHIPPED_WEIGHTS", "detector_model", "has_truth", "resolve_backend", "resolve_tau_conf", "resolved_filter",
           "shipped_weights", "weights_candidates"]
