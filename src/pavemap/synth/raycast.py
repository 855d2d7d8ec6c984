"""Ray casting of the synthetic world: first ground hit, and boxes / spheres on their screen rectangles.

Ground: every pixel's ray ``o + λ d`` (``d = R K⁻¹ [u, v, 1]``, so λ is the camera depth) is
bracketed inside a slab around the plane through the ground under the camera (the world's relief
relative to that plane is bounded: curbs, verge, potholes, vertical curves), marched in a fixed
number of steps to find the first sign change of ``g(λ) = o_z + λ d_z − h(x(λ), y(λ))`` and refined
by Illinois regula falsi on the exact (bilinear) surface. Boxes and spheres are intersected
analytically, only on the pixels of their projected screen rectangle (pixel–primitive pairs in one
batch).
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np
import torch

from pavemap.synth.surface import bilinear_t

if TYPE_CHECKING:
    from pavemap.synth.scene import World

FAR_M = 220.0  # horizontal distance beyond which the ground is not rendered (haze → sky colour)
MARCH_STEPS = 7
REFINE_STEPS = 6


# ---------------------------------------------------------------------------- ground intersection


def _ground_g(tw: dict, o: torch.Tensor, dx, dy, dz, lam):
    """g(λ) = ray height − surface height."""
    x = o[0] + lam * dx
    y = o[1] + lam * dy
    return o[2] + lam * dz - bilinear_t(tw["height"], tw["hgrid"], x, y)


def _ground_g_nearest(tw: dict, o: torch.Tensor, dx, dy, dz, lam):
    """g(λ) with the nearest height sample: a quarter of the gathers, only used to find the bracket."""
    x0, y0, res, ny, nx = tw["hgrid"]
    i = ((o[0] + lam * dx - x0) / res).round().clamp(0, nx - 1).int()
    j = ((o[1] + lam * dy - y0) / res).round().clamp(0, ny - 1).int()
    return o[2] + lam * dz - tw["height"].index_select(0, j * nx + i)


def intersect_ground(world: World, tw: dict, o_np: np.ndarray, dx, dy, dz,
                     ground_ref: tuple[float, float, float], limit: torch.Tensor | None = None) -> torch.Tensor:
    """(N,) camera depth of the first ground hit of each ray, +inf where none within FAR_M.

    ``limit`` (N,): depth of a nearer object; rays whose slab starts behind it are skipped.
    """
    dev = dx.device
    p = world.params
    ox, oy, oz = (float(v) for v in o_np)
    zf, gx, gy = ground_ref
    a = dz - gx * dx - gy * dy  # rate at which the ray descends relative to that plane
    h0 = oz - zf
    lam_out = torch.full_like(dx, float("inf"))
    U, L = 0.9 + 0.02 * p.width, -0.35 - 0.02 * p.width
    cand = a < -1e-5
    if limit is not None:
        cand &= (h0 - U - 6.0) / (-a).clamp(min=1e-5) < limit
    idx = torch.nonzero(cand).squeeze(1)
    if idx.numel() == 0:
        return lam_out
    a_ = a[idx]
    dx_, dy_, dz_ = dx[idx], dy[idx], dz[idx]
    horiz = torch.sqrt(dx_ * dx_ + dy_ * dy_).clamp(min=1e-9)
    # relief relative to the plane: curbs + sidewalk + verge rise above, potholes and crown below;
    # the vertical curve and banking changes add a quadratic allowance in the horizontal distance.
    kv = p.vert_amp * (2 * math.pi / p.vert_wavelength) ** 2 + 2e-5
    lam_bot0 = (h0 - L) / (-a_)
    allow = (0.5 * kv * (lam_bot0 * horiz) ** 2).clamp(max=6.0)
    lam_top = ((h0 - U - allow) / (-a_)).clamp(min=0.15)
    lam_bot = torch.minimum((h0 - L + allow) / (-a_), FAR_M / horiz)
    ok = lam_bot > lam_top
    o = torch.tensor([ox, oy, oz], dtype=dx.dtype, device=dev)
    step = (lam_bot - lam_top) / MARCH_STEPS
    g_top = _ground_g(tw, o, dx_, dy_, dz_, lam_top)
    # a ray already below the surface at the top of the slab (relief bound exceeded): take lam_top
    first = torch.where(g_top <= 0, torch.zeros_like(lam_top), torch.full_like(lam_top, MARCH_STEPS + 1.0))
    for i in range(MARCH_STEPS, 0, -1):  # backwards: the last write is the first crossing
        g = _ground_g_nearest(tw, o, dx_, dy_, dz_, lam_top + step * i)
        first = torch.where((g <= 0) & (first > 0), torch.full_like(first, float(i)), first)
    found = ok & (first <= MARCH_STEPS)
    res = torch.full_like(lam_top, float("inf"))
    direct = torch.nonzero(found & (first == 0)).squeeze(1)
    res[direct] = lam_top[direct]
    sel = torch.nonzero(found & (first > 0)).squeeze(1)
    if sel.numel():
        sdx, sdy, sdz = dx_[sel], dy_[sel], dz_[sel]
        hi = lam_top[sel] + step[sel] * first[sel]
        lo = hi - step[sel]
        glo = _ground_g(tw, o, sdx, sdy, sdz, lo)
        ghi = _ground_g(tw, o, sdx, sdy, sdz, hi)
        # the bracket came from nearest samples: where the exact surface disagrees, widen it by a step
        bad = torch.nonzero(glo <= 0).squeeze(1)
        if bad.numel():
            lo[bad] = (lo[bad] - step[sel][bad]).clamp(min=0.0)
            glo[bad] = _ground_g(tw, o, sdx[bad], sdy[bad], sdz[bad], lo[bad])
        bad = torch.nonzero(ghi > 0).squeeze(1)
        if bad.numel():
            hi[bad] = hi[bad] + step[sel][bad]
            ghi[bad] = _ground_g(tw, o, sdx[bad], sdy[bad], sdz[bad], hi[bad])
        side = torch.zeros_like(lo)
        for _ in range(REFINE_STEPS):  # Illinois regula falsi: bracket kept, converges superlinearly
            lam = (lo * ghi - hi * glo) / (ghi - glo)
            g = _ground_g(tw, o, sdx, sdy, sdz, lam)
            pos = g > 0
            glo_s = torch.where((~pos) & (side < 0), glo * 0.5, glo)
            ghi_s = torch.where(pos & (side > 0), ghi * 0.5, ghi)
            lo = torch.where(pos, lam, lo)
            glo = torch.where(pos, g, glo_s)
            hi = torch.where(pos, hi, lam)
            ghi = torch.where(pos, ghi_s, g)
            side = torch.where(pos, torch.ones_like(side), -torch.ones_like(side))
        res[sel] = (lo * ghi - hi * glo) / (ghi - glo)
    lam_out[idx] = res
    return lam_out


# ---------------------------------------------------------------------------- objects


BOX_EDGES = np.array([[0, 1], [1, 2], [2, 3], [3, 0], [4, 5], [5, 6], [6, 7], [7, 4], [0, 4], [1, 5], [2, 6],
                       [3, 7]])
NEAR = 0.05


def screen_rects(corners: np.ndarray, R: np.ndarray, o: np.ndarray, K: np.ndarray, W: int, H: int,
                  max_dist: float = 160.0, edges: np.ndarray | None = None) -> list[tuple[int, int, int, int, int]]:
    """Pixel rectangles (k, u0, u1, v0, v1) of objects' corner sets (Nk, C, 3) that may be visible.

    Objects straddling the camera plane are clipped against the near plane (edge intersections
    added), so a long wall beside the camera does not cost the whole image.
    """
    if len(corners) == 0:
        return []
    Xc = (corners - o[None, None]) @ R  # (Nk, C, 3) camera coordinates (R is camera-to-world)
    z = Xc[..., 2]
    zmin = z.min(1)
    zmax = z.max(1)
    dist = np.linalg.norm(corners.mean(1) - o[None], axis=1)
    keep = np.nonzero((zmax > NEAR) & (dist < max_dist))[0]
    out = []
    for k in keep:
        P = Xc[k]
        if zmin[k] <= NEAR:
            if edges is None:
                out.append((int(k), 0, W, 0, H))
                continue
            a, b = P[edges[:, 0]], P[edges[:, 1]]
            za, zb = a[:, 2], b[:, 2]
            cross = (za - NEAR) * (zb - NEAR) < 0
            tt = (NEAR - za[cross]) / (zb[cross] - za[cross])
            P = np.concatenate([P[P[:, 2] > NEAR], a[cross] + tt[:, None] * (b[cross] - a[cross])])
            P[:, 2] = np.maximum(P[:, 2], NEAR)
        u = K[0, 0] * P[:, 0] / P[:, 2] + K[0, 2]
        v = K[1, 1] * P[:, 1] / P[:, 2] + K[1, 2]
        u0, u1 = max(0, int(math.floor(max(u.min(), -1.0)))), min(W, int(math.ceil(min(u.max(), W + 1.0))) + 1)
        v0, v1 = max(0, int(math.floor(max(v.min(), -1.0)))), min(H, int(math.ceil(min(v.max(), H + 1.0))) + 1)
        if u1 > u0 and v1 > v0:
            out.append((int(k), u0, u1, v0, v1))
    return out


def _pairs(rects, W: int, dev) -> tuple[torch.Tensor, torch.Tensor]:
    pix, ids = [], []
    for k, u0, u1, v0, v1 in rects:
        uu = torch.arange(u0, u1, device=dev)
        vv = torch.arange(v0, v1, device=dev)
        pp = (vv[:, None] * W + uu[None, :]).reshape(-1)
        pix.append(pp)
        ids.append(torch.full_like(pp, k))
    if not pix:
        e = torch.zeros(0, dtype=torch.long, device=dev)
        return e, e
    return torch.cat(pix), torch.cat(ids)


def _winner(n: int, pix: torch.Tensor, lam: torch.Tensor, hit: torch.Tensor):
    """Per pixel the nearest hit among pairs: (depth (n,), index of the winning pair or -1 (n,))."""
    depth = torch.full((n,), float("inf"), device=lam.device, dtype=lam.dtype)
    win = torch.full((n,), -1, dtype=torch.long, device=lam.device)
    if pix.numel() == 0:
        return depth, win
    hp, hl = pix[hit], lam[hit]
    depth.scatter_reduce_(0, hp, hl, reduce="amin")
    pair_idx = torch.nonzero(hit).squeeze(1)
    is_min = hl == depth[hp]
    win.scatter_reduce_(0, hp[is_min], pair_idx[is_min], reduce="amax")
    return depth, win


def intersect_boxes(tw: dict, rects, o: torch.Tensor, dx, dy, dz, W: int):
    """Nearest oriented-box hit per pixel (slab test in each box frame, only on its screen rectangle).

    Returns depth (N,), the winning pair (N,) or -1, and the pair data to shade winners.
    """
    n = dx.shape[0]
    pix, bid = _pairs(rects, W, dx.device)
    if pix.numel() == 0:
        depth, win = _winner(n, pix, torch.zeros(0, device=dx.device), torch.zeros(0, dtype=torch.bool))
        return depth, win, None
    b = tw["boxes"]
    cb, sb = torch.cos(b[:, 6]), torch.sin(b[:, 6])
    rx, ry, rz = o[0] - b[:, 0], o[1] - b[:, 1], o[2] - b[:, 2]
    # camera centre in each box frame: per box, not per pair
    lo_all = torch.stack([cb * rx + sb * ry, -sb * rx + cb * ry, rz], 1)
    bid32 = bid.int()
    c = cb.index_select(0, bid32)
    s = sb.index_select(0, bid32)
    pix32 = pix.int()
    ddx, ddy, ddz = dx.index_select(0, pix32), dy.index_select(0, pix32), dz.index_select(0, pix32)
    ld = (c * ddx + s * ddy, -s * ddx + c * ddy, ddz)
    lo = lo_all.index_select(0, bid32)
    hs = b[:, 3:6].index_select(0, bid32)
    tn = None
    tf = None
    axis = None
    for k in range(3):
        dk = torch.where(ld[k].abs() < 1e-9, torch.full_like(ld[k], 1e-9), ld[k])
        inv = 1.0 / dk
        ta = (-hs[:, k] - lo[:, k]) * inv
        tb = (hs[:, k] - lo[:, k]) * inv
        tmin = torch.minimum(ta, tb)
        tmax = torch.maximum(ta, tb)
        if tn is None:
            tn, tf, axis = tmin, tmax, torch.zeros_like(pix)
        else:
            axis = torch.where(tmin > tn, torch.full_like(axis, k), axis)
            tn = torch.maximum(tn, tmin)
            tf = torch.minimum(tf, tmax)
    hit = (tf >= tn) & (tn > NEAR)
    depth, win = _winner(n, pix, tn, hit)
    return depth, win, (pix, bid, lo, ld, tn, axis)


def intersect_spheres(tw: dict, rects, o: torch.Tensor, dx, dy, dz, W: int):
    n = dx.shape[0]
    pix, sid = _pairs(rects, W, dx.device)
    if pix.numel() == 0:
        depth, win = _winner(n, pix, torch.zeros(0, device=dx.device), torch.zeros(0, dtype=torch.bool))
        return depth, win, None
    sp = tw["spheres"]
    oc_all = o[None] - sp[:, :3]
    C_all = (oc_all * oc_all).sum(1) - sp[:, 3] ** 2
    sid32 = sid.int()
    pix32 = pix.int()
    ddx, ddy, ddz = dx.index_select(0, pix32), dy.index_select(0, pix32), dz.index_select(0, pix32)
    oc = oc_all.index_select(0, sid32)
    A = ddx * ddx + ddy * ddy + ddz * ddz
    B = oc[:, 0] * ddx + oc[:, 1] * ddy + oc[:, 2] * ddz
    C = C_all.index_select(0, sid32)
    disc = B * B - A * C
    lam = (-B - torch.sqrt(disc.clamp(min=0))) / A
    hit = (disc > 0) & (lam > NEAR)
    depth, win = _winner(n, pix, lam, hit)
    return depth, win, (pix, sid, lam)
