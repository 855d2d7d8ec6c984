"""Gaussian-splatted BEV maps (SPEC §3): ``M(x) = sum_i G_sigma(x - x_i) P_i`` over the vertices.

Vertices are binned into map cells (each carrying its area ``r^2``), turning the sum into a
density ``sum P_i r^2 / s^2`` on cells of size ``s``; a normalised Gaussian blur of that density
is the continuous splat with a normalised kernel. So on a dense vertex grid a uniform P gives
M = P, and M stays in [0, 1] for the priority bands.
"""

from __future__ import annotations

import numpy as np
from scipy.ndimage import gaussian_filter

from pavemap.geometry.grid import GridSpec


def bev_grid(surface: GridSpec, splat_res: float) -> GridSpec:
    """Map grid of step ``splat_res`` inside the vertex grid ``surface``, sharing its origin.

    Cell centres at ``(x0 + c*s, y0 + r*s)``; the last column / row stays within the vertex grid.
    """
    W = int(np.floor((surface.nx - 1) * surface.res / splat_res + 1e-9)) + 1
    H = int(np.floor((surface.ny - 1) * surface.res / splat_res + 1e-9)) + 1
    return GridSpec(surface.x0, surface.y0, splat_res, W, H)


def splat(values: np.ndarray, xy: np.ndarray, vertex_res: float, grid: GridSpec, sigma: float) -> np.ndarray:
    """values (C, V) at vertex positions xy (V, 2) -> maps (C, H, W) float32 on ``grid``."""
    H, W = grid.shape
    s = grid.res
    col = np.clip(np.round((xy[:, 0] - grid.x0) / s).astype(np.int64), 0, W - 1)
    row = np.clip(np.round((xy[:, 1] - grid.y0) / s).astype(np.int64), 0, H - 1)
    flat = row * W + col
    out = np.empty((values.shape[0], H, W), dtype=np.float32)
    area = (vertex_res / s) ** 2
    for c in range(values.shape[0]):  # a handful of channels (total + 4 classes)
        dens = np.bincount(flat, weights=values[c] * area, minlength=H * W).reshape(H, W)
        if sigma > 0:
            dens = gaussian_filter(dens, sigma / s, mode="constant", truncate=3.0)
        out[c] = np.clip(dens, 0.0, 1.0)
    return out
