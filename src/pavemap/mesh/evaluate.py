"""Stage-1 evaluation: PSNR and semantic accuracy of rendered pixels, height error against a true surface."""

from __future__ import annotations

import math
import os
import time

import torch

from pavemap.geometry import HeightField, find_hits, hits_to_rayhit, surface_bounds
from pavemap.io.truth import has_truth_height, read_truth_height
from pavemap.mesh import exposure as exposure_model
from pavemap.mesh.data import PixelPool
from pavemap.mesh.model import RoadMesh, RoadMeshModel
from pavemap.mesh.pose import corrected_poses
from pavemap.mesh.render import view_rays
from pavemap.mesh.setup import TrainData
from pavemap.mesh.step import Fit


def psnr(mse: float) -> float:
    """PSNR (dB) of a mean squared error of colours in [0, 1]."""
    return float(10 * math.log10(1.0 / max(mse, 1e-10)))


@torch.no_grad()
def evaluate_pool(model: RoadMeshModel, pool: PixelPool, heights: torch.Tensor, max_dist: float,
                  delta: torch.Tensor | None = None, max_pixels: int | None = None, batch: int = 131072,
                  generator: torch.Generator | None = None, exposure: torch.Tensor | None = None,
                  seen: torch.Tensor | None = None) -> dict[str, float]:
    """Render the pool's pixels (a random ``max_pixels`` of them when given) on dense ``heights`` (ny, nx)
    from the pool's poses corrected by ``delta`` (V, 6), each view at its ``exposure`` (V, 2) when given.
    Returns psnr over road pixels the mesh covers, sem_acc over labelled hit pixels, coverage (hit fraction)
    and road_pixels.

    ``seen``: (Nv,) bool the vertices some training pixel textured. With it, ``psnr`` counts only road pixels
    on faces whose three vertices are textured: elsewhere the colour is the bake's gap fill, which measures no
    reconstruction, only how far the held-out view sees past the training views (the first frame of a drive
    sees road no later frame does). ``psnr_all`` then keeps every covered road pixel and ``textured_share`` says
    what share of them ``psnr`` rests on."""
    n = len(pool)
    idx = torch.arange(n, device=pool.view.device)
    if max_pixels is not None and n > max_pixels:
        idx = torch.randperm(n, generator=generator)[:max_pixels].to(pool.view.device)
    hf = model.field(heights)
    bounds = surface_bounds(hf, pool.uv.dtype)
    T = corrected_poses(pool.T, delta)
    se = torch.zeros((), dtype=torch.float64, device=heights.device)
    se_all = torch.zeros((), dtype=torch.float64, device=heights.device)
    n_road = n_road_all = n_sem = n_ok = n_hit = 0
    for s in range(0, idx.numel(), batch):
        b = idx[s:s + batch]
        o, d = view_rays(pool.K, T, pool.view[b], pool.uv[b])
        hit = hits_to_rayhit(hf, o, d, find_hits(hf, o, d, max_dist, bounds=bounds))
        hv = hit.hit
        n_hit += int(hv.sum())
        cid = model.flat_to_compact[hit.vertex_ids[hv]]
        bary = hit.bary[hv]
        rgb = exposure_model.apply((bary[..., None] * model.rgb[cid]).sum(1), exposure, pool.view[b][hv]).clamp(0, 1)
        gt = pool.rgb[b][hv].float() / 255.0
        road = pool.road[b][hv]
        err = ((rgb - gt) ** 2).mean(1)
        se_all += err[road].double().sum()
        n_road_all += int(road.sum())
        if seen is not None:
            road = road & seen.to(cid.device)[cid].all(1)
        se += err[road].double().sum()
        n_road += int(road.sum())
        ch = pool.channel[b][hv]
        lab = ch >= 0
        if lab.any() and model.sem.shape[1]:
            pred = (bary[lab][..., None] * model.sem[cid[lab]]).sum(1).argmax(1)
            n_ok += int((pred == ch[lab]).sum())
            n_sem += int(lab.sum())
    out = {
        "psnr": psnr(float(se) / n_road) if n_road else float("nan"),
        "sem_acc": n_ok / n_sem if n_sem else float("nan"),
        "coverage": n_hit / max(1, idx.numel()),
        "road_pixels": n_road,
    }
    if seen is not None:
        out["psnr_all"] = psnr(float(se_all) / n_road_all) if n_road_all else float("nan")
        out["textured_share"] = n_road / n_road_all if n_road_all else float("nan")
    return out


def _height_sq_err(mesh_heights: torch.Tensor, valid: torch.Tensor, grid_xy: torch.Tensor,
                   truth: HeightField) -> tuple[float, int]:
    """Sum of squared height errors (m^2) of the mesh against the truth raster over the kept vertices
    ``valid`` inside the truth grid, and their count."""
    xy = grid_xy[valid].double().cpu()
    z, inside = truth.height_at(xy)  # float32 heights interpolated in float64 weights (no float64 raster copy)
    h = mesh_heights[valid].double().cpu()
    err = h[inside] - z[inside]
    return float((err ** 2).sum()), int(inside.sum())


def truth_metrics(mesh: RoadMesh, seq_root: str | os.PathLike, seen: torch.Tensor | None,
                  band_rows: int = 1024) -> dict[str, float | int]:
    """Height RMSE of the mesh against the true surface of the sequence at ``seq_root`` over all kept
    vertices, and, with ``seen`` (ny, nx) bool, over the vertices some training pixel reaches. The mesh is
    taken ``band_rows`` rows at a time with the truth's window under them: a whole drive's truth and vertex
    coordinates do not fit in memory together."""
    s = mesh.surface
    acc = {"all": [0.0, 0], "seen": [0.0, 0]}
    for j0 in range(0, s.ny, band_rows):
        band = HeightField(s.x0, s.y0 + j0 * s.res, s.res, s.heights[j0:j0 + band_rows], s.valid[j0:j0 + band_rows])
        if not bool(band.valid.any()):
            continue
        truth = read_truth_height(seq_root, band.extent)
        xy = band.grid_xy()
        masks = {"all": band.valid}
        if seen is not None:
            masks["seen"] = band.valid & seen[j0:j0 + band_rows].to(band.valid.device)
        for key, mask in masks.items():
            se, n = _height_sq_err(band.heights, mask, xy, truth)
            acc[key][0] += se
            acc[key][1] += n
    out: dict[str, float | int] = {"height_rmse": _rmse(*acc["all"]), "height_rmse_vertices": acc["all"][1]}
    if seen is not None:
        # A forward camera never sees the crop behind the first frame: its heights are a guess, so the
        # error over the vertices a training pixel does reach is reported too.
        out.update(height_rmse_seen=_rmse(*acc["seen"]), height_rmse_seen_vertices=acc["seen"][1])
    return out


def _rmse(se: float, n: int) -> float:
    return math.sqrt(se / n) if n else float("nan")


def stage_metrics(fit: Fit, data: TrainData, mesh: RoadMesh, fill: float, eval_delta: torch.Tensor | None,
                  seen: torch.Tensor | None, seq_root: str | os.PathLike | None,
                  exposure: torch.Tensor | None = None) -> dict:
    """The final evaluation of a run: held-out psnr / sem_acc / coverage on all evaluation pixels, the fit to
    the training views (on their refined poses), the grid, the refined poses, and the height error where
    the sequence has a true surface. ``seen``: (Nv,) bool vertices a training pixel reaches, or None;
    ``exposure``: (V, 2) the training views' (held-out views get theirs interpolated in time)."""
    model, pool, cfg = fit.model, fit.pool, fit.cfg
    heights = model.dense_heights(fill)
    t_ev = time.perf_counter()
    ev_exposure = None if exposure is None else exposure_model.interpolate(pool.keys, exposure, data.epool.keys)
    ev = evaluate_pool(model, data.epool, heights, cfg.max_dist, delta=eval_delta, exposure=ev_exposure, seen=seen)
    ev_s = time.perf_counter() - t_ev
    # The fit to the training views (on their refined poses): with pose refinement the held-out views keep
    # their raw poses (plus interpolated corrections), so this is where aligned poses show.
    view_delta = None if fit.poses is None else fit.poses.view_delta()
    ev_train = evaluate_pool(model, pool, heights, cfg.max_dist, view_delta, max_pixels=200000,
                             generator=torch.Generator().manual_seed(cfg.seed + 3), exposure=exposure)
    grid = data.grid
    metrics: dict = {
        "psnr": ev["psnr"], "sem_acc": ev["sem_acc"] if data.use_sem else None, "train_psnr": ev_train["psnr"],
        "heldout": data.heldout, "heldout_views": len(data.epool.keys), "train_views": len(pool.keys),
        "coverage": ev["coverage"], "psnr_untextured_included": ev.get("psnr_all"),
        "heldout_textured_share": ev.get("textured_share"), "vertices": grid.vertices, "faces": grid.faces,
        "grid": grid.spec.to_dict(),
        "eval_pixels_per_second": len(data.epool) / max(ev_s, 1e-9),
        "exposure": exposure_model.summary(exposure),
    }
    if view_delta is not None:
        with torch.no_grad():
            Tr = corrected_poses(pool.T, view_delta).double().cpu().numpy()
        metrics["refined_poses"] = {f"{k.frame}/{k.camera}": Tr[i].tolist() for i, k in enumerate(pool.keys)}
    if has_truth_height(seq_root):
        seen_grid = None if seen is None else model.dense(seen, fill=False).cpu()
        metrics.update(truth_metrics(mesh, seq_root, seen_grid))
    return metrics
