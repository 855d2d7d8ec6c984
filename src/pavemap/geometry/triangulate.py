"""Multi-view triangulation with known poses, local ground fits and surface checks (pure functions, no I/O).

Conventions (SPEC §0): world metric z up, cameras OpenCV axes, ``T_world_cam`` camera-to-world, pixel
centres at integer ``u`` (:meth:`pavemap.types.Camera.scaled`). A *track* is one world point seen in
several views; its observations are flat arrays indexed by ``track`` (M,) so every step is vectorised
over all tracks at once (``np.add.at`` accumulates the per-track normal equations).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from pavemap.geometry.camera import pixel_rays
from pavemap.geometry.grid import GridSpec


@dataclass
class Triangulation:
    """Points of tracks and their quality.

    points (N, 3) float64 world; per track: n_views (N,) int, rms_px (N,) reprojection RMS over its
    kept observations, max_px (N,), angle_deg (N,) the largest angle between two of its rays, ok (N,)
    bool (passed every check). Per observation (M,): err_px reprojection error, depth camera z (m),
    used bool (kept after outlier removal).
    """

    points: np.ndarray
    n_views: np.ndarray
    rms_px: np.ndarray
    max_px: np.ndarray
    angle_deg: np.ndarray
    ok: np.ndarray
    err_px: np.ndarray
    depth: np.ndarray
    used: np.ndarray


def plane_homography(K_i: np.ndarray, T_i: np.ndarray, K_j: np.ndarray, T_j: np.ndarray,
                     normal: np.ndarray, offset: float, normalise: bool = True) -> np.ndarray:
    """(3, 3) homography taking pixels of view i to pixels of view j through the world plane
    ``normal . X = offset``: ``H = K_j (R_ji + t_ji n_i^T / d_i) K_i^-1``. ``normalise`` False: unscaled, so
    the third coordinate of ``H x`` is the plane point's depth in j over its depth in i (its sign says whether
    the point is on the same side of both cameras; normalised, ``H[2, 2]`` = 1 loses that sign)."""
    R_i, t_i, R_j, t_j = T_i[:3, :3], T_i[:3, 3], T_j[:3, :3], T_j[:3, 3]
    n_i = R_i.T @ normal
    d_i = offset - float(normal @ t_i)
    R_ji = R_j.T @ R_i
    t_ji = R_j.T @ (t_i - t_j)
    H = K_j @ (R_ji + np.outer(t_ji, n_i) / d_i) @ np.linalg.inv(K_i)
    return H / H[2, 2] if normalise else H


def apply_homography(H: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """(N, 2) pixels mapped by (3, 3) ``H``."""
    p = np.c_[uv, np.ones(len(uv))] @ H.T
    return p[:, :2] / p[:, 2:3]


def world_rays(K: np.ndarray, T: np.ndarray, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rays of observations: K (M, 3, 3), T (M, 4, 4), uv (M, 2) -> origins (M, 3), unit dirs (M, 3) float64."""
    o, d = pixel_rays(K, T, torch.as_tensor(np.asarray(uv, np.float64)))
    d = d.numpy()
    return o.numpy().copy(), d / np.linalg.norm(d, axis=1, keepdims=True)


def _midpoint(o: np.ndarray, d: np.ndarray, track: np.ndarray, n: int, w: np.ndarray) -> np.ndarray:
    """Weighted least-squares point nearest to each track's rays (unit dirs): sum w (I - d d^T)(X - o) = 0."""
    P = np.eye(3)[None] - d[:, :, None] * d[:, None, :]
    A = np.zeros((n, 3, 3))
    b = np.zeros((n, 3))
    np.add.at(A, track, w[:, None, None] * P)
    np.add.at(b, track, w[:, None] * np.einsum("mij,mj->mi", P, o))
    A += 1e-9 * np.eye(3)[None]
    return np.linalg.solve(A, b[..., None])[..., 0]


def _project(K: np.ndarray, T: np.ndarray, X: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per observation: uv (M, 2), camera depth (M,), camera-frame point (M, 3)."""
    pc = np.einsum("mji,mj->mi", T[:, :3, :3], X - T[:, :3, 3])  # R^T (X - t)
    z = pc[:, 2]
    zs = np.where(np.abs(z) > 1e-9, z, 1e-9)
    uvw = np.einsum("mij,mj->mi", K, pc)
    return uvw[:, :2] / zs[:, None], z, pc


def _gauss_newton(K, T, uv, track, n, X, used, iters: int = 5) -> np.ndarray:
    """Refine each track's point on its reprojection error (Levenberg-damped Gauss-Newton)."""
    R_T = np.transpose(T[:, :3, :3], (0, 2, 1))
    for _ in range(iters):
        Xm = X[track]
        uv_hat, z, _ = _project(K, T, Xm)
        zs = np.where(z > 1e-6, z, 1e-6)
        # d(u)/d(X_c) = (K[0] - u K[2]) / z, d(v)/d(X_c) = (K[1] - v K[2]) / z; chain with d(X_c)/d(X) = R^T
        Jc = (K[:, :2, :] - uv_hat[:, :, None] * K[:, 2:3, :]) / zs[:, None, None]
        J = Jc @ R_T
        r = (uv - uv_hat) * used[:, None]
        J = J * used[:, None, None]
        H = np.zeros((n, 3, 3))
        g = np.zeros((n, 3))
        np.add.at(H, track, np.einsum("mki,mkj->mij", J, J))
        np.add.at(g, track, np.einsum("mki,mk->mi", J, r))
        damp = 1e-6 * np.trace(H, axis1=1, axis2=2)[:, None, None] + 1e-12
        X = X + np.linalg.solve(H + damp * np.eye(3)[None], g[..., None])[..., 0]
    return X


def _max_angle(d: np.ndarray, track: np.ndarray, n: int, used: np.ndarray) -> np.ndarray:
    """(n,) degrees: the largest angle between two used rays of each track (rays padded per track)."""
    order = np.lexsort((~used, track))
    t_sorted = track[order]
    start = np.searchsorted(t_sorted, np.arange(n))
    slot = np.arange(len(order)) - start[t_sorted]
    width = int(slot.max()) + 1 if len(order) else 1
    pad = np.zeros((n, width, 3))
    mask = np.zeros((n, width), bool)
    pad[t_sorted, slot] = d[order]
    mask[t_sorted, slot] = used[order]
    cos = np.einsum("nai,nbi->nab", pad, pad)
    cos = np.where(mask[:, :, None] & mask[:, None, :], cos, 1.0)
    return np.degrees(np.arccos(np.clip(cos.min(axis=(1, 2)), -1.0, 1.0)))


def triangulate_tracks(K: np.ndarray, T: np.ndarray, uv: np.ndarray, track: np.ndarray, n_tracks: int, *,
                       max_err_px: float = 1.0, min_angle_deg: float = 1.0, min_views: int = 2,
                       max_depth: float = 60.0) -> Triangulation:
    """Triangulate tracks with the poses held fixed.

    K (M, 3, 3), T (M, 4, 4) per observation; uv (M, 2) pixels; track (M,) int in [0, n_tracks).
    Weighted midpoint (weights 1/depth^2 make it ~angular), Gauss-Newton on reprojection error, then each
    observation off by more than ``max_err_px`` is dropped and the track refit (multi-view consistency:
    a track keeps only views that agree on one point). A track is ``ok`` with at least ``min_views``
    agreeing views, every kept view seeing it in front (0 < depth <= max_depth) and a triangulation
    angle of at least ``min_angle_deg`` (parallax: below it depth is noise).
    """
    K = np.asarray(K, np.float64)
    T = np.asarray(T, np.float64)
    uv = np.asarray(uv, np.float64)
    track = np.asarray(track, np.int64)
    o, d = world_rays(K, T, uv)
    used = np.ones(len(track), bool)
    X = _midpoint(o, d, track, n_tracks, np.ones(len(track)))
    width = int(np.bincount(track, minlength=n_tracks).max(initial=0))
    for _ in range(width + 1):  # ends on a fit: the last round drops nothing
        dep = np.maximum(np.einsum("mi,mi->m", X[track] - o, d), 0.5)
        X = _midpoint(o, d, track, n_tracks, used / dep**2)
        X = _gauss_newton(K, T, uv, track, n_tracks, X, used)
        uv_hat, z, _ = _project(K, T, X[track])
        err = np.where(z > 0, np.linalg.norm(uv - uv_hat, axis=1), np.inf)
        # drop only each track's worst view per round: one bad view also pulls the good ones off
        worst = np.full(n_tracks, -1.0)
        np.maximum.at(worst, track, np.where(used, err, -1.0))
        drop = used & (err == worst[track]) & (err > max_err_px)
        if not drop.any():
            break
        used &= ~drop
    err = np.where(np.isfinite(err), err, 1e9)
    n_views = np.bincount(track, weights=used, minlength=n_tracks).astype(np.int64)
    sq = np.bincount(track, weights=used * err**2, minlength=n_tracks)
    rms = np.sqrt(sq / np.maximum(n_views, 1))
    mx = np.zeros(n_tracks)
    np.maximum.at(mx, track, np.where(used, err, 0.0))
    # every view of a track, used or not, must see the point in front: a point behind a camera is a mismatch
    bad_depth = np.zeros(n_tracks, bool)
    np.logical_or.at(bad_depth, track, (z <= 0) | (z > max_depth))
    angle = _max_angle(d, track, n_tracks, used)
    ok = (n_views >= max(min_views, 2)) & ~bad_depth & (angle >= min_angle_deg) & np.all(np.isfinite(X), axis=1)
    return Triangulation(X, n_views, rms, mx, angle, ok, err, z, used)


# ---------------------------------------------------------------------------- scores along a ray


def parabola_vertex(ym: np.ndarray, y0: np.ndarray, yp: np.ndarray) -> np.ndarray:
    """Sub-step offset in [-1, 1] of the vertex of the parabola through (-1, ym), (0, y0), (1, yp)."""
    den = ym - 2 * y0 + yp
    safe = np.where(den < -1e-9, den, -1.0)
    return np.clip(np.where(den < -1e-9, 0.5 * (ym - yp) / safe, 0.0), -1.0, 1.0)


def second_peak(ncc: np.ndarray, k: np.ndarray) -> np.ndarray:
    """(R,) highest NCC outside the main peak of each row of ncc (R, S): the main peak spans the monotone
    descent on both sides of its maximum k, so its own shoulders never count as a rival (repetitive or
    flat texture along the epipolar line gives a rival close to the peak)."""
    R, S = ncc.shape
    s = np.arange(S)[None]
    rises_left = np.zeros((R, S), bool)  # ncc[s] > ncc[s + 1]: going left from k, the descent ends at s
    rises_left[:, :-1] = ncc[:, :-1] > ncc[:, 1:]
    rises_right = np.zeros((R, S), bool)  # ncc[s] > ncc[s - 1]
    rises_right[:, 1:] = ncc[:, 1:] > ncc[:, :-1]
    left = np.where(rises_left & (s < k[:, None]), s, -1).max(1)  # last index still in a rival region
    right = np.where(rises_right & (s > k[:, None]), s, S).min(1)
    rival = (s <= left[:, None]) | (s >= right[:, None])
    return np.where(rival, ncc, -1.0).max(1)


# ---------------------------------------------------------------------------- local ground fits


@dataclass
class LocalGround:
    """Robust local planes ``z = h0 + a (x - cx) + b (y - cy)`` under query centres (C,).

    h0 (C,) ground height under each centre (NaN where not observable), slope (C, 2) (a, b), n (C,) int
    inliers, sigma (C,) robust residual scale (m) of the inliers.
    """

    h0: np.ndarray
    slope: np.ndarray
    n: np.ndarray
    sigma: np.ndarray


def _wls_plane(dx: np.ndarray, dy: np.ndarray, z: np.ndarray, w: np.ndarray) -> np.ndarray:
    A = np.c_[np.ones_like(dx), dx, dy]
    Aw = A * w[:, None]
    return np.linalg.lstsq(Aw.T @ A + 1e-9 * np.eye(3), Aw.T @ z, rcond=None)[0]


def fit_plane_robust(dx: np.ndarray, dy: np.ndarray, z: np.ndarray, *, inlier_m: float = 0.05,
                     trials: int = 64, seed: int = 0) -> tuple[np.ndarray, np.ndarray, float]:
    """One robust plane ``z = p0 + p1 dx + p2 dy`` through (N,) samples: vectorised RANSAC (``trials``
    triplets scored at once), then Tukey-biweight IRLS on the consensus. Returns p (3,), inlier mask (N,),
    robust scale (m). RANSAC first because off-ground points (cars, rails) can be a large minority."""
    n = len(z)
    rng = np.random.default_rng(seed)
    idx = rng.integers(0, n, size=(trials, 3))
    A = np.stack([np.ones((trials, 3)), dx[idx], dy[idx]], axis=-1)
    det = np.linalg.det(A)
    good = np.abs(det) > 1e-6
    P = np.zeros((trials, 3))
    P[good] = np.linalg.solve(A[good], z[idx][good][..., None])[..., 0]
    res = np.abs(z[None] - (P[:, :1] + P[:, 1:2] * dx[None] + P[:, 2:3] * dy[None]))
    score = np.where(good, (res < inlier_m).sum(1), -1)
    p = P[int(np.argmax(score))] if good.any() else np.array([np.median(z), 0.0, 0.0])
    scale = inlier_m
    for _ in range(6):
        r = z - (p[0] + p[1] * dx + p[2] * dy)
        inl = np.abs(r) < 3 * max(scale, 0.005)
        if inl.sum() < 3:
            break
        scale = max(1.4826 * float(np.median(np.abs(r[inl]))), 0.003)
        u = r / (4.685 * scale)
        w = np.where(np.abs(u) < 1, (1 - u**2) ** 2, 0.0)
        p = _wls_plane(dx, dy, z, w)
    r = z - (p[0] + p[1] * dx + p[2] * dy)
    inl = np.abs(r) < 3 * max(scale, 0.005)
    return p, inl, scale


def local_ground(points: np.ndarray, centres: np.ndarray, *, radius: float = 4.0, max_radius: float = 12.0,
                 min_points: int = 30, inlier_m: float = 0.05, seed: int = 0) -> LocalGround:
    """Robust ground plane under each centre from the points within a horizontal radius.

    points (N, 3), centres (C, 3) float64. The radius doubles (up to ``max_radius``) until ``min_points``
    fall in it: a front camera never sees the ground right under itself, only views of other frames do.
    Points are weighted by nothing but the robust fit; the plane is evaluated at the centre's (x, y).
    """
    from scipy.spatial import cKDTree

    C = len(centres)
    out = LocalGround(np.full(C, np.nan), np.zeros((C, 2)), np.zeros(C, np.int64), np.full(C, np.nan))
    if len(points) < 3:
        return out
    tree = cKDTree(points[:, :2])
    for c in range(C):
        r = radius
        while True:
            idx = np.asarray(tree.query_ball_point(centres[c, :2], r), np.int64)
            if len(idx) >= min_points or r >= max_radius:
                break
            r = min(2 * r, max_radius)
        if len(idx) < min_points:
            continue
        q = points[idx]
        p, inl, scale = fit_plane_robust(q[:, 0] - centres[c, 0], q[:, 1] - centres[c, 1], q[:, 2],
                                         inlier_m=inlier_m, seed=seed + c)
        if inl.sum() < min_points // 2:
            continue
        out.h0[c], out.slope[c], out.n[c], out.sigma[c] = p[0], p[1:], int(inl.sum()), scale
    return out


def within_corridor(points: np.ndarray, traj: np.ndarray, corridor: float) -> np.ndarray:
    """(N,) bool: points (N, 3) within ``corridor`` metres (horizontally) of the path traj (F, 3)."""
    from scipy.spatial import cKDTree

    # densify the path so the nearest sample approximates the nearest point of the polyline
    seg = np.linspace(0, 1, 6)[:-1]
    dense = (traj[:-1, None, :2] * (1 - seg)[None, :, None] + traj[1:, None, :2] * seg[None, :, None]).reshape(-1, 2)
    dense = np.r_[dense, traj[-1:, :2]] if len(traj) > 1 else traj[:, :2]
    return cKDTree(dense).query(points[:, :2])[0] <= corridor


def agrees_with_neighbours(points: np.ndarray, radius: float, max_dev: float, min_n: int = 8) -> np.ndarray:
    """(N,) bool: a point (N, 3) lies within ``max_dev`` of the robust plane of the points around it.

    The consistency check of 2-view tracks, which have nothing else to check them against. One plane per
    occupied ``radius`` cell, fitted over 1.5 radius around the cell; points with too few neighbours pass.
    """
    from scipy.spatial import cKDTree

    ok = np.ones(len(points), bool)
    if len(points) == 0:
        return ok
    tree = cKDTree(points[:, :2])
    cell = np.floor(points[:, :2] / radius).astype(np.int64)
    _, inv = np.unique(cell, axis=0, return_inverse=True)
    inv = inv.ravel()
    order = np.argsort(inv, kind="stable")
    groups = np.split(order, np.nonzero(np.diff(inv[order]))[0] + 1)
    for mine in groups:
        idx = np.asarray(tree.query_ball_point(cell[mine[0]] * radius + radius / 2, 1.5 * radius))
        if len(idx) < min_n:
            continue
        q, o = points[idx], points[mine[0]]
        p, _, _ = fit_plane_robust(q[:, 0] - o[0], q[:, 1] - o[1], q[:, 2], inlier_m=0.05, trials=32)
        r = points[mine, 2] - (p[0] + p[1] * (points[mine, 0] - o[0]) + p[2] * (points[mine, 1] - o[1]))
        ok[mine] = np.abs(r) <= max_dev
    return ok


# ---------------------------------------------------------------------------- surface checks


def sample_grid(grid: GridSpec, heights: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """Bilinear height (N,) at world xy (N, 2) of a raster (ny, nx) on ``grid``; NaN outside or on NaN nodes."""
    fx = (xy[:, 0] - grid.x0) / grid.res
    fy = (xy[:, 1] - grid.y0) / grid.res
    i0 = np.floor(fx).astype(np.int64)
    j0 = np.floor(fy).astype(np.int64)
    inside = (i0 >= 0) & (j0 >= 0) & (i0 < grid.nx - 1) & (j0 < grid.ny - 1)
    i0c, j0c = np.clip(i0, 0, grid.nx - 2), np.clip(j0, 0, grid.ny - 2)
    tx, ty = fx - i0c, fy - j0c
    h = heights
    z = ((1 - tx) * (1 - ty) * h[j0c, i0c] + tx * (1 - ty) * h[j0c, i0c + 1]
         + (1 - tx) * ty * h[j0c + 1, i0c] + tx * ty * h[j0c + 1, i0c + 1])
    return np.where(inside, z, np.nan)


@dataclass
class SurfaceCheck:
    """Triangulated points against a surface: residual = point z - surface z (m).

    n points compared, median signed residual, robust RMS (1.4826 MAD about zero), p90 of |residual|,
    fraction within ``tol_m``, and ``flagged`` with the reason when the surface disagrees with the points.
    """

    n: int
    median: float
    robust_rms: float
    p90: float
    frac_within: float
    flagged: bool
    reason: str


def check_residuals(residual: np.ndarray, *, max_bias_m: float = 0.05, max_rms_m: float = 0.10,
                    max_p90_m: float = 0.25, tol_m: float = 0.05, min_points: int = 20) -> SurfaceCheck:
    """Score residuals (N,) (NaN ignored). Flags a bias beyond ``max_bias_m``, a robust RMS beyond
    ``max_rms_m``, or a tenth of the points farther than ``max_p90_m`` (a part of the surface grossly off, which
    the median and the MAD of the rest do not see); too few points is flagged as not checkable rather than
    passed."""
    r = residual[np.isfinite(residual)]
    if len(r) < min_points:
        return SurfaceCheck(len(r), float("nan"), float("nan"), float("nan"), float("nan"), True,
                            f"only {len(r)} triangulated ground points on the surface: geometry not checkable")
    med = float(np.median(r))
    rms = float(1.4826 * np.median(np.abs(r)))
    p90 = float(np.quantile(np.abs(r), 0.9))
    within = float(np.mean(np.abs(r) <= tol_m))
    why = []
    if abs(med) > max_bias_m:
        why.append(f"surface is {-med:+.2f} m off the triangulated ground points (median)")
    if rms > max_rms_m:
        why.append(f"robust RMS {rms:.2f} m to the triangulated ground points exceeds {max_rms_m:.2f} m")
    if p90 > max_p90_m:
        why.append(f"{np.mean(np.abs(r) > max_p90_m):.0%} of the triangulated ground points lie more than "
                   f"{max_p90_m:.2f} m off the surface (p90 {p90:.2f} m): part of it is grossly wrong")
    return SurfaceCheck(len(r), med, rms, p90, within, bool(why), "; ".join(why))


def check_height_field(points: np.ndarray, grid: GridSpec, heights: np.ndarray, **kw) -> SurfaceCheck:
    """:func:`check_residuals` of points (N, 3) against a height raster (ny, nx) on ``grid``."""
    return check_residuals(points[:, 2] - sample_grid(grid, heights, points[:, :2]), **kw)
