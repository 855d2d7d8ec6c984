"""Not assessed is not perfect (issue 41): where a segment's condition index may be given at all.

A segment scores 100 when no defect was mapped in it, which is only true when the survey *could* have
mapped one. Two things can make it blind, and both turn the segment "not assessed" (no index, grade or
rating; its mapped defects still count and are listed) with the reason in ``not_assessed_reason``:

- **geometry** (:func:`assess_coverage`): the road must have been seen finely enough for the smallest defect
  the policy cares about. Points every ``SAMPLE_RES_M`` inside the segment's corridor, on the road surface,
  are graded by :func:`pavemap.geo.coverage.ground_resolution`: the best pixels per cm of road any view gave
  them at the detector's input (:func:`input_scale`) and how many views reached the policy's need
  (:meth:`pavemap.maintain.policy.Assessment.need_px_per_cm`: ``min_defect_px / min_defect_m``, 0.4 px/cm by
  default). A point is covered when ``min_views`` did; the segment is assessed when covered points make up
  ``min_covered_share`` of its road points (corridor points where the surface is valid and observed);
- **the detector** (:func:`detector_check`): on real footage, a detector that returns almost nothing at or
  above ``filter.tau_conf`` (domain shift: the shared nuScenes clip gave 7 of 60 boxes in 21 images) cannot
  tell a clean road from one it does not understand. The run logs a warning, ``metrics.json`` records it and
  every segment is not assessed (the map may be empty because of the detector, not the road).
"""

from __future__ import annotations

import logging
import math
from dataclasses import asdict, dataclass

import numpy as np

from pavemap.maintain.policy import Assessment, Policy
from pavemap.maintain.segments import Segment
from pavemap.types import Sequence

log = logging.getLogger("pavemap.maintain")

#: Spacing of the corridor's sample points (m): a cell of the survey layer's coarse grid.
SAMPLE_RES_M = 0.5
#: What the simulated detector needs across a defect: its ``min_pixels`` (12) visible pixels, as a square's side.
SIM_MIN_DEFECT_PX = math.sqrt(12.0)


@dataclass
class DetectorCheck:
    """The detector's confidence statistics of one run and whether they make it *low-confidence*.

    ``images``: views in the drive; ``confident``: valid boxes at or above ``tau_conf``; ``below_conf``:
    valid boxes below it; ``real``: not the simulated detector; ``low``: the rule of :func:`detector_check`.
    """

    real: bool
    images: int
    confident: int
    below_conf: int
    tau_conf: float | None
    low: bool
    message: str = ""

    def to_dict(self) -> dict:
        """``metrics.json → maintenance → detector_confidence``."""
        d = asdict(self)
        boxes = self.confident + self.below_conf
        d["confident_share"] = round(self.confident / boxes, 4) if boxes else None
        d["confident_per_image"] = round(self.confident / self.images, 4) if self.images else None
        return d


def input_scale(seq: Sequence, backend: str, imgsz: int | None = None) -> dict[str, float]:
    """Per camera: detector input pixels per image pixel. yolo letterboxes the long side to ``imgsz``
    (min(1, imgsz / max(W, H)): upscaling adds no detail); the simulated detector and a detections file
    work on the image itself (1)."""
    if backend != "yolo" or not imgsz:
        return {n: 1.0 for n in seq.cameras}
    return {n: min(1.0, float(imgsz) / max(c.width, c.height)) for n, c in seq.cameras.items()}


def detector_check(metrics: dict, seq: Sequence, real: bool, policy: Policy,
                   tau_conf: float | None = None) -> DetectorCheck:
    """Low-confidence rule on stage 2's counts (``metrics``: a FusionResult's ``total_detections``, the valid
    boxes at or above tau_conf, and ``below_conf``): real footage, and the confident boxes number fewer than
    ``min_confident_per_image`` per image *and* fewer than ``min_confident_share`` of all valid boxes (no box at
    all counts as low too). Logs the warning when low."""
    rule = policy.assessment
    images = sum(len(f.views) for f in seq.frames)
    good, below = int(metrics.get("total_detections", 0)), int(metrics.get("below_conf", 0))
    boxes = good + below
    low = (real and images > 0 and good < rule.min_confident_per_image * images
           and (boxes == 0 or good < rule.min_confident_share * boxes))
    msg = ""
    if low:
        tau = f" ({tau_conf:g})" if tau_conf is not None else ""
        msg = (f"the detector found almost nothing above filter.tau_conf{tau} on this footage: {good} of {boxes} "
               f"boxes in {images} images; the map may be empty because of the detector, not the road, so no "
               "segment is assessed (check the detector on this footage, e.g. detector.imgsz or other weights)")
        log.warning("%s", msg)
    return DetectorCheck(real, images, good, below, tau_conf, bool(low), msg)


def mark_not_assessed(seg: Segment, reason: str) -> None:
    """No index for ``seg`` (pci, grade, rating and corrected deduct None), ``reason`` added to its reasons."""
    seg.assessed = False
    seg.pci = seg.grade = seg.rating = seg.corrected_deduct = None
    seg.not_assessed_reason = "; ".join(r for r in (seg.not_assessed_reason, reason) if r)


def corridor_points(segments: list[Segment], res: float = SAMPLE_RES_M) -> tuple[np.ndarray, np.ndarray]:
    """Sample points inside the segments' corridors: (N, 2) world x, y on a ``res`` grid, (N,) int64 segment
    index (0-based, a point in two corridors at a bend counts for both)."""
    import shapely

    xy, which = [np.zeros((0, 2))], [np.zeros(0, dtype=np.int64)]
    for k, seg in enumerate(segments):
        x0, y0, x1, y1 = seg.polygon.bounds  # type: ignore[attr-defined]
        X, Y = np.meshgrid(np.arange(math.floor(x0 / res), math.ceil(x1 / res) + 1) * res,
                           np.arange(math.floor(y0 / res), math.ceil(y1 / res) + 1) * res)
        inside = shapely.contains_xy(seg.polygon, X, Y)
        xy.append(np.column_stack([X[inside], Y[inside]]))
        which.append(np.full(int(inside.sum()), k, dtype=np.int64))
    return np.concatenate(xy), np.concatenate(which)


def _on_road(xy: np.ndarray, surface: object | None, observed: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """(N,) height and (N,) bool road of points (N, 2): on the surface's valid triangles and, with ``observed``
    ((ny, nx) bool on its vertex grid), at an observed vertex. Without a surface: height 0, all road."""
    if surface is None:
        return np.zeros(len(xy)), np.ones(len(xy), dtype=bool)
    import torch

    z, inside = surface.height_at(torch.as_tensor(xy, dtype=surface.heights.dtype))  # type: ignore[attr-defined]
    z, road = z.detach().cpu().double().numpy(), inside.detach().cpu().numpy().astype(bool)
    if observed is not None:
        g = surface.grid  # type: ignore[attr-defined]
        i, j = g.to_cell(xy[:, 0], xy[:, 1])
        ok = g.contains(i, j)
        obs = np.zeros(len(xy), dtype=bool)
        obs[ok] = np.asarray(observed, dtype=bool)[j[ok], i[ok]]
        road &= obs
    if road.any():
        z[~road] = np.median(z[road])  # a height to grade unseen points by; they are not road either way
    return z, road


def assess_coverage(segments: list[Segment], seq: Sequence, policy: Policy, surface: object | None = None,
                    observed: np.ndarray | None = None, scale: dict[str, float] | None = None,
                    min_defect_px: float | None = None) -> None:
    """Each segment's ``coverage_share`` and ``px_per_cm_median`` (its road points' best resolution), and "not
    assessed" where the share is below the policy's (in place; module docstring). ``scale``: :func:`input_scale`;
    ``min_defect_px``: overrides the policy's pixels (the simulated detector's :data:`SIM_MIN_DEFECT_PX`)."""
    from pavemap.geo.coverage import ground_resolution

    if not segments:
        return
    rule: Assessment = policy.assessment
    need = rule.need_px_per_cm(min_defect_px)
    xy, which = corridor_points(segments)
    z, road = _on_road(xy, surface, observed)
    best, views = ground_resolution(seq, np.column_stack([xy, z]), need, scale)
    covered = road & (views >= rule.min_views)
    K = len(segments)
    n_road = np.bincount(which, weights=road, minlength=K)
    n_cov = np.bincount(which, weights=covered, minlength=K)
    for k, seg in enumerate(segments):
        mine = road & (which == k)
        seg.px_per_cm_median = round(float(np.median(best[mine])), 3) if mine.any() else None
        seg.coverage_share = round(float(n_cov[k] / n_road[k]), 3) if n_road[k] else 0.0
        if not n_road[k]:
            mark_not_assessed(seg, "no reconstructed, observed road surface in its corridor")
        elif seg.coverage_share < rule.min_covered_share:
            mark_not_assessed(seg, f"seen finely enough on {100 * seg.coverage_share:.0f} % of its road, "
                                   f"{100 * rule.min_covered_share:.0f} % needed (>= {need:.2g} px/cm at the "
                                   f"detector's input from {rule.min_views} view(s); median best "
                                   f"{seg.px_per_cm_median or 0:.2g} px/cm)")


def survey_inputs(seq: Sequence, backend: str, metrics: dict, policy: Policy, imgsz: int | None = None,
                  tau_conf: float | None = None) -> dict:
    """:func:`pavemap.maintain.assess`'s ``scale``, ``min_defect_px`` and ``check`` for a run whose detections came
    from ``backend`` ("sim", "yolo" or "file"; ``metrics`` the FusionResult's)."""
    sim = backend == "sim"
    return {"scale": input_scale(seq, backend, imgsz), "min_defect_px": SIM_MIN_DEFECT_PX if sim else None,
            "check": detector_check(metrics, seq, not sim, policy, tau_conf)}


def apply_detector_check(segments: list[Segment], check: DetectorCheck | None) -> None:
    """Every segment not assessed when the run is low-confidence (:func:`detector_check`)."""
    if check is not None and check.low:
        for seg in segments:
            mark_not_assessed(seg, "the detector found almost nothing above filter.tau_conf on this footage")


__all__ = ["SAMPLE_RES_M", "SIM_MIN_DEFECT_PX", "DetectorCheck", "apply_detector_check", "assess_coverage",
           "corridor_points", "detector_check", "input_scale", "mark_not_assessed", "survey_inputs"]
