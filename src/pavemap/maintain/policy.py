"""The maintenance policy: severity levels, certainty and urgency of a defect (issue 16).

The policy is a YAML file a city can replace (the built-in one, ``pavemap/configs/maintenance_policy.yaml``,
documents every entry). :func:`load_policy` checks it and raises :class:`~pavemap.errors.PavemapError`
naming the file and the entry: bands that overlap, leave a gap, miss a level or do not cover [0, .inf),
an unknown class, a missing number.

Three questions, kept apart:

- :func:`severity_level` how bad the defect is (low / medium / high) from one measure per class;
- :func:`certainty` how sure the survey is (confirmed / probable / single sighting);
- :func:`urgency` what to do first (repair now / schedule / monitor, and a score to sort by) from the
  severity level, the size, the class and the position across the lane (:func:`lane_position`).
"""

from __future__ import annotations

import functools
import math
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pavemap.errors import PavemapError
from pavemap.types import DEFECT_CODES, UNASSESSED

LEVELS: tuple[str, ...] = ("low", "medium", "high")
CERTAINTIES: tuple[str, ...] = ("confirmed", "probable", "single sighting")
#: Most urgent first; ``priority_rank`` sorts by this order, then by the score.
PRIORITIES: tuple[str, ...] = ("repair now", "schedule", "monitor")
POSITIONS: tuple[str, ...] = ("wheel path", "lane centre", "edge")
BUILTIN_POLICY = Path(__file__).resolve().parent.parent / "configs" / "maintenance_policy.yaml"
#: Other names of a measure (and the factor to the policy's unit), tried in order: synthetic truth
#: records carry ``depth_max_m`` (the carved surface's deepest point), ``depth_m`` (the generator's
#: parameter) and ``depth_mean_m`` in metres and a crack's ``length_m``; a mapped crack without a
#: skeleton length falls back on its principal extent ``length_m``.
MEASURE_ALIASES: dict[str, tuple[tuple[str, float], ...]] = {
    "depth_max_mm": (("depth_max_m", 1000.0), ("depth_m", 1000.0)),
    "depth_mean_mm": (("depth_mean_m", 1000.0),),
    "crack_length_m": (("length_m", 1.0),),
}
_TOP_KEYS = ("version", "severity", "certainty", "lanes", "urgency", "segments", "assessment")


@dataclass(frozen=True)
class Bands:
    """Contiguous half-open bands ``[lo_k, lo_{k+1})`` of one measure; the last runs to infinity."""

    measure: str
    names: tuple[str, ...]
    lower: tuple[float, ...]  # lower edge of each band, increasing, lower[0] == 0

    def level(self, value: float) -> str:
        """The band holding ``value`` (negative values count as 0; an edge takes the higher band)."""
        k = int(np.searchsorted(np.asarray(self.lower), max(float(value), 0.0), side="right")) - 1
        return self.names[max(k, 0)]


@dataclass(frozen=True)
class Assessment:
    """When a segment's index may be given at all (policy ``assessment``; the built-in YAML says why each number).

    A road cell is *covered* when at least ``min_views`` views saw it at ``need_px_per_cm`` or finer at the
    detector's input: ``min_defect_px`` pixels across the smallest defect the policy cares about,
    ``min_defect_m`` (:mod:`pavemap.maintain.assessment`). A segment is assessed when covered cells make up
    at least ``min_covered_share`` of its corridor. A run is *low-confidence* when its detections at or above
    ``filter.tau_conf`` number fewer than ``min_confident_per_image`` per image and make up less than
    ``min_confident_share`` of the detector's boxes; its segments are then not assessed either.
    """

    min_defect_m: float = 0.2
    min_defect_px: float = 8.0
    min_views: int = 1
    min_covered_share: float = 0.5
    min_confident_per_image: float = 0.5
    min_confident_share: float = 0.25

    def need_px_per_cm(self, min_defect_px: float | None = None) -> float:
        """Pixels per cm of road (at the detector's input) the smallest defect needs; ``min_defect_px``
        overrides the policy's pixels (the simulated detector's own need)."""
        return float(min_defect_px or self.min_defect_px) / (100.0 * self.min_defect_m)


@dataclass(frozen=True)
class Policy:
    """A checked maintenance policy (see the built-in YAML for the meaning of every entry)."""

    source: str
    severity: dict[int, Bands]  # by class index
    fallback: dict[int, Bands]  # by class index, where the class has a fallback measure
    certainty: tuple[tuple[str, float, int], ...]  # (name, min_probability, min_observations), best first
    lane_width_m: float
    wheel_path_offset_m: float
    wheel_path_half_width_m: float
    severity_points: dict[str, float]
    class_weight: dict[int, float]
    position_weight: dict[str, float]
    size_gain: float
    size: dict[int, tuple[str, float]]  # class -> (measure, reference size)
    priority: Bands
    corridor_lanes: float
    merge_short_fraction: float
    deduct: dict[int, dict[str, float]]  # class -> {knee, low, medium, high}
    grades: tuple[float, ...]
    assessment: Assessment = Assessment()


# ---------------------------------------------------------------------------- loading and checks


def _err(where: str, problem: str) -> PavemapError:
    return PavemapError(f"{where}: {problem}")


def _map(d: object, where: str, keys: tuple[str, ...] | None = None, required: bool = True) -> dict:
    if not isinstance(d, dict):
        raise _err(where, f"must be a mapping, got {type(d).__name__}")
    if keys is not None:
        extra = [str(k) for k in d if k not in keys]
        if extra:
            raise _err(where, f"unknown key {extra[0]!r}; expected {', '.join(keys)}")
        if required:
            missing = [k for k in keys if k not in d]
            if missing:
                raise _err(where, f"missing {missing[0]!r}")
    return d


def _number(v: object, where: str, lo: float = -math.inf, hi: float = math.inf, inf_ok: bool = False) -> float:
    if isinstance(v, bool) or not isinstance(v, int | float) or math.isnan(v) or (math.isinf(v) and not inf_ok):
        raise _err(where, f"must be a number, got {v!r}")
    if not lo <= float(v) <= hi:
        raise _err(where, f"must be in [{lo}, {hi}], got {v!r}")
    return float(v)


def _fmt(v: float) -> str:
    return ".inf" if math.isinf(v) else f"{v:g}"


def _exact_keys(d: dict, names: tuple[str, ...], where: str, what: str, missing_hint: str) -> None:
    """A PavemapError naming the first key of ``d`` not in ``names``, or the first of ``names`` not in ``d``."""
    unknown = [str(k) for k in d if k not in names]
    if unknown:
        plural = "classes" if what == "class" else f"{what}s"
        raise _err(where, f"unknown {what} {unknown[0]!r}; the {plural} are {', '.join(names)}")
    missing = [n for n in names if n not in d]
    if missing:
        raise _err(where, f"missing {what} {missing[0]!r} ({missing_hint})")


def check_bands(spec: object, names: tuple[str, ...], measure: str, where: str) -> Bands:
    """Bands ``{name: [from, to]}`` -> :class:`Bands`; ``names`` in increasing order, all required.

    They must be contiguous and non-overlapping and cover [0, .inf): a PavemapError names the band otherwise.
    """
    spec = _map(spec, where)
    _exact_keys(spec, names, where, "band", f"the bands are {', '.join(names)}, each [from, to]")
    edges = []
    for n in names:
        iv = spec[n]
        if not isinstance(iv, list | tuple) or len(iv) != 2:
            raise _err(f"{where}.{n}", f"must be [from, to], got {iv!r}")
        lo = _number(iv[0], f"{where}.{n}", inf_ok=False)
        hi = _number(iv[1], f"{where}.{n}", inf_ok=True)
        if not hi > lo:
            raise _err(f"{where}.{n}", f"empty band [{_fmt(lo)}, {_fmt(hi)}): 'to' must exceed 'from'")
        edges.append((lo, hi))
    first = edges[0][0]
    if first != 0:
        why = f"values in [0, {_fmt(first)}) have no band" if first > 0 else "the first band must start at 0"
        raise _err(where, f"band {names[0]!r} starts at {_fmt(first)}; the bands must cover [0, .inf) ({why})")
    for k in range(1, len(names)):
        (plo, phi), (lo, hi) = edges[k - 1], edges[k]
        a = f"{names[k - 1]!r} [{_fmt(plo)}, {_fmt(phi)})"
        b = f"{names[k]!r} [{_fmt(lo)}, {_fmt(hi)})"
        if lo < phi:
            raise _err(where, f"bands {a} and {b} overlap")
        if lo > phi:
            raise _err(where, f"gap between bands {a} and {b}: values in [{_fmt(phi)}, {_fmt(lo)}) have no band")
    if not math.isinf(edges[-1][1]):
        raise _err(where, f"band {names[-1]!r} ends at {_fmt(edges[-1][1])}; the last band must end at .inf "
                          f"(values from {_fmt(edges[-1][1])} have no band)")
    return Bands(measure, tuple(names), tuple(lo for lo, _ in edges))


def _per_class(d: object, where: str) -> dict[int, object]:
    d = _map(d, where)
    _exact_keys(d, tuple(DEFECT_CODES), where, "class", f"every class {', '.join(DEFECT_CODES)} needs an entry")
    return {DEFECT_CODES.index(c): v for c, v in d.items()}


def _measure(d: dict, where: str) -> str:
    m = d.get("measure")
    if not isinstance(m, str) or not m:
        raise _err(f"{where}.measure", f"must name a measure (e.g. depth_max_mm, area_m2), got {m!r}")
    return m


def _severity(d: object, where: str) -> tuple[dict[int, Bands], dict[int, Bands]]:
    sev, fb = {}, {}
    for k, spec in _per_class(d, where).items():
        w = f"{where}.{DEFECT_CODES[k]}"
        spec = _map(spec, w, ("measure", "bands", "fallback"), required=False)
        sev[k] = check_bands(spec.get("bands"), LEVELS, _measure(spec, w), f"{w}.bands")
        if spec.get("fallback") is not None:
            f = _map(spec["fallback"], f"{w}.fallback", ("measure", "bands"))
            fb[k] = check_bands(f["bands"], LEVELS, _measure(f, f"{w}.fallback"), f"{w}.fallback.bands")
    return sev, fb


def _certainty(d: object, where: str) -> tuple[tuple[str, float, int], ...]:
    d = _map(d, where, CERTAINTIES[:2])
    out = []
    for name in CERTAINTIES[:2]:
        e = _map(d[name], f"{where}.{name}", ("min_probability", "min_observations"))
        p = _number(e["min_probability"], f"{where}.{name}.min_probability", 0.0, 1.0)
        n = _number(e["min_observations"], f"{where}.{name}.min_observations", 1, 1e9)
        out.append((name, p, int(n)))
    if out[0][1] < out[1][1] or out[0][2] < out[1][2]:
        raise _err(where, "confirmed must ask at least as much as probable (probability and observations)")
    return tuple(out)


def _urgency(d: object, where: str) -> dict:
    keys = ("severity_points", "class_weight", "position_weight", "size_gain", "size", "priority")
    d = _map(d, where, keys)
    pts = _map(d["severity_points"], f"{where}.severity_points", LEVELS)
    pos = _map(d["position_weight"], f"{where}.position_weight", POSITIONS)
    size = {}
    for k, s in _per_class(d["size"], f"{where}.size").items():
        w = f"{where}.size.{DEFECT_CODES[k]}"
        s = _map(s, w, ("measure", "ref"))
        size[k] = (_measure(s, w), _number(s["ref"], f"{w}.ref", 1e-9))
    return {
        "severity_points": {n: _number(pts[n], f"{where}.severity_points.{n}", 0.0) for n in LEVELS},
        "class_weight": {k: _number(v, f"{where}.class_weight.{DEFECT_CODES[k]}", 0.0)
                         for k, v in _per_class(d["class_weight"], f"{where}.class_weight").items()},
        "position_weight": {n: _number(pos[n], f"{where}.position_weight.{n}", 0.0) for n in POSITIONS},
        "size_gain": _number(d["size_gain"], f"{where}.size_gain", 0.0),
        "size": size,
        "priority": check_bands(d["priority"], PRIORITIES[::-1], "score", f"{where}.priority"),
    }


def _segments(d: object, where: str) -> dict:
    d = _map(d, where, ("corridor_lanes", "merge_short_fraction", "deduct", "grades"))
    deduct = {}
    for k, e in _per_class(d["deduct"], f"{where}.deduct").items():
        w = f"{where}.deduct.{DEFECT_CODES[k]}"
        e = _map(e, w, ("knee", *LEVELS))
        deduct[k] = {"knee": _number(e["knee"], f"{w}.knee", 1e-9),
                     **{n: _number(e[n], f"{w}.{n}", 0.0, 100.0) for n in LEVELS}}
    g = d["grades"]
    if not isinstance(g, list) or len(g) != 4:
        raise _err(f"{where}.grades", f"must be 4 index thresholds (grades 1..4), got {g!r}")
    grades = tuple(_number(v, f"{where}.grades", 0.0, 100.0) for v in g)
    if any(a <= b for a, b in zip(grades, grades[1:], strict=False)):
        raise _err(f"{where}.grades", f"must decrease (grade 1 needs the highest index), got {list(g)}")
    return {"corridor_lanes": _number(d["corridor_lanes"], f"{where}.corridor_lanes", 0.1, 20.0),
            "merge_short_fraction": _number(d["merge_short_fraction"], f"{where}.merge_short_fraction", 0.0, 1.0),
            "deduct": deduct, "grades": grades}


def _assessment(d: object, where: str) -> Assessment:
    """The optional ``assessment`` section (a policy without it gets :class:`Assessment`'s defaults)."""
    if d is None:
        return Assessment()
    d = _map(d, where, tuple(Assessment.__dataclass_fields__), required=False)
    lim = {"min_defect_m": (0.01, 10.0), "min_defect_px": (1.0, 1000.0), "min_views": (1, 1000),
           "min_covered_share": (0.0, 1.0), "min_confident_per_image": (0.0, 1000.0), "min_confident_share": (0.0, 1.0)}
    v = {k: _number(d[k], f"{where}.{k}", *lim[k]) for k in d}
    if "min_views" in v:
        v["min_views"] = int(v["min_views"])
    return Assessment(**v)


def policy_from_dict(data: object, source: str = "<policy>") -> Policy:
    """Check a parsed policy mapping; errors name ``source`` and the entry."""
    data = _map(data, source, _TOP_KEYS, required=False)
    for k in _TOP_KEYS[1:-1]:  # assessment is optional (older policies lack it)
        if k not in data:
            raise _err(source, f"missing section {k!r}")
    sev, fb = _severity(data["severity"], f"{source}: severity")
    lanes = _map(data["lanes"], f"{source}: lanes", ("lane_width_m", "wheel_path_offset_m", "wheel_path_half_width_m"))
    lw = _number(lanes["lane_width_m"], f"{source}: lanes.lane_width_m", 1.5, 8.0)
    wp = _number(lanes["wheel_path_offset_m"], f"{source}: lanes.wheel_path_offset_m", 0.0, lw / 2)
    hw = _number(lanes["wheel_path_half_width_m"], f"{source}: lanes.wheel_path_half_width_m", 0.0, lw / 2)
    return Policy(source=source, severity=sev, fallback=fb,
                  certainty=_certainty(data["certainty"], f"{source}: certainty"),
                  lane_width_m=lw, wheel_path_offset_m=wp, wheel_path_half_width_m=hw,
                  **_urgency(data["urgency"], f"{source}: urgency"),
                  **_segments(data["segments"], f"{source}: segments"),
                  assessment=_assessment(data.get("assessment"), f"{source}: assessment"))


@functools.lru_cache(maxsize=8)
def _load_cached(path: str, mtime_ns: int) -> Policy:
    from pavemap.io.yamlfile import read_yaml

    p = Path(path)
    return policy_from_dict(read_yaml(p, "maintenance policy"), str(p))


def load_policy(path: str | os.PathLike | None = None) -> Policy:
    """The policy in ``path`` (None or "": the built-in one), checked; cached per file and modification time."""
    p = BUILTIN_POLICY if path is None or str(path) == "" else Path(path)
    try:
        mtime = p.stat().st_mtime_ns
    except OSError:
        raise PavemapError(f"{p}: maintenance policy not found") from None
    return _load_cached(str(p), mtime)


# ---------------------------------------------------------------------------- the three questions


def _cls(cls: int | str) -> int:
    if isinstance(cls, str):
        if cls not in DEFECT_CODES:
            raise PavemapError(f"unknown defect class {cls!r}; the classes are {', '.join(DEFECT_CODES)}")
        return DEFECT_CODES.index(cls)
    k = int(cls)
    if not 0 <= k < len(DEFECT_CODES):
        raise PavemapError(f"unknown defect class {cls!r}; class indices are 0..{len(DEFECT_CODES) - 1}")
    return k


def measure_value(measures: dict, name: str) -> float | None:
    """``measures[name]`` as a finite float, else its alias (:data:`MEASURE_ALIASES`) converted; None if neither."""
    for key, factor in ((name, 1.0), *MEASURE_ALIASES.get(name, ())):
        v = measures.get(key)
        if isinstance(v, int | float | np.floating | np.integer) and not isinstance(v, bool) and math.isfinite(v):
            return float(v) * factor
    return None


def severity_of(cls: int | str, measures: dict, policy: Policy | None = None) -> tuple[str, str, float]:
    """(level, measure used, its value): the class's measure, else its fallback (e.g. a pothole's area)."""
    pol = policy or load_policy()
    k = _cls(cls)
    for bands in (pol.severity[k], pol.fallback.get(k)):
        if bands is None:
            continue
        v = measure_value(measures, bands.measure)
        if v is not None:
            return bands.level(v), bands.measure, v
    tried = [b.measure for b in (pol.severity[k], pol.fallback.get(k)) if b is not None]
    raise PavemapError(f"{DEFECT_CODES[k]}: no severity measure ({' or '.join(tried)}) in the record "
                       f"(keys: {', '.join(sorted(measures)) or 'none'})")


def severity_level(cls: int | str, measures: dict, policy: Policy | None = None) -> str:
    """"low" | "medium" | "high" of one defect by the policy's bands for its class.

    A plain function of the class (index 0-3 or code "D00".."D40") and a dict of measures, so it
    grades mapped defects and synthetic truth alike (the maintenance benchmark compares the two):

    - potholes (D40): ``depth_max_mm`` (mapped, :mod:`pavemap.maintain.measure`) or ``depth_max_m`` /
      ``depth_m`` (truth, metres); without a finite depth (not measurable) the fallback measure ``area_m2``;
    - cracks (D00, D10): ``crack_length_m`` (mapped skeleton length) or ``length_m`` (truth polyline
      length, or a mapped defect's principal extent);
    - alligator cracking (D20): ``area_m2``.

    None / NaN values count as missing. Raises PavemapError when no measure the policy names is present.
    """
    return severity_of(cls, measures, policy)[0]


def certainty(probability: float, observations: int, policy: Policy | None = None) -> str:
    """"confirmed" | "probable" | "single sighting" from the fused probability and distinct detections."""
    pol = policy or load_policy()
    for name, p_min, n_min in pol.certainty:
        if float(probability) >= p_min and int(observations) >= n_min:
            return name
    return CERTAINTIES[-1]


def lane_positions(offset_m: np.ndarray, policy: Policy | None = None,
                   lane_width_m: float | None = None) -> np.ndarray:
    """(N,) lateral offsets from the route -> (N,) str array of "wheel path" | "lane centre" | "edge".

    Offset 0 is the centre of the lane the vehicle drives in; lanes repeat every ``lane_width_m`` (default
    the policy's). Within its lane a point at ``|u|`` from the lane centre is in a wheel path when
    ``|u - wheel_path_offset_m| <= wheel_path_half_width_m``, nearer the centre in the lane centre,
    farther out at the edge.
    """
    pol = policy or load_policy()
    w = float(lane_width_m or pol.lane_width_m)
    o = np.asarray(offset_m, dtype=np.float64).reshape(-1)
    u = np.abs(o - w * np.round(o / w))  # distance from the nearest lane centre, in [0, w/2]
    lo = pol.wheel_path_offset_m - pol.wheel_path_half_width_m
    hi = pol.wheel_path_offset_m + pol.wheel_path_half_width_m
    return np.where(u < lo, POSITIONS[1], np.where(u <= hi, POSITIONS[0], POSITIONS[2])).astype(object)


def lane_position(offset_m: float, policy: Policy | None = None, lane_width_m: float | None = None) -> str:
    """One offset's position in its lane (:func:`lane_positions`)."""
    return str(lane_positions(np.array([offset_m]), policy, lane_width_m)[0])


def urgency(cls: int | str, level: str, measures: dict, position: str,
            policy: Policy | None = None) -> tuple[str, float]:
    """(priority "repair now" | "schedule" | "monitor", score) of one defect.

    score = severity_points[level] x class_weight[cls] x position_weight[position]
    x (1 + size_gain x min(size / size_ref, 1)); the priority is the score's band (policy ``urgency``).
    A defect without a size measure gets the size factor 1.
    """
    pol = policy or load_policy()
    k = _cls(cls)
    if level not in LEVELS:
        raise PavemapError(f"unknown severity level {level!r}; the levels are {', '.join(LEVELS)}")
    if position not in POSITIONS:
        raise PavemapError(f"unknown lane position {position!r}; the positions are {', '.join(POSITIONS)}")
    measure, ref = pol.size[k]
    size = measure_value(measures, measure)
    factor = 1.0 + pol.size_gain * (min(max(size, 0.0) / ref, 1.0) if size is not None else 0.0)
    score = pol.severity_points[level] * pol.class_weight[k] * pol.position_weight[position] * factor
    return pol.priority.level(score), round(float(score), 4)


def priority_ranks(priorities: list[str], scores: list[float], ids: list[int]) -> list[int]:
    """Ranks 1..N (1 = most urgent), unique: sorted by (priority class, score descending, id)."""
    order = sorted(range(len(ids)), key=lambda i: (PRIORITIES.index(priorities[i]) if priorities[i] in PRIORITIES
                                                   else len(PRIORITIES), -float(scores[i]), ids[i]))
    ranks = [0] * len(ids)
    for r, i in enumerate(order, start=1):
        ranks[i] = r
    return ranks


__all__ = ["BUILTIN_POLICY", "CERTAINTIES", "LEVELS", "MEASURE_ALIASES", "POSITIONS", "PRIORITIES", "UNASSESSED",
           "Assessment", "Bands", "Policy", "certainty", "check_bands", "lane_position",
           "lane_positions", "load_policy", "measure_value", "policy_from_dict", "priority_ranks", "severity_level",
           "severity_of", "urgency"]
