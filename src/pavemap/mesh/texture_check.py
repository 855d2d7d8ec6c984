"""Where the BEV texture may hold a vehicle rather than the road (issue 13: moving objects without a segmenter).

The final bake averages every training pixel that lands on a vertex. A vehicle passing the camera covers a
road vertex in some of those views; where it covers most of them, its colour *is* the texture there, and no
per-pixel rejection (:func:`pavemap.mesh.bake.static_pixels`) can take it out again, because the majority
agrees with it. What is still visible is the disagreement: some views saw something else there. This module
measures it on the final texture, with the views' exposures, and marks the squares of the grid where a share
of their pixels disagrees, so that the report can say *where* the texture may hold a vehicle instead of
claiming a clean road.

Disagreeing pixels: colour distance to the texture where they land (exposure-compensated, RGB in [0, 1])
above ``cutoff``, and part of a blob at least 2 ``blob_px`` + 1 pixels wide in its image (a vehicle is a
blob; a paint edge seen through a surface a centimetre off is a thin line). Pixels are counted per square of
``block`` x ``block`` cells, each pixel once at its triangle's nearest vertex (at render scale a vertex sees
a handful). A square is *contested* where the disagreeing share of its pixels is at least ``min_share`` and
at least ``min_views`` views disagree there (fewer squares from one view's glare).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from pavemap.geometry import GridSpec, HeightField
from pavemap.mesh import exposure as exposure_model
from pavemap.mesh.bake import Hits, _opened, march_pool
from pavemap.mesh.data import PixelPool
from pavemap.mesh.model import RoadMesh
from pavemap.types import SemanticClass


@dataclass
class TextureCheck:
    """Per grid vertex, dense (ny, nx), each the value of the vertex's square: ``share`` float32 the
    disagreeing share of its pixels (NaN where no pixel lands), ``views`` int32 the number of views with
    disagreeing pixels there, ``seen_by`` int32 the number of views with pixels there, ``contested`` bool."""

    share: torch.Tensor
    views: torch.Tensor
    seen_by: torch.Tensor
    contested: torch.Tensor


@torch.no_grad()
def check_texture(surface: HeightField, pool: PixelPool, T: torch.Tensor, max_dist: float, rgb: torch.Tensor,
                  exposure: torch.Tensor | None, cutoff: float, blob_px: int, min_share: float, min_views: int,
                  block: int = 1, hits: list[Hits] | None = None) -> TextureCheck:
    """The texture's disagreement with the pixels it was baked from, per square of ``block`` × ``block`` cells
    (a vertex sees a handful of pixels at render scale; a vehicle's imprint is square metres).

    surface: the final surface (dense heights (ny, nx), crop); pool: the training pixels, T (V, 4, 4) their
    posed views; rgb (ny, nx, 3) float the final texture; exposure (V, 2) float64 or None (the views'
    gains and offsets of the final bake); hits: the pool's march on this surface when one was made already
    (:func:`pavemap.mesh.bake.march_pool`). Each pixel counts once, at its triangle's nearest vertex."""
    ny, nx = surface.heights.shape
    bx, by = -(-nx // block), -(-ny // block)
    flat = rgb.reshape(-1, 3).double()
    resid = torch.full((len(pool),), float("nan"), dtype=torch.float32, device=rgb.device)
    at = torch.full((len(pool),), -1, dtype=torch.long, device=rgb.device)  # each hit pixel's block
    for h in march_pool(surface, pool, T, max_dist) if hits is None else hits:
        if h.rows is None:
            raise ValueError("check_texture: hits without their pool rows (make them with march_pool or batch_hits)")
        obs = exposure_model.compensate(h.c8.double() / 255.0, exposure, h.view)
        resid[h.rows] = torch.linalg.norm(obs - (h.w.double()[..., None] * flat[h.vid]).sum(1), dim=1).float()
        near = h.vid.gather(1, h.w.argmax(1, keepdim=True)).squeeze(1)
        at[h.rows] = (near // nx // block) * bx + (near % nx) // block
    off = resid > cutoff  # NaN (a miss) compares False
    off = _opened(off, pool, blob_px) if blob_px > 0 and bool(off.any()) else off
    hit = at >= 0
    n = bx * by
    total = torch.bincount(at[hit], minlength=n).double()
    share = torch.where(total > 0, torch.bincount(at[off & hit], minlength=n) / total.clamp_min(1), torch.nan)
    nv = len(pool.keys)
    views = _count_views(at[off & hit] * nv + pool.view[off & hit], n, nv)
    seen_by = _count_views(at[hit] * nv + pool.view[hit], n, nv)
    jj = torch.arange(ny, device=rgb.device)[:, None] // block
    ii = torch.arange(nx, device=rgb.device)[None, :] // block
    cell = jj * bx + ii  # (ny, nx) block of each cell

    def dense(a: torch.Tensor) -> torch.Tensor:
        return a[cell]

    contested = (share >= min_share) & (views >= min_views)
    return TextureCheck(dense(share.float()), dense(views), dense(seen_by),
                        dense(contested) & surface.valid.to(contested.device))


def _count_views(keys: torch.Tensor, n: int, n_views: int) -> torch.Tensor:
    """(n,) int32 distinct views per block from keys ``block * n_views + view`` (M,) long."""
    uniq = torch.unique(keys)
    return torch.bincount(uniq // n_views, minlength=n).to(torch.int32)


def contested_patches(contested: np.ndarray, res: float, min_patch_m2: float
                      ) -> tuple[np.ndarray, list[dict]]:
    """The contested cells (ny, nx) bool in patches (8-connected) of at least ``min_patch_m2``: the mask of
    those patches and, largest first, each patch's ``area_m2`` and centre cell ``(i, j)`` (float, grid index)."""
    from scipy import ndimage

    lab, n = ndimage.label(contested, structure=np.ones((3, 3), bool))
    if n == 0:
        return np.zeros_like(contested), []
    flat = lab.reshape(-1)
    counts = np.bincount(flat, minlength=n + 1)
    jj, ii = np.divmod(np.arange(flat.size), contested.shape[1])
    ci = np.bincount(flat, weights=ii, minlength=n + 1) / np.maximum(counts, 1)  # one pass for every patch
    cj = np.bincount(flat, weights=jj, minlength=n + 1) / np.maximum(counts, 1)
    big = np.flatnonzero(counts * res * res >= min_patch_m2)
    big = big[big > 0]
    keep = np.isin(lab, big)
    patches = [{"area_m2": float(counts[k] * res * res), "centre_ij": (float(ci[k]), float(cj[k]))}
               for k in big[np.argsort(-counts[big], kind="stable")]]
    return keep, patches


def texture_summary(contested: np.ndarray, g: GridSpec, min_patch_m2: float, mesh_cells: int
                    ) -> tuple[np.ndarray, dict]:
    """The contested cells (ny, nx) bool in patches of at least ``min_patch_m2`` on grid ``g`` and what
    ``metrics.json`` says of them (``texture_check``): area, share of the mesh's ``mesh_cells`` (its crop),
    patches largest first (area and centre in the grid's metres, at most 20 listed)."""
    keep, patches = contested_patches(contested, g.res, min_patch_m2)
    area = float(keep.sum()) * g.res * g.res
    return keep, {
        "contested_m2": round(area, 2), "contested_share": round(float(keep.sum() / max(1, mesh_cells)), 5),
        "patches": [{"area_m2": round(p["area_m2"], 2), "x_m": round(g.x0 + p["centre_ij"][0] * g.res, 2),
                     "y_m": round(g.y0 + p["centre_ij"][1] * g.res, 2)} for p in patches[:20]],
        "patch_count": len(patches)}


def check_model_texture(model, mesh: RoadMesh, classes: list[SemanticClass], pool: PixelPool, T: torch.Tensor,  # noqa: ANN001
                        fill: float, cfg, exposure: torch.Tensor | None, warn,  # noqa: ANN001
                        hits: list[Hits] | None = None) -> tuple[torch.Tensor, dict]:
    """:func:`check_texture` of a stage-1 model's final texture (RoadMeshModel, its RoadMesh, MeshConfig): the
    contested vertices (ny, nx) bool in patches of at least ``cfg.texture_min_patch_m2`` and the metrics;
    ``warn`` (a str callable) is told where the texture may hold vehicles. Only the road and what the mesh
    labels a vehicle count: off the road a kerb's face or a wall is not a height field, and its views disagree
    for that reason (the clean bench drive's only contested squares)."""
    field = model.field(model.dense_heights(fill))
    rgb = model.dense(model.rgb.detach().float(), fill=0.0)
    g = model.grid.spec
    tc = check_texture(field, pool, T, cfg.max_dist, rgb, exposure, cfg.texture_cutoff, cfg.texture_blob_px,
                       cfg.texture_min_share, cfg.texture_min_views, max(1, round(cfg.texture_block_m / g.res)), hits)
    valid = mesh.surface.valid.cpu().numpy()
    where = valid & torch.isfinite(tc.share).cpu().numpy()
    if mesh.has_semantics and mesh.class_ids:
        where &= np.isin(mesh.labels().cpu().numpy(), [c.id for c in classes if c.road or c.movable])
    keep, out = texture_summary(tc.contested.cpu().numpy() & where, g, cfg.texture_min_patch_m2, int(valid.sum()))
    # a vehicle in every view that saw the road is the majority there and invisible to the check: say how much
    # of the road's texture rests on too few views to tell (the shared nuScenes clip's bus, docs/history)
    few = where & (tc.seen_by.cpu().numpy() < 2 * max(1, cfg.texture_min_views))
    out["few_views_m2"] = round(float(few.sum()) * g.res * g.res, 2)
    area, patches = out["contested_m2"], out["patches"]
    if patches:
        top = patches[0]
        warn(f"the BEV texture may hold vehicles or other moving objects over {area:.1f} m² in {out['patch_count']} "
             f"patch(es) (largest {top['area_m2']:.1f} m² at x {top['x_m']:.1f}, y {top['y_m']:.1f} m): views there "
             "disagree with it, from a vehicle, sun glare on the road, or poses or surface off there "
             "(bev_contested.npy; `--set mesh.moving_cutoff=0.15` leaves out a vehicle that a minority of the "
             "views saw)")
    return torch.from_numpy(keep), out
