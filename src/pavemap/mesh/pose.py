"""Per-view pose alignment to the baked road texture and the measured depth (Gauss-Newton, pure torch).

Why not only Adam (SPEC's joint refinement): a training step samples pixels from all views at once, so
each view's pose gradient comes from a few dozen pixels; Adam then moves every pose by ~lr per step in a
noisy direction and the refinement stalls near its start (docs/history: pose refinement). Here each
view is aligned on thousands of its own pixels by damped Gauss-Newton (direct image alignment, as in
photometric visual odometry): residuals are the pixel colour minus the baked texture where its ray meets
the surface, and, where LiDAR depth exists, the rendered minus the measured depth in height units. The
texture is re-baked on the new poses between iterations, so the views converge on their consensus.

Jacobians come from autograd without a per-view loop: every pixel gets its own copy of its view's
correction (N, 6), and a pixel's residual depends only on its own copy, so the gradient of the summed
residual channel ``c`` w.r.t. the copies is exactly the per-pixel Jacobian row of channel ``c``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from pavemap.geometry import HeightField, find_hits, hits_to_rayhit, pixel_rays, surface_bounds
from pavemap.geometry.heightfield import SurfaceBounds
from pavemap.mesh.bake import _gaussian_blur, bake_colours
from pavemap.mesh.data import PixelPool, ViewKey


def _so3_exp(w: torch.Tensor) -> torch.Tensor:
    """Rodrigues: rotation vectors (V, 3) -> (V, 3, 3), smooth at 0."""
    theta2 = (w * w).sum(-1, keepdim=True)
    theta = torch.sqrt(theta2 + 1e-12)
    a = torch.where(theta2 > 1e-8, torch.sin(theta) / theta, 1 - theta2 / 6)
    b = torch.where(theta2 > 1e-8, (1 - torch.cos(theta)) / (theta2 + 1e-12), 0.5 - theta2 / 24)
    z = torch.zeros_like(w[:, 0])
    Kx = torch.stack([z, -w[:, 2], w[:, 1], w[:, 2], z, -w[:, 0], -w[:, 1], w[:, 0], z], -1).reshape(-1, 3, 3)
    eye = torch.eye(3, dtype=w.dtype, device=w.device).expand_as(Kx)
    return eye + a[..., None] * Kx + b[..., None] * (Kx @ Kx)


def corrected_poses(T0: torch.Tensor, delta: torch.Tensor | None) -> torch.Tensor:
    """Apply per-view corrections delta (V, 6) = (rotation vector, translation) in the world frame:
    ``R = exp(w) R0``, ``t = t0 + tau``."""
    if delta is None:
        return T0
    R = _so3_exp(delta[:, :3]) @ T0[:, :3, :3]
    t = T0[:, :3, 3] + delta[:, 3:]
    top = torch.cat([R, t[:, :, None]], dim=2)
    bottom = T0[:, 3:, :]
    return torch.cat([top, bottom], dim=1)


def rig_corrections(delta: torch.Tensor, group: torch.Tensor, arm: torch.Tensor) -> torch.Tensor:
    """Per-view corrections (V, 6) from per-frame ones ``delta`` (G, 6): the cameras of a frame move as one
    rigid rig, rotating by ``w`` about the rig's centre and shifting by ``tau``. group: (V,) long frame of each
    view; arm: (V, 3) camera centre minus its rig's centre. For :func:`corrected_poses` that is
    ``w_v = w``, ``tau_v = tau + (exp(w) - I) arm_v``.
    """
    w, tau = delta[group, :3], delta[group, 3:]
    return torch.cat([w, tau + (_so3_exp(w) @ arm[..., None]).squeeze(-1) - arm], 1)


def rig_groups(keys: list[ViewKey], T: torch.Tensor, per: str) -> tuple[torch.Tensor, torch.Tensor, int]:
    """Group (V,) long, arm (V, 3) and the number of groups for corrections ``per`` "view" or "frame"
    (every camera of a frame shares one rigid correction: the error of an ego pose)."""
    V = len(keys)
    if per == "view":
        return torch.arange(V, device=T.device), torch.zeros(V, 3, dtype=T.dtype, device=T.device), V
    frames = sorted({k.frame for k in keys})
    index = {f: i for i, f in enumerate(frames)}
    group = torch.tensor([index[k.frame] for k in keys], dtype=torch.long, device=T.device)
    G = len(frames)
    centre = torch.zeros(G, 3, dtype=T.dtype, device=T.device).index_add_(0, group, T[:, :3, 3])
    centre = centre / torch.bincount(group, minlength=G).to(T.dtype)[:, None]
    return group, T[:, :3, 3] - centre[group], G


def interpolate_corrections(train_keys: list[ViewKey], delta: torch.Tensor, keys: list[ViewKey]) -> torch.Tensor:
    """(len(keys), 6) corrections for other views (held-out frames): linear in the frame index between the
    nearest training frames of the same camera, the nearest one's beyond the ends, 0 for an unknown camera.

    Pose errors of a driving log drift smoothly (odometry, time sync), so a held-out frame's error is close
    to its neighbours'; evaluating it on its raw pose would mix pose error into the held-out PSNR.
    """
    out = delta.new_zeros(len(keys), 6)
    by_cam: dict[str, list[tuple[int, int]]] = {}
    for i, k in enumerate(train_keys):
        by_cam.setdefault(k.camera, []).append((k.frame, i))
    for cam in by_cam:
        by_cam[cam].sort()
    for e, k in enumerate(keys):
        lst = by_cam.get(k.camera)
        if not lst:
            continue
        frames = [f for f, _ in lst]
        if k.frame <= frames[0]:
            out[e] = delta[lst[0][1]]
        elif k.frame >= frames[-1]:
            out[e] = delta[lst[-1][1]]
        else:
            hi = next(n for n, f in enumerate(frames) if f >= k.frame)
            (f0, i0), (f1, i1) = lst[hi - 1], lst[hi]
            a = (k.frame - f0) / max(f1 - f0, 1)
            out[e] = (1 - a) * delta[i0] + a * delta[i1]
    return out


def _skew(p: torch.Tensor) -> torch.Tensor:
    """(N, 3) -> (N, 3, 3) cross-product matrices."""
    z = torch.zeros_like(p[:, 0])
    return torch.stack([z, -p[:, 2], p[:, 1], p[:, 2], z, -p[:, 0], -p[:, 1], p[:, 0], z], -1).reshape(-1, 3, 3)


def remove_common_motion(delta: torch.Tensor, centres: torch.Tensor, length: float = 10.0) -> torch.Tensor:
    """Corrections (V, 6) minus the rigid motion of the whole rig that fits them best (least squares).

    Why: the texture and the surface are built from the same views, so moving every camera together by one
    rigid motion changes no residual (a gauge freedom), and the alignment may drift along it (errors
    grew on some seeds). Raw poses are right on average (GNSS / odometry), so the refined rig keeps
    their mean position and heading and only the views' errors relative to each other are corrected.
    A small rigid motion (omega, tau) about the centroid moves view v by w = omega, t = tau + omega x p_v;
    ``length`` (m) weighs rotation against translation. centres: (V, 3) raw camera centres.
    """
    p = (centres - centres.mean(0)).double()
    V = p.shape[0]
    eye = torch.eye(3, dtype=p.dtype, device=p.device).expand(V, 3, 3)
    A = torch.cat([torch.cat([length * eye, torch.zeros_like(eye)], 2), torch.cat([-_skew(p), eye], 2)], 1)
    b = torch.cat([length * delta[:, :3], delta[:, 3:]], 1).double()
    x = torch.linalg.lstsq(A.reshape(-1, 6), b.reshape(-1, 1)).solution.squeeze(1)
    omega, tau = x[:3], x[3:]
    motion = torch.cat([omega.expand(V, 3), tau + torch.cross(omega.expand(V, 3), p, dim=1)], 1)
    return (delta.double() - motion).to(delta.dtype)


def _sample_per_view(view: torch.Tensor, n_views: int, per_view: int, generator: torch.Generator) -> torch.Tensor:
    """Row indices (M,) of at most ``per_view`` random pixels of each view."""
    r = torch.rand(view.numel(), generator=generator).to(view.device)
    order = torch.argsort(view.double() + r.double())  # views in turn, random order inside each view
    v_sorted = view[order]
    start = torch.searchsorted(v_sorted, torch.arange(n_views, device=view.device))
    rank = torch.arange(view.numel(), device=view.device) - start[v_sorted]
    return order[rank < per_view]


def align_poses(surface: HeightField, pool: PixelPool, delta: torch.Tensor, max_dist: float, iters: int = 8,
                per_view: int = 1000, prior_sigma: tuple[float, float] = (0.3, 0.2), n_eff: float = 20.0,
                rgb_sigma: float = 0.05, depth_sigma: float = 0.03, depth_gate: float = 0.25,
                blur_cells: tuple[float, ...] = (4.0, 4.0, 2.0, 2.0, 1.0), fill_sigma: float = 1.0,
                gauge_length: float = 10.0, texture: torch.Tensor | None = None, bake_pixels: int = 300_000,
                group: torch.Tensor | None = None, arm: torch.Tensor | None = None,
                seed: int = 0) -> tuple[torch.Tensor, list[float]]:
    """Refine per-view corrections ``delta`` (V, 6) on a fixed surface; returns the new corrections and the
    weighted residual cost per iteration (mean per residual, before each step).

    surface: float32 dense heights (ny, nx) and bool crop. Each iteration bakes the texture on the current
    poses, blurred by ``blur_cells[it]`` cells (the last value repeats): coarse to fine, since the sharp
    0.1 m texture is linear only within a texel and 0.2 m errors are two texels; aligning to it sharp made
    the errors grow. Then one Gauss-Newton step per view on Huber-weighted residuals (:func:`_residuals`):
    colour (``rgb_sigma``) and, where measured, depth as a height (``depth_sigma`` m; residuals over
    ``depth_gate`` m are not ground and dropped).

    The MAP step has a Gaussian prior of ``prior_sigma`` (degrees, metres) on the correction, the accuracy
    of the raw poses, and the data of one view counts as ``n_eff`` independent residuals whatever the number
    of pixels: pixel residuals are model errors (texture below the grid's resolution), strongly correlated,
    and at face value thousands of them overruled any prior, so the views drifted together along modes the
    images barely see. ``texture`` (ny, nx, 3): align to this fixed texture instead of baking. With
    ``group``/``arm`` (see :func:`rig_groups`) ``delta`` is (G, 6), one rigid correction per frame
    (:func:`rig_corrections`).
    """
    dev = surface.heights.device
    V = len(pool.keys)
    G = delta.shape[0]
    if group is None or arm is None:
        group, arm = torch.arange(V, device=dev), torch.zeros(V, 3, device=dev)
    per_group_views = torch.bincount(group, minlength=G).double()
    centres = torch.zeros(G, 3, dtype=torch.float64, device=dev).index_add_(
        0, group, (pool.T[:, :3, 3] - arm).double()) / per_group_views.clamp_min(1)[:, None]
    gen = torch.Generator().manual_seed(seed)
    px = _Pixels.sample(pool, per_view, gen)
    bounds = surface_bounds(surface, pool.uv.dtype)
    prior_w = torch.tensor([math.radians(prior_sigma[0]) ** -2] * 3 + [prior_sigma[1] ** -2] * 3,
                           dtype=torch.float64, device=dev)
    # The texture is baked from a random subset of at most ``bake_pixels`` pixels: a full bake per iteration
    # cost more than the alignment itself, and the texture is blurred by a cell or more anyway.
    bake_pool = pool if len(pool) <= bake_pixels else pool.subset(
        torch.randperm(len(pool), generator=gen)[:bake_pixels].to(pool.view.device))
    delta = delta.detach().clone()
    costs: list[float] = []
    for it in range(iters):
        sigma = blur_cells[min(it, len(blur_cells) - 1)] if blur_cells else 0.0
        T = None if texture is not None else corrected_poses(pool.T, rig_corrections(delta, group, arm))
        tex = _texture(surface, bake_pool, T, max_dist, fill_sigma, sigma, texture)
        d_pix = delta[group[px.view]].clone().requires_grad_(True)  # each pixel's own copy of its group's correction
        out = _residuals(surface, bounds, px, tex, d_pix, arm[px.view], max_dist, rgb_sigma, depth_sigma, depth_gate)
        if out is None:
            break
        r, J, hr = out
        huber = torch.clamp(2.0 / r.abs().clamp_min(1e-9), max=1.0)  # Huber weights at 2 sigma
        costs.append(float((huber * r * r).sum() / max(1, r.numel())))
        step = _map_step(J, r, huber, group[px.view[hr]], delta, n_eff * per_group_views, prior_w)
        delta = delta + step.to(delta.dtype)
        if gauge_length > 0:
            delta = remove_common_motion(delta, centres.to(delta.dtype), gauge_length)
    return delta, costs


@dataclass
class _Pixels:
    """The pixels an alignment uses: view (N,) long, uv (N, 2), K (N, 3, 3) and raw pose T (N, 4, 4) of
    their views, colour gt (N, 3) in [0, 1], measured depth (N,) (0 unknown) or None."""

    view: torch.Tensor
    uv: torch.Tensor
    K: torch.Tensor
    T: torch.Tensor
    gt: torch.Tensor
    depth: torch.Tensor | None

    @classmethod
    def sample(cls, pool: PixelPool, per_view: int, generator: torch.Generator) -> _Pixels:
        rows = _sample_per_view(pool.view, len(pool.keys), per_view, generator)
        view = pool.view[rows]
        return cls(view, pool.uv[rows], pool.K[view], pool.T[view], pool.rgb[rows].float() / 255.0,
                   pool.depth[rows] if pool.depth is not None else None)


def _texture(surface: HeightField, pool: PixelPool, T: torch.Tensor | None, max_dist: float, fill_sigma: float,
             sigma: float, texture: torch.Tensor | None) -> torch.Tensor:
    """(ny*nx, 3) texture to align to: ``texture`` or the one baked from ``pool`` on poses T, blurred by
    ``sigma`` cells (normalised over the coloured vertices)."""
    if texture is not None:
        tex, coloured = texture, surface.valid
    else:
        tex, _, coloured = bake_colours(surface, pool, T, max_dist, fill_sigma)
    if sigma > 0:
        w = coloured.float()
        tex = (_gaussian_blur((tex * w[..., None]).permute(2, 0, 1), sigma)
               / _gaussian_blur(w[None], sigma).clamp_min(1e-6)).permute(1, 2, 0)
    return tex.reshape(-1, 3)


def _residuals(surface: HeightField, bounds: SurfaceBounds, px: _Pixels, tex: torch.Tensor, d_pix: torch.Tensor,
               arm: torch.Tensor, max_dist: float, rgb_sigma: float, depth_sigma: float, depth_gate: float
               ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None:
    """Whitened residuals r (M, C) of the pixels whose rays hit the surface, their Jacobians J (M, C, 6)
    w.r.t. the pixels' own corrections ``d_pix`` (N, 6) and the hit rows (M,); None when nothing hits.
    arm: (N, 3) each pixel's camera centre minus its rig's centre."""
    rows = torch.arange(px.view.numel(), device=d_pix.device)
    o, d = pixel_rays(px.K, corrected_poses(px.T, rig_corrections(d_pix, rows, arm)), px.uv)
    cells = find_hits(surface, o, d, max_dist, bounds=bounds)
    if cells.idx.numel() == 0:
        return None
    hit = hits_to_rayhit(surface, o, d, cells)
    hr = cells.idx
    col = (hit.bary[hr][..., None] * tex[cells.vertex_ids(surface.nx)]).sum(1)
    res_list = [(col - px.gt[hr]) / rgb_sigma]
    if px.depth is not None:
        dm = px.depth[hr]
        r_d = (hit.lam[hr] - dm) * d[hr, 2].detach().abs()
        has = (dm > 0) & (r_d.detach().abs() < depth_gate)
        res_list.append((torch.where(has, r_d, torch.zeros_like(r_d)) / depth_sigma)[:, None])
    r = torch.cat(res_list, 1)
    J = torch.stack([torch.autograd.grad(r[:, c].sum(), d_pix, retain_graph=c < r.shape[1] - 1)[0][hr]
                     for c in range(r.shape[1])], 1)
    return r.detach(), J, hr


def _map_step(J: torch.Tensor, r: torch.Tensor, huber: torch.Tensor, vw: torch.Tensor, delta: torch.Tensor,
              n_eff_views: torch.Tensor, prior_w: torch.Tensor) -> torch.Tensor:
    """(G, 6) damped Gauss-Newton (MAP) step of every group from residuals r (M, C), Jacobians J (M, C, 6),
    Huber weights (M, C) and each residual's group vw (M,). A group's data count as ``n_eff_views`` (G,)
    residuals; prior_w (6,) the prior's inverse variances around 0."""
    G = delta.shape[0]
    dev = delta.device
    n_res = torch.bincount(vw, minlength=G).double() * r.shape[1]
    scale = (n_eff_views / n_res.clamp_min(1.0))[:, None]
    H = torch.zeros(G, 6, 6, dtype=torch.float64, device=dev)
    g = torch.zeros(G, 6, dtype=torch.float64, device=dev)
    Jw = (J * huber[..., None]).double()
    H.index_add_(0, vw, torch.einsum("mci,mcj->mij", Jw, J.double()))
    g.index_add_(0, vw, torch.einsum("mci,mc->mi", Jw, r.double()))
    H = H * scale[..., None] + torch.diag_embed(prior_w.expand(G, 6))
    g = g * scale + prior_w * delta.double()
    return -torch.linalg.solve(H, g.unsqueeze(-1)).squeeze(-1)


class PoseCorrections:
    """The learnable pose corrections of the training views (pose refinement, SPEC §1).

    One rigid correction per group (a frame's rig with ``pose_per: frame``, else a view; see
    :func:`rig_groups`): rotation ``w`` (G, 3) rad and translation ``t`` (G, 3) m as separate parameters in
    their own Adam groups, because Adam moves each by ~lr per step whatever the gradient's scale, and
    1 mrad at the ~5-20 m where the ground is seen shifts the image as much as 5-20 mm of translation
    (see MeshConfig.lr_pose_rot). group: (V,) long; arm: (V, 3).
    """

    def __init__(self, group: torch.Tensor, arm: torch.Tensor, n_groups: int, device: torch.device):
        self.group, self.arm = group, arm
        self.w = torch.nn.Parameter(torch.zeros(n_groups, 3, device=device))
        self.t = torch.nn.Parameter(torch.zeros(n_groups, 3, device=device))

    def delta(self) -> torch.Tensor:
        """(G, 6) detached per-group corrections (rotation vector, translation)."""
        return torch.cat([self.w, self.t], 1).detach()

    def set(self, delta: torch.Tensor) -> None:
        """Overwrite the corrections with ``delta`` (G, 6)."""
        self.w.data.copy_(delta[:, :3].to(self.w.device))
        self.t.data.copy_(delta[:, 3:].to(self.t.device))

    def view_delta(self, detach: bool = True) -> torch.Tensor:
        """(V, 6) corrections of the training views (from the per-frame ones with ``pose_per: frame``)."""
        d = rig_corrections(torch.cat([self.w, self.t], 1), self.group, self.arm)
        return d.detach() if detach else d
