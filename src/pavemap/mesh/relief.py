"""The road's relief from sparse ground points, fitted in road coordinates (pure numpy / scipy, no I/O).

The initial surface of stage 1 is the ground under the trajectory plus a relief measured by ground points
(triangulated from the images, or depth pixels). Points are sparse and uneven: they cluster on lane paint,
kerbs and sidewalk edges, and plain asphalt, where the defects are, gets few. This module fits the relief
``r(s, t)`` on a lattice in road coordinates (``s`` along the trajectory, ``t`` across it, from
:func:`pavemap.mesh.init_surface.along_track`) by regularised least squares:

    sum_i w_i (r(s_i, t_i) - r_i)^2                      data: bilinear on the lattice, robust weights w_i
  + curv_s^2 |d2 r / ds2|^2 + curv_t^2 |d2 r / dt2|^2     bending along and across the road
  + slope^2 (|dr / ds|^2 + |dr / dt|^2)                  a membrane that keeps gaps level, not extrapolated

Why in road coordinates: a road's cross-section (crown, gutter, kerb, sidewalk) changes slowly along it, so
the bending along ``s`` is penalised an order more than across ``t``, and a gap between points takes the
cross-section measured a few metres before and after. The robust weights (iteratively reweighted, Huber
beyond ``robust_k`` sigmas) keep a few mismatched points from denting it. Measured on the no-depth bench
drives (initial surface, observed vertices): nuScenes-like 5.6 -> 2.5 cm RMSE, kitti-like (seed 23)
5.6 -> 1.7 cm, against the earlier per-bin medians with Gaussian and along-the-road fills.

Points farther off than ``reject_m`` (and ``reject_k`` robust sigmas) after a round leave the next one: Huber's
linear tail let two points 40 cm high lift 8 m of road by 6-8 cm. With the vertices' classes (``side_q``) the
bending and slope between road and off-road nodes nearly vanish, so a kerb stays a step where forward cameras
left no point beside it (nuScenes-like, observed vertices, no depth: 2.27 -> 1.93 cm; docs/history, stage 1).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from scipy.linalg import cho_solve_banded, cholesky_banded, solveh_banded
from scipy.sparse.linalg import spsolve


@dataclass(frozen=True)
class ReliefFit:
    """Lattice and weights of :func:`fit_relief` (metres; weights relative to one point of unit weight)."""

    ds: float = 0.5  # lattice step along the road
    dt: float = 0.1  # across it (a kerb stays a step of one lattice cell)
    curv_s: float = 3.0
    curv_t: float = 0.3
    slope: float = 0.3
    gate: float = 0.5  # points farther than this from the trajectory plane are not ground (facades, poles)
    robust_k: float = 2.5
    sigma_floor: float = 0.005  # m: the robust scale never drops below this
    iterations: int = 4
    # rounds of a fit that starts from an earlier fit's weights (``state``, the kerb refit): with 2 the robust
    # weights had not settled once the kerb could step, leaving two strips of ground at the crop's edge 5 cm high
    # (kitti-like bench drive, observed RMSE 1.91 -> 1.63 cm with 4; five other drives within 0.01 cm; 8 rounds:
    # 1.59 cm there, the same elsewhere, up to 3 s more a drive; docs/refine.md, section 6)
    refit_iterations: int = 4
    margin_s: float = 5.0  # the lattice reaches this far beyond the query points along the road ...
    margin_t: float = 4.0  # ... and across it: points just outside the crop still hold its edge
    max_nodes: int = 4_000_000  # a longer drive is cut into segments before stage 1 (see docs/guide/long-drives.md)
    # a point farther off the fit than both of these after a round is not ground (weight 0 in the next): a
    # car's bonnet, a mismatch; relative too, so that noisy points (poses off by decimetres) are not thinned
    reject_m: float = 0.10
    reject_k: float = 6.0
    break_weight: float = 0.001  # bending and slope between nodes of different sides (``side_q``), relative


def _bilinear(s: np.ndarray, t: np.ndarray, s0: float, t0: float, fit: ReliefFit, ns: int, nt: int) -> sp.csr_matrix:
    """(N, ns * nt) bilinear interpolation weights of points (s, t) on the lattice (node (a, b) at s0 + a ds,
    t0 + b dt; flat index a * nt + b); points are clamped into the lattice."""
    fs, ft = (s - s0) / fit.ds, (t - t0) / fit.dt
    a = np.clip(np.floor(fs).astype(np.int64), 0, ns - 2)
    b = np.clip(np.floor(ft).astype(np.int64), 0, nt - 2)
    u, v = np.clip(fs - a, 0.0, 1.0), np.clip(ft - b, 0.0, 1.0)
    cols = np.stack([a * nt + b, (a + 1) * nt + b, a * nt + b + 1, (a + 1) * nt + b + 1], 1).ravel()
    w = np.stack([(1 - u) * (1 - v), u * (1 - v), (1 - u) * v, u * v], 1).ravel()
    rows = np.repeat(np.arange(len(s)), 4)
    return sp.csr_matrix((w, (rows, cols)), shape=(len(s), ns * nt))


def _difference(ns: int, nt: int, axis: int, order: int) -> sp.csr_matrix:
    """First (order 1) or second (order 2) differences of the lattice values along ``axis`` (0: s, 1: t)."""
    idx = np.arange(ns * nt).reshape(ns, nt)
    n_ax = idx.shape[axis]
    if n_ax <= order:
        return sp.csr_matrix((0, ns * nt))
    taps = (np.array([-1.0, 1.0]), np.array([1.0, -2.0, 1.0]))[order - 1]
    parts = [np.take(idx, np.arange(k, n_ax - order + k), axis=axis).ravel() for k in range(order + 1)]
    m = len(parts[0])
    rows = np.repeat(np.arange(m), order + 1)
    return sp.csr_matrix((np.tile(taps, m), (rows, np.stack(parts, 1).ravel())), shape=(m, ns * nt))


def fit_relief(s_pts: np.ndarray, t_pts: np.ndarray, r: np.ndarray, s_q: np.ndarray, t_q: np.ndarray,
               fit: ReliefFit | None = None, min_points: int = 100, side_q: np.ndarray | None = None,
               state: dict | None = None) -> np.ndarray | None:
    """(Q,) float64 relief at query points (s_q, t_q) (Q,) from point residuals r (N,) at (s_pts, t_pts) (N,).

    r: the points' heights minus the trajectory plane (m). The lattice spans the query points; points outside
    it or beyond ``fit.gate`` are left out. None with fewer than ``min_points`` usable points, or a lattice
    over ``fit.max_nodes`` nodes (the caller falls back to its binned relief).

    side_q (Q,) int, optional: the surface each query point lies on (e.g. 1 a road class, 0 any other; -1 not
    known). Each node takes the most common side of its query points, and the bending and slope terms between
    nodes of different sides are weighted by ``fit.break_weight``: the surface may step there, as at a kerb,
    instead of rounding the step off over the metre or two where forward cameras leave no point.

    state: a dict that keeps the points' robust weights between two fits of the same points; a second fit
    starts from the first one's weights and runs ``fit.refit_iterations`` rounds.
    """
    fit = fit or ReliefFit()
    s0, s1 = float(s_q.min()) - fit.margin_s, float(s_q.max()) + fit.margin_s
    t0, t1 = float(t_q.min()) - fit.margin_t, float(t_q.max()) + fit.margin_t
    ns, nt = int(np.ceil((s1 - s0) / fit.ds)) + 2, int(np.ceil((t1 - t0) / fit.dt)) + 2
    ok = (np.abs(r) < fit.gate) & (s_pts >= s0) & (s_pts <= s1) & (t_pts >= t0) & (t_pts <= t1)
    if ok.sum() < min_points or ns * nt > fit.max_nodes:
        return None
    A = _bilinear(s_pts[ok], t_pts[ok], s0, t0, fit, ns, nt)
    rr = r[ok]
    node_side = None if side_q is None else _node_side(s_q, t_q, side_q, s0, t0, fit, ns, nt)
    reg = sum(k ** 2 * _gram(_difference(ns, nt, axis, order), node_side, fit.break_weight)
              for k, axis, order in ((fit.curv_s, 0, 2), (fit.curv_t, 1, 2), (fit.slope, 0, 1), (fit.slope, 1, 1)))
    w, rounds = np.ones(len(rr)), fit.iterations
    if state is not None and state.get("w") is not None and len(state["w"]) == len(r):
        w, rounds = state["w"][ok], fit.refit_iterations
    values = np.zeros(ns * nt)
    for _ in range(max(1, rounds)):
        W = sp.diags(w)
        values = _solve_spd((A.T @ W @ A + reg).tocsr(), A.T @ (w * rr), ns, nt)
        res = A @ values - rr
        sigma = max(1.4826 * float(np.median(np.abs(res))), fit.sigma_floor)
        w = 1.0 / np.maximum(1.0, np.abs(res) / (fit.robust_k * sigma))  # Huber: linear beyond k sigma
        w[np.abs(res) > max(fit.reject_m, fit.reject_k * sigma)] = 0.0  # Huber alone left a 6-8 cm bump
    if state is not None:
        state["w"] = np.zeros(len(r))
        state["w"][ok] = w
    return _bilinear(s_q, t_q, s0, t0, fit, ns, nt) @ values


def _solve_spd(M: sp.csr_matrix, b: np.ndarray, ns: int, nt: int, tol: float = 1e-10, max_refine: int = 10
               ) -> np.ndarray:
    """(ns * nt,) solution of the normal equations M x = b (M symmetric positive definite, on the ns x nt
    lattice) by a banded Cholesky, the lattice numbered along its shorter axis first (bandwidth 2 x that
    axis's nodes: second differences reach two nodes); the general sparse solve if M is not numerically SPD.

    Why banded: SuperLU treats M as unsymmetric and its fill grows with the lattice's width. Measured on one
    core (results equal to 1e-13 m): lattices of 92 / 202 / 402 x 322 nodes 0.86 / 2.65 / 7.4 s -> 0.24 / 0.86 /
    4.4 s at the same peak memory. Conjugate gradients preconditioned by the lattice lines lost on the
    data-free margins (~600-800 iterations), and so did algebraic multigrid (pyamg: 230-310 iterations, 2-3x
    slower than the banded solve).

    The factor is computed in float32 and the solution refined in float64 until the residual is ``tol`` of
    ``|b|`` (mixed-precision iterative refinement; a float32 solve alone is off by up to 1 cm): half the
    factor's memory and time (docs/history, stage 1); the float64 factor where float32 is not SPD or the
    refinement stalls."""
    n = ns * nt
    order = np.arange(n).reshape(ns, nt)
    order = (order.T if ns < nt else order).ravel()  # position in the band -> lattice index
    C = M[order][:, order].tocsr()
    coo = C.tocoo()
    upper = coo.col >= coo.row
    bw = int((coo.col - coo.row)[upper].max(initial=0))
    bo = b[order]
    x = _refined(C, coo, upper, bw, bo, tol, max_refine)
    if x is None:
        ab = np.zeros((bw + 1, n))
        ab[bw + coo.row[upper] - coo.col[upper], coo.col[upper]] = coo.data[upper]
        try:
            x = solveh_banded(ab, bo, overwrite_ab=True, check_finite=False)
        except np.linalg.LinAlgError:
            return spsolve(M.tocsc(), b)
    out = np.empty(n)
    out[order] = x
    return out


def _refined(C: sp.csr_matrix, coo: sp.coo_matrix, upper: np.ndarray, bw: int, b: np.ndarray, tol: float,
             max_refine: int) -> np.ndarray | None:
    """Solution of C x = b from C's float32 banded Cholesky factor and float64 residuals; None if the factor
    fails or the residual does not reach ``tol`` of ``|b|``."""
    ab = np.zeros((bw + 1, C.shape[0]), np.float32)
    ab[bw + coo.row[upper] - coo.col[upper], coo.col[upper]] = coo.data[upper]
    try:
        factor = (cholesky_banded(ab, overwrite_ab=True, check_finite=False), False)
    except np.linalg.LinAlgError:
        return None
    x = np.zeros_like(b)
    r, goal = b, tol * max(float(np.linalg.norm(b)), 1e-300)
    for _ in range(max_refine):
        x += cho_solve_banded(factor, r.astype(np.float32), check_finite=False)
        r = b - C @ x
        if float(np.linalg.norm(r)) <= goal:
            return x
    return None


def _node_side(s_q: np.ndarray, t_q: np.ndarray, side_q: np.ndarray, s0: float, t0: float, fit: ReliefFit,
               ns: int, nt: int) -> np.ndarray:
    """(ns * nt,) int64 side of each lattice node: the most common among the query points nearest to it that
    know theirs, -1 where none does (no break there)."""
    a = np.clip(np.rint((s_q - s0) / fit.ds).astype(np.int64), 0, ns - 1)
    b = np.clip(np.rint((t_q - t0) / fit.dt).astype(np.int64), 0, nt - 1)
    known = side_q >= 0
    node, side = (a * nt + b)[known], side_q[known].astype(np.int64)
    k = int(side.max(initial=0)) + 1
    counts = np.bincount(node * k + side, minlength=ns * nt * k).reshape(ns * nt, k)
    return np.where(counts.any(1), counts.argmax(1), -1)


def _gram(D: sp.csr_matrix, node_side: np.ndarray | None = None, break_weight: float = 1.0) -> sp.csr_matrix:
    """D^T W D, W down-weighting the rows (differences) that reach nodes of both sides."""
    if node_side is None:
        return (D.T @ D).tocsr()
    Dc = D.tocoo()
    side = node_side[Dc.col]
    big = np.iinfo(np.int64).max
    lo, hi = np.full(D.shape[0], big), np.full(D.shape[0], -1)
    known = side >= 0
    np.minimum.at(lo, Dc.row[known], side[known])
    np.maximum.at(hi, Dc.row[known], side[known])
    w = np.where((hi >= 0) & (lo < hi), break_weight, 1.0)
    return (D.T @ sp.diags(w) @ D).tocsr()


__all__ = ["ReliefFit", "fit_relief"]
