"""Maintenance measures (issue 16): what to repair first.

The stage after fusion: fused instances in, the same instances out with what a road engineer needs,
and the road cut into segments with a condition index. Modules, following the data:

- :mod:`.chainage`  distance along the route and lateral offset (one implementation for all users);
- :mod:`.measure`   pothole depth / volume, crack length / orientation, alligator area from the 3D surface;
- :mod:`.policy`    the maintenance policy (YAML a city can replace): severity levels, certainty, urgency;
- :mod:`.segments`  chainage segments with a PCI-like condition index;
- :mod:`.assessment` where that index may be given at all ("not assessed" is not "perfect").

Record keys written into ``DefectInstance.extra`` are listed in
:data:`pavemap.export.geojson.PROPERTY_SCHEMA` (the one defect schema).
"""

from __future__ import annotations

import os
from typing import TYPE_CHECKING

import numpy as np

from pavemap.geometry.chainage import chainage, route_polyline
from pavemap.maintain.assessment import DetectorCheck, apply_detector_check, assess_coverage
from pavemap.maintain.config import MaintenanceConfig
from pavemap.maintain.policy import (
    POSITIONS,
    UNASSESSED,
    Policy,
    certainty,
    lane_positions,
    load_policy,
    priority_ranks,
    severity_of,
    urgency,
)
from pavemap.maintain.segments import Segment, build_segments
from pavemap.types import DefectInstance, Sequence

if TYPE_CHECKING:  # measure imports scipy: loaded when the stage runs, not with the package
    from pavemap.maintain.measure import MeasureConfig


def _policy(policy: Policy | str | os.PathLike | None) -> Policy:
    return policy if isinstance(policy, Policy) else load_policy(policy)


def measures_of(inst: DefectInstance) -> dict:
    """The measures dict of a mapped defect for the policy: its extras plus ``area_m2`` and ``length_m``."""
    return {**inst.extra, "area_m2": float(inst.area_m2), "length_m": float(inst.length_m)}


def assess_instances(instances: list[DefectInstance], route: np.ndarray | None,
                     policy: Policy | str | os.PathLike | None = None, lane_width_m: float | None = None) -> None:
    """Severity level, certainty, chainage / offset / lane position, urgency and rank of every instance (in place).

    route (M, 2) world metres (:func:`route_polyline`), or None / empty: then chainage, offset and lane
    position stay unset and urgency takes the largest position weight (a defect of unknown position may
    lie in a wheel path). Sets ``inst.priority`` to the urgency text and ``extra`` keys severity_level,
    certainty, chainage_m, offset_m, lane_position, urgency_score, priority_rank; a severity taken from a
    fallback measure (a pothole without a measurable depth: its area) is named in ``measure_note``.
    """
    pol = _policy(policy)
    if not instances:
        return
    have_route = route is not None and len(route) > 0
    if have_route:
        xy = np.array([inst.centroid for inst in instances], dtype=np.float64).reshape(-1, 2)
        s, o = chainage(np.asarray(route, dtype=np.float64), xy)
        pos = lane_positions(o, pol, lane_width_m)
    worst = max(POSITIONS, key=lambda p: pol.position_weight[p])
    scores = []
    for k, inst in enumerate(instances):
        m = measures_of(inst)
        level, used, value = severity_of(inst.cls, m, pol)
        if used != pol.severity[inst.cls].measure:  # the class's fallback decided: say so in the record
            why = str(inst.extra.get("measure_note") or f"no {pol.severity[inst.cls].measure}")
            inst.extra["measure_note"] = f"{why}; severity from {used} = {value:.3g}"
        ex = inst.extra
        ex["severity_level"] = level
        ex["certainty"] = certainty(inst.probability, inst.observations, pol)
        if have_route:
            ex["chainage_m"] = round(float(s[k]), 2)
            ex["offset_m"] = round(float(o[k]), 2)
            ex["lane_position"] = str(pos[k])
        inst.priority, score = urgency(inst.cls, level, m, str(pos[k]) if have_route else worst, pol)
        ex["urgency_score"] = score
        scores.append(score)
    ranks = priority_ranks([i.priority for i in instances], scores, [i.id for i in instances])
    for inst, r in zip(instances, ranks, strict=True):
        inst.extra["priority_rank"] = r


def assess(instances: list[DefectInstance], seq: Sequence, surface=None, labels: np.ndarray | None = None,  # noqa: ANN001
           observed=None, policy: Policy | str | os.PathLike | None = None, segment_m: float = 100.0,  # noqa: ANN001
           lane_width_m: float | None = None, samples: np.ndarray | None = None,
           measure: MeasureConfig | None = None, floor_sweep: bool = False, *,
           scale: dict[str, float] | None = None, min_defect_px: float | None = None,
           check: DetectorCheck | None = None) -> list[Segment]:
    """The maintenance stage: measure, grade and rank the fused instances (in place) and cut the road into segments.

    instances: stage 3's :class:`DefectInstance` list; seq: the drive (its trajectory is the route);
    surface: the HeightField the instances lie on (None: no surface measures, severity from the
    fallback measures); labels (ny, nx) int32 instance ids on the surface's vertex grid
    (``FusionResult.instance_labels``); observed (ny, nx) bool or None (the mesh's observed layer);
    policy: a :class:`Policy`, a policy YAML path, or None / "" for the built-in one; samples (N, 3) the
    mesh's height measurements (``RoadMesh.samples``) or None, to which the sequence's full-resolution depth
    pixels under the potholes are added (:func:`pavemap.maintain.samples.depth_samples`); measure: the
    :class:`~pavemap.maintain.measure.MeasureConfig` (default: ``surface_floor`` False, a pothole's depth only
    from measurements inside it, see :func:`_pothole_samples`); floor_sweep: without a depth layer, measure the
    floors by :func:`pavemap.maintain.floor_sweep.floor_samples`. ``scale`` (detector input pixels per image pixel
    per camera, :func:`pavemap.maintain.assessment.input_scale`; None: 1), ``min_defect_px`` (None: the policy's)
    and ``check`` (:func:`pavemap.maintain.assessment.detector_check`, or None) decide which segments are
    "not assessed" (:mod:`pavemap.maintain.assessment`).

    Runs :func:`pavemap.maintain.measure.measure_instances` (depth, volume, crack length, orientation) ->
    chainage, offset, lane position -> severity level, certainty -> urgency, priority rank ->
    segments (each instance's ``extra["segment"]``) -> coverage, not assessed. Returns the segments
    (``FusionResult.segments``).
    """
    from pavemap.maintain.measure import MeasureConfig, measure_instances

    pol = _policy(policy)
    route = route_polyline(seq.trajectory()) if seq.frames else np.zeros((0, 2))
    outlines = {i.id: i.extra.pop("footprint_outline", None) for i in instances}  # fusion's, never exported
    if surface is not None:
        mcfg = measure or MeasureConfig(surface_floor=False)
        measure_instances(instances, surface, labels, observed=observed, route=route if len(route) else None,
                          samples=_pothole_samples(instances, seq, samples, surface if floor_sweep else None,
                                                   outlines, mcfg.min_samples),
                          config=mcfg)
    adopt_footprint_sizes(instances)
    assess_instances(instances, route, pol, lane_width_m)
    if len(route) == 0:
        return []
    records = [{**measures_of(i), "cls": i.cls} for i in instances]
    segments = build_segments(route, records, pol, segment_m, lane_width_m)
    for inst, r in zip(instances, records, strict=True):
        inst.extra["segment"] = r.get("segment")
    assess_coverage(segments, seq, pol, surface, observed, scale, min_defect_px)
    apply_detector_check(segments, check)
    return segments


def _pothole_samples(instances: list[DefectInstance], seq: Sequence, samples: np.ndarray | None,
                     surface=None, outlines: dict | None = None,  # noqa: ANN001
                     min_samples: int = 5) -> np.ndarray | None:
    """The height measurements that can measure a pothole's floor: where the drive has a depth layer, the mesh's
    samples plus the depth pixels under the potholes (their polygons' boxes, 0.7 m wider); without one None,
    and with ``surface`` each pothole gets its own floor samples from the images (:func:`_sweep_floors`).

    Without depth the mesh's samples are not used: they are triangulated ground points, matched by a sweep of
    horizontal planes over the whole road (exact on flat road, not in a dent), and inside a pothole they sit on
    the rim and the far wall (on the bench's no-depth kitti-like drive 5 potholes' depths came out 16-76 mm
    off, median 23 mm).
    """
    pots = [i for i in instances if i.cls == 3 and i.polygon is not None and not i.polygon.is_empty]
    if not any(v.depth for f in seq.frames for v in f.views.values()):
        if surface is not None:
            _sweep_floors(pots, seq, surface, outlines or {}, min_samples)
        return None
    from pavemap.maintain.samples import depth_samples

    boxes = np.array([np.asarray(i.polygon.bounds) + [-0.7, -0.7, 0.7, 0.7] for i in pots]).reshape(-1, 4)
    extra = depth_samples(seq, boxes) if len(boxes) else np.zeros((0, 3))
    parts = [p for p in (samples, extra) if p is not None and len(p)]
    return np.concatenate(parts).astype(np.float64) if parts else np.zeros((0, 3))


def _sweep_floors(pots: list[DefectInstance], seq: Sequence, surface, outlines: dict,  # noqa: ANN001
                  min_samples: int) -> None:
    """Each pothole's floor samples and their road plane from :func:`pavemap.maintain.floor_sweep.floor_sets` into
    ``extra["floor_samples"]`` (measure takes them out), and the sweep's reason where it found fewer than
    ``min_samples`` into ``extra["floor_sweep_note"]``. The sweep's outline: the finest detection's footprint
    scaled to the inscribed ellipse's area (:data:`pavemap.fuse.footprint.FILL`), else the fused polygon. One
    sweep over all potholes, so neighbours along the route share their decoded images."""
    from shapely import affinity
    from shapely.geometry import Polygon

    from pavemap.fuse.footprint import FILL
    from pavemap.maintain.floor_sweep import floor_sets

    k = float(np.sqrt(FILL[3]))
    polys = []
    for inst in pots:
        quad = outlines.get(inst.id)
        poly = Polygon(quad) if quad else None
        ok = poly is not None and poly.is_valid and poly.area > 0
        polys.append(affinity.scale(poly, k, k, origin="centroid") if ok else inst.polygon)
    for inst, (pts, why, plane) in zip(pots, floor_sets(seq, polys, surface), strict=True):
        note = why or (f"{len(pts)} floor-sweep cells inside it, {min_samples} needed" if len(pts) < min_samples
                       else "")
        inst.extra["floor_sweep_note"] = note
        if not note:  # measured from the road plane the sweep measured them from
            inst.extra["floor_samples"] = (pts, plane)


def adopt_footprint_sizes(instances: list[DefectInstance]) -> None:
    """The measured size of each defect from its detections' footprints (:mod:`pavemap.fuse.footprint`), in place.

    ``area_m2`` of a pothole or an alligator patch becomes the footprint estimate, ``crack_length_m`` of a crack
    the footprint's length, where any detection gave a footprint; the fused vertices' own area (what the
    polygon covers: the hit association's disks around each detection's hit) stays as ``mapped_area_m2``, the
    skeleton length as ``skeleton_length_m``; ``size_views`` counts the footprints. Measured on the maintenance
    bench drives: the vertex union misses the area by 40-60 % and the skeleton the length by 60-70 %.
    """
    for inst in instances:
        ex = inst.extra
        area, length = ex.pop("footprint_area_m2", None), ex.pop("footprint_length_m", None)
        ex["size_views"] = int(ex.pop("footprint_views", 0) or 0)
        ex["mapped_area_m2"] = round(float(inst.area_m2), 4)
        if inst.cls in (2, 3) and area is not None:
            inst.area_m2 = float(area)
        if inst.cls in (0, 1) and length is not None:
            ex["skeleton_length_m"] = ex.get("crack_length_m")
            ex["crack_length_m"] = float(length)


def summary(instances: list[DefectInstance], segments: list[Segment], check: DetectorCheck | None = None) -> dict:
    """``metrics.json``'s ``maintenance`` entry: defects per priority, severity level and certainty; the index over
    the assessed segments only; assessed and not-assessed segments and their length; the detector check."""
    from collections import Counter

    def count(key: str) -> dict:
        return dict(Counter(str(i.extra.get(key)) for i in instances if i.extra.get(key) is not None))

    pci = [s.pci for s in segments if s.pci is not None]
    out = {"priority": dict(Counter(i.priority for i in instances)), "severity_level": count("severity_level"),
           "certainty": count("certainty"), "segments": len(segments),
           "pci_mean": round(float(np.mean(pci)), 1) if pci else None,
           "pci_min": round(float(np.min(pci)), 1) if pci else None,
           "index": "PCI-like, not a certified ASTM D6433 survey"}
    for name, sel in (("assessed", True), ("not_assessed", False)):
        mine = [s for s in segments if s.assessed is sel]
        out[f"{name}_segments"] = len(mine)
        out[f"{name}_length_m"] = round(sum(s.end_m - s.start_m for s in mine), 1)
    out["not_assessed_reasons"] = dict(Counter(s.not_assessed_reason for s in segments if not s.assessed))
    if check is not None:
        out["detector_confidence"] = check.to_dict()
    return out


__all__ = ["UNASSESSED", "MaintenanceConfig", "Policy", "Segment", "adopt_footprint_sizes", "assess",
           "assess_instances", "load_policy", "measures_of", "summary"]
