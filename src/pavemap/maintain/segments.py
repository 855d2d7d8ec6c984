"""Road segments of chainage with a PCI-like condition index (issue 16).

The driven route is cut into segments of ``segment_m`` metres of chainage (default 100 m); a last
piece shorter than ``merge_short_fraction * segment_m`` (policy, default half) joins the segment
before it, a longer one stays a short segment of its own. Each segment has a corridor polygon (the
route piece buffered by half the corridor width, ``corridor_lanes`` lane widths) whose area is the
density's denominator, like ASTM D6433's sample unit. A defect belongs to the segment of its chainage
(its offset does not matter, so a defect just outside the corridor still counts).

The index is **PCI-like, not a certified ASTM D6433 survey**. It follows D6433's steps with stated
simplifications:

1. density per distress type and severity level, in per cent of the corridor area: potholes by count,
   cracks (D00, D10) by length, alligator cracking (D20) by area (D6433's units);
2. a deduct value per type and level, ``scale * log10(1 + density / knee)`` capped at 100 (policy
   ``segments.deduct``): the shape of D6433's curves, not values digitised from them;
3. the corrected deduct value by D6433's iteration (q = deducts above 2; reduce the smallest one above
   2 to 2 and repeat; take the largest corrected value), with the curves CDV = TDV / (1 + 0.18 (q - 1))
   (q = 1: CDV = TDV), a linear stand-in for D6433's CDV charts. D6433's cap on the number of deducts
   (m = 1 + 9/98 (100 - HDV)) is left out: it can raise the index when one distress worsens, and
   leaving it out keeps the index monotone (never higher) in every density;
4. index = 100 - max CDV, clipped to [0, 100]; grade 1 (very good) .. 5 (very bad) from the index
   like vialytics / RoadBotics (policy ``segments.grades``), and D6433's rating words.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from shapely.geometry import LineString, Point
from shapely.ops import substring

from pavemap.geometry.chainage import cumulative_length
from pavemap.maintain.policy import LEVELS, Policy, load_policy, measure_value
from pavemap.types import DEFECT_CODES

#: CDV = TDV / (1 + CDV_Q_SLOPE * (q - 1)): a linear stand-in for D6433's corrected-deduct curves.
CDV_Q_SLOPE = 0.18
#: D6433's rating words by index (lower bound, word), best first.
RATINGS: tuple[tuple[float, str], ...] = ((85, "good"), (70, "satisfactory"), (55, "fair"), (40, "poor"),
                                          (25, "very poor"), (10, "serious"), (0, "failed"))
#: The quantity a class's density counts (D6433): potholes by number, cracks by length, alligator by area.
DENSITY_QUANTITY = {0: "crack_length_m", 1: "crack_length_m", 2: "area_m2", 3: "count"}
#: The one record schema of a segment (segments.csv, the ``segments`` GIS layer): (name, type, unit, meaning).
SEGMENT_SCHEMA: tuple[tuple[str, str, str, str], ...] = (
    ("segment", "int", "", "segment id, from 1 along the route"),
    ("chainage_start_m", "float", "m", "chainage where the segment starts (distance along the route)"),
    ("chainage_end_m", "float", "m", "chainage where it ends"),
    ("length_m", "float", "m", "its length along the route"),
    ("corridor_area_m2", "float", "m²", "area of its corridor (the density's denominator)"),
    ("assessed", "bool", "", "whether the survey saw the segment well enough for an index (false: not assessed)"),
    ("pci", "float", "0-100", "PCI-like condition index (100 = no defects; not a certified ASTM D6433 survey); "
                              "null when not assessed"),
    ("grade", "int", "1-5", "condition grade 1 very good .. 5 very bad, from the index; null when not assessed"),
    ("rating", "str", "", "ASTM D6433 rating word of the index (good .. failed); null when not assessed"),
    ("not_assessed_reason", "str", "", "why the segment has no index (empty when assessed)"),
    ("coverage_share", "float", "0-1", "share of its road seen finely enough for the smallest defect the policy "
                                       "cares about (policy assessment)"),
    ("px_per_cm_median", "float", "px/cm", "median over its road of the best resolution any view gave, in pixels "
                                           "per cm at the detector's input"),
    ("defects", "int", "count", "defects in the segment"),
    *((f"n_{c}", "int", "count", f"{c} defects") for c in DEFECT_CODES),
    *((f"length_m_{c}", "float", "m", f"summed length of its {c} defects (cracks: skeleton length)")
      for c in DEFECT_CODES),
    *((f"area_m2_{c}", "float", "m²", f"summed area of its {c} defects") for c in DEFECT_CODES),
    ("total_deduct", "float", "", "sum of its deduct values"),
    ("corrected_deduct", "float", "", "corrected deduct value (100 - pci)"),
    ("deducts", "str", "", "deduct value per class and severity level: code level density%: value"),
)


@dataclass
class Segment:
    """One road segment. ``polygon`` is the corridor in world x, y metres."""

    id: int
    start_m: float
    end_m: float
    polygon: object
    corridor_area_m2: float
    counts: dict[str, int] = field(default_factory=dict)
    lengths_m: dict[str, float] = field(default_factory=dict)
    areas_m2: dict[str, float] = field(default_factory=dict)
    deducts: list[dict] = field(default_factory=list)  # {code, level, density_pct, deduct}
    total_deduct: float = 0.0
    corrected_deduct: float | None = 0.0
    pci: float | None = 100.0  # None: not assessed (pavemap.maintain.assessment)
    grade: int | None = 1
    rating: str | None = "good"
    assessed: bool = True
    not_assessed_reason: str = ""
    coverage_share: float | None = None  # None: coverage not evaluated
    px_per_cm_median: float | None = None

    def record(self) -> dict:
        """The flat record of :data:`SEGMENT_SCHEMA` (segments.csv row, GIS feature properties)."""
        r = {"segment": self.id, "chainage_start_m": round(self.start_m, 2), "chainage_end_m": round(self.end_m, 2),
             "length_m": round(self.end_m - self.start_m, 2), "corridor_area_m2": round(self.corridor_area_m2, 1),
             "assessed": self.assessed, "pci": None if self.pci is None else round(self.pci, 1),
             "grade": self.grade, "rating": self.rating, "not_assessed_reason": self.not_assessed_reason,
             "coverage_share": self.coverage_share, "px_per_cm_median": self.px_per_cm_median,
             "defects": int(sum(self.counts.values()))}
        r.update({f"n_{c}": int(self.counts.get(c, 0)) for c in DEFECT_CODES})
        r.update({f"length_m_{c}": round(self.lengths_m.get(c, 0.0), 3) for c in DEFECT_CODES})
        r.update({f"area_m2_{c}": round(self.areas_m2.get(c, 0.0), 3) for c in DEFECT_CODES})
        r["total_deduct"] = round(self.total_deduct, 2)
        r["corrected_deduct"] = None if self.corrected_deduct is None else round(self.corrected_deduct, 2)
        r["deducts"] = "; ".join(f"{d['code']} {d['level']} {d['density_pct']:.3g}%: {d['deduct']:.1f}"
                                 for d in self.deducts)
        return r


def segment_edges(length_m: float, segment_m: float = 100.0, merge_short_fraction: float = 0.5) -> np.ndarray:
    """(K + 1,) float64 chainage edges of the segments of a route ``length_m`` long (module docstring)."""
    if not segment_m > 0:
        raise ValueError(f"segment_m must be > 0, got {segment_m}")
    L = max(float(length_m), 0.0)
    n = int(math.floor(L / segment_m + 1e-9))
    edges = list(np.arange(n + 1, dtype=np.float64) * segment_m)
    rest = L - n * segment_m
    if n == 0:
        return np.array([0.0, L])
    if rest > 1e-6:
        if rest < merge_short_fraction * segment_m:
            edges[-1] = L  # the short rest joins the last full segment
        else:
            edges.append(L)
    return np.asarray(edges)


def corridor(route: np.ndarray, start_m: float, end_m: float, half_width_m: float) -> object:
    """The route piece between two chainages buffered by ``half_width_m`` (flat ends), world metres."""
    if len(route) < 2 or end_m - start_m <= 1e-9:
        return Point(*np.asarray(route, dtype=np.float64)[0, :2]).buffer(half_width_m)
    piece = substring(LineString(np.asarray(route, dtype=np.float64)[:, :2]), start_m, end_m)
    return piece.buffer(half_width_m, cap_style="flat", join_style="round")


def deduct_value(cls: int, level: str, density_pct: float, policy: Policy) -> float:
    """Deduct value of one class and level at ``density_pct``: scale log10(1 + d / knee), capped at 100."""
    c = policy.deduct[int(cls)]
    return float(min(100.0, c[level] * math.log10(1.0 + max(float(density_pct), 0.0) / c["knee"])))


def corrected_deduct(deducts: list[float]) -> tuple[float, float]:
    """(total deduct, corrected deduct) by D6433's iteration with linear CDV curves (module docstring)."""
    dv = np.sort(np.asarray(deducts, dtype=np.float64))[::-1]
    total = float(dv.sum())
    q0 = int((dv > 2.0).sum())
    if q0 == 0:
        return total, min(100.0, total)
    best = 0.0
    for q in range(q0, 0, -1):  # q deducts kept, the smaller ones reduced to 2 (at most 2 for those below)
        t = float(dv[:q].sum() + np.minimum(dv[q:], 2.0).sum())
        best = max(best, min(100.0, t / (1.0 + CDV_Q_SLOPE * (q - 1))))
    return total, best


def grade_of(index: float, policy: Policy) -> int:
    """Condition grade 1..5 from the index (policy ``segments.grades``: lower bounds of grades 1..4)."""
    for g, lo in enumerate(policy.grades, start=1):
        if index >= lo:
            return g
    return len(policy.grades) + 1


def rating_of(index: float) -> str:
    return next(word for lo, word in RATINGS if index >= lo)


def _quantity(rec: dict, cls: int) -> float:
    q = DENSITY_QUANTITY[cls]
    if q == "count":
        return 1.0
    v = measure_value(rec, q)
    return 0.0 if v is None else max(v, 0.0)


def score_segment(seg: Segment, records: list[dict], policy: Policy) -> Segment:
    """Fill a segment's counts, lengths, areas, deducts and index from its defect records.

    Records are flat dicts with ``cls`` (0-3), ``severity_level`` and the measures (``area_m2``,
    ``crack_length_m`` or ``length_m``): mapped defects' properties or synthetic truth records alike.
    """
    area = max(seg.corridor_area_m2, 1e-6)
    qty: dict[tuple[int, str], float] = {}
    for r in records:
        k = int(r["cls"])
        c = DEFECT_CODES[k]
        seg.counts[c] = seg.counts.get(c, 0) + 1
        length = measure_value(r, "crack_length_m") if k in (0, 1) else measure_value(r, "length_m")
        seg.lengths_m[c] = seg.lengths_m.get(c, 0.0) + (length or 0.0)
        seg.areas_m2[c] = seg.areas_m2.get(c, 0.0) + (measure_value(r, "area_m2") or 0.0)
        level = r.get("severity_level")
        if level in LEVELS:
            qty[(k, level)] = qty.get((k, level), 0.0) + _quantity(r, k)
    seg.deducts = []
    for (k, level), q in sorted(qty.items(), key=lambda kv: (kv[0][0], LEVELS.index(kv[0][1]))):
        d = 100.0 * q / area
        seg.deducts.append({"code": DEFECT_CODES[k], "level": level, "density_pct": d,
                            "deduct": deduct_value(k, level, d, policy)})
    seg.total_deduct, seg.corrected_deduct = corrected_deduct([d["deduct"] for d in seg.deducts])
    seg.pci = float(np.clip(100.0 - seg.corrected_deduct, 0.0, 100.0))
    seg.grade = grade_of(seg.pci, policy)
    seg.rating = rating_of(seg.pci)
    return seg


def build_segments(route: np.ndarray, records: list[dict], policy: Policy | None = None, segment_m: float = 100.0,
                   lane_width_m: float | None = None) -> list[Segment]:
    """Segments of a route (M, 2) world metres with the defect ``records`` (each with ``chainage_m``) scored.

    Returns the segments in chainage order, ids from 1. A record's ``segment`` key is set to its segment id.
    """
    pol = policy or load_policy()
    route = np.asarray(route, dtype=np.float64).reshape(-1, 2)
    if len(route) == 0:
        return []
    cum = cumulative_length(route)
    edges = segment_edges(float(cum[-1]), segment_m, pol.merge_short_fraction)
    half = 0.5 * pol.corridor_lanes * float(lane_width_m or pol.lane_width_m)
    s = np.array([float(r.get("chainage_m") or 0.0) for r in records], dtype=np.float64)
    # interior edges only: chainage below 0 or past the end (clipped by chainage()) lands in the end segments
    which = np.searchsorted(edges[1:-1], s, side="right") if len(records) else np.zeros(0, dtype=np.int64)
    out = []
    for k in range(len(edges) - 1):
        poly = corridor(route, edges[k], edges[k + 1], half)
        seg = Segment(k + 1, float(edges[k]), float(edges[k + 1]), poly, float(poly.area))
        mine = [records[i] for i in np.nonzero(which == k)[0]]
        for r in mine:
            r["segment"] = k + 1
        out.append(score_segment(seg, mine, pol))
    return out


def segment_records(segments: list[Segment]) -> list[dict]:
    return [s.record() for s in segments]


def segments_csv_text(segments: list[Segment]) -> str:
    """segments.csv: one row per segment, the columns of :data:`SEGMENT_SCHEMA` (a header only without segments)."""
    import csv
    import io

    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=[n for n, *_ in SEGMENT_SCHEMA], lineterminator="\n")
    w.writeheader()
    for r in segment_records(segments):
        w.writerow(r)
    return buf.getvalue()


__all__ = ["CDV_Q_SLOPE", "DENSITY_QUANTITY", "RATINGS", "SEGMENT_SCHEMA", "Segment", "build_segments",
           "corrected_deduct", "corridor", "deduct_value", "grade_of", "rating_of", "score_segment", "segment_edges",
           "segment_records", "segments_csv_text"]
