"""The surveyed area: map cells some camera saw on the road surface, within ``SURVEY_RANGE_M``.

Outside it the defect map says nothing (nodata in the GeoTIFF), and its outline is the geometry
of the GeoPackage's ``survey`` layer. A cell counts as seen when its centre, at the surface height,
projects inside a view's image in front of the camera and within the range. Computed on a coarse
grid (``COARSE_RES_M``) and views at least ``VIEW_STEP_M`` apart, then looked up at full resolution:
the edge is good to a coarse cell, which is all nodata needs.

The same per-view test also grades how *well* a view saw a point (:func:`view_resolution`: pixels per cm of
road) and, over all views, each point's best resolution and how many views reached a given one
(:func:`ground_resolution`), which decides whether a road segment can be assessed
(:mod:`pavemap.maintain.assessment`).
"""

from __future__ import annotations

import numpy as np
import torch

from pavemap.geometry.camera import project
from pavemap.geometry.grid import GridSpec
from pavemap.types import Camera, Sequence

SURVEY_RANGE_M = 30.0  # beyond this a detection's position is too uncertain to call the road surveyed
COARSE_RES_M = 0.5
VIEW_STEP_M = 1.0


def _heights(surface: object | None, g: GridSpec) -> tuple[np.ndarray, np.ndarray]:
    """(ny, nx) surface height at the coarse cell centres and whether the surface is valid there."""
    if surface is None:
        return np.zeros(g.shape), np.ones(g.shape, dtype=bool)
    H = np.asarray(surface.heights.detach().cpu().numpy(), dtype=np.float64)
    V = np.asarray(surface.valid.detach().cpu().numpy(), dtype=bool)
    X, Y = g.centres()
    i = np.rint((X - surface.x0) / surface.res).astype(np.int64)
    j = np.rint((Y - surface.y0) / surface.res).astype(np.int64)
    inside = (i >= 0) & (i < H.shape[1]) & (j >= 0) & (j < H.shape[0])
    ic, jc = np.clip(i, 0, H.shape[1] - 1), np.clip(j, 0, H.shape[0] - 1)
    return np.where(inside, H[jc, ic], 0.0), inside & V[jc, ic]


def _views(seq: Sequence) -> list[tuple[np.ndarray, Camera]]:
    """(T_world_cam, Camera) of views at least VIEW_STEP_M apart per camera."""
    out: list[tuple[np.ndarray, Camera]] = []
    last: dict[str, np.ndarray] = {}
    for f in seq.frames:
        for name, v in f.views.items():
            c = v.T_world_cam[:3, 3]
            if name in last and np.linalg.norm(c - last[name]) < VIEW_STEP_M:
                continue
            last[name] = c
            out.append((np.asarray(v.T_world_cam, dtype=np.float64), seq.cameras[name]))
    return out


def coarse_coverage(seq: Sequence, grid: GridSpec, surface: object | None = None,
                    max_range: float = SURVEY_RANGE_M) -> tuple[np.ndarray, GridSpec]:
    """(ny, nx) bool on a coarse grid over ``grid``'s area, and that grid."""
    g = grid.resampled(max(COARSE_RES_M, grid.res))
    Z, ok = _heights(surface, g)
    seen = np.zeros(g.shape, dtype=bool)
    xs, ys = g.xs(), g.ys()
    for T, cam in _views(seq):
        C = T[:3, 3]
        c0, c1 = np.searchsorted(xs, [C[0] - max_range, C[0] + max_range])
        r0, r1 = np.searchsorted(ys, [C[1] - max_range, C[1] + max_range])
        if c1 <= c0 or r1 <= r0:
            continue
        X, Y = np.meshgrid(xs[c0:c1], ys[r0:r1])
        P = np.stack([X, Y, Z[r0:r1, c0:c1]], axis=-1).reshape(-1, 3)
        hit = (view_resolution(cam, T, P, max_range) > 0).reshape(X.shape)
        seen[r0:r1, c0:c1] |= hit
    return seen & ok, g


def view_resolution(cam: Camera, T_world_cam: np.ndarray, points: np.ndarray, max_range: float = SURVEY_RANGE_M,
                    ego: np.ndarray | None = None, scale: float = 1.0) -> np.ndarray:
    """(N,) float64 pixels per cm with which one view sees world points (N, 3) on a level road; 0 where it
    does not see them: behind or within 0.1 m of the camera plane, outside the image, farther than ``max_range``
    horizontally, or on ``ego`` ((H, W) bool, the camera's ego mask at full resolution).

    The scale is the area-equivalent one, sqrt(pixel area of 1 cm² of road): a level road patch dA at X, camera
    centre C and camera depth z covers fx fy |X_z - C_z| / z³ dA pixels (the plane homography's Jacobian), so
    the foreshortened direction counts. ``scale`` resizes the image (the detector's input: px/cm times scale).
    """
    P = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    uv, z = project(cam.K, T_world_cam, torch.from_numpy(P))
    u, v, z = uv[:, 0].numpy(), uv[:, 1].numpy(), z.numpy()
    C = np.asarray(T_world_cam, dtype=np.float64)[:3, 3]
    hit = (z > 0.1) & (u >= -0.5) & (u < cam.width - 0.5) & (v >= -0.5) & (v < cam.height - 0.5)
    hit &= np.hypot(P[:, 0] - C[0], P[:, 1] - C[1]) <= max_range
    if ego is not None and hit.any():
        iu = np.clip(np.rint(u[hit]).astype(np.int64), 0, ego.shape[1] - 1)
        iv = np.clip(np.rint(v[hit]).astype(np.int64), 0, ego.shape[0] - 1)
        hit[np.nonzero(hit)[0][ego[iv, iu]]] = False
    K = np.asarray(cam.K, dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        px2 = K[0, 0] * K[1, 1] * np.abs(P[:, 2] - C[2]) / np.maximum(z, 0.1) ** 3  # pixels per m²
    return np.where(hit, np.maximum(np.sqrt(px2) * float(scale) / 100.0, 1e-12), 0.0)  # seen: > 0


def ground_resolution(seq: Sequence, points: np.ndarray, need_px_per_cm: float, scale: dict[str, float] | None = None,
                      max_range: float = SURVEY_RANGE_M) -> tuple[np.ndarray, np.ndarray]:
    """How well the drive saw world points (N, 3): (N,) float64 best px/cm of any view (:func:`view_resolution`,
    times the camera's ``scale``, default 1) and (N,) int64 the number of views at ``need_px_per_cm`` or finer.

    Views at least ``VIEW_STEP_M`` apart per camera (a car standing still does not multiply its views), ego masks
    applied; each view projects only the points within ``max_range`` of it (a KD-tree over the points' x, y).
    """
    from scipy.spatial import cKDTree

    from pavemap.io.egomask import ego_mask_at

    P = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    best, n = np.zeros(len(P)), np.zeros(len(P), dtype=np.int64)
    views = _views(seq)
    if not len(P) or not views:
        return best, n
    near = cKDTree(P[:, :2]).query_ball_point(np.array([T[:2, 3] for T, _ in views]), r=max_range)
    masks = {c.name: ego_mask_at(seq, c.name, c.width, c.height) for c in seq.cameras.values()}
    for (T, cam), idx in zip(views, near, strict=True):
        if not idx:
            continue
        idx = np.asarray(idx, dtype=np.int64)
        r = view_resolution(cam, T, P[idx], max_range, masks.get(cam.name), (scale or {}).get(cam.name, 1.0))
        best[idx] = np.maximum(best[idx], r)
        n[idx] += r >= need_px_per_cm
    return best, n


def coverage_mask(seq: Sequence, grid: GridSpec, surface: object | None = None,
                  max_range: float = SURVEY_RANGE_M) -> np.ndarray:
    """(grid.ny, grid.nx) bool: the surveyed cells of ``grid`` (rows going +y, like the BEV maps)."""
    coarse, g = coarse_coverage(seq, grid, surface, max_range)
    i = np.clip(np.rint((grid.xs() - g.x0) / g.res).astype(np.int64), 0, g.nx - 1)
    j = np.clip(np.rint((grid.ys() - g.y0) / g.res).astype(np.int64), 0, g.ny - 1)
    return coarse[np.ix_(j, i)]


def coverage_polygon(mask: np.ndarray, grid: GridSpec) -> object | None:
    """The outline of a coverage mask as a shapely (Multi)Polygon in world metres (None when empty)."""
    import shapely
    from rasterio import features
    from rasterio.transform import Affine

    if not mask.any():
        return None
    # rows go +y: the affine maps (col, row) corners to world x, y directly
    tr = Affine(grid.res, 0.0, grid.x0 - grid.res / 2, 0.0, grid.res, grid.y0 - grid.res / 2)
    polys = [shapely.geometry.shape(geom) for geom, val in
             features.shapes(mask.astype(np.uint8), mask=mask, transform=tr) if val]
    geom = shapely.union_all(polys).simplify(grid.res / 2)
    return geom if not geom.is_empty else None


__all__ = ["SURVEY_RANGE_M", "coarse_coverage", "coverage_mask", "coverage_polygon", "ground_resolution",
           "view_resolution"]
