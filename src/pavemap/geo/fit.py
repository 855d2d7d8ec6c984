"""Robust 2D similarity / rigid fit of a trajectory to GPS fixes (both in metres of one plane).

The model maps trajectory points ``p`` (world x, y) onto fix positions ``q`` (east, north of a
local projection): ``q = s R(theta) p + t``. ``scale=False`` holds ``s = 1`` (metric poses);
``scale=True`` frees it (poses from SfM, whose scale is only as good as the camera height).

Robustness: RANSAC over two-point samples (a similarity has four degrees of freedom, two point
pairs fix it) finds the consensus set; then least squares on the inliers alternates with a new
inlier threshold from the residuals' median (isotropic 2D Gaussian: median |r| = 1.1774 sigma),
so a 2 % share of 50 m outlier fixes never pulls the fit and the threshold adapts to the
receiver's noise (1-10 m) without a setting.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

#: first consensus radius (m): wider than any plain GNSS noise, narrower than multipath jumps
RANSAC_RADIUS_M = 15.0
#: inliers after RANSAC: |r| < K_SIGMA * sigma (2D Gaussian: 0.2 % of good fixes fall outside)
K_SIGMA = 3.5
MIN_THRESHOLD_M = 0.5
SCORE_POINTS = 2000  # RANSAC scores candidates on at most this many pairs (memory: trials x points)
RAYLEIGH_MEDIAN = math.sqrt(2.0 * math.log(2.0))


@dataclass
class Fit2D:
    """``q = scale * R(theta) @ p + t``; residuals and inliers over the input pairs."""

    scale: float
    theta: float  # radians, counter-clockwise
    t: np.ndarray  # (2,)
    inliers: np.ndarray  # (N,) bool
    residuals: np.ndarray  # (N,) float64 metres, |q - model(p)|
    rms_m: float  # over the inliers
    sigma_m: float  # robust noise estimate from the inliers' median residual
    scale_se: float  # standard error of the scale (0 when held at 1)

    @property
    def rotation(self) -> np.ndarray:
        c, s = math.cos(self.theta), math.sin(self.theta)
        return np.array([[c, -s], [s, c]])

    def apply(self, p: np.ndarray) -> np.ndarray:
        """(N, 2) trajectory points -> (N, 2) modelled fix positions."""
        return self.scale * np.asarray(p, dtype=np.float64) @ self.rotation.T + self.t


def umeyama_2d(p: np.ndarray, q: np.ndarray, scale: bool) -> tuple[float, float, np.ndarray]:
    """Least-squares (s, theta, t) with ``q ~ s R p + t`` for (N, 2) arrays (N >= 2)."""
    mp, mq = p.mean(0), q.mean(0)
    a, b = p - mp, q - mq
    # 2D: the optimal rotation angle comes from the summed cross and dot products
    dot = float(np.sum(a * b))
    cross = float(np.sum(a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]))
    theta = math.atan2(cross, dot)
    var = float(np.sum(a * a))
    s = math.hypot(dot, cross) / var if (scale and var > 0) else 1.0
    c, sn = math.cos(theta), math.sin(theta)
    R = np.array([[c, -sn], [sn, c]])
    return s, theta, mq - s * R @ mp


def _ransac(p: np.ndarray, q: np.ndarray, scale: bool, rng: np.random.Generator, trials: int) -> np.ndarray:
    """Consensus mask of the best two-point model (pairs at least a fifth of the extent apart)."""
    n = len(p)
    score_on = np.sort(rng.choice(n, SCORE_POINTS, replace=False)) if n > SCORE_POINTS else np.arange(n)
    i = rng.integers(0, n, trials)
    j = rng.integers(0, n, trials)
    dp = p[j] - p[i]
    extent = float(np.linalg.norm(p.max(0) - p.min(0)))
    ok = np.linalg.norm(dp, axis=1) > 0.2 * extent
    i, j, dp = i[ok], j[ok], dp[ok]
    if len(i) == 0:
        return np.ones(n, dtype=bool)
    dq = q[j] - q[i]
    theta = np.arctan2(dq[:, 1], dq[:, 0]) - np.arctan2(dp[:, 1], dp[:, 0])
    s = np.linalg.norm(dq, axis=1) / np.linalg.norm(dp, axis=1) if scale else np.ones(len(i))
    c, sn = np.cos(theta), np.sin(theta)
    # model(p) = s R (p - p_i) + q_i, evaluated for every candidate (M, N, 2)
    ps, qs = p[score_on], q[score_on]
    rel = ps[None] - p[i][:, None]
    mx = s[:, None] * (c[:, None] * rel[..., 0] - sn[:, None] * rel[..., 1]) + q[i][:, None, 0]
    my = s[:, None] * (sn[:, None] * rel[..., 0] + c[:, None] * rel[..., 1]) + q[i][:, None, 1]
    r = np.hypot(qs[None, :, 0] - mx, qs[None, :, 1] - my)
    inl = r < RANSAC_RADIUS_M
    score = inl.sum(1) - 1e-6 * np.where(inl, r, 0).sum(1)  # ties: the tighter consensus
    k = int(np.argmax(score))
    rel = p - p[i[k]]
    model = s[k] * rel @ np.array([[c[k], sn[k]], [-sn[k], c[k]]]) + q[i[k]]
    return np.linalg.norm(q - model, axis=1) < RANSAC_RADIUS_M


def robust_fit(p: np.ndarray, q: np.ndarray, scale: bool = False, seed: int = 0, trials: int = 400,
               iterations: int = 6) -> Fit2D:
    """Fit ``q ~ s R p + t`` robustly; ``p``, ``q`` (N, 2) metres, N >= 3.

    Returns the fit on the final inliers (at least 3, else all points).
    """
    p = np.asarray(p, dtype=np.float64)
    q = np.asarray(q, dtype=np.float64)
    rng = np.random.default_rng(seed)
    inl = _ransac(p, q, scale, rng, trials)
    if inl.sum() < 3:
        inl = np.ones(len(p), dtype=bool)
    for _ in range(iterations):
        s, th, t = umeyama_2d(p[inl], q[inl], scale)
        fit = Fit2D(s, th, t, inl, np.zeros(len(p)), 0.0, 0.0, 0.0)
        r = np.linalg.norm(q - fit.apply(p), axis=1)
        sigma = float(np.median(r[inl])) / RAYLEIGH_MEDIAN
        new = r < max(K_SIGMA * sigma, MIN_THRESHOLD_M)
        if new.sum() < 3 or np.array_equal(new, inl):
            break
        inl = new
    s, th, t = umeyama_2d(p[inl], q[inl], scale)
    fit = Fit2D(s, th, t, inl, np.zeros(len(p)), 0.0, 0.0, 0.0)
    r = np.linalg.norm(q - fit.apply(p), axis=1)
    fit.residuals = r
    fit.rms_m = float(np.sqrt(np.mean(r[inl] ** 2)))
    fit.sigma_m = float(np.median(r[inl])) / RAYLEIGH_MEDIAN
    if scale:
        spread = float(np.sum((p[inl] - p[inl].mean(0)) ** 2))
        fit.scale_se = fit.sigma_m / math.sqrt(spread) if spread > 0 else math.inf
    return fit


__all__ = ["Fit2D", "robust_fit", "umeyama_2d"]
