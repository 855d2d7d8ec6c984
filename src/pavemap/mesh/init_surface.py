"""The initial road surface of stage 1: the ground under the trajectory plus the measured relief.

Why it matters: the height MLP learns at the SPEC's lr 1e-3 (Adam moves each weight ~lr per step), and a
CPU budget affords only ~100-200 steps, so it can move the surface by a few cm: the initial surface decides
most of the height error. The pieces, in order:

1. the camera mount height (:func:`camera_height`: measured depth; without depth the triangulated ground
   points of :mod:`pavemap.mesh.geometry`, and this module's multi-view colour search only as the fallback
   when they are not observable);
2. the ground under the trajectory, its grade continued beyond both ends (:func:`ground_under_trajectory`);
3. the relief of measured ground points relative to it, binned coarse and fine, gaps filled along the road
   (:func:`depth_relief`).

The entry point is :func:`initial_heights`. Ground points come from the pool's depth pixels
(:func:`depth_points`) and, through its ``ground_points`` argument, from any other sparse source
(e.g. points triangulated from the images): every source is just an (N, 3) array of world points.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from pavemap.mesh.config import MeshConfig
from pavemap.mesh.data import PixelPool
from pavemap.mesh.model import MeshGrid
from pavemap.mesh.relief import ReliefFit
from pavemap.mesh.render import view_rays


def initial_heights(pool: PixelPool, grid: MeshGrid, traj: np.ndarray, cam_h: float, cfg: MeshConfig,
                    ground_points: np.ndarray | None = None, vertex_side: np.ndarray | None = None,
                    relief_state: dict | None = None) -> np.ndarray:
    """(Nv,) float32 starting heights of the kept vertices (compact order).

    The plane ``cam_h`` under the trajectory ``traj`` (F, 3) (camera centres per frame), plus, with
    ``cfg.init_from_depth``, the relief of the measured ground: the pool's depth pixels cast on its poses
    ``pool.T`` and the extra world points ``ground_points`` (N, 3) when given. ``vertex_side`` (Nv,) int: 1 on the
    road-class vertices, 0 on the others, -1 unknown; the road relief may step where it changes
    (:func:`pavemap.mesh.relief.fit_relief`).
    ``relief_state``: a dict the first call fills with its points and the fit's robust weights; a second call
    with it (the kerb refit) fits the same points from those weights.
    """
    ground_z = traj[:, 2] - cam_h
    z = ground_under_trajectory(grid, traj[:, :2], ground_z)
    if not cfg.init_from_depth:
        return z
    if relief_state is not None and "points" in relief_state:
        pts = relief_state["points"]  # a refit: the same points as the first fit, whose weights it starts from
    else:
        sources = [p for p in (depth_points(pool, seed=cfg.seed), ground_points) if p is not None and len(p)]
        if not sources:
            return z
        pts = np.concatenate(sources)
        if relief_state is not None:
            relief_state["points"] = pts
    relief = depth_relief(pts, grid, traj, ground_z, cfg.init_cell_m,
                          fine_cell=cfg.init_fine_cell_m, fill_sigmas=(1.0, 2.0, 4.0),
                          along_sigma_m=cfg.init_along_fill_m, method=cfg.init_relief, vertex_side=vertex_side,
                          relief_state=relief_state)
    return z if relief is None else z + relief


def camera_height(pool: PixelPool, cfg: MeshConfig) -> float:
    """The camera mount height above the road: ``cfg.camera_height``, refined by :func:`plane_search`
    with ``cfg.init_height_search``."""
    if not cfg.init_height_search:
        return cfg.camera_height
    return plane_search(pool, cfg.camera_height, cfg.resolution, seed=cfg.seed)


@torch.no_grad()
def depth_points(pool: PixelPool, n_max: int = 1000000, seed: int = 0) -> np.ndarray | None:
    """(N, 3) float64 world points ``o + D d`` of (a random subset of at most ``n_max``) pixels with measured
    depth, on the pool's poses; None with fewer than 100. Only ground pixels carry depth (see build_pool)."""
    if pool.depth is None:
        return None
    sel = (pool.depth > 0).nonzero().squeeze(1)
    if sel.numel() < 100:
        return None
    g = torch.Generator().manual_seed(seed)
    sel = sel[torch.randperm(sel.numel(), generator=g)[:n_max].to(sel.device)]
    o, d = view_rays(pool.K, pool.T, pool.view[sel], pool.uv[sel])
    return (o.double() + pool.depth[sel].double()[:, None] * d.double()).cpu().numpy()


def plane_search(pool: PixelPool, cam_height: float, res: float, n_max: int = 60000, seed: int = 0) -> float:
    """Camera mount height: the offset below each camera at which the views agree best on colour
    (min per-cell colour variance of road pixels cast onto the local plane under their camera).

    Coarse-to-fine over +-1 m around ``cam_height`` (0.1 m steps, then 0.02 m). Without it the MLP
    must learn a global offset of tens of cm at lr 1e-3, which costs epochs.
    """
    g = torch.Generator().manual_seed(seed)
    sel = pool.road.nonzero().squeeze(1).cpu()
    if sel.numel() < 100:
        return cam_height
    if pool.depth is not None:
        # Measured depth gives the height of road points below their camera directly.
        dsel = sel[(pool.depth[sel.to(pool.view.device)] > 0).cpu()]
        if dsel.numel() >= 100:
            dsel = dsel[torch.randperm(dsel.numel(), generator=g)[:n_max]].to(pool.view.device)
            _, d = view_rays(pool.K, pool.T, pool.view[dsel], pool.uv[dsel])
            return float((-(pool.depth[dsel] * d[:, 2])).median())
    sel = sel[torch.randperm(sel.numel(), generator=g)[:n_max]].to(pool.view.device)
    o, d = view_rays(pool.K, pool.T, pool.view[sel], pool.uv[sel])
    o, d = o.double().cpu(), d.double().cpu()
    col = pool.rgb[sel].float().cpu() / 255.0
    view = pool.view[sel].cpu()
    best_z = cam_height
    for span, steps in ((1.0, 21), (0.1, 11)):
        cands = [best_z + float(t) for t in np.linspace(-span, span, steps) if best_z + float(t) > 0.05]
        scores = [_plane_score(o, d, col, view, z, res) for z in cands]
        k = int(np.argmin(scores))
        if math.isfinite(scores[k]):
            best_z = cands[k]
    return best_z


def _plane_score(o: torch.Tensor, d: torch.Tensor, col: torch.Tensor, view: torch.Tensor, hcam: float,
                 res: float) -> float:
    """Colour disagreement of rays o, d (N, 3) float64 with colours col (N, 3) on the plane ``hcam`` below
    each camera: the count-weighted per-cell colour variance over cells (2 ``res`` m) seen from two views."""
    down = d[:, 2] < -1e-6
    lam = -hcam / torch.where(down, d[:, 2], torch.ones_like(d[:, 2]))
    ok = down & (lam > 0) & (lam < 40)
    if ok.sum() < 100:
        return math.inf
    xy = o[ok, :2] + lam[ok, None] * d[ok, :2]
    cell = torch.floor(xy / (2 * res)).long()
    cell = cell - cell.min(0).values
    key = cell[:, 0] * (int(cell[:, 1].max()) + 1) + cell[:, 1]
    uniq, inv = torch.unique(key, return_inverse=True)
    n = torch.bincount(inv, minlength=uniq.numel()).float()
    # only cells seen from at least two views carry multi-view evidence
    vmin = torch.full((uniq.numel(),), 1 << 30, dtype=torch.long).scatter_reduce(0, inv, view[ok], "amin")
    vmax = torch.zeros(uniq.numel(), dtype=torch.long).scatter_reduce(0, inv, view[ok], "amax")
    multi = (vmax != vmin) & (n >= 2)
    if multi.sum() < 20:
        return math.inf
    s1 = torch.zeros(uniq.numel(), 3).index_add_(0, inv, col[ok])
    s2 = torch.zeros(uniq.numel(), 3).index_add_(0, inv, col[ok] ** 2)
    var = (s2 / n[:, None] - (s1 / n[:, None]) ** 2).sum(1)
    return float((var * n)[multi].sum() / n[multi].sum())


def ground_under_trajectory(grid: MeshGrid, traj_xy: np.ndarray, ground_z: np.ndarray, k: int = 4) -> np.ndarray:
    """(Nv,) float32 initial heights of the kept vertices: inverse-distance weighting of the ground
    heights ``ground_z`` (F,) under the trajectory points ``traj_xy`` (F, 2), k nearest."""
    return idw_ground(traj_xy, ground_z, grid.vertex_xy(), k)


def idw_ground(traj_xy: np.ndarray, ground_z: np.ndarray, xy: np.ndarray, k: int = 4,
               grade_m: float = 5.0) -> np.ndarray:
    """(N,) float32 ground height under the trajectory at points ``xy`` (N, 2): inverse-distance weighting
    of ``ground_z`` (F,) at the trajectory points ``traj_xy`` (F, 2), k nearest; beyond either end of each
    pass (:func:`path_passes`) the road's grade over its last ``grade_m`` metres continues linearly, for the
    points whose nearest trajectory point is that end.

    Why the grade: behind the first frame a forward camera never sees the ground, and holding the first
    height there leaves the start of a climbing road off by the climb. Why only beyond the path: a long
    drive's segment holds several passes, and a road another pass drove along lies "beyond" this pass's end
    too; continuing the end's grade over it put a KITTI-00 segment 6.8 m below the road 120 m away.
    """
    from scipy.spatial import cKDTree

    traj_xy = np.asarray(traj_xy, dtype=np.float64).reshape(-1, 2)
    q = np.asarray(xy, dtype=np.float64).copy()
    rise = np.zeros(len(q))
    if len(traj_xy) >= 2:
        d_min, _ = cKDTree(traj_xy).query(q)
        for p in path_passes(traj_xy):
            piece = traj_xy[p]
            along = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(piece, axis=0), axis=1))])
            for end, inner in ((0, int(np.searchsorted(along, min(grade_m, along[-1])))),
                               (len(piece) - 1, int(np.searchsorted(along, max(along[-1] - grade_m, 0.0))))):
                out = piece[end] - piece[inner]
                n = float(np.linalg.norm(out))
                if inner == end or n < 1e-6:
                    continue
                past = np.linalg.norm(xy - piece[end], axis=1) <= d_min + 1e-9  # this end is the nearest point
                beyond = np.clip((q - piece[end]) @ (out / n), 0.0, None) * past  # metres past it, along the road
                q -= beyond[:, None] * (out / n)  # the height at the end's cross-section, then the grade
                rise += beyond * (ground_z[p][end] - ground_z[p][inner]) / n
    k = min(k, len(traj_xy))
    dist, idx = cKDTree(traj_xy).query(q, k=k)
    dist, idx = dist.reshape(len(q), k), idx.reshape(len(q), k)
    w = 1.0 / np.maximum(dist, 0.5) ** 2
    z = (w * ground_z[idx]).sum(1) / w.sum(1) + rise
    return z.astype(np.float32)


def depth_relief(pts: np.ndarray, grid: MeshGrid, traj: np.ndarray, ground_z: np.ndarray, cell: float,
                 gate: float = 0.5, fine_cell: float = 0.0, fine_min: int = 3,
                 fill_sigmas: tuple[float, ...] = (1.0,), along_sigma_m: float = 0.0,
                 method: str = "bins", vertex_side: np.ndarray | None = None, relief_state: dict | None = None
                 ) -> np.ndarray | None:
    """(Nv,) float32 relief of measured ground points ``pts`` (N, 3) relative to the trajectory plane (the
    ground ``ground_z`` (F,) under ``traj`` (F, 3)), at the kept vertices; None with fewer than 100 usable.

    ``method`` "road": the regularised fit in road coordinates of :mod:`pavemap.mesh.relief` (a standing
    vehicle, whose trajectory has no "along", and an oversized lattice fall back to the bins below).

    The points within ``gate`` m of the trajectory plane (not facades, poles) are averaged per ``cell`` m
    bin (:func:`_coarse_bins`) and sampled bilinearly at the vertices; with ``fine_cell`` the median
    residual per finer bin is added (:func:`_fine_relief`), and with ``along_sigma_m`` vertices no point
    reaches take the cross-section measured along the road (:func:`fill_along_track`). The MLP then
    learns only what these bins miss.
    """
    g = grid.spec
    r = pts[:, 2] - idw_ground(traj[:, :2], ground_z, pts[:, :2])
    moving = len(traj) >= 2 and np.linalg.norm(np.diff(traj[:, :2], axis=0), axis=1).sum() > 2 * cell
    if method == "road" and moving:
        relief = road_relief(traj[:, :2], pts[:, :2], r, grid.vertex_xy(), side_q=vertex_side, state=relief_state)
        if relief is not None:
            return relief.astype(np.float32)
    px, py = pts[:, 0] - g.x0, pts[:, 1] - g.y0  # offsets from the grid origin
    val = _coarse_bins(px, py, r, grid, cell, gate, fill_sigmas)
    if val is None:
        return None
    vid = np.flatnonzero(grid.valid.reshape(-1))
    vx, vy = (vid % g.nx) * g.res, (vid // g.nx) * g.res  # vertex offsets from the grid origin
    relief = _sample_bins(val, vx, vy, cell)
    if fine_cell and fine_cell < cell:
        fine, support = _fine_relief(px, py, r - _sample_bins(val, px, py, cell), grid, fine_cell, fine_min, vx, vy)
        relief = relief + fine
        # a standing vehicle has no "along the road": the isotropic fill stays
        if along_sigma_m > 0 and np.linalg.norm(np.diff(traj[:, :2], axis=0), axis=1).sum() > 2 * cell:
            s, l = along_track(traj[:, :2], np.stack([vx + g.x0, vy + g.y0], 1))
            relief = fill_along_track(relief, support > 0.5, s, l, along_sigma_m)
    return relief.astype(np.float32)


def _coarse_bins(px: np.ndarray, py: np.ndarray, r: np.ndarray, grid: MeshGrid, cell: float, gate: float,
                 fill_sigmas: tuple[float, ...]) -> np.ndarray | None:
    """(rows, cols) mean residual ``r`` per ``cell`` m bin of the points at offsets px, py (N,) from the grid
    origin: points within ``gate`` of the plane, twice, the second pass dropping points 0.15 m off their bin
    mean; gaps filled by normalised Gaussian smoothing (widths ``fill_sigmas`` bins, narrowest first).
    None with fewer than 100 points inside."""
    from scipy import ndimage

    key, inside, (nby, nbx) = _bin_keys(px, py, grid, cell)
    ok = (np.abs(r) < gate) & inside
    if ok.sum() < 100:
        return None
    for _ in range(2):
        cnt = np.bincount(key[ok], minlength=nbx * nby).astype(np.float64)
        tot = np.bincount(key[ok], weights=r[ok], minlength=nbx * nby)
        mean = tot / np.maximum(cnt, 1)
        ok = ok & (np.abs(r - mean[np.clip(key, 0, nbx * nby - 1)]) < 0.15)
    cnt = np.bincount(key[ok], minlength=nbx * nby).astype(np.float64).reshape(nby, nbx)
    tot = np.bincount(key[ok], weights=r[ok], minlength=nbx * nby).reshape(nby, nbx)
    val = np.zeros_like(tot)
    empty = np.ones(tot.shape, dtype=bool)
    # Gaps the size of an object standing on the ground (its foot is never seen) take their surroundings'
    # height from ever wider normalised Gaussians. Bins farther from any seen one keep 0 (the trajectory
    # plane): filling them with the nearest seen bin's value made the unseen first metres of a forward
    # camera's drive worse.
    for sigma in fill_sigmas:
        w = ndimage.gaussian_filter(cnt, sigma, mode="nearest")
        fill = empty & (w > 1e-3)
        val[fill] = (ndimage.gaussian_filter(tot, sigma, mode="nearest") / np.maximum(w, 1e-3))[fill]
        empty &= ~fill
    return val


def _bin_keys(px: np.ndarray, py: np.ndarray, grid: MeshGrid, cell: float
              ) -> tuple[np.ndarray, np.ndarray, tuple[int, int]]:
    """Flat bin index (N,) of points at offsets px, py from the grid origin in ``cell`` m bins covering the
    grid, whether each falls inside, and the bins' (rows, cols)."""
    g = grid.spec
    nbx = int(math.ceil((g.nx - 1) * g.res / cell)) + 1
    nby = int(math.ceil((g.ny - 1) * g.res / cell)) + 1
    ix, iy = np.floor(px / cell).astype(np.int64), np.floor(py / cell).astype(np.int64)
    inside = (ix >= 0) & (ix < nbx) & (iy >= 0) & (iy < nby)
    return iy * nbx + ix, inside, (nby, nbx)


def _sample_bins(values: np.ndarray, px: np.ndarray, py: np.ndarray, cell: float) -> np.ndarray:
    """Bilinear samples of per-bin ``values`` (rows, cols) at offsets px, py (bin centres at (k + 0.5) cell)."""
    from scipy import ndimage

    return ndimage.map_coordinates(values, [py / cell - 0.5, px / cell - 0.5], order=1, mode="nearest")


def _fine_relief(px: np.ndarray, py: np.ndarray, r2: np.ndarray, grid: MeshGrid, fine: float, fine_min: int,
                 vx: np.ndarray, vy: np.ndarray, gate: float = 0.3) -> tuple[np.ndarray, np.ndarray]:
    """(Nv,) what the coarse bins miss: the median of the points' residuals ``r2`` (N,) to the coarse surface
    per ``fine`` m bin (bins with at least ``fine_min`` points; 0 elsewhere), sampled bilinearly at the vertex
    offsets vx, vy; and (Nv,) the sampled bin support. px, py: the points' offsets from the grid origin.

    Why: the coarse bins smear a 0.12 m curb over +-1 m, and the height MLP cannot sharpen it (its finest
    positional-encoding period is 1/2^(L-1) of the grid's extent: ~10 m on a 160 m drive). The median keeps the
    step where the two sides of a curb meet in one bin.
    """
    key, inside, (nfy, nfx) = _bin_keys(px, py, grid, fine)
    ok = (np.abs(r2) < gate) & inside
    key, val = key[ok], r2[ok]
    order = np.lexsort((val, key))
    key, val = key[order], val[order]
    uniq, start, count = np.unique(key, return_index=True, return_counts=True)
    med = 0.5 * (val[start + (count - 1) // 2] + val[start + count // 2])
    keep = count >= fine_min
    grid_v = np.zeros(nfx * nfy)
    grid_w = np.zeros(nfx * nfy)
    grid_v[uniq[keep]] = med[keep]
    grid_w[uniq[keep]] = 1.0
    grid_v, grid_w = grid_v.reshape(nfy, nfx), grid_w.reshape(nfy, nfx)
    w = _sample_bins(grid_w, vx, vy, fine)
    v = _sample_bins(grid_v * grid_w, vx, vy, fine)
    return np.where(w > 1e-6, v / np.maximum(w, 1e-6), 0.0), w


PASS_GAP_S = 100.0  # m of "along the road" between passes: fills along the road never reach across


def path_cuts(traj_xy: np.ndarray, min_gap_m: float = 5.0, gap_factor: float = 5.0) -> np.ndarray:
    """(C,) int64 positions c where the path (F, 2) jumps between frames c and c + 1: more than
    ``max(min_gap_m, gap_factor x the median moving step)`` apart (dropped frames, or the passes of a long
    drive's segment)."""
    t = np.asarray(traj_xy, dtype=np.float64).reshape(-1, 2)
    if len(t) < 3:
        return np.zeros(0, np.int64)
    step = np.linalg.norm(np.diff(t, axis=0), axis=1)
    moving = step[step > 1e-3]
    limit = max(min_gap_m, gap_factor * float(np.median(moving))) if moving.size else math.inf
    return np.flatnonzero(step > limit)


def travel_direction(traj_xy: np.ndarray, end: int, span_m: float = 5.0) -> np.ndarray | None:
    """(2,) unit direction of travel over the last (end=-1) or first (end=0) ``span_m`` of the path, pointing
    out of the path (forward at its end, backward at its start); None for a path shorter than 0.5 m."""
    t = traj_xy if end == -1 else traj_xy[::-1]
    step = np.linalg.norm(np.diff(t, axis=0), axis=1)
    back = np.cumsum(step[::-1])
    k = int(np.searchsorted(back, span_m))  # segments covering the last span_m
    d = t[-1] - t[max(len(t) - 2 - k, 0)]
    n = float(np.hypot(*d))
    return d / n if n > 0.5 else None


def path_passes(traj_xy: np.ndarray) -> list[slice]:
    """The stretches of the path (F, 2) between its jumps (:func:`path_cuts`), as slices, in order."""
    b = np.concatenate([[0], path_cuts(traj_xy) + 1, [len(traj_xy)]])
    return [slice(int(a), int(c)) for a, c in zip(b[:-1], b[1:], strict=True)]


def track_coords(traj_xy: np.ndarray, xy: np.ndarray, step: float = 0.1
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(N,) pass, along-track s and signed cross-track l (m, left positive) of points ``xy`` (N, 2) relative
    to the nearest pass (:func:`path_passes`, those of two frames or more) of the trajectory ``traj_xy``
    (F, 2), F >= 2. Beyond a pass's ends s continues along its end tangents; each pass's s starts
    ``PASS_GAP_S`` after the previous one's end. The polyline never crosses a jump between passes: a
    straight line there (over buildings, fields) is no road."""
    from scipy.spatial import cKDTree

    t = np.asarray(traj_xy, dtype=np.float64).reshape(-1, 2)
    passes = [p for p in path_passes(t) if p.stop - p.start >= 2] or [slice(0, len(t))]
    cs, ss, ts, ks, offset = [], [], [], [], 0.0
    for k, p in enumerate(passes):
        along = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(t[p], axis=0), axis=1))])
        s_dense = np.linspace(0.0, along[-1], max(2, int(along[-1] / step) + 1))
        c = np.stack([np.interp(s_dense, along, t[p, 0]), np.interp(s_dense, along, t[p, 1])], 1)
        tg = np.gradient(c, axis=0)
        cs.append(c), ts.append(tg / np.maximum(np.linalg.norm(tg, axis=1, keepdims=True), 1e-12))
        ss.append(s_dense + offset), ks.append(np.full(len(c), k))
        offset += float(along[-1]) + PASS_GAP_S
    c, s_dense, tg, kk = np.concatenate(cs), np.concatenate(ss), np.concatenate(ts), np.concatenate(ks)
    _, i = cKDTree(c).query(xy)
    d = xy - c[i]
    return kk[i], s_dense[i] + (d * tg[i]).sum(1), d[:, 0] * -tg[i, 1] + d[:, 1] * tg[i, 0]


def along_track(traj_xy: np.ndarray, xy: np.ndarray, step: float = 0.1) -> tuple[np.ndarray, np.ndarray]:
    """(N,) along-track s and signed cross-track l of points ``xy`` (N, 2): :func:`track_coords` without
    the pass."""
    return track_coords(traj_xy, xy, step)[1:]


def road_relief(traj_xy: np.ndarray, pts_xy: np.ndarray, r: np.ndarray, q_xy: np.ndarray,
                fit: ReliefFit | None = None, side_q: np.ndarray | None = None, state: dict | None = None
                ) -> np.ndarray | None:
    """(Q,) float64 relief at ``q_xy`` (Q, 2) from the residuals ``r`` (N,) of points at ``pts_xy`` (N, 2),
    fitted in road coordinates (:func:`pavemap.mesh.relief.fit_relief`) pass by pass: each pass of
    ``traj_xy`` (F, 2) fits the points and query points nearest to it. 0 where a pass has too few points;
    None where none has enough.

    Why per pass: one lattice along a path that jumps between passes spans the jumps (road no camera saw)
    and couples roads that only meet at a junction."""
    from pavemap.mesh.relief import fit_relief

    k_p, s_p, t_p = track_coords(traj_xy, pts_xy)
    k_q, s_q, t_q = track_coords(traj_xy, q_xy)
    out, fitted = np.zeros(len(q_xy)), False
    for k in np.unique(k_q):
        qi, pi = k_q == k, k_p == k
        rel = fit_relief(s_p[pi], t_p[pi], r[pi], s_q[qi], t_q[qi], fit, side_q=None if side_q is None else side_q[qi],
                         state=None if state is None else state.setdefault(("pass", int(k)), {}))
        if rel is not None:
            out[qi], fitted = rel, True
    return out if fitted else None


def fill_along_track(relief: np.ndarray, measured: np.ndarray, s: np.ndarray, l: np.ndarray,
                     sigma_s: float, cell_s: float = 0.5, cell_l: float = 0.1) -> np.ndarray:
    """(Nv,) ``relief`` with the vertices not ``measured`` (Nv,) bool replaced by the normalised Gaussian
    average of measured ones at about the same cross-track offset (sigma ``cell_l``) along the road (sigma
    ``sigma_s`` m), where there are any.

    Why: a road's cross-section (crown, gutter, curb, sidewalk) changes slowly along it, so ground a camera
    never saw (behind a parked car, behind the first frame) is best guessed from the same offset a few metres
    before or after; an isotropic fill mixed the road and the 0.12 m higher sidewalk there.
    """
    from scipy import ndimage

    if measured.all() or not measured.any():
        return relief
    i_s = np.floor((s - s.min()) / cell_s).astype(np.int64)
    i_l = np.floor((l - l.min()) / cell_l).astype(np.int64)
    shape = (int(i_s.max()) + 1, int(i_l.max()) + 1)
    key = i_s * shape[1] + i_l
    tot = np.bincount(key[measured], weights=relief[measured], minlength=shape[0] * shape[1]).reshape(shape)
    cnt = np.bincount(key[measured], minlength=shape[0] * shape[1]).astype(np.float64).reshape(shape)
    sig = (sigma_s / cell_s, 1.0)
    w = ndimage.gaussian_filter(cnt, sig, mode="constant")
    v = ndimage.gaussian_filter(tot, sig, mode="constant") / np.maximum(w, 1e-12)
    wv, vv = w.reshape(-1)[key], v.reshape(-1)[key]
    fill = ~measured & (wv > 1e-3)
    return np.where(fill, vv, relief)
