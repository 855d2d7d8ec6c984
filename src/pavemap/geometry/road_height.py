"""A camera's height over the road it drives over, from road points (pure functions, no I/O).

The one estimate of it, used by stage 1 (the mount height that places the surface,
:mod:`pavemap.mesh.geometry`), by the ground points' per-camera report and by the import's SfM scale and checks
(the height along the path, :mod:`pavemap.sfm.scale`, :mod:`pavemap.sfm.pipeline`). World metric, ``up`` the
world's vertical.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class HeightEstimate:
    """Camera height above the road: per centre (C,) (NaN unobserved), the median over observed centres, its
    robust spread (1.4826 MAD, m), a standard error, counts and whether it is observable."""

    per_centre: np.ndarray
    median: float
    spread: float
    stderr: float
    n_centres: int
    observable: bool
    reason: str


def height_estimate(h: np.ndarray, *, min_centres: int = 3) -> HeightEstimate:
    """Per-centre heights ``h`` (C,) m (NaN: not measured) summarised robustly."""
    h = np.asarray(h, dtype=np.float64)
    ok = np.isfinite(h)
    n = int(ok.sum())
    if n < min_centres:
        return HeightEstimate(h, float("nan"), float("nan"), float("nan"), n, False,
                              f"ground observed under {n} camera position(s), need {min_centres}")
    med = float(np.median(h[ok]))
    spread = float(1.4826 * np.median(np.abs(h[ok] - med)))
    # neighbouring centres share points, so n over-counts independent samples; sqrt(n/4) is conservative
    stderr = float(1.2533 * spread / np.sqrt(max(n / 4.0, 1.0)))
    return HeightEstimate(h, med, spread, stderr, n, True, "")


def _cross_fall(offset: np.ndarray, h: np.ndarray, prior_sigma: float, iterations: int = 8) -> float:
    """Robust slope of heights ``h`` (N,) m over lateral ``offset`` (N,) m: Tukey-biweight IRLS with a
    Gaussian prior N(0, ``prior_sigma``²) on the slope, so a few points on one side do not invent a camber."""
    w = np.ones_like(h)
    sig = 0.03
    b = 0.0
    for _ in range(iterations):
        sw, so = w.sum(), (w * offset).sum()
        A = np.array([[sw, so], [so, (w * offset * offset).sum() + sig**2 / prior_sigma**2]])
        a, b = np.linalg.solve(A, np.array([(w * h).sum(), (w * offset * h).sum()]))
        r = h - a - b * offset
        sig = max(1.4826 * float(np.median(np.abs(r))), 0.01)
        u = r / (4.685 * sig)
        w = np.where(np.abs(u) < 1, (1 - u**2) ** 2, 0.0)
        if w.sum() < 3:
            return 0.0
    return float(b)


def camera_heights(P: np.ndarray, C: np.ndarray, up: np.ndarray, lateral: float = 1.5, window: float = 8.0,
                   min_points: int = 5, fall_lateral: float = 3.0, fall_window: float = 24.0,
                   fall_prior: float = 0.04) -> np.ndarray:
    """(R,) height of each camera centre ``C`` (R, 3), in time order, over the road points ``P`` (M, 3) it
    drives over, along ``up`` (3,); NaN where fewer than ``min_points`` points lie within ``lateral`` m beside
    the path and ``window`` m along it from the camera, and for a non-finite centre.

    A point's height is the path's own height at the point's chainage (interpolated between the cameras)
    minus the point's, so the road's grade cancels and what varies is the camera's height over the road
    under it, which a drifting scale or pitch of the path changes. The road's cross-fall (a camber, a turn's
    superelevation: 4-8 % on the KITTI sample) is taken out first, fitted over ``fall_lateral`` m beside the
    path and ``fall_window`` m along it with a prior of ``fall_prior`` on it. Road beyond the path's ends
    counts only within ``lateral`` of the end camera. A path that retraces itself exactly gives both passes
    one chainage. Why not a plane per camera with a free slope over a radius
    (:func:`pavemap.geometry.triangulate.local_ground`): where the road's points lie metres ahead of a camera,
    or few of them beside the lane (a parked car's sill), that plane's tilt is set by a handful of points and
    its extrapolation to the camera moves the height (docs/history, "One estimate of the camera height").
    """
    from pavemap.geometry.chainage import chainage, route_polyline

    up = np.asarray(up, dtype=np.float64) / np.linalg.norm(up)
    e1 = np.cross(up, [1.0, 0.0, 0.0] if abs(up[0]) < 0.9 else [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    basis = np.stack([e1, np.cross(up, e1)], axis=1)  # (3, 2) horizontal axes
    C = np.asarray(C, dtype=np.float64)
    P = np.asarray(P, dtype=np.float64).reshape(-1, 3)
    out = np.full(len(C), np.nan)
    cams = np.flatnonzero(np.isfinite(C).all(1))
    P = P[np.isfinite(P).all(1)]
    if len(P) < min_points or len(cams) < 2:
        return out
    route = route_polyline(C[cams] @ basis)
    if len(route) < 2:
        return out
    s_cam, _ = chainage(route, C[cams] @ basis)
    s, o = chainage(route, P @ basis)
    beside = np.abs(o) <= max(lateral, fall_lateral)
    P, s, o = P[beside], s[beside], o[beside]
    order = np.argsort(s_cam, kind="stable")
    h = np.interp(s, s_cam[order], (C[cams] @ up)[order]) - P @ up
    by_s = np.argsort(s, kind="stable")
    s, o, h = s[by_s], o[by_s], h[by_s]
    for j, sj in zip(cams, s_cam, strict=True):
        lo, hi = np.searchsorted(s, [sj - fall_window, sj + fall_window], side="left")
        sw, ow, hw = s[lo:hi], o[lo:hi], h[lo:hi]
        near = (np.abs(sw - sj) <= window) & (np.abs(ow) <= lateral)
        if near.sum() < min_points:
            continue
        wide = np.abs(ow) <= fall_lateral
        fall = _cross_fall(ow[wide], hw[wide], fall_prior) if wide.sum() >= min_points else 0.0
        out[j] = float(np.median(hw[near] - fall * ow[near]))
    return out


__all__ = ["HeightEstimate", "camera_heights", "height_estimate"]
