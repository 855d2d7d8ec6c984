"""The synthetic road world: a curved road with exact height field, materials, defects and clutter.

Geometry lives in two coordinate systems:

* world ``(x, y, z)`` metres, z up (SPEC §0);
* road ``(s, t)``: arc length along the centreline and signed lateral offset (t > 0 left of the
  direction of travel). ``st_of_xy`` maps world to road coordinates through a coarse 0.5 m raster
  of the exact nearest-point projection, bilinearly interpolated (error < 1 mm inside the
  corridor because s and t are smooth there).

The surface *is* the float32 raster ``World.height`` at 0.05 m (exported as ``truth/height.npy``),
read with bilinear interpolation: the renderer, the clutter placement and the truth export all use
the same surface, so "the height field is exact" holds by construction. It is computed from an
analytic profile (crown, superelevation, grade, curb, sidewalk, verge) plus potholes.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from pavemap.geometry.grid import GridSpec
from pavemap.synth.clutter import make_clutter, shadow_raster
from pavemap.synth.defects import blob_q_np, make_decoys, make_defects
from pavemap.synth.params import (
    CENTRELINE_DS,
    DEFAULT_THREADS,
    HEIGHT_RES,
    SHADOW_RES,
    ST_RES,
    WorldParams,
    torch_threads,
    world_params,
)
from pavemap.synth.scene import World, _to_tensors
from pavemap.synth.surface import profile_height, st_lookup

# ---------------------------------------------------------------------------- world


def make_world(preset: str = "nuscenes-like", seed: int = 0, threads: int | None = DEFAULT_THREADS,
               **overrides: object) -> World:
    """Build the world of ``preset`` with ``seed``; ``overrides`` set any WorldParams field."""
    p = world_params(preset, seed, **overrides)
    with torch_threads(threads):
        return _build_world(p)


def _build_world(p: WorldParams) -> World:
    rng = _rngs(p.seed)
    ego_u = None
    if p.path is not None:
        from pavemap.synth.trajectory import path_centreline

        cl_s, cl_xy, cl_theta, cl_kappa, ego_u = path_centreline(p)
    else:
        cl_s, cl_xy, cl_theta, cl_kappa = _centreline(p, rng["road"])
    tiles = rng["tex"].random((6, 128, 128)).astype(np.float32)
    st_grid, st = _st_raster(cl_s, cl_xy, cl_theta, margin=45.0, tie_m=0.0 if p.path is None else 1.5)
    hgrid = _grid_around(cl_xy, margin=28.0, res=HEIGHT_RES)
    w = World(
        params=p, cl_s=cl_s, cl_xy=cl_xy, cl_theta=cl_theta, cl_kappa=cl_kappa, st_grid=st_grid, st=st,
        height_grid=hgrid, height=np.zeros((hgrid.ny, hgrid.nx), np.float32),
        shadow_grid=_grid_around(cl_xy, margin=28.0, res=SHADOW_RES), shadow=np.zeros((1, 1), np.float32),
        defects=[], decoys=[], boxes=np.zeros((0, 12), np.float32), spheres=np.zeros((0, 8), np.float32),
        sphere_kind=np.zeros(0, np.int64), noise_tiles=tiles, sun=_sun(p), cl_ego_u=ego_u,
    )
    if p.path is not None:
        from pavemap.synth.trajectory import base_raster

        ego_xy = w.xy_of_st(cl_s, np.full_like(cl_s, _ego_t(p)))
        w.base_grid, w.base = base_raster(p, ego_xy, ego_u, hgrid)
    w.defects = _one_pass(w, make_defects(w, rng["defects"]))
    w.height = _height_raster(w)
    w._cache.clear()
    w.decoys = make_decoys(w, rng["decoys"])
    w.boxes, w.spheres, w.sphere_kind = make_clutter(w, rng["clutter"])
    if p.path is not None:
        _off_other_roads(w)
    w.shadow = shadow_raster(w) if p.shadows else np.zeros((1, 1), np.float32)
    w._cache.clear()
    return w


def _ego_t(p: WorldParams) -> float:
    from pavemap.synth.trajectory import ego_lane_t

    return ego_lane_t(p)


def _one_pass(w: World, defects: list[dict]) -> list[dict]:
    """Along a given trajectory, the defects whose whole box lies on the pass they were placed on (a loop's
    other pass would cut the rest); ids renumbered. Generated roads never come back: all kept."""
    if w.params.path is None or not defects:
        return defects
    from pavemap.synth.trajectory import own_pass

    keep = []
    for d in defects:
        x0, y0, x1, y1 = d["aabb"]
        xs, ys = np.array([x0, x1, x0, x1, d["centre"][0]]), np.array([y0, y0, y1, y1, d["centre"][1]])
        if own_pass(w, np.tile(np.asarray(d["s_range"], float), (5, 1)), xs, ys).all():
            keep.append({**d, "id": len(keep)})
    return keep


def _off_other_roads(w: World) -> None:
    """Along a given trajectory: drop the objects and streaks placed beside one pass that stand on the road of
    another (a loop, a crossing); their own pass puts them beside its carriageway, never on it."""
    from pavemap.synth.trajectory import on_some_road

    b = w.boxes
    if len(b):
        c, si = np.cos(b[:, 6]), np.sin(b[:, 6])
        hit = np.zeros(len(b), bool)
        for ex, ey in ((1, 1), (1, -1), (-1, 1), (-1, -1), (0, 0)):
            x = b[:, 0] + ex * b[:, 3] * c - ey * b[:, 4] * si
            y = b[:, 1] + ex * b[:, 3] * si + ey * b[:, 4] * c
            hit |= on_some_road(w, x, y, -0.6)
        w.boxes = b[~hit]
    sp = w.spheres
    if len(sp):
        hit = np.zeros(len(sp), bool)
        for ex, ey in ((1, 0), (-1, 0), (0, 1), (0, -1), (0, 0)):
            hit |= on_some_road(w, sp[:, 0] + ex * sp[:, 3], sp[:, 1] + ey * sp[:, 3], -0.6)
        w.spheres, w.sphere_kind = sp[~hit], w.sphere_kind[~hit]
    kept = []
    for d in w.decoys:
        line = np.asarray(d["line"], float)
        if not on_some_road(w, line[:, 0], line[:, 1], 0.0).any():
            kept.append(d)
    w.decoys = kept


def _rngs(seed: int) -> dict[str, np.random.Generator]:
    # Independent streams: changing the defect density does not move the road or the cars.
    names = ("road", "tex", "defects", "decoys", "clutter", "rig")
    return {n: np.random.default_rng([int(seed), i]) for i, n in enumerate(names)}


def _sun(p: WorldParams) -> np.ndarray:
    az = math.radians(p.sun_azimuth_deg)
    el = math.radians(p.sun_elevation_deg)
    return np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])


# ---------------------------------------------------------------------------- centreline


def _centreline(p: WorldParams, rng: np.random.Generator):
    """Straights and arcs with curvature ramps; origin at the first ego position, heading +x there."""
    L = p.road_length + 10.0
    ds = CENTRELINE_DS
    n = int(math.ceil(L / ds)) + 1
    s = np.arange(n) * ds - 5.0  # a little before s = 0 so lookups near the ends stay inside
    kappa = np.zeros(n)
    pos = -5.0
    sign = rng.choice([-1.0, 1.0])
    while pos < s[-1]:
        if rng.random() < p.straight_fraction:
            seg = rng.uniform(25.0, 70.0)
        else:
            radius = rng.uniform(p.min_radius, p.max_radius)
            angle = math.radians(rng.uniform(15.0, 60.0))
            seg = radius * angle
            m = (s >= pos) & (s < pos + seg)
            kappa[m] = sign / radius
            sign = -sign if rng.random() < 0.7 else sign
        pos += seg
    # curvature ramps (clothoid-like transitions) by smoothing over ~20 m
    k = int(20.0 / ds)
    ker = np.hanning(2 * k + 1)
    ker /= ker.sum()
    kappa = np.convolve(np.pad(kappa, k, mode="edge"), ker, mode="valid")
    theta = np.concatenate([[0.0], np.cumsum(0.5 * (kappa[1:] + kappa[:-1]) * ds)])
    xy = np.zeros((n, 2))
    xy[1:, 0] = np.cumsum(0.5 * (np.cos(theta[1:]) + np.cos(theta[:-1])) * ds)
    xy[1:, 1] = np.cumsum(0.5 * (np.sin(theta[1:]) + np.sin(theta[:-1])) * ds)
    # put the ego start (s = road_before) at the origin with heading 0
    s0 = p.road_before
    th0 = np.interp(s0, s, theta)
    c0 = np.array([np.interp(s0, s, xy[:, 0]), np.interp(s0, s, xy[:, 1])])
    rot = np.array([[math.cos(-th0), -math.sin(-th0)], [math.sin(-th0), math.cos(-th0)]])
    xy = (xy - c0) @ rot.T
    theta = theta - th0
    return s, xy, theta, kappa


def _grid_around(xy: np.ndarray, margin: float, res: float) -> GridSpec:
    return GridSpec.covering(tuple(xy.min(0) - margin), tuple(xy.max(0) + margin), res)


def _st_raster(s: np.ndarray, xy: np.ndarray, theta: np.ndarray, margin: float,
               tie_m: float = 0.0) -> tuple[GridSpec, np.ndarray]:
    """Exact nearest-point (s, t) on a coarse raster: KD-tree to the nearest sample, then tangent projection.

    ``tie_m`` > 0 (a road that comes back): among the samples within ``tie_m`` of the nearest, the earliest
    (smallest s) owns the point, so that where two passes share the road the first pass owns it everywhere
    instead of the two alternating by centimetres."""
    from scipy.spatial import cKDTree

    g = _grid_around(xy, margin, ST_RES)
    X, Y = g.centres()
    P = np.stack([X.ravel(), Y.ravel()], axis=1)
    tree = cKDTree(xy)
    if tie_m > 0:
        kq = min(48, len(xy))
        k = np.empty(len(P), np.int64)
        for a in range(0, len(P), 100_000):  # (chunk, 48) candidates at a time: bounded memory
            dd, kk = tree.query(P[a:a + 100_000], k=kq)
            cand = np.where(dd <= dd[:, :1] + tie_m, s[kk], np.inf)
            k[a:a + 100_000] = kk[np.arange(len(kk)), cand.argmin(1)]
    else:
        _, k = tree.query(P)
    d = P - xy[k]
    T = np.stack([np.cos(theta[k]), np.sin(theta[k])], axis=1)
    N = np.stack([-T[:, 1], T[:, 0]], axis=1)
    ss = s[k] + (d * T).sum(1)
    tt = (d * N).sum(1)
    return g, np.stack([ss.reshape(g.ny, g.nx), tt.reshape(g.ny, g.nx)]).astype(np.float32)


def _height_raster(w: World) -> np.ndarray:
    """The exact surface on the 0.05 m grid: profile everywhere, potholes carved in their footprints."""
    tw = _to_tensors(w, torch.device("cpu"))
    g = w.height_grid
    out = np.empty((g.ny, g.nx), np.float32)
    xs = torch.as_tensor(g.xs(), dtype=torch.float32)
    rows = max(1, 262_144 // g.nx)  # cache-sized chunks: large temporaries are slow
    for j0 in range(0, g.ny, rows):
        j1 = min(g.ny, j0 + rows)
        ys = torch.as_tensor(g.ys()[j0:j1], dtype=torch.float32)
        Y, X = torch.meshgrid(ys, xs, indexing="ij")
        X = X.reshape(-1)
        Y = Y.reshape(-1)
        s, t = st_lookup(tw, X, Y)
        z = profile_height(w.params, tw["tiles"], tw["kappa"], tw["cl_s0"], X, Y, s, t, tw["base"])
        out[j0:j1] = z.reshape(j1 - j0, g.nx).numpy()
    for d in w.defects:
        if d["cls"] != 3:
            continue
        rows, cols = pothole_window(d, g)
        X, Y = np.meshgrid(g.xs()[cols], g.ys()[rows])
        out[rows, cols] -= pothole_dent(d, X, Y).astype(np.float32)
    return out


def pothole_window(d: dict, g: GridSpec) -> tuple[slice, slice]:
    """(rows, cols) slices of grid ``g`` covering a pothole's bounding box (where it is carved)."""
    i0 = max(0, int((d["aabb"][0] - g.x0) / g.res))
    i1 = min(g.nx, int((d["aabb"][2] - g.x0) / g.res) + 2)
    j0 = max(0, int((d["aabb"][1] - g.y0) / g.res))
    j1 = min(g.ny, int((d["aabb"][3] - g.y0) / g.res) + 2)
    return slice(j0, j1), slice(i0, i1)


def pothole_dent(d: dict, X: np.ndarray, Y: np.ndarray) -> np.ndarray:
    """Depth (m, + down) a pothole carves at world points X, Y (same shape, float64; 0 outside it).

    The one definition of the dent: the height raster subtracts it and the truth's depth / volume
    integrate it. A flat-ish bottom with walls over the outer 30 % of the radius, plus a rough bottom
    (+-6 mm) inside the outline; the roughness can make the dent slightly negative near the rim.
    """
    q = blob_q_np(d, X, Y)
    depth = d["depth_m"] * np.clip((1 - q) / 0.3, 0, 1) ** 1.5
    rough = 0.006 * np.sin(X * 37.0 + d["phase"][0]) * np.sin(Y * 41.0 + d["phase"][1])
    return depth + np.where(q < 1, rough, 0.0)
