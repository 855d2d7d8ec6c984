"""The coarse-to-fine Gauss-Newton solve of the photometric refinement (:mod:`pavemap.mesh.refine`).

Heights ``z = z0 + B delta``: level by level, B is a global offset and tilt (3 columns), then bilinear control
grids of a given spacing; the normal equations of the robustly weighted consistency residuals plus a
smoothness prior between neighbouring controls (and a weak prior towards the closed form) are solved by
conjugate gradients on a sparse matrix (a grid of 1 m over a long drive has thousands of controls).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from pavemap.mesh.refine import Residuals, ViewStack, find_pairs, residuals, view_stack


@dataclass
class Basis:
    """dz (M,) = (w * delta[ids]).sum(1) for points with ids, w (M, k); ``edges`` (E, 2) neighbouring controls
    (the smoothness prior; empty for the plane) and ``n`` controls."""

    ids: torch.Tensor
    w: torch.Tensor
    edges: torch.Tensor
    n: int

    def apply(self, delta: torch.Tensor) -> torch.Tensor:
        return (self.w * delta[self.ids]).sum(1)


def plane_basis(xy: torch.Tensor, centre: torch.Tensor, span: float) -> Basis:
    """Offset and tilt: columns 1, (x - cx) / span, (y - cy) / span for points xy (M, 2)."""
    q = (xy - centre) / span
    w = torch.cat([torch.ones_like(q[:, :1]), q], 1)
    ids = torch.arange(3, device=xy.device).expand(xy.shape[0], 3)
    return Basis(ids, w, torch.zeros(0, 2, dtype=torch.long, device=xy.device), 3)


def grid_bases(xy_all: torch.Tensor, xy_pts: torch.Tensor, spacing: float) -> tuple[Basis, Basis]:
    """Bilinear control grids of ``spacing`` m over the vertices xy_all (Nv, 2): the bases of the vertices and of
    the points xy_pts (M, 2) (a subset of them), over the controls some vertex needs (compact numbering)."""
    lo = xy_all.min(0).values
    nx = int(((xy_all[:, 0].max() - lo[0]) / spacing).floor()) + 2

    def corners(xy: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        g = (xy - lo) / spacing
        i0, j0 = g[:, 0].floor().long(), g[:, 1].floor().long()
        ax, ay = g[:, 0] - i0, g[:, 1] - j0
        ids = torch.stack([j0 * nx + i0, j0 * nx + i0 + 1, (j0 + 1) * nx + i0, (j0 + 1) * nx + i0 + 1], 1)
        w = torch.stack([(1 - ax) * (1 - ay), ax * (1 - ay), (1 - ax) * ay, ax * ay], 1)
        return ids, w

    ids_v, w_v = corners(xy_all)
    used, compact = torch.unique(ids_v.reshape(-1), return_inverse=True)
    lut = torch.full((int(used.max()) + 2,), -1, dtype=torch.long, device=xy_all.device)
    lut[used] = torch.arange(used.numel(), device=xy_all.device)
    ids_p, w_p = corners(xy_pts)
    right, up = lut[(used + 1).clamp(max=lut.numel() - 1)], lut[(used + nx).clamp(max=lut.numel() - 1)]
    me = torch.arange(used.numel(), device=xy_all.device)
    edges = torch.cat([torch.stack([me, right], 1)[(right >= 0) & ((used % nx) < nx - 1)],
                       torch.stack([me, up], 1)[up >= 0]])
    n = used.numel()
    return (Basis(compact.reshape(-1, 4), w_v, edges, n), Basis(lut[ids_p], w_p, edges, n))


def _normal_matrix(basis: Basis, a: torch.Tensor, lam_s: float, lam_0: float) -> torch.Tensor:
    """Sparse (n, n): sum_i a_i b_i b_i^T + lam_s sum over edges (e_k - e_l)(e_k - e_l)^T + lam_0 I."""
    k = basis.ids.shape[1]
    rows = basis.ids[:, :, None].expand(-1, k, k).reshape(-1)
    cols = basis.ids[:, None, :].expand(-1, k, k).reshape(-1)
    vals = (a[:, None, None] * basis.w[:, :, None] * basis.w[:, None, :]).reshape(-1)
    e = basis.edges
    me = torch.arange(basis.n, device=a.device)
    rows = torch.cat([rows, e[:, 0], e[:, 1], e[:, 0], e[:, 1], me])
    cols = torch.cat([cols, e[:, 0], e[:, 1], e[:, 1], e[:, 0], me])
    ones = torch.ones(e.shape[0], device=a.device)
    vals = torch.cat([vals, lam_s * ones, lam_s * ones, -lam_s * ones, -lam_s * ones,
                      torch.full((basis.n,), lam_0, device=a.device)])
    return torch.sparse_coo_tensor(torch.stack([rows, cols]), vals, (basis.n, basis.n)).coalesce()


def _prior_gradient(basis: Basis, delta: torch.Tensor, lam_s: float, lam_0: float) -> torch.Tensor:
    """The gradient (n,) of the priors at delta: lam_s L delta + lam_0 delta."""
    e = basis.edges
    diff = delta[e[:, 0]] - delta[e[:, 1]]
    g = lam_0 * delta.clone()
    g.index_add_(0, e[:, 0], lam_s * diff)
    g.index_add_(0, e[:, 1], -lam_s * diff)
    return g


def conjugate_gradient(A: torch.Tensor, b: torch.Tensor, iters: int = 200, tol: float = 1e-6) -> torch.Tensor:
    """Solve A x = b for a sparse symmetric positive definite A (n, n), b (n,), Jacobi-preconditioned."""
    diag = torch.zeros_like(b).index_add_(0, A.indices()[0], torch.where(A.indices()[0] == A.indices()[1],
                                                                             A.values(), torch.zeros_like(A.values())))
    minv = 1.0 / diag.clamp(min=1e-12)
    x = torch.zeros_like(b)
    r = b.clone()
    z = minv * r
    p = z.clone()
    rz = (r * z).sum()
    b_norm = b.norm().clamp(min=1e-30)
    for _ in range(iters):
        Ap = torch.sparse.mm(A, p[:, None]).squeeze(1)
        alpha = rz / (p * Ap).sum().clamp(min=1e-30)
        x += alpha * p
        r -= alpha * Ap
        if r.norm() < tol * b_norm:
            break
        z = minv * r
        rz_new = (r * z).sum()
        p = z + (rz_new / rz) * p
        rz = rz_new
    return x


@dataclass
class Level:
    """One level of the schedule: ``kind`` "plane" or a grid of ``spacing`` m, images blurred by ``sigma`` px,
    ``iters`` Gauss-Newton steps of at most ``max_step`` m per control, smoothness sd ``smooth_m`` between
    neighbouring controls."""

    kind: str
    sigma: float
    iters: int
    spacing: float = 0.0
    max_step: float = 0.05
    smooth_m: float = 0.02


def point_system(res: Residuals, pt: torch.Tensor, n_points: int, noise: float
                 ) -> tuple[torch.Tensor, torch.Tensor]:
    """Per point (P,): the Gauss-Newton curvature a and gradient g of its pairs' weighted squared residuals,
    in units of the residual noise ``noise`` (so that the priors in metres weigh against them)."""
    a = torch.zeros(n_points, device=pt.device).index_add_(0, pt, res.w * (res.J ** 2).sum(1))
    g = torch.zeros(n_points, device=pt.device).index_add_(0, pt, res.w * (res.J * res.r).sum(1))
    return a / noise ** 2, g / noise ** 2


def solve_level(st: ViewStack, xy: torch.Tensor, z: torch.Tensor, basis: Basis, lv: Level, max_dist: float,
                max_views: int, corr: float = 4.0) -> tuple[torch.Tensor, list[float]]:
    """Gauss-Newton on the controls of ``basis`` for points xy (P, 2) at heights z (P,): delta (n,) and the
    weighted mean squared residual before each step. ``corr``: the pairs of neighbouring points share pixels,
    so the data counts ``corr`` times less than independent samples would."""
    pt, view = find_pairs(st, xy, z, max_dist, max_views)
    delta = torch.zeros(basis.n, device=z.device)
    costs: list[float] = []
    if pt.numel() == 0:
        return delta, costs
    n = z.shape[0]
    lam_s = 0.0 if lv.kind == "plane" else 1.0 / lv.smooth_m ** 2
    lam_0 = 1.0 / 0.3 ** 2  # the closed form is within decimetres
    noise = None
    for _ in range(lv.iters):
        zc = z + basis.apply(delta)
        res = residuals(st, pt, view, xy, zc, n)
        cost = float((res.w * (res.r ** 2).sum(1)).sum() / res.w.sum().clamp(min=1e-9))
        costs.append(cost)
        if noise is None:
            noise = max(cost, 1e-8) ** 0.5 * corr ** 0.5
        a, g = point_system(res, pt, n, noise)
        A = _normal_matrix(basis, a, lam_s, lam_0)
        b = -(torch.zeros(basis.n, device=z.device).index_add_(0, basis.ids.reshape(-1),
                                                                   (basis.w * g[:, None]).reshape(-1))
              + _prior_gradient(basis, delta, lam_s, lam_0))
        step = conjugate_gradient(A, b)
        delta += step.clamp(-lv.max_step, lv.max_step)
    return delta, costs


LEVELS = (Level("plane", 2.0, 4), Level("plane", 1.0, 3), Level("grid", 1.0, 4, spacing=2.0),
          Level("grid", 0.5, 3, spacing=1.0))


MAX_POINTS = 20000  # a global offset is measured as well from 20,000 points as from all (nuScenes-like: 160,000)


def _point_subset(xy: torch.Tensor, res: float, stride: int, max_points: int = MAX_POINTS) -> torch.Tensor:
    """(M,) indices of the vertices xy (Nv, 2) on every ``stride``-th row and column of their grid of ``res`` m,
    at most ``max_points`` of them (evenly spread over the list)."""
    ij = torch.round(xy / res).long()
    idx = torch.nonzero(((ij[:, 0] % stride) == 0) & ((ij[:, 1] % stride) == 0)).squeeze(1)
    if idx.numel() > max_points:
        idx = idx[torch.linspace(0, idx.numel() - 1, max_points).round().long()]
    return idx


def refine_heights(rgb: torch.Tensor, mask: torch.Tensor, K: torch.Tensor, T: torch.Tensor, vertex_xy: torch.Tensor,
                   z0: torch.Tensor, res: float, max_dist: float, levels: tuple[Level, ...] = LEVELS,
                   stride: int = 2, max_views: int = 8) -> tuple[torch.Tensor, list[dict]]:
    """The refined heights (Nv,) of the vertices ``vertex_xy`` (Nv, 2) (float64 world) from z0 (Nv,), seen in
    the images rgb (V, 3, H, W), mask (V, H, W) with intrinsics K (V, 3, 3) and poses T (V, 4, 4), level by
    level; also per level its kind, the mean squared residual before its first and after its last step and
    the mean correction. Points: every ``stride``-th vertex row and column."""
    origin = torch.cat([vertex_xy.double().mean(0), z0.double().mean()[None]])
    T = T.double().clone()
    T[:, :3, 3] -= origin.to(T.device)
    xy = (vertex_xy.double() - origin[:2]).float().to(rgb.device)
    zb = (z0.double() - origin[2]).float().to(rgb.device)
    pts = _point_subset(vertex_xy.double(), res, stride).to(rgb.device)
    dz = torch.zeros_like(zb)
    stacks: dict[float, ViewStack] = {}
    log: list[dict] = []
    for lv in levels:
        if lv.sigma not in stacks:
            stacks[lv.sigma] = view_stack(rgb, mask, K, T.float(), lv.sigma)
        st = stacks[lv.sigma]
        if lv.kind == "plane":
            span = float(xy.abs().max().clamp(min=1.0))
            b_v, b_p = plane_basis(xy, torch.zeros(2, device=xy.device), span), None
            b_p = plane_basis(xy[pts], torch.zeros(2, device=xy.device), span)
        else:
            b_v, b_p = grid_bases(xy, xy[pts], lv.spacing)
        delta, costs = solve_level(st, xy[pts], (zb + dz)[pts], b_p, lv, max_dist, max_views)
        step = b_v.apply(delta)
        dz += step
        log.append({"level": lv.kind if lv.kind == "plane" else f"grid {lv.spacing:g} m", "sigma_px": lv.sigma,
                    "cost_first": costs[0] if costs else None, "cost_last": costs[-1] if costs else None,
                    "mean_step_m": round(float(step.mean()), 4)})
    return (zb + dz).double().cpu() + origin[2].cpu(), log


COARSE = tuple(round(0.02 * k, 2) for k in range(-10, 11))  # m: the scan's offsets (+-20 cm in 2 cm)


def offset_scan(st: ViewStack, xy: torch.Tensor, z: torch.Tensor, offsets: tuple[float, ...], max_dist: float,
                max_views: int = 8) -> tuple[float | None, list[float]]:
    """The global offset (m) of points xy (P, 2), z (P,) that minimises the mean squared consistency residual
    over ``offsets`` (a parabola through the best one and its neighbours), and the cost at each offset.

    The pairs are those usable at every offset: a pair that leaves the usable pixels at some offsets (a mask
    edge, where residuals are large) would otherwise make those offsets look better (measured: a maximum of
    the cost at the true height). None when no point is seen twice."""
    pt, view = find_pairs(st, xy, z, max_dist, max_views)
    if pt.numel() == 0:
        return None, []
    n = z.shape[0]
    ok = torch.stack([residuals(st, pt, view, xy, z + e, n).w > 0 for e in offsets]).all(0)
    pt, view = pt[ok], view[ok]
    if pt.numel() == 0:
        return None, []
    costs = []
    for e in offsets:
        res = residuals(st, pt, view, xy, z + e, n)
        costs.append(float((res.w * (res.r ** 2).sum(1)).sum() / res.w.sum().clamp(min=1e-9)))
    k = min(range(len(costs)), key=costs.__getitem__)
    best = offsets[k]
    if 0 < k < len(costs) - 1:
        c0, c1, c2 = costs[k - 1], costs[k], costs[k + 1]
        den = c0 - 2 * c1 + c2
        if den > 0:
            best += 0.5 * (c0 - c2) / den * (offsets[k + 1] - offsets[k])
    return best, costs


def consistency_scan(rgb: torch.Tensor, mask: torch.Tensor, K: torch.Tensor, T: torch.Tensor,
                     vertex_xy: torch.Tensor, z: torch.Tensor, res: float, max_dist: float, sigma: float = 1.0,
                     stride: int = 2, offsets: tuple[float, ...] = COARSE) -> tuple[float | None, list[float]]:
    """:func:`offset_scan` on the surface z (Nv,) at ``vertex_xy`` (Nv, 2) float64 world, images rgb
    (V, 3, H, W), mask (V, H, W), intrinsics K (V, 3, 3), poses T (V, 4, 4): the global offset the views ask."""
    origin = torch.cat([vertex_xy.double().mean(0), z.double().mean()[None]])
    T = T.double().clone()
    T[:, :3, 3] -= origin.to(T.device)
    xy = (vertex_xy.double() - origin[:2]).float().to(rgb.device)
    zb = (z.double() - origin[2]).float().to(rgb.device)
    pts = _point_subset(vertex_xy.double(), res, stride).to(rgb.device)
    st = view_stack(rgb, mask, K, T.float(), sigma)
    return offset_scan(st, xy[pts], zb[pts], offsets, max_dist)

