"""The ground of the synthetic world as functions of road coordinates: profile, materials, paint, lookups.

``bilinear_np`` / ``bilinear_t`` read the world's rasters (numpy for placement and tests, torch for
the renderer); ``profile_height``, ``ground_label`` and ``markings`` define the surface and its
materials from road coordinates ``(s, t)``.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np
import torch

from pavemap.geometry.grid import GridSpec
from pavemap.synth.params import CENTRELINE_DS, CURB, HEIGHT_RES, MARKING, ROAD, SIDEWALK, TERRAIN

if TYPE_CHECKING:
    from pavemap.synth.params import WorldParams

# ---------------------------------------------------------------------------- rasters / lookups


def bilinear_np(a: np.ndarray, g: GridSpec, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Bilinear lookup in raster ``a`` (ny, nx) at world points; clamps to the edge."""
    fx = np.clip((x - g.x0) / g.res, 0, g.nx - 1.000001)
    fy = np.clip((y - g.y0) / g.res, 0, g.ny - 1.000001)
    i = np.floor(fx).astype(np.int64)
    j = np.floor(fy).astype(np.int64)
    ax = fx - i
    ay = fy - j
    v00, v01 = a[j, i].astype(np.float64), a[j, i + 1].astype(np.float64)
    v10, v11 = a[j + 1, i].astype(np.float64), a[j + 1, i + 1].astype(np.float64)
    return (1 - ay) * ((1 - ax) * v00 + ax * v01) + ay * ((1 - ax) * v10 + ax * v11)


def bilinear_t(a: torch.Tensor, g: tuple[float, float, float, int, int], x: torch.Tensor, y: torch.Tensor,
               grad: bool = False):
    """Bilinear lookup in a flattened raster ``a`` ((ny*nx,) or (C, ny*nx)); optional x/y gradient.

    ``g`` is ``(x0, y0, res, ny, nx)`` of the raster's :class:`GridSpec` (plain numbers: no attribute
    lookups in the renderer's inner loop).
    Indices are int32 + index_select: several times faster than int64 advanced indexing on CPU.
    """
    x0, y0, res, ny, nx = g
    fx = ((x - x0) / res).clamp(0, nx - 1.01)
    fy = ((y - y0) / res).clamp(0, ny - 1.01)
    i = fx.floor()
    j = fy.floor()
    ax = fx - i
    ay = fy - j
    idx = j.int() * nx + i.int()
    dim = a.dim() - 1
    v00 = a.index_select(dim, idx)
    v01 = a.index_select(dim, idx + 1)
    v10 = a.index_select(dim, idx + nx)
    v11 = a.index_select(dim, idx + (nx + 1))
    top = v00 + ax * (v01 - v00)
    bot = v10 + ax * (v11 - v10)
    val = top + ay * (bot - top)
    if not grad:
        return val
    dx = ((1 - ay) * (v01 - v00) + ay * (v11 - v10)) / res
    dy = (bot - top) / res
    return val, dx, dy


def value_noise(tile: torch.Tensor, x: torch.Tensor, y: torch.Tensor, scale: float) -> torch.Tensor:
    """Smooth value noise in [0, 1] with feature size ``scale`` metres from a periodic (128, 128) tile."""
    u = x / scale
    v = y / scale
    i = u.floor()
    j = v.floor()
    fu = u - i
    fv = v - j
    fu = fu * fu * (3 - 2 * fu)
    fv = fv * fv * (3 - 2 * fv)
    i0 = i.int() & 127
    j0 = (j.int() & 127) * 128
    i1 = (i0 + 1) & 127
    j1 = (j0 + 128) & 16383
    flat = tile.reshape(-1)
    a = flat.index_select(0, j0 + i0)
    b = flat.index_select(0, j0 + i1)
    c = flat.index_select(0, j1 + i0)
    d = flat.index_select(0, j1 + i1)
    top = a + fu * (b - a)
    bot = c + fu * (d - c)
    return top + fv * (bot - top)


# ---------------------------------------------------------------------------- ground profile


def ground_label(p: WorldParams, s: torch.Tensor, t: torch.Tensor, marking: torch.Tensor) -> torch.Tensor:
    """(N,) long ground class from road coordinates; ``marking`` (N,) paint coverage in [0, 1]."""
    a = t.abs()
    w2 = p.width / 2
    sw = torch.where(t > 0, torch.full_like(t, p.sidewalk_left), torch.full_like(t, p.sidewalk_right))
    lab = torch.full_like(s, TERRAIN, dtype=torch.long)
    lab = torch.where(a < w2 + p.curb_width + sw, torch.full_like(lab, SIDEWALK), lab)
    lab = torch.where(a < w2 + p.curb_width, torch.full_like(lab, CURB), lab)
    lab = torch.where(a < w2, torch.full_like(lab, ROAD), lab)
    return torch.where((lab == ROAD) & (marking > 0.5), torch.full_like(lab, MARKING), lab)


WHITE_PAINT = (0.92, 0.92, 0.9)
YELLOW_PAINT = (0.92, 0.74, 0.22)


def marking_lines(p: WorldParams) -> list[tuple[float, float, bool, tuple[float, float, float]]]:
    """Painted lines as (t centre, width, dashed, colour): edge lines, lane dividers, double yellow centre."""
    w2 = p.width / 2
    out = [(-(w2 - 0.3), 0.15, False, WHITE_PAINT), (w2 - 0.3, 0.15, False, WHITE_PAINT)]
    for k in range(1, p.lanes):
        tk = -w2 + k * p.lane_width
        if p.lanes % 2 == 0 and k == p.lanes // 2:
            out += [(tk - 0.1, 0.1, False, YELLOW_PAINT), (tk + 0.1, 0.1, False, YELLOW_PAINT)]
        else:
            out.append((tk, 0.12, True, WHITE_PAINT))
    return out


def markings(p: WorldParams, s: torch.Tensor, t: torch.Tensor, fp: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Paint coverage (N,) in [0, 1] and paint colour (N, 3), anti-aliased over the pixel footprint ``fp`` (m)."""
    cov = torch.zeros_like(s)
    col = torch.zeros(s.shape + (3,), dtype=s.dtype, device=s.device)
    fpc = fp.clamp(min=1e-3)
    for i, (tc, wid, dashed, colour) in enumerate(marking_lines(p)):
        c = ((wid / 2 - (t - tc).abs()) / fpc + 0.5).clamp(0, 1) * (wid / fpc).clamp(max=1)
        if dashed:
            m = torch.remainder(s + 2.1 * i, 9.0)
            d = torch.where(m < 3.0, torch.minimum(m, 3.0 - m), -torch.minimum(m - 3.0, 9.0 - m))
            c = c * (d / fpc + 0.5).clamp(0, 1)
        upd = c > cov
        cov = torch.where(upd, c, cov)
        col = torch.where(upd[..., None], torch.tensor(colour, dtype=s.dtype, device=s.device), col)
    return cov, col


def profile_height(p: WorldParams, tiles: torch.Tensor, kappa: torch.Tensor, cl_s0: float,
                   x: torch.Tensor, y: torch.Tensor, s: torch.Tensor, t: torch.Tensor,
                   base: tuple[torch.Tensor, tuple] | None = None) -> torch.Tensor:
    """Analytic height without potholes: grade + vertical curve (or, along a given trajectory, the road's
    height at the place from ``base``: the flat raster and its bilinear_t grid) + cross-section + small
    unevenness."""
    a = t.abs()
    w2 = p.width / 2
    k = ((s - cl_s0) / CENTRELINE_DS).round().clamp(0, kappa.numel() - 1).int()
    # superelevation: the road banks into turns (inner side lower), capped
    e = (kappa.index_select(0, k) * 3.0).clamp(-p.max_superelevation, p.max_superelevation)
    if base is None:
        z = p.grade * s + p.vert_amp * torch.sin(2 * math.pi * s / p.vert_wavelength)
    else:
        z = bilinear_t(base[0], base[1], x, y)
    road = p.crown * (1 - (a / w2) ** 2) + e * t
    edge = e * t.sign() * w2
    sw = torch.where(t > 0, torch.full_like(t, p.sidewalk_left), torch.full_like(t, p.sidewalk_right))
    d = a - w2
    curb = (d / HEIGHT_RES).clamp(0, 1) * p.curb_height
    walk = 0.02 * (d - p.curb_width).clamp(min=0).minimum(sw)
    dv = (d - p.curb_width - sw).clamp(min=0)
    verge = (0.06 * dv).clamp(max=0.35) + 0.06 * (value_noise(tiles[4], x, y, 3.0) - 0.5) * (dv / 2).clamp(max=1)
    off = edge + curb + walk + verge
    uneven = 0.012 * (value_noise(tiles[5], x, y, 4.0) - 0.5) + 0.004 * (value_noise(tiles[5], x, y, 0.7) - 0.5)
    return z + torch.where(a <= w2, road, off) + uneven


def st_lookup(tw: dict, x: torch.Tensor, y: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    st = bilinear_t(tw["st"], tw["stgrid"], x, y)
    return st[0], st[1]
