"""The surveyed area: map cells some camera saw on the road surface, within ``SURVEY_RANGE_M``.

Outside it the defect map says nothing (nodata in the GeoTIFF), and its outline is the geometry
of the GeoPackage's ``survey`` layer. A cell counts as seen when its centre, at the surface height,
projects inside a view's image in front of the camera and within the range. Computed on a coarse
grid (``COARSE_RES_M``) and views at least ``VIEW_STEP_M`` apart, then looked up at full resolution:
the edge is good to a coarse cell, which is all nodata needs.
"""

from __future__ import annotations

import numpy as np

from pavemap.geometry.grid import GridSpec
from pavemap.types import Sequence

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


def _views(seq: Sequence) -> list[tuple[np.ndarray, object]]:
    """(T_world_cam, Camera) of views at least VIEW_STEP_M apart per camera."""
    out, last = [], {}
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
        C, R, K = T[:3, 3], T[:3, :3], np.asarray(cam.K, dtype=np.float64)
        c0, c1 = np.searchsorted(xs, [C[0] - max_range, C[0] + max_range])
        r0, r1 = np.searchsorted(ys, [C[1] - max_range, C[1] + max_range])
        if c1 <= c0 or r1 <= r0:
            continue
        X, Y = np.meshgrid(xs[c0:c1], ys[r0:r1])
        P = np.stack([X, Y, Z[r0:r1, c0:c1]], axis=-1) - C
        Xc = P @ R  # world -> camera: R^T (X - C), row vectors
        z = Xc[..., 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            u = K[0, 0] * Xc[..., 0] / z + K[0, 2]
            v = K[1, 1] * Xc[..., 1] / z + K[1, 2]
        hit = (z > 0.1) & (u >= -0.5) & (u < cam.width - 0.5) & (v >= -0.5) & (v < cam.height - 0.5)
        hit &= np.hypot(P[..., 0], P[..., 1]) <= max_range
        seen[r0:r1, c0:c1] |= hit
    return seen & ok, g


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


__all__ = ["SURVEY_RANGE_M", "coarse_coverage", "coverage_mask", "coverage_polygon"]
