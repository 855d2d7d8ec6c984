"""One stage-1 optimisation step: render a batch of pixels differentiably, the SPEC's losses, one update.

``L = w_rgb L_rgb + w_sem L_sem + w_depth L_depth + w_smooth L_smooth`` over the hit pixels (SPEC §1:
weights 1, 0.5, lambda_depth, 1). Triangles are found on a cached copy of the heights (no autograd);
the height MLP runs only at the vertices of the triangles hit, and one exact Newton step per ray
(:func:`pavemap.geometry.hits_to_rayhit`) carries the gradient to heights, colours, logits and poses.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import torch
from torch.nn import functional as F  # noqa: N812

from pavemap.geometry import find_hits, hits_to_rayhit
from pavemap.geometry.heightfield import SurfaceBounds
from pavemap.mesh.config import MeshConfig
from pavemap.mesh.data import PixelPool
from pavemap.mesh.model import RoadMeshModel
from pavemap.mesh.pose import PoseCorrections, corrected_poses
from pavemap.mesh.render import view_rays


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


def make_optimizer(model: RoadMeshModel, poses: PoseCorrections | None, cfg: MeshConfig
                   ) -> tuple[MultiOptimizer, list[torch.Tensor]]:
    """The optimizer over the model (and the pose corrections), and the list of all its parameters."""
    groups = [{"params": list(model.height_mlp.parameters()), "lr": cfg.lr_height, "name": "height"}]
    if poses is not None:
        groups.append({"params": [poses.t], "lr": cfg.lr_pose, "name": "pose"})
        groups.append({"params": [poses.w], "lr": cfg.lr_pose_rot, "name": "pose_rot"})
    # Per-vertex colours and logits get gradients only where a sampled pixel hits them; dense Adam would
    # keep moving every other vertex on stale momentum (overshooting by ~30 lr), so these use the lazy
    # (sparse) Adam, which updates only the rows hit in the step.
    opt = MultiOptimizer(torch.optim.Adam(groups), torch.optim.SparseAdam([
        {"params": [model.rgb], "lr": cfg.lr_rgb, "name": "rgb"},
        {"params": [model.sem], "lr": cfg.lr_sem, "name": "sem"},
    ]))
    return opt, [p for grp in groups for p in grp["params"]] + [model.rgb, model.sem]


class RayRender(NamedTuple):
    """A differentiable render of the rays that hit: rows (M,) of those rays, tri (M, 3) compact vertex ids,
    bary (M, 3), lam (M,) depth, rgb (M, 3), sem (M, C) or None, and ht (K, 3) the fresh triangles' heights."""

    rows: torch.Tensor
    tri: torch.Tensor
    bary: torch.Tensor
    lam: torch.Tensor
    rgb: torch.Tensor
    sem: torch.Tensor | None
    ht: torch.Tensor


def forward_rays(model: RoadMeshModel, cache: torch.Tensor, bounds: SurfaceBounds, o: torch.Tensor,
                 d: torch.Tensor, max_dist: float, height_rays: int | None = None) -> RayRender | None:
    """Differentiable render of rays o, d (N, 3) for one training step; None when nothing is hit.

    Triangles are found on the cached heights ``cache`` (ny*nx,) float32 with its ``bounds``; the height
    MLP then runs only on the hit triangles' vertices, and one exact Newton step per ray carries the
    gradient. With ``height_rays`` only the triangles of the first ``height_rays`` rays get fresh MLP
    heights (and height gradients); the others render on the cached heights and train colours and
    logits only (cheap: no MLP). The fresh triangles' heights feed the Laplacian term (a sample of the
    mesh edges E, weighted by how often views see them).
    """
    cells = find_hits(model.field(cache), o, d, max_dist, bounds=bounds)
    if cells.idx.numel() == 0:
        return None
    tri = model.flat_to_compact[cells.vertex_ids(model.grid.spec.nx)]
    fresh = tri if height_rays is None else tri[cells.idx < height_rays]
    need, inv = torch.unique(fresh.reshape(-1), return_inverse=True)
    h_need = model.heights(need)
    heights = cache.index_copy(0, model.vertex_flat_ids[need], h_need.float())
    hit = hits_to_rayhit(model.field(heights), o, d, cells)
    rows = cells.idx
    bary = hit.bary[rows]
    # sparse row gradients: only the vertices hit in this step are touched by the (lazy) optimizer
    rgb = (bary[..., None] * F.embedding(tri, model.rgb, sparse=True)).sum(1)
    sem = (bary[..., None] * F.embedding(tri, model.sem, sparse=True)).sum(1) if model.sem.shape[1] else None
    return RayRender(rows, tri, bary, hit.lam[rows], rgb, sem, h_need[inv].reshape(-1, 3))


class NonFiniteStepError(Exception):
    """A step whose losses or gradients were not finite; it was skipped (``what`` says which)."""

    def __init__(self, what: str):
        super().__init__(what)
        self.what = what


@dataclass
class Fit:
    """What an optimisation step works on: the model, its optimizer and all their parameters, the pose
    corrections (None without pose refinement), the training pixels, the config, and which losses apply.
    ``opt`` is None in a run without training epochs."""

    cfg: MeshConfig
    model: RoadMeshModel
    opt: MultiOptimizer | None
    params: list[torch.Tensor]
    poses: PoseCorrections | None
    pool: PixelPool
    use_sem: bool
    depth_on: bool


def train_step(fit: Fit, b: torch.Tensor, cache: torch.Tensor, bounds: SurfaceBounds, frac: float
               ) -> dict[str, float] | None:
    """One update on the training pixels ``b`` (B,) at ``frac`` of the run (learning-rate schedule).

    Returns the losses (``loss``, ``rgb``, ``sem``, ``depth``, ``smooth``) and the road pixels' summed squared
    colour error ``se`` over ``n`` pixels; None when no ray hits the mesh. Raises :class:`NonFiniteStepError`
    (after clearing the gradients) when the losses or gradients are not finite.
    """
    cfg, pool = fit.cfg, fit.pool
    if fit.depth_on and cfg.depth_first:
        # Measured depth is the strongest height signal: put those pixels first so that they fall
        # in the ``height_pixels_per_step`` rays whose triangles get fresh MLP heights and gradients.
        b = b[torch.sort((pool.depth[b] <= 0).to(torch.int8), stable=True).indices]
    T = corrected_poses(pool.T, None if fit.poses is None else fit.poses.view_delta(detach=False))
    o, d = view_rays(pool.K, T, pool.view[b], pool.uv[b])
    fw = forward_rays(fit.model, cache, bounds, o, d, cfg.max_dist, height_rays=cfg.height_pixels_per_step)
    if fw is None:
        return None
    gt = pool.rgb[b][fw.rows].float() / 255.0
    terms = _losses(fit, b, fw, d, gt)
    _update(fit, terms["loss"], frac)
    with torch.no_grad():
        road = pool.road[b][fw.rows]
        se = float(((fw.rgb.detach().clamp(0, 1) - gt) ** 2).mean(1)[road].sum())
    return {**{k: float(v.detach()) for k, v in terms.items()}, "se": se, "n": int(road.sum())}


def _losses(fit: Fit, b: torch.Tensor, fw: RayRender, d: torch.Tensor, gt: torch.Tensor) -> dict[str, torch.Tensor]:
    """The SPEC's loss terms of one batch and their weighted sum ``loss``."""
    cfg, pool, dev = fit.cfg, fit.pool, gt.device
    l_rgb = (fw.rgb - gt).abs().mean()
    loss = cfg.w_rgb * l_rgb
    l_sem = torch.zeros((), device=dev)
    if fit.use_sem and fit.model.sem.shape[1]:
        ch = pool.channel[b][fw.rows]
        lab = ch >= 0
        if lab.any():
            l_sem = F.cross_entropy(fw.sem[lab], ch[lab])
            loss = loss + cfg.w_sem * l_sem
    l_depth = torch.zeros((), device=dev)
    if fit.depth_on:
        dg = pool.depth[b][fw.rows]
        # A height field cannot stand up into a wall: a pixel whose measured depth is far from
        # the surface's (a facade, a pole) is an outlier, not a reason to bend the road.
        # The gate is in height units: the residual times the ray's vertical speed per unit depth
        # (a depth-relative gate dropped exactly the far road pixels whose heights were off most).
        dz = d[fw.rows, 2].detach().abs()
        m = (dg > 0) & ((fw.lam.detach() - dg).abs() * dz < cfg.depth_outlier_m)
        if m.any():
            l_depth = (fw.lam[m] - dg[m]).abs().mean()
            loss = loss + cfg.w_depth * l_depth
    l_smooth = ((fw.ht - fw.ht.roll(1, dims=1)) ** 2).mean()
    loss = loss + cfg.w_smooth * l_smooth
    return {"loss": loss, "rgb": l_rgb, "sem": l_sem, "depth": l_depth, "smooth": l_smooth}


def _update(fit: Fit, loss: torch.Tensor, frac: float) -> None:
    """Back-propagate ``loss`` and step the optimizer with the rates scheduled for ``frac`` of the run."""
    cfg, opt = fit.cfg, fit.opt
    opt.zero_grad(set_to_none=True)
    if not bool(torch.isfinite(loss)):
        opt.zero_grad(set_to_none=True)
        raise NonFiniteStepError("losses")
    loss.backward()
    # a sparse gradient's raw values are checked as they come: coalescing them here sorted them twice a step
    if not all(p.grad is None or torch.isfinite(p.grad._values() if p.grad.is_sparse else p.grad).all()
               for p in fit.params):
        opt.zero_grad(set_to_none=True)
        raise NonFiniteStepError("gradients")
    per_group = {"height": cfg.lr_height_decay_final ** frac}
    if frac < cfg.pose_warmup:
        # Poses stay put until the colours are fitted: a pose gradient through a still random
        # texture points nowhere, and Adam would move the poses by ~lr per step regardless.
        per_group.update(pose=0.0, pose_rot=0.0)
    opt.set_lr_factor(cfg.lr_decay_final ** frac, per_group)
    opt.step()
