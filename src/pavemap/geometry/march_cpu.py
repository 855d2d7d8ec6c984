"""The CPU kernel of the ray / height-field march: :func:`pavemap.geometry.heightfield._find_roots`, compiled.

The torch march in ``heightfield.py`` is the reference (and the CUDA path). On a CPU it spends its time in Python
and in many small tensor ops over shrinking sets of rays: measured on a 60-frame kitti-like drive it was 14 of
stage 1's 46 s on an idle machine (97 of 175 s on a busy one). This module runs the same algorithm one ray at a
time, compiled by numba, on one thread (a parallel loop over the rays measured 0.97x on kitti-like views and 1.66x
on nuScenes-like ones, for a march that is now ~3 % of stage 1): the same bracket (the ray between the surface's
lowest and highest point, inside the grid's box), the same half-cell samples in chunks with the same empty-space
skipping over the dilated tile maxima, the same first "above, then below" pair, and the same Newton-or-bisection
refinement with the same convergence test. It computes in float64 (the reference computes in the rays' dtype), so a
root can differ in the last bits, and a ray that grazes a triangle edge may land on its neighbour; the tests
compare both.

numba is a dependency of the package; where it is missing anyway, :func:`available` is False and the torch march runs.
"""

from __future__ import annotations

import functools
import os
from collections.abc import Callable

import numpy as np
import torch

_MARCH = None  # the compiled kernel, built on first use (importing numba costs ~0.25 s)


@functools.cache
def available() -> bool:
    """Whether the compiled march can run here: numba imports (asked once per process; find_hits asks per call, and
    a broken numba install falls back to the torch march instead of failing in the middle of a run)."""
    try:
        import numba  # noqa: F401
    except ImportError:
        return False
    return True


def compiled_on_first_use(fn: Callable) -> Callable:
    """``fn`` compiled by numba (``cache=True``) at its first call, not at import (importing numba costs ~0.25 s;
    the cache sits beside ``fn``'s module). The numba kernels of :mod:`pavemap.geometry` share this."""
    kernel = None

    @functools.wraps(fn)
    def call(*args):
        nonlocal kernel
        if kernel is None:
            import numba

            kernel = numba.njit(cache=True)(fn)
        return kernel(*args)

    return call


def use_for(rays: torch.Tensor) -> bool:
    """Whether rays (N, 3) are marched by this kernel: on a CPU with numba, unless ``PAVEMAP_MARCH=torch`` asks
    for the reference (benchmarks compare the two that way)."""
    return rays.device.type == "cpu" and os.environ.get("PAVEMAP_MARCH", "").lower() != "torch" and available()


def _compiled():
    """The compiled :func:`_march_py` (numba caches the machine code beside this file: ~4 s the first time)."""
    global _MARCH
    if _MARCH is None:
        import numba

        g = globals()
        g["_triangle"] = numba.njit(cache=True, inline="always")(_triangle_py)
        g["_g_at"] = numba.njit(cache=True, inline="always")(_g_at_py)
        _MARCH = numba.njit(cache=True)(_march_py)
    return _MARCH


def _triangle_py(uu, vv, nx, ny):
    """The triangle under grid coordinates (uu, vv), clamped into the grid as ``heightfield._triangle`` does:
    cell (i, j), lower, its vertex ids (v00, i1, i2), the barycentric weights (w0, w1, w2) and whether (uu, vv)
    lies inside the grid."""
    inside = (uu >= 0.0) and (uu <= nx - 1) and (vv >= 0.0) and (vv <= ny - 1)
    i = min(max(int(np.floor(uu)), 0), max(nx - 2, 0))
    j = min(max(int(np.floor(vv)), 0), max(ny - 2, 0))
    fx, fy = uu - i, vv - j
    v00 = j * nx + i
    lower = fx >= fy
    if lower:
        return i, j, lower, v00, v00 + 1, v00 + nx + 1, 1.0 - fx, fx - fy, fy, inside
    return i, j, lower, v00, v00 + nx + 1, v00 + nx, 1.0 - fy, fx, fy - fx, inside


def _g_at_py(u0, v0, du, dv, oz, dz, lam, H, V, nx, ny):
    """(g, ok) of one ray at ``lam``: ray height minus surface height, and whether the triangle exists."""
    _, _, _, v00, i1, i2, w0, w1, w2, inside = _triangle(u0 + lam * du, v0 + lam * dv, nx, ny)
    ok = inside and V[v00] and V[i1] and V[i2]
    return oz + lam * dz - (w0 * H[v00] + w1 * H[i1] + w2 * H[i2]), ok


_triangle = _triangle_py  # the compiled ones once built (see _compiled)
_g_at = _g_at_py


def _march_py(o, d, H, V, tmax, tile, x0, y0, res, nx, ny, hmin, hmax, max_dist, step, chunk, refine_iters,
           found, lam_out, ci, cj, clower):
    """Fill found (N,), lam_out (N,), ci, cj (N,) and clower (N,) for the rays o, d (N, 3) float64 over the flat
    heights H (ny*nx,) (float32 or float64, read as float64) and crop V (ny*nx,) bool."""
    tny, tnx = tmax.shape
    reach = float(tile - 1)
    x_min, x_max = x0, x0 + (nx - 1) * res
    y_min, y_max = y0, y0 + (ny - 1) * res
    for r in range(o.shape[0]):
        ox, oy, oz = o[r, 0], o[r, 1], o[r, 2]
        dx, dy, dz = d[r, 0], d[r, 1], d[r, 2]
        lo, hi = 0.0, max_dist
        if abs(dz) > 1e-12:
            l1, l2 = (hmin - oz) / dz, (hmax - oz) / dz
            lo, hi = max(lo, min(l1, l2)), min(hi, max(l1, l2))
        elif oz < hmin or oz > hmax:
            hi = -1.0
        for a0, a1, oa, da in ((x_min, x_max, ox, dx), (y_min, y_max, oy, dy)):
            if abs(da) > 1e-12:
                t1, t2 = (a0 - oa) / da, (a1 - oa) / da
                lo, hi = max(lo, min(t1, t2)), min(hi, max(t1, t2))
            elif oa < a0 or oa > a1:
                hi = -1.0
        if lo > hi:
            continue
        u0, v0 = (ox - x0) / res, (oy - y0) / res
        du, dv = dx / res, dy / res
        speed = max(max(abs(du), abs(dv)), 1e-12)
        dl = min(step / speed, max(hi - lo, 1e-12))
        cur = lo
        hit = False
        a = b = 0.0
        while cur <= hi and not hit:
            tx = min(max(int(np.floor((u0 + cur * du) / tile)), 0), tnx - 1)
            ty = min(max(int(np.floor((v0 + cur * dv) / tile)), 0), tny - 1)
            margin = oz + cur * dz - tmax[ty, tx]
            adv = reach / speed
            if dz < 0 and margin > 0:
                adv = min(adv, margin / max(-dz, 1e-30))
            if margin > 0 and adv >= chunk * dl:
                cur = cur + adv
                continue
            prev_above = False
            prev_lam = cur
            for k in range(chunk + 1):
                lam = min(cur + k * dl, hi)
                g, ok = _g_at(u0, v0, du, dv, oz, dz, lam, H, V, nx, ny)
                if k > 0 and prev_above and ok and g < 0:
                    hit, a, b = True, prev_lam, lam
                    break
                prev_above = g >= 0 or not ok
                prev_lam = lam
            cur = cur + chunk * dl
        if not hit:
            continue
        for _it in range(refine_iters):
            i, j, lower, v00, i1, i2, w0, w1, w2, _inside = _triangle(u0 + b * du, v0 + b * dv, nx, ny)
            h0, h1, h2 = H[v00], H[i1], H[i2]
            gb = oz + b * dz - (w0 * h0 + w1 * h1 + w2 * h2)
            # d(weights)/d(lam) of the triangle type, as heightfield._weight_slope
            slope = dz - ((-du * h0 + (du - dv) * h1 + dv * h2) if lower else (-dv * h0 + du * h1 + (dv - du) * h2))
            safe = slope if abs(slope) > 1e-12 else -1e-12
            lp = b - gb / safe
            tol = 1e-7 * (abs(b - a) + 1e-9) + 1e-12
            px, py = u0 + lp * du - i, v0 + lp * dv - j
            wmin = min(1.0 - px, min(px - py, py)) if lower else min(1.0 - py, min(px, py - px))
            if slope < 0 and lp >= a - tol and lp <= b + tol and wmin >= -1e-6:
                found[r] = True
                lam_out[r], ci[r], cj[r], clower[r] = lp, i, j, lower
                break
            m = 0.5 * (a + b)
            gm, okm = _g_at(u0, v0, du, dv, oz, dz, m, H, V, nx, ny)
            if okm and gm < 0:
                b = m
            else:
                a = m


def find_roots_cpu(hf, o: torch.Tensor, d: torch.Tensor, max_dist: float, step: float, chunk: int,
                   refine_iters: int, bounds) -> tuple[torch.Tensor, ...]:
    """What :func:`pavemap.geometry.heightfield._find_roots` returns, from the compiled march.

    hf: the HeightField; o, d: (N, 3) CPU rays; bounds: its SurfaceBounds. Returns (idx (M,) long, lam0 (M,)
    in the rays' dtype, i (M,) long, j (M,) long, lower (M,) bool) for the M rays that hit.
    """
    n = o.shape[0]
    found = np.zeros(n, dtype=np.bool_)
    lam = np.zeros(n, dtype=np.float64)
    ci = np.zeros(n, dtype=np.int64)
    cj = np.zeros(n, dtype=np.int64)
    clower = np.zeros(n, dtype=np.bool_)
    march = _compiled()
    march(np.ascontiguousarray(o.detach().double().numpy()), np.ascontiguousarray(d.detach().double().numpy()),
          bounds.H.detach().contiguous().numpy(), bounds.V.contiguous().numpy(),
          bounds.tmax.detach().contiguous().numpy(), int(bounds.tile), float(hf.x0), float(hf.y0), float(hf.res),
          int(hf.nx), int(hf.ny), float(bounds.hmin), float(bounds.hmax), float(max_dist), float(step),
          int(chunk), int(refine_iters), found, lam, ci, cj, clower)
    idx = torch.from_numpy(np.flatnonzero(found))
    return (idx, torch.from_numpy(lam[found]).to(o.dtype), torch.from_numpy(ci[found]),
            torch.from_numpy(cj[found]), torch.from_numpy(clower[found]))
