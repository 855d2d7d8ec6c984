"""Stage-1 training: fit heights, colours and semantics of the BEV mesh to the frames (SPEC §1).

Each optimizer step samples ``pixels_per_step`` pixels from all training views, finds their
triangles on a cached copy of the heights (no autograd), evaluates the height MLP only at the
vertices of those triangles, and back-propagates through one exact
Newton step per ray (:func:`pavemap.geometry.hits_to_rayhit`). The full-grid heights used by the
march are refreshed every ``height_refresh_steps`` steps. Losses and weights are the SPEC's:
``L = L_rgb + 0.5 L_sem + lambda_depth L_depth + 1.0 L_smooth`` over valid pixels.
"""

from __future__ import annotations

import dataclasses
import math
import time
import warnings
from pathlib import Path

import numpy as np
import torch
from torch.nn import functional as F  # noqa: N812
from tqdm.auto import tqdm

from pavemap.errors import PavemapError
from pavemap.geometry import HeightField, find_hits, hits_to_rayhit, surface_bounds
from pavemap.mesh.bake import bake_colours
from pavemap.mesh.config import MeshConfig
from pavemap.mesh.data import PixelPool, build_pool, finite_views, split_frames
from pavemap.mesh.model import RoadMesh, RoadMeshModel, build_grid, ground_under_trajectory
from pavemap.mesh.pose import align_poses, corrected_poses, interpolate_corrections, rig_corrections, rig_groups
from pavemap.mesh.render import view_rays
from pavemap.types import Sequence

CHECKPOINT = "checkpoint.pt"


def resolve_device(name: str) -> torch.device:
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name.startswith("cuda") and not torch.cuda.is_available():
        raise PavemapError(f"device {name!r} requested but CUDA is not available; use --device cpu")
    return torch.device(name)


def _plane_search(pool: PixelPool, cam_height: float, res: float, n_max: int = 60000, seed: int = 0) -> float:
    """Camera mount height: the offset below each camera at which the views agree best on colour
    (min per-cell colour variance of road pixels cast onto the local plane under their camera).

    Coarse-to-fine over +-1 m around ``cam_height`` (0.1 m steps, then 0.02 m). Without it the MLP
    must learn a global offset of tens of cm at lr 1e-3, which costs epochs.
    """
    z0 = cam_height
    g = torch.Generator().manual_seed(seed)
    sel = pool.road.nonzero().squeeze(1).cpu()
    if sel.numel() < 100:
        return z0
    if pool.depth is not None:
        # Measured depth gives the height of road points below their camera directly.
        dsel = sel[(pool.depth[sel.to(pool.view.device)] > 0).cpu()]
        if dsel.numel() >= 100:
            dsel = dsel[torch.randperm(dsel.numel(), generator=g)[:n_max]].to(pool.view.device)
            _, d = view_rays(pool.Kinv, pool.T, pool.view[dsel], pool.uv[dsel])
            below = -(pool.depth[dsel] * d[:, 2])
            return float(below.median())
    sel = sel[torch.randperm(sel.numel(), generator=g)[:n_max]].to(pool.view.device)
    o, d = view_rays(pool.Kinv, pool.T, pool.view[sel], pool.uv[sel])
    o, d = o.double().cpu(), d.double().cpu()
    col = pool.rgb[sel].float().cpu() / 255.0
    view = pool.view[sel].cpu()
    down = d[:, 2] < -1e-6
    dz_safe = torch.where(down, d[:, 2], torch.ones_like(d[:, 2]))

    def score(hcam: float) -> float:
        lam = -hcam / dz_safe  # plane hcam below the camera
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

    best_z = z0
    for span, steps in ((1.0, 21), (0.1, 11)):
        cands = [best_z + float(t) for t in np.linspace(-span, span, steps) if best_z + float(t) > 0.05]
        scores = [score(z) for z in cands]
        k = int(np.argmin(scores))
        if math.isfinite(scores[k]):
            best_z = cands[k]
    return best_z


def _depth_relief(pool: PixelPool, grid, traj: np.ndarray, ground_z: np.ndarray, cell: float,
                  gate: float = 0.5, n_max: int = 1000000, seed: int = 0, fine_cell: float = 0.0,
                  fine_min: int = 3, fill_sigmas: tuple[float, ...] = (1.0,),
                  along_sigma_m: float = 0.0) -> np.ndarray | None:
    """(Nv,) float32 relief of the measured ground relative to the trajectory plane, at the kept vertices.

    Why: the height MLP learns at the SPEC's lr 1e-3 (Adam moves each weight ~lr per step), and a CPU
    budget affords ~130 steps, so it can move the surface by only a few cm: the initial surface decides
    most of the height error. Where depth exists, the measured points (``o + D d``) within ``gate`` m of
    the trajectory plane (not facades, poles) are averaged per ``cell`` m bin (twice, the second pass
    dropping points 0.15 m off their bin mean), gaps filled by normalised Gaussian smoothing (widths
    ``fill_sigmas`` bins, narrowest first), and sampled bilinearly at the vertices; with ``fine_cell`` the
    median residual per finer bin is added (:func:`_fine_relief`). The MLP then learns only what these bins
    miss. Only ground pixels carry depth in the pool (see build_pool). Returns None without enough depth.
    """
    from scipy import ndimage

    from pavemap.mesh.model import idw_ground

    if pool.depth is None:
        return None
    sel = (pool.depth > 0).nonzero().squeeze(1)
    if sel.numel() < 100:
        return None
    g = torch.Generator().manual_seed(seed)
    sel = sel[torch.randperm(sel.numel(), generator=g)[:n_max].to(sel.device)]
    with torch.no_grad():
        o, d = view_rays(pool.Kinv, pool.T, pool.view[sel], pool.uv[sel])
        pts = (o.double() + pool.depth[sel].double()[:, None] * d.double()).cpu().numpy()
    r = pts[:, 2] - idw_ground(traj[:, :2], ground_z, pts[:, :2])
    px, py = pts[:, 0] - grid.x0, pts[:, 1] - grid.y0  # offsets from the grid origin
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
    # plane): filling them with the nearest seen bin's value was tried and made the unseen first metres of
    # the KITTI-like drive worse (0.14 -> 0.22 m RMSE).
    for sigma in fill_sigmas:
        w = ndimage.gaussian_filter(cnt, sigma, mode="nearest")
        fill = empty & (w > 1e-3)
        val[fill] = (ndimage.gaussian_filter(tot, sigma, mode="nearest") / np.maximum(w, 1e-3))[fill]
        empty &= ~fill
    vid = np.flatnonzero(grid.valid.reshape(-1))
    vx, vy = (vid % grid.nx) * grid.res, (vid // grid.nx) * grid.res  # vertex offsets from the grid origin
    relief = _sample_bins(val, vx, vy, cell)
    if fine_cell and fine_cell < cell:
        fine, support = _fine_relief(px, py, r - _sample_bins(val, px, py, cell), grid, fine_cell, fine_min, vx, vy)
        relief = relief + fine
        # a standing vehicle has no "along the road": the isotropic fill stays
        if along_sigma_m > 0 and np.linalg.norm(np.diff(traj[:, :2], axis=0), axis=1).sum() > 2 * cell:
            s, l = _along_track(traj[:, :2], np.stack([vx + grid.x0, vy + grid.y0], 1))
            relief = _fill_along_track(relief, support > 0.5, s, l, along_sigma_m)
    return relief.astype(np.float32)


def _initial_surface(pool: PixelPool, grid, traj: np.ndarray, cam_h: float, cfg: MeshConfig,
                     use_depth: bool) -> np.ndarray:
    """(Nv,) float32 starting heights of the kept vertices: the plane ``cam_h`` under the trajectory, plus the
    measured relief where depth exists (:func:`_depth_relief`, on the pool's poses ``pool.T``)."""
    z = ground_under_trajectory(grid, traj[:, :2], traj[:, 2] - cam_h)
    if cfg.init_from_depth and use_depth:
        relief = _depth_relief(pool, grid, traj, traj[:, 2] - cam_h, cfg.init_cell_m, seed=cfg.seed,
                               fine_cell=cfg.init_fine_cell_m, fill_sigmas=(1.0, 2.0, 4.0),
                               along_sigma_m=cfg.init_along_fill_m)
        if relief is not None:
            z = z + relief
    return z


def _align_stage(model: RoadMeshModel, pool: PixelPool, cfg: MeshConfig, fill: float, grid, traj: np.ndarray,
                 cam_h: float, use_depth: bool, group: torch.Tensor, arm: torch.Tensor,
                 n_groups: int) -> tuple[torch.Tensor, list[dict]]:
    """Pose refinement before training: (V, 6) corrections from :func:`align_poses` on the initial surface,
    and per round the weighted residual cost before and after.

    With depth the initial surface was binned from points cast on the raw poses (blurred by their errors),
    so each round rebuilds it on the corrected poses (the next round aligns to the rebuilt one).
    """
    delta = torch.zeros(n_groups, 6, device=pool.T.device)
    log: list[dict] = []
    g = model.grid
    for rnd in range(cfg.pose_align_rounds):
        with torch.no_grad():
            heights = model.dense(model.heights(), fill=fill).float()
        delta, costs = align_poses(heights, model.valid_t, g.x0, g.y0, g.res, pool, delta, cfg.max_dist,
                                   iters=cfg.pose_align_iters, per_view=cfg.pose_align_pixels_per_view,
                                   prior_sigma=(cfg.pose_prior_deg, cfg.pose_prior_m), group=group, arm=arm,
                                   seed=cfg.seed + rnd)
        if costs:
            log.append({"round": rnd + 1, "cost_first": costs[0], "cost_last": costs[-1]})
        if use_depth and cfg.init_from_depth:
            moved = dataclasses.replace(pool, T=corrected_poses(pool.T, rig_corrections(delta, group, arm)))
            z = _initial_surface(moved, grid, traj, cam_h, cfg, use_depth)
            model.z_base.copy_(torch.as_tensor(z, dtype=model.z_base.dtype, device=model.z_base.device))
    return delta, log


def _bin_keys(px: np.ndarray, py: np.ndarray, grid, cell: float) -> tuple[np.ndarray, np.ndarray, tuple[int, int]]:
    """Flat bin index (N,) of points at offsets px, py from the grid origin in ``cell`` m bins covering the
    grid, whether each falls inside, and the bins' (rows, cols)."""
    nbx = int(math.ceil((grid.nx - 1) * grid.res / cell)) + 1
    nby = int(math.ceil((grid.ny - 1) * grid.res / cell)) + 1
    ix, iy = np.floor(px / cell).astype(np.int64), np.floor(py / cell).astype(np.int64)
    inside = (ix >= 0) & (ix < nbx) & (iy >= 0) & (iy < nby)
    return iy * nbx + ix, inside, (nby, nbx)


def _sample_bins(values: np.ndarray, px: np.ndarray, py: np.ndarray, cell: float) -> np.ndarray:
    """Bilinear samples of per-bin ``values`` (rows, cols) at offsets px, py (bin centres at (k + 0.5) cell)."""
    from scipy import ndimage

    return ndimage.map_coordinates(values, [py / cell - 0.5, px / cell - 0.5], order=1, mode="nearest")


def _fine_relief(px: np.ndarray, py: np.ndarray, r2: np.ndarray, grid, fine: float, fine_min: int,
                 vx: np.ndarray, vy: np.ndarray, gate: float = 0.3) -> np.ndarray:
    """(Nv,) what the coarse bins miss: the median of the points' residuals ``r2`` (N,) to the coarse surface
    per ``fine`` m bin (bins with at least ``fine_min`` points; 0 elsewhere), sampled bilinearly at the vertex
    offsets vx, vy. px, py: the points' offsets from the grid origin.

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


def _along_track(traj_xy: np.ndarray, xy: np.ndarray, step: float = 0.1) -> tuple[np.ndarray, np.ndarray]:
    """(N,) along-track s and signed cross-track l (m, left positive) of points ``xy`` (N, 2) relative to the
    trajectory polyline ``traj_xy`` (F, 2), F >= 2; beyond the ends s continues along the end tangents."""
    from scipy.spatial import cKDTree

    seg = np.linalg.norm(np.diff(traj_xy, axis=0), axis=1)
    along = np.concatenate([[0.0], np.cumsum(seg)])
    s_dense = np.linspace(0.0, along[-1], max(2, int(along[-1] / step) + 1))
    c = np.stack([np.interp(s_dense, along, traj_xy[:, 0]), np.interp(s_dense, along, traj_xy[:, 1])], 1)
    t = np.gradient(c, axis=0)
    t /= np.maximum(np.linalg.norm(t, axis=1, keepdims=True), 1e-12)
    _, i = cKDTree(c).query(xy)
    d = xy - c[i]
    return s_dense[i] + (d * t[i]).sum(1), d[:, 0] * -t[i, 1] + d[:, 1] * t[i, 0]


def _fill_along_track(relief: np.ndarray, measured: np.ndarray, s: np.ndarray, l: np.ndarray,
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


class MultiOptimizer:
    """Dense Adam (MLP, poses) and sparse Adam (vertex colours, logits) stepped together."""

    def __init__(self, *opts: torch.optim.Optimizer):
        self.opts = opts
        self.base = [[g["lr"] for g in o.param_groups] for o in opts]

    def zero_grad(self, set_to_none: bool = True) -> None:
        for o in self.opts:
            o.zero_grad(set_to_none=set_to_none)

    def step(self) -> None:
        for o in self.opts:
            o.step()

    def set_lr_factor(self, f: float, per_group: dict[str, float] | None = None) -> None:
        """Scale every group's rate from its base by ``f``, or by ``per_group[name]`` for the named groups
        (per-vertex L1 / Adam steps jitter around the optimum unless the rate decays)."""
        per_group = per_group or {}
        for o, base in zip(self.opts, self.base, strict=True):
            for g, b in zip(o.param_groups, base, strict=True):
                g["lr"] = b * per_group.get(g.get("name", ""), f)

    def state_dict(self) -> dict:
        return {"opts": [o.state_dict() for o in self.opts]}

    def load_state_dict(self, state: dict) -> None:
        for o, s in zip(self.opts, state["opts"], strict=True):
            o.load_state_dict(s)


def _psnr(mse: float) -> float:
    return float(10 * math.log10(1.0 / max(mse, 1e-10)))


@torch.no_grad()
def evaluate_pool(model: RoadMeshModel, pool: PixelPool, cfg: MeshConfig, heights: torch.Tensor,
                  delta: torch.Tensor | None = None, max_pixels: int | None = None, batch: int = 131072,
                  generator: torch.Generator | None = None) -> dict:
    """PSNR over road pixels the mesh covers, semantic accuracy over labelled valid pixels, coverage."""
    n = len(pool)
    idx = torch.arange(n, device=pool.view.device)
    if max_pixels is not None and n > max_pixels:
        idx = torch.randperm(n, generator=generator)[:max_pixels].to(pool.view.device)
    g = model.grid
    hf = HeightField(g.x0, g.y0, g.res, heights, model.valid_t)
    bounds = surface_bounds(hf, pool.uv.dtype)
    T = corrected_poses(pool.T, delta)
    se = torch.zeros((), dtype=torch.float64, device=heights.device)
    n_road = n_sem = n_ok = n_hit = 0
    for s in range(0, idx.numel(), batch):
        b = idx[s:s + batch]
        o, d = view_rays(pool.Kinv, T, pool.view[b], pool.uv[b])
        cells = find_hits(hf, o, d, cfg.max_dist, bounds=bounds)
        hit = hits_to_rayhit(hf, o, d, cells)
        hv = hit.hit
        n_hit += int(hv.sum())
        cid = model.flat_to_compact[hit.vertex_ids[hv]]
        bary = hit.bary[hv]
        rgb = (bary[..., None] * model.rgb[cid]).sum(1).clamp(0, 1)
        gt = pool.rgb[b][hv].float() / 255.0
        road = pool.road[b][hv]
        se += ((rgb - gt) ** 2).mean(1)[road].double().sum()
        n_road += int(road.sum())
        ch = pool.channel[b][hv]
        lab = ch >= 0
        if lab.any() and model.sem.shape[1]:
            pred = (bary[lab][..., None] * model.sem[cid[lab]]).sum(1).argmax(1)
            n_ok += int((pred == ch[lab]).sum())
            n_sem += int(lab.sum())
    return {
        "psnr": _psnr(float(se) / n_road) if n_road else float("nan"),
        "sem_acc": n_ok / n_sem if n_sem else float("nan"),
        "coverage": n_hit / max(1, idx.numel()),
        "road_pixels": n_road,
    }


def height_rmse(mesh_heights: torch.Tensor, valid: torch.Tensor, grid_xy: torch.Tensor,
                truth: HeightField) -> tuple[float, int]:
    """RMSE (m) of mesh heights vs the truth raster over kept vertices inside the truth grid."""
    xy = grid_xy[valid].double().cpu()
    t = HeightField(truth.x0, truth.y0, truth.res, truth.heights.double(), truth.valid)
    z, inside = t.height_at(xy)
    h = mesh_heights[valid].double().cpu()
    if not inside.any():
        return float("nan"), 0
    err = (h[inside] - z[inside])
    return float(torch.sqrt((err ** 2).mean())), int(inside.sum())


def forward_rays(model: RoadMeshModel, cache: torch.Tensor, bounds, o: torch.Tensor, d: torch.Tensor,
                 max_dist: float, height_rays: int | None = None):
    """Differentiable render of rays for one training step.

    Triangles are found on the cached heights ``cache`` (ny*nx,) float32 with its ``bounds``; the height
    MLP then runs only on the hit triangles' vertices, and one exact Newton step per ray carries the
    gradient. With ``height_rays`` only the triangles of the first ``height_rays`` rays get fresh MLP
    heights (and height gradients); the others render on the cached heights and train colours and
    logits only (cheap: no MLP). Returns None when nothing is hit, else rows (M,) of hit rays, tri (M, 3)
    compact vertex ids, bary (M, 3), lam (M,) depth, rgb (M, 3), sem (M, C) and the fresh triangles'
    heights (K, 3), whose edges the Laplacian term uses (a sample of the mesh edges E, weighted by how
    often views see them).
    """
    g = model.grid
    hf_cache = HeightField(g.x0, g.y0, g.res, cache.reshape(g.ny, g.nx), model.valid_t)
    cells = find_hits(hf_cache, o, d, max_dist, bounds=bounds)
    if cells.idx.numel() == 0:
        return None
    tri = model.flat_to_compact[cells.vertex_ids(g.nx)]
    fresh = tri if height_rays is None else tri[cells.idx < height_rays]
    need, inv = torch.unique(fresh.reshape(-1), return_inverse=True)
    h_need = model.heights(need)
    heights = cache.index_copy(0, model.vertex_flat_ids[need], h_need.float()).reshape(g.ny, g.nx)
    hit = hits_to_rayhit(HeightField(g.x0, g.y0, g.res, heights, model.valid_t), o, d, cells)
    rows = cells.idx
    bary = hit.bary[rows]
    # sparse row gradients: only the vertices hit in this step are touched by the (lazy) optimizer
    rgb = (bary[..., None] * F.embedding(tri, model.rgb, sparse=True)).sum(1)
    sem = (bary[..., None] * F.embedding(tri, model.sem, sparse=True)).sum(1) if model.sem.shape[1] else None
    return rows, tri, bary, hit.lam[rows], rgb, sem, h_need[inv].reshape(-1, 3)


def reconstruct(seq: Sequence, out_dir: Path | None, config: MeshConfig, progress: bool = True
                ) -> tuple[RoadMesh, dict]:
    """Stage 1 on a sequence: returns the mesh and its metrics; writes outputs to ``out_dir`` when given.

    Metrics: psnr (held-out road pixels), sem_acc, height_rmse (with synthetic truth), seconds,
    vertices, faces, device, history (per epoch), warnings.
    """
    threads_before = torch.get_num_threads()
    if config.threads:
        torch.set_num_threads(int(config.threads))
    try:
        return _reconstruct(seq, out_dir, config, progress)
    finally:
        torch.set_num_threads(threads_before)


def _reconstruct(seq: Sequence, out_dir: Path | None, config: MeshConfig, progress: bool
                 ) -> tuple[RoadMesh, dict]:
    from pavemap.mesh.outputs import load_checkpoint, save_checkpoint, write_outputs

    t_start = time.perf_counter()
    cfg = config
    cfg.validate()
    device = resolve_device(cfg.device)
    notes: list[str] = []

    def warn(msg: str) -> None:
        notes.append(msg)
        warnings.warn(msg, stacklevel=3)

    if not seq.frames:
        raise PavemapError(f"sequence {seq.name!r} has no frames")
    train_pos, held_pos = split_frames(len(seq.frames), cfg.holdout_every, cfg.frame_stride)
    if cfg.holdout_every > 0 and not held_pos:
        warn("fewer than 2 frames: no frame held out; metrics are measured on the training views")
    train_views, dropped = finite_views(seq, train_pos)
    held_views, dropped_h = finite_views(seq, held_pos)
    if dropped + dropped_h:
        warn(f"{dropped + dropped_h} view(s) with a NaN/infinite pose skipped")
    if not train_views:
        raise PavemapError(f"sequence {seq.name!r}: no training view with a finite pose")
    use_sem = any(v.semantics for _, v in train_views)
    if not use_sem:
        warn("no semantic maps in the sequence: RGB-only reconstruction, road mask = mesh footprint")
    use_depth = any(v.depth for _, v in train_views)
    classes = seq.classes if use_sem else []
    class_ids = [c.id for c in classes]
    channel_lut = np.full(256, -1, dtype=np.int64)
    for ch, cid in enumerate(class_ids):
        channel_lut[cid] = ch

    # Grid from the trajectory of the views used.
    centres = {}
    for fi, v in train_views + held_views:
        centres.setdefault(fi, []).append(v.T_world_cam[:3, 3])
    traj = np.array([np.mean(centres[k], axis=0) for k in sorted(centres)])
    grid = build_grid(traj[:, :2], cfg.resolution, cfg.crop_m)
    if grid.vertices < 3 or grid.faces == 0:
        raise PavemapError("the trajectory crop holds no triangle; check crop_m and resolution")

    pool = build_pool(seq, train_views, cfg.render_scale, channel_lut, use_sem, use_depth).to(device)
    eval_views = held_views if held_views else train_views
    epool = build_pool(seq, eval_views, cfg.eval_scale, channel_lut, use_sem, use_depth).to(device)
    if use_sem and int((epool.channel >= 0).sum()) == 0:
        warn("held-out views carry no labelled pixels: semantic accuracy is undefined")

    cam_h = cfg.camera_height
    if cfg.init_height_search:
        cam_h = _plane_search(pool, cam_h, cfg.resolution, seed=cfg.seed)
    z_vertices = _initial_surface(pool, grid, traj, cam_h, cfg, use_depth)
    z0 = float(np.median(z_vertices))  # fill value off the crop (never used as surface)

    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(cfg.seed)
        gen = torch.Generator().manual_seed(cfg.seed)
        model = RoadMeshModel(grid, len(class_ids), cfg.pe_levels, cfg.hidden, z_vertices, generator=gen)
    model.to(device)

    pose_w = pose_t = None
    align_log: list[dict] = []
    group, arm, n_groups = rig_groups(pool.keys, pool.T, cfg.pose_per)
    if cfg.pose_refine:
        # Rotation (rad) and translation (m) are separate parameters in their own Adam groups: Adam moves
        # each by ~lr per step whatever the gradient's scale, and 1 mrad at the ~5-20 m where the ground is
        # seen shifts the image as much as 5-20 mm of translation (see MeshConfig.lr_pose_rot).
        pose_w = torch.nn.Parameter(torch.zeros(n_groups, 3, device=device))
        pose_t = torch.nn.Parameter(torch.zeros(n_groups, 3, device=device))

    def view_delta(detach: bool = True) -> torch.Tensor | None:
        """(V, 6) corrections of the training views (from the per-frame ones with ``pose_per: frame``)."""
        if pose_w is None:
            return None
        d = rig_corrections(torch.cat([pose_w, pose_t], 1), group, arm)
        return d.detach() if detach else d
    groups = [{"params": list(model.height_mlp.parameters()), "lr": cfg.lr_height, "name": "height"}]
    if pose_w is not None:
        groups.append({"params": [pose_t], "lr": cfg.lr_pose, "name": "pose"})
        groups.append({"params": [pose_w], "lr": cfg.lr_pose_rot, "name": "pose_rot"})
    # Per-vertex colours and logits get gradients only where a sampled pixel hits them; dense Adam would
    # keep moving every other vertex on stale momentum (overshooting by ~30 lr), so these use the lazy
    # (sparse) Adam, which updates only the rows hit in the step.
    opt = MultiOptimizer(torch.optim.Adam(groups), torch.optim.SparseAdam([
        {"params": [model.rgb], "lr": cfg.lr_rgb, "name": "rgb"},
        {"params": [model.sem], "lr": cfg.lr_sem, "name": "sem"},
    ]))
    all_params = [p for grp in groups for p in grp["params"]] + [model.rgb, model.sem]

    # Drop pixels whose rays cannot meet the mesh (sky, far off the crop): they would fill batches with misses.
    with torch.no_grad():
        flat = model.dense(model.heights(), fill=float(z0)).float()
        hf0 = HeightField(grid.x0, grid.y0, grid.res, flat, model.valid_t)
        keep = torch.zeros(len(pool), dtype=torch.bool, device=device)
        T_all = pool.T
        for s in range(0, len(pool), 262144):
            o, d = view_rays(pool.Kinv, T_all, pool.view[s:s + 262144], pool.uv[s:s + 262144])
            keep[s + find_hits(hf0, o, d, cfg.max_dist).idx] = True
        seen = torch.bincount(pool.view[keep], minlength=len(pool.keys))
        blind = int((seen == 0).sum())
        if blind:
            # Usually not an error: a forward camera's nearest visible ground lies several metres ahead
            # (~7 m for KITTI's), so in the last frames it looks past the crop around the trajectory's end.
            names = [f"{pool.keys[i].frame}/{pool.keys[i].camera}" for i in (seen == 0).nonzero().squeeze(1).tolist()]
            warn(f"{blind} training view(s) see no part of the road mesh and are unused ({', '.join(names[:6])}"
                 f"{', ...' if blind > 6 else ''}): pointing at the sky, or looking past the crop around the "
                 "trajectory's ends")
        pool = pool.subset(keep)
    if len(pool) == 0:
        raise PavemapError(f"sequence {seq.name!r}: no training view sees the road area around the trajectory")
    if use_sem and int(pool.road.sum()) == 0:
        warn("no pixel of a road class is visible on the mesh area")

    history: list[dict] = []
    start_epoch = 0
    elapsed_before = 0.0
    gen = torch.Generator().manual_seed(cfg.seed + 1)
    if out_dir is not None and cfg.resume and (Path(out_dir) / CHECKPOINT).is_file():
        state = load_checkpoint(Path(out_dir) / CHECKPOINT, grid, len(class_ids), n_groups, device)
        if state is not None:
            model.load_state_dict(state["model"])
            opt.load_state_dict(state["opt"])
            if pose_w is not None and state.get("delta") is not None:
                pose_w.data.copy_(state["delta"][:, :3].to(device))
                pose_t.data.copy_(state["delta"][:, 3:].to(device))
            history = state["history"]
            start_epoch = int(state["epoch"])
            elapsed_before = float(state.get("seconds", 0.0))
            gen.set_state(state["gen"])
        else:
            warn("checkpoint in the output folder does not match this run; starting afresh")

    if pose_w is not None and cfg.pose_align_iters > 0 and start_epoch == 0:
        delta0, align_log = _align_stage(model, pool, cfg, z0, grid, traj, cam_h, use_depth, group, arm, n_groups)
        pose_w.data.copy_(delta0[:, :3])
        pose_t.data.copy_(delta0[:, 3:])

    def eval_delta() -> torch.Tensor | None:
        """Pose corrections of the evaluation views: the training views' own, or interpolated for held-out frames."""
        if pose_w is None:
            return None
        delta = view_delta()
        return delta if epool.keys == pool.keys else interpolate_corrections(pool.keys, delta, epool.keys)

    if cfg.bake_init and start_epoch == 0:
        _bake_into(model, pool, view_delta(), cfg, z0)

    n_epoch = max(1, int(round(len(pool) * min(cfg.pixel_fraction, 1.0))))
    steps_per_epoch = max(1, math.ceil(n_epoch / cfg.pixels_per_step))
    depth_on = use_depth and pool.depth is not None and cfg.w_depth > 0
    depth_first = depth_on and cfg.depth_first
    total_steps = max(1, cfg.epochs * steps_per_epoch)
    bar = tqdm(total=(cfg.epochs - start_epoch) * steps_per_epoch, disable=not progress, desc="mesh",
               unit="step", dynamic_ncols=True)
    bad = 0
    gy = grid
    for epoch in range(start_epoch, cfg.epochs):
        t_ep = time.perf_counter()
        perm = torch.randperm(len(pool), generator=gen)[:n_epoch].to(device)
        sums = {"loss": 0.0, "rgb": 0.0, "sem": 0.0, "depth": 0.0, "smooth": 0.0, "se": 0.0, "n": 0}
        cache = None
        for step in range(steps_per_epoch):
            if cache is None or step % cfg.height_refresh_steps == 0:
                with torch.no_grad():
                    cache = model.dense(model.heights(), fill=float(z0)).reshape(-1).float()
                    hf_cache = HeightField(gy.x0, gy.y0, gy.res, cache.reshape(gy.ny, gy.nx), model.valid_t)
                    bounds = surface_bounds(hf_cache, torch.float32)
            gstep = epoch * steps_per_epoch + step
            if pose_w is not None and gstep >= cfg.pose_warmup * total_steps and \
                    (gstep - math.ceil(cfg.pose_warmup * total_steps)) % cfg.pose_bake_every == 0:
                # Poses align to the consensus texture of all views: re-baked on the current poses, it is the
                # multi-view average, whereas Adam's per-vertex colours fit single pixels and leave a pose loss
                # ~0.1 m wide (the refinement went 0.200 -> 0.196 m on the test scene; with it, ~0.1 m).
                _bake_into(model, pool, view_delta(), cfg, z0)
            b = perm[step * cfg.pixels_per_step:(step + 1) * cfg.pixels_per_step]
            if b.numel() == 0:
                continue
            if depth_first:
                # Measured depth is the strongest height signal: put those pixels first so that they fall
                # in the ``height_pixels_per_step`` rays whose triangles get fresh MLP heights and gradients.
                b = b[torch.sort((pool.depth[b] <= 0).to(torch.int8), stable=True).indices]
            T = corrected_poses(pool.T, view_delta(detach=False))
            o, d = view_rays(pool.Kinv, T, pool.view[b], pool.uv[b])
            fw = forward_rays(model, cache, bounds, o, d, cfg.max_dist, height_rays=cfg.height_pixels_per_step)
            if fw is None:
                bar.update(1)
                continue
            rows, tri, bary, lam, rgb, sem_all, ht = fw
            gt = pool.rgb[b][rows].float() / 255.0
            l_rgb = (rgb - gt).abs().mean()
            loss = cfg.w_rgb * l_rgb
            l_sem = torch.zeros((), device=device)
            if use_sem and model.sem.shape[1]:
                ch = pool.channel[b][rows]
                lab = ch >= 0
                if lab.any():
                    l_sem = F.cross_entropy(sem_all[lab], ch[lab])
                    loss = loss + cfg.w_sem * l_sem
            l_depth = torch.zeros((), device=device)
            if depth_on:
                dg = pool.depth[b][rows]
                # A height field cannot stand up into a wall: a pixel whose measured depth is far from
                # the surface's (a facade, a pole) is an outlier, not a reason to bend the road.
                # The gate is in height units: the residual times the ray's vertical speed per unit depth
                # (a depth-relative gate dropped exactly the far road pixels whose heights were off most).
                dz = d[rows, 2].detach().abs()
                m = (dg > 0) & ((lam.detach() - dg).abs() * dz < cfg.depth_outlier_m)
                if m.any():
                    l_depth = (lam[m] - dg[m]).abs().mean()
                    loss = loss + cfg.w_depth * l_depth
            l_smooth = ((ht - ht.roll(1, dims=1)) ** 2).mean()
            loss = loss + cfg.w_smooth * l_smooth
            opt.zero_grad(set_to_none=True)
            what = "losses"
            if bool(torch.isfinite(loss)):
                loss.backward()
                what = "gradients"
                step_ok = all(p.grad is None or torch.isfinite(p.grad.coalesce().values() if p.grad.is_sparse
                                                              else p.grad).all() for p in all_params)
            else:
                step_ok = False
            if not step_ok:  # skip the step; give up only when it keeps happening
                bad += 1
                opt.zero_grad(set_to_none=True)
                if bad >= cfg.max_bad_steps:
                    raise PavemapError(f"training diverged: {bad} consecutive non-finite {what} (epoch {epoch + 1})")
                bar.update(1)
                continue
            bad = 0
            frac = (epoch * steps_per_epoch + step) / total_steps
            per_group = {"height": cfg.lr_height_decay_final ** frac}
            if frac < cfg.pose_warmup:
                # Poses stay put until the colours are fitted: a pose gradient through a still random
                # texture points nowhere, and Adam would move the poses by ~lr per step regardless.
                per_group.update(pose=0.0, pose_rot=0.0)
            opt.set_lr_factor(cfg.lr_decay_final ** frac, per_group)
            opt.step()
            with torch.no_grad():
                road = pool.road[b][rows]
                se = float(((rgb.detach().clamp(0, 1) - gt) ** 2).mean(1)[road].sum())
                sums["se"] += se
                sums["n"] += int(road.sum())
                sums["loss"] += float(loss)
                sums["rgb"] += float(l_rgb)
                sums["sem"] += float(l_sem)
                sums["depth"] += float(l_depth)
                sums["smooth"] += float(l_smooth)
            bar.update(1)
            if step % 4 == 0:
                bar.set_postfix(epoch=f"{epoch + 1}/{cfg.epochs}", loss=f"{float(loss.detach()):.4f}",
                                psnr=f"{_psnr(sums['se'] / max(1, sums['n'])):.2f}")
        with torch.no_grad():
            heights_now = model.dense(model.heights(), fill=float(z0)).float()
        ev = evaluate_pool(model, epool, cfg, heights_now, delta=eval_delta(), max_pixels=100000,
                           generator=torch.Generator().manual_seed(cfg.seed + 2))
        k = max(1, steps_per_epoch)
        history.append({
            "epoch": epoch + 1,
            "loss": sums["loss"] / k, "l_rgb": sums["rgb"] / k, "l_sem": sums["sem"] / k,
            "l_depth": sums["depth"] / k, "l_smooth": sums["smooth"] / k,
            "train_psnr": _psnr(sums["se"] / max(1, sums["n"])),
            "eval_psnr": ev["psnr"], "eval_sem_acc": ev["sem_acc"],
            "seconds": time.perf_counter() - t_ep,
        })
        bar.set_postfix(epoch=f"{epoch + 1}/{cfg.epochs}", loss=f"{history[-1]['loss']:.4f}",
                        psnr=f"{ev['psnr']:.2f}")
        if out_dir is not None:
            delta = None if pose_w is None else torch.cat([pose_w, pose_t], 1).detach()
            save_checkpoint(Path(out_dir) / CHECKPOINT, model, opt, delta, epoch + 1, history, gen, grid, cfg,
                            elapsed_before + time.perf_counter() - t_start)
    bar.close()

    seen = None
    if cfg.bake_final:
        delta = view_delta()
        seen = _bake_into(model, pool, delta, cfg, z0, sharpen_iters=cfg.bake_sharpen_iters)

    # Final evaluation on all held-out pixels.
    with torch.no_grad():
        heights_now = model.dense(model.heights(), fill=float(z0)).float()
    t_ev = time.perf_counter()
    ev = evaluate_pool(model, epool, cfg, heights_now, delta=eval_delta())
    ev_s = time.perf_counter() - t_ev
    # The fit to the training views (on their refined poses): with pose refinement the held-out views keep
    # their raw poses (plus interpolated corrections), so this is where aligned poses show.
    ev_train = evaluate_pool(model, pool, cfg, heights_now, view_delta(),
                             max_pixels=200000, generator=torch.Generator().manual_seed(cfg.seed + 3))
    mesh = to_road_mesh(model, class_ids, use_sem)
    metrics: dict = {
        "psnr": ev["psnr"], "sem_acc": ev["sem_acc"] if use_sem else None, "train_psnr": ev_train["psnr"],
        "heldout": bool(held_views), "heldout_views": len(eval_views), "train_views": len(pool.keys),
        "coverage": ev["coverage"],
        "vertices": grid.vertices, "faces": grid.faces, "grid": grid.as_dict(),
        "device": str(device), "epochs": cfg.epochs, "steps_per_epoch": steps_per_epoch,
        "pixels_per_epoch": n_epoch, "camera_height_init": cam_h,
        "eval_pixels_per_second": len(epool) / max(ev_s, 1e-9),
        "history": history, "warnings": notes, "config": cfg.to_dict(),
    }
    if pose_w is not None:
        with torch.no_grad():
            Tr = corrected_poses(pool.T, view_delta()).double().cpu().numpy()
        metrics["pose_alignment"] = align_log
        metrics["refined_poses"] = {f"{k.frame}/{k.camera}": Tr[i].tolist() for i, k in enumerate(pool.keys)}
    if seq.root is not None and (Path(seq.root) / "truth" / "height.npy").is_file():
        truth = HeightField.from_truth(seq.root)
        rmse, n = height_rmse(mesh.surface.heights, mesh.surface.valid, mesh.surface.grid_xy(), truth)
        metrics["height_rmse"] = rmse
        metrics["height_rmse_vertices"] = n
        if seen is not None:
            # A forward camera never sees the crop behind the first frame: its heights are a guess, so the
            # error over the vertices a training pixel does reach is reported too.
            seen_grid = model.dense(seen.cpu(), fill=False)
            rmse_s, n_s = height_rmse(mesh.surface.heights, mesh.surface.valid & seen_grid, mesh.surface.grid_xy(),
                                      truth)
            metrics["height_rmse_seen"] = rmse_s
            metrics["height_rmse_seen_vertices"] = n_s
    metrics["seconds"] = elapsed_before + time.perf_counter() - t_start
    if not torch.isfinite(mesh.surface.heights[mesh.surface.valid]).all():
        raise PavemapError("reconstruction produced non-finite heights")
    if out_dir is not None:
        write_outputs(Path(out_dir), mesh, metrics, classes)
    return mesh, metrics


@torch.no_grad()
def _bake_into(model: RoadMeshModel, pool: PixelPool, delta: torch.Tensor | None, cfg: MeshConfig,
               fill: float, sharpen_iters: int = 0) -> torch.Tensor:
    """Replace the model's vertex colours by the baked ones on its current surface (where any pixel
    reaches them, directly or through the gap fill). Returns (Nv,) bool: the vertices some training pixel sees."""
    g = model.grid
    heights = model.dense(model.heights(), fill=fill).float()
    rgb, support, coloured = bake_colours(heights, model.valid_t, g.x0, g.y0, g.res, pool,
                                          corrected_poses(pool.T, delta), cfg.max_dist, cfg.bake_fill_sigma,
                                          sharpen_iters=sharpen_iters)
    flat = model.vertex_flat_ids
    ok = coloured.reshape(-1)[flat]
    model.rgb.data[ok] = rgb.reshape(-1, 3)[flat][ok].to(model.rgb.dtype)
    return support.reshape(-1)[flat] > 0


@torch.no_grad()
def to_road_mesh(model: RoadMeshModel, class_ids: list[int], has_semantics: bool) -> RoadMesh:
    """Densify the trained model into a RoadMesh (CPU tensors)."""
    g = model.grid
    h = model.heights()
    heights = model.dense(h, fill=0.0).float().cpu()
    rgb = model.dense(model.rgb.clamp(0, 1)).float().cpu()
    sem = model.dense(model.sem).float().cpu()
    surf = HeightField(g.x0, g.y0, g.res, heights, torch.from_numpy(g.valid.copy()))
    return RoadMesh(surf, rgb, sem, list(class_ids), has_semantics)
