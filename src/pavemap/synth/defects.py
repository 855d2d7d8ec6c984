"""Defects of the synthetic world: placement of cracks, alligator patches and potholes, and off-road decoys.

A defect is a dict (``kind`` ``line`` with a polyline, or ``blob`` with an ellipse-like outline);
:func:`pavemap.synth.scene.item_tables` packs them into the padded tensors the renderer reads.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from pavemap.synth.scene import World

# ---------------------------------------------------------------------------- defects


def blob_q_np(d: dict, X: np.ndarray, Y: np.ndarray) -> np.ndarray:
    """Normalised radius of points in a blob defect: < 1 inside, 1 on the boundary."""
    c, r = math.cos(d["rot"]), math.sin(d["rot"])
    dx = X - d["centre"][0]
    dy = Y - d["centre"][1]
    u = (c * dx + r * dy) / d["ax"]
    v = (-r * dx + c * dy) / d["ay"]
    rho = np.hypot(u, v)
    phi = np.arctan2(v, u)
    h = d["harm"]
    return rho / (1 + h[0] * np.cos(2 * phi + d["phase"][0]) + h[1] * np.cos(3 * phi + d["phase"][1]))


def blob_polygon(d: dict, n: int = 48) -> np.ndarray:
    """(n, 2) boundary of a blob defect (the q = 1 curve)."""
    phi = np.linspace(0, 2 * np.pi, n, endpoint=False)
    h = d["harm"]
    r = 1 + h[0] * np.cos(2 * phi + d["phase"][0]) + h[1] * np.cos(3 * phi + d["phase"][1])
    u = r * np.cos(phi) * d["ax"]
    v = r * np.sin(phi) * d["ay"]
    c, s = math.cos(d["rot"]), math.sin(d["rot"])
    return np.stack([d["centre"][0] + c * u - s * v, d["centre"][1] + s * u + c * v], axis=1)


def _crack_polyline(w: World, rng: np.random.Generator, s0: float, t0: float, length: float,
                    along: bool, n: int = 12) -> np.ndarray:
    """(n, 2) world vertices of a wandering crack in road coordinates (along s or across t)."""
    u = np.linspace(0, length, n)
    wander = np.cumsum(rng.normal(0, 0.035, n)) + 0.05 * np.sin(u * rng.uniform(2, 5) + rng.uniform(0, 6))
    wander -= wander[0]
    if along:
        s, t = s0 + u, t0 + wander
    else:
        ang = math.radians(rng.uniform(-15, 15))
        s = s0 + u * math.sin(ang) + wander
        t = t0 + u * math.cos(ang)
    return w.xy_of_st(s, t)


def make_defects(w: World, rng: np.random.Generator) -> list[dict]:
    p = w.params
    s_lo, s_hi = 3.0, p.road_length - 3.0
    if p.defect_free_until_m is not None:  # a clean stretch first (s = road_before at the first frame)
        s_lo = max(s_lo, p.road_before + float(p.defect_free_until_m))
    n = int(rng.poisson(p.defect_density * max(s_hi - s_lo, 0.0) / 100.0))
    mix = np.asarray(p.class_mix, float)
    mix = mix / mix.sum()
    placed: list[tuple[float, float, float, float]] = []  # (s0, s1, t0, t1) boxes, to avoid overlaps
    out: list[dict] = []
    for _ in range(n):
        cls = int(rng.choice(4, p=mix))
        _place_defect(w, rng, cls, placed, out, s_lo, s_hi)
    if p.survey > 0:
        _later_survey(w, out, placed, s_lo, s_hi)
    return out


def _later_survey(w: World, out: list[dict], placed: list, s_lo: float, s_hi: float) -> None:
    """Survey k of the same road: grow a share of the existing defects, add new ones (own random stream)."""
    p = w.params
    rng = np.random.default_rng([int(p.seed), 1000 + int(p.survey)])
    g = p.survey_growth
    for d in out:
        if rng.random() >= p.survey_grow_share:
            continue
        d["grown"] = True
        if d["kind"] == "blob":
            d["ax"] *= g
            d["ay"] *= g
            if "depth_m" in d:
                d["depth_m"] = min(d["depth_m"] * 1.3, 0.12)
            poly = blob_polygon(d)
            d["aabb"] = [*(poly.min(0) - 0.02), *(poly.max(0) + 0.02)]
            d["length_m"] = float(np.ptp(poly @ [math.cos(d["rot"]), math.sin(d["rot"])]))
        else:  # a crack grows longer about its middle
            line = np.asarray(d["line"], dtype=float)
            mid = line.mean(0)
            line = mid + (line - mid) * g
            d["line"] = line.tolist() if isinstance(d["line"], list) else line
            d["length_m"] = float(np.linalg.norm(np.diff(line, axis=0), axis=1).sum())
            d["aabb"] = [*(line.min(0) - d["band_m"]), *(line.max(0) + d["band_m"])]
    mix = np.asarray(p.class_mix, float)
    mix = mix / mix.sum()
    n_new = int(rng.poisson(p.survey_new_per_100m * max(s_hi - s_lo, 0.0) / 100.0))
    for _ in range(n_new):
        before = len(out)
        _place_defect(w, rng, int(rng.choice(4, p=mix)), placed, out, s_lo, s_hi)
        if len(out) > before:
            out[-1]["new_in_survey"] = int(p.survey)


def _place_defect(w: World, rng: np.random.Generator, cls: int, placed: list, out: list[dict],
                  s_lo: float, s_hi: float) -> None:
    p = w.params
    w2 = p.width / 2
    sz = p.defect_size
    for _try in range(30):
        sc = rng.uniform(s_lo, s_hi)
        if cls == 0:
            length = rng.uniform(1.0, 4.0) * sz
            ext_s, ext_t = length, 0.3
        elif cls == 1:
            length = min(rng.uniform(1.0, 3.5) * sz, p.width - 1.0)
            ext_s, ext_t = 0.8, length
        elif cls == 2:
            ax, ay = rng.uniform(0.5, 1.25) * sz, rng.uniform(0.4, 1.0) * sz
            ext_s, ext_t = 2.6 * ax, 2.6 * ay
        else:
            rad = rng.uniform(0.15, 0.75) * sz
            ax, ay = rad * rng.uniform(1.0, 1.3), rad
            ext_s, ext_t = 2.6 * ax, 2.6 * ax
        half_t = w2 - 0.35 - ext_t / 2
        if half_t <= 0:
            continue
        tc = rng.uniform(-half_t, half_t)
        box = (sc - ext_s / 2 - 0.3, sc + ext_s / 2 + 0.3, tc - ext_t / 2 - 0.3, tc + ext_t / 2 + 0.3)
        if any(b[0] < box[1] and box[0] < b[1] and b[2] < box[3] and box[2] < b[3] for b in placed):
            continue
        placed.append(box)
        did = len(out)
        if cls in (0, 1):
            if cls == 0:
                line = _crack_polyline(w, rng, sc - length / 2, tc, length, along=True)
            else:
                line = _crack_polyline(w, rng, sc, tc - length / 2, length, along=False)
            d = {"id": did, "cls": cls, "kind": "line", "line": line, "width_m": rng.uniform(0.012, 0.03),
                 "band_m": 0.10, "length_m": float(np.linalg.norm(np.diff(line, axis=0), axis=1).sum()),
                 "darkness": rng.uniform(0.55, 0.8)}
            d["centre"] = line[len(line) // 2].tolist()
            d["aabb"] = [*(line.min(0) - d["band_m"]), *(line.max(0) + d["band_m"])]
        else:
            centre = w.xy_of_st(np.array([sc]), np.array([tc]))[0]
            rot = float(w.heading_at(np.array([sc]))[0]) + rng.uniform(-0.35, 0.35)
            d = {"id": did, "cls": cls, "kind": "blob", "centre": centre.tolist(), "ax": ax, "ay": ay,
                 "rot": rot, "harm": [rng.uniform(0, 0.12), rng.uniform(0, 0.08)],
                 "phase": [rng.uniform(0, 6.283), rng.uniform(0, 6.283)],
                 "darkness": rng.uniform(0.5, 0.8)}
            if cls == 2:
                d["cell_m"] = rng.uniform(0.14, 0.28)
                d["width_m"] = rng.uniform(0.01, 0.022)
            else:
                d["depth_m"] = rng.uniform(0.03, 0.10)
            poly = blob_polygon(d)
            d["aabb"] = [*(poly.min(0) - 0.02), *(poly.max(0) + 0.02)]
            d["length_m"] = float(np.ptp(poly @ [math.cos(rot), math.sin(rot)]))
        d["s_range"] = [box[0], box[1]]
        out.append(d)
        break


def make_decoys(w: World, rng: np.random.Generator) -> list[dict]:
    """Crack-like dark streaks off the road (sidewalk, curb, verge): classic detector false positives."""
    p = w.params
    w2 = p.width / 2
    n = int(rng.poisson(p.decoy_density * p.road_length / 100.0))
    out = []
    for i in range(n):
        side = rng.choice([-1.0, 1.0])
        sw = p.sidewalk_left if side > 0 else p.sidewalk_right
        t0 = side * (w2 + p.curb_width + rng.uniform(0.3, sw + 3.0))
        s0 = rng.uniform(2.0, p.road_length - 6.0)
        length = rng.uniform(0.8, 3.0)
        line = _crack_polyline(w, rng, s0, t0, length, along=rng.random() < 0.6)
        d = {"id": i, "cls": -1, "kind": "line", "line": line, "width_m": rng.uniform(0.015, 0.035), "band_m": 0.10,
             "darkness": rng.uniform(0.5, 0.75), "s_range": [s0 - 1.5, s0 + length + 1.5]}
        d["aabb"] = [*(line.min(0) - 0.1), *(line.max(0) + 0.1)]
        d["centre"] = line[len(line) // 2].tolist()
        out.append(d)
    return out
