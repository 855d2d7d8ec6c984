"""Photometric refinement of the stage-1 surface by multi-view consistency (issue 47; docs/refine.md).

Why not the training loss: a colour loss against a baked texture cannot see a wrong height, because the bake
averages every view's colours onto whatever surface there is (bench/refine_diag.py: the colour term's height
gradient falls 10-40x after a re-bake and its sign is noise). Here a surface point is projected into the
several training views that see it and the views are compared with each other: at the true height they agree,
at a wrong one each view samples a different patch of road (a view 6 m away and one 15 m away land ~0.6 m apart
on the road for a 10 cm error).

The images are the training pool's pixels at ``render_scale`` (masked classes, the bonnet and the sky are
holes; the road class only, see :func:`pool_images`), in log colour (a view's exposure gain and white balance
become a constant, fitted per view and removed) and blurred by ``sigma`` px (the blur widens the basin of the
coarse levels). The heights are ``z = z0 + B delta`` with B a global offset and tilt first, then bilinear
control grids; each level takes Gauss-Newton steps on the robustly weighted sum of squared differences of
each view's sample from the point's mean over its views (:mod:`pavemap.mesh.refine_solve`).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch.nn import functional as F  # noqa: N812

from pavemap.mesh.data import PixelPool

# Each view's exposure gain and white balance, constants in log colour, are removed as per-view offsets fitted to
# the points it shares with the other views (:func:`_view_offsets`). A band-pass (blur minus a 6 px blur) removed
# them too, but biased the height by +4..+5 cm on the kitti-like bench drive: the same road point sits at
# different image rows in different views, and foreshortening changes what a fixed image-space window averages.
SIGMA_LOW = 0.0  # px: a band-pass's low cut (0: none)
VIEW_OFFSETS = True
EPS_LOG = 0.02  # log(rgb + eps): dark pixels' noise stays bounded
# A point is compared only in the views whose pixel covers at most this many times the road length (sqrt of the
# area) of its sharpest view's pixel. An image-space window (the pixel, the bilinear weights, the blur) averages
# more road on its far side than on its near one, so a view shows each road point's colour slightly farther from
# itself than it is, by a shift that grows with the footprint; views of very different footprints then agree
# best below the true surface. On the nuScenes-like bench drive (pixels of 0.3 m median, 1.4 m at the 90th
# percentile) all views within reach asked -1.25 cm of the true surface, these -0.3 cm (docs/refine.md).
FOOTPRINT_RATIO = 3.0


@dataclass
class ViewStack:
    """Filtered images of the training views: img (C, V*H*W) float32 flat, ok (V*H*W,) bool usable pixels,
    P (V, 3, 4) world-to-pixel projections, centres (V, 3), H, W."""

    img: torch.Tensor
    ok: torch.Tensor
    P: torch.Tensor
    centres: torch.Tensor
    H: int
    W: int


def pool_images(pool: PixelPool, road_only: bool = True) -> tuple[torch.Tensor, torch.Tensor]:
    """The pool's pixels as images: rgb (V, 3, H, W) float32 in [0, 1] and mask (V, H, W) bool, H, W the
    largest pixel row / column + 1 (smaller cameras are padded with masked pixels). ``road_only``: the mask
    keeps the road-class pixels only: off the road the views see trees, poles and facades standing on the
    ground that the height field holds, and their colours agree at no height of it."""
    uv = pool.uv.round().long()
    W, H = int(uv[:, 0].max()) + 1, int(uv[:, 1].max()) + 1
    V = len(pool.keys)
    flat = pool.view * (H * W) + uv[:, 1].clamp(0, H - 1) * W + uv[:, 0].clamp(0, W - 1)
    rgb = torch.zeros(3, V * H * W, device=pool.uv.device)
    rgb[:, flat] = pool.rgb.float().T / 255.0
    mask = torch.zeros(V * H * W, dtype=torch.bool, device=pool.uv.device)
    mask[flat] = pool.road if road_only else True
    return rgb.reshape(3, V, H, W).permute(1, 0, 2, 3).contiguous(), mask.reshape(V, H, W)


def _blur(x: torch.Tensor, m: torch.Tensor, sigma: float) -> torch.Tensor:
    """Normalised-convolution Gaussian blur of x (V, C, H, W) over the pixels m (V, 1, H, W) float."""
    if sigma <= 0.25:
        return x
    r = max(1, int(3 * sigma))
    k = torch.exp(-0.5 * (torch.arange(-r, r + 1, device=x.device, dtype=x.dtype) / sigma) ** 2)
    k = k / k.sum()
    both = torch.cat([x * m, m], 1)
    c = both.shape[1]
    both = F.conv2d(F.pad(both, (r, r, 0, 0), mode="replicate"), k.view(1, 1, 1, -1).expand(c, 1, 1, -1), groups=c)
    both = F.conv2d(F.pad(both, (0, 0, r, r), mode="replicate"), k.view(1, 1, -1, 1).expand(c, 1, -1, 1), groups=c)
    return both[:, :-1] / both[:, -1:].clamp(min=1e-6)


def view_stack(rgb: torch.Tensor, mask: torch.Tensor, K: torch.Tensor, T: torch.Tensor, sigma: float) -> ViewStack:
    """Blurred log images (``sigma`` px; a band-pass with :data:`SIGMA_LOW` > 0) of rgb (V, 3, H, W), mask
    (V, H, W), seen by intrinsics K (V, 3, 3) from camera-to-world poses T (V, 4, 4)."""
    V, C, H, W = rgb.shape
    m = mask[:, None].float()
    log = torch.log(rgb + EPS_LOG)
    band = _blur(log, m, sigma) if SIGMA_LOW <= 0 else _blur(log, m, sigma) - _blur(log, m, SIGMA_LOW)
    R, t = T[:, :3, :3].float(), T[:, :3, 3].float()
    Rc = R.transpose(1, 2)
    P = K.float() @ torch.cat([Rc, -(Rc @ t[:, :, None])], 2)
    img = band.permute(1, 0, 2, 3).reshape(C, -1).contiguous()
    return ViewStack(img, mask.reshape(-1), P, t, H, W)


def project(P: torch.Tensor, xy: torch.Tensor, z: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Points (N, 2) xy and (N,) z through per-pair projections P (N, 3, 4) -> uv (N, 2), duv/dz (N, 2) and the
    camera depth (N,)."""
    X = torch.cat([xy, z[:, None], torch.ones_like(z)[:, None]], 1)
    p = (P @ X[:, :, None]).squeeze(2)
    dp = P[:, :, 2]
    w = p[:, 2:3]
    uv = p[:, :2] / w
    duv = (dp[:, :2] * w - p[:, :2] * dp[:, 2:3]) / (w * w)
    return uv, duv, w.squeeze(1)


def sample(st: ViewStack, view: torch.Tensor, uv: torch.Tensor
           ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Bilinear samples of the views ``view`` (N,) at uv (N, 2): values (N, C) (differentiable w.r.t. uv),
    their derivatives d/du, d/dv (N, 2, C), and ok (N,) where all four pixels are usable and in the image."""
    H, W = st.H, st.W
    x0f, y0f = uv[:, 0].floor(), uv[:, 1].floor()
    inside = (x0f >= 0) & (y0f >= 0) & (x0f <= W - 2) & (y0f <= H - 2)
    x0 = x0f.clamp(0, W - 2).long()
    y0 = y0f.clamp(0, H - 2).long()
    ax, ay = (uv[:, 0] - x0).clamp(0, 1)[:, None], (uv[:, 1] - y0).clamp(0, 1)[:, None]
    i00 = view * (H * W) + y0 * W + x0
    idx = torch.stack([i00, i00 + 1, i00 + W, i00 + W + 1])
    f = st.img[:, idx.reshape(-1)].reshape(-1, 4, idx.shape[1]).permute(1, 2, 0)  # (4, N, C)
    ok = inside & st.ok[idx].all(0)
    val = (1 - ay) * ((1 - ax) * f[0] + ax * f[1]) + ay * ((1 - ax) * f[2] + ax * f[3])
    ax, ay = ax.detach(), ay.detach()
    fu = (1 - ay) * (f[1] - f[0]) + ay * (f[3] - f[2])
    fv = (1 - ax) * (f[2] - f[0]) + ax * (f[3] - f[1])
    return val, torch.stack([fu, fv], 1), ok


def footprints(P: torch.Tensor, w: torch.Tensor, z: torch.Tensor) -> torch.Tensor:
    """(Np, V) the road length (m, the square root of the area) that one pixel covers on the horizontal plane
    at each point's height z (Np,), seen through the projections P (V, 3, 4) at camera depths w (Np, V).

    The plane z = const maps to the image by the homography H = [P0, P1, z P2 + P3] (P's columns), whose
    Jacobian determinant at a point of depth w is det(H) / w^3; det(H) is linear in z."""
    a = torch.linalg.det(torch.stack([P[:, :, 0], P[:, :, 1], P[:, :, 3]], 2))
    b = torch.linalg.det(torch.stack([P[:, :, 0], P[:, :, 1], P[:, :, 2]], 2))
    return (w.abs() ** 3 / (a[None] + z[:, None] * b[None]).abs().clamp(min=1e-12)).sqrt()


@torch.no_grad()
def find_pairs(st: ViewStack, xy: torch.Tensor, z: torch.Tensor, max_dist: float, max_views: int,
               chunk: int = 8192, footprint_ratio: float = FOOTPRINT_RATIO) -> tuple[torch.Tensor, torch.Tensor]:
    """The (point, view) pairs to compare: for each point xy (P, 2), z (P,) the ``max_views`` nearest views
    (within ``max_dist`` m) in whose usable pixels it lands and whose pixel covers at most ``footprint_ratio``
    times the road length of its sharpest such view's (0: any). Returns point (N,) and view (N,) long, grouped
    by point; points seen by fewer than two views are left out."""
    pts, views = [], []
    V = st.P.shape[0]
    for s in range(0, xy.shape[0], chunk):
        X = torch.cat([xy[s:s + chunk], z[s:s + chunk, None], torch.ones_like(z[s:s + chunk, None])], 1)
        p = torch.einsum("vij,pj->pvi", st.P, X)  # (p, V, 3)
        w = p[..., 2]
        uv = p[..., :2] / w.clamp(min=1e-6)[..., None]
        dist = (X[:, None, :3] - st.centres[None]).norm(dim=2)
        n = X.shape[0]
        vv = torch.arange(V, device=xy.device).expand(n, V)
        _, _, ok = sample(st, vv.reshape(-1), uv.reshape(-1, 2))
        ok = ok.reshape(n, V) & (w > 0.5) & (dist < max_dist)
        if footprint_ratio > 0:
            fp = torch.where(ok, footprints(st.P, w, z[s:s + chunk]), torch.full_like(dist, float("inf")))
            ok &= fp <= footprint_ratio * fp.min(1, keepdim=True).values
        dist = torch.where(ok, dist, torch.full_like(dist, float("inf")))
        k = min(max_views, V)
        d_k, v_k = dist.topk(k, dim=1, largest=False)
        keep = torch.isfinite(d_k)
        keep &= keep.sum(1, keepdim=True) >= 2
        pts.append((torch.arange(n, device=xy.device) + s)[:, None].expand(n, k)[keep])
        views.append(v_k[keep])
    return torch.cat(pts), torch.cat(views)


@dataclass
class Residuals:
    """Per pair (N,): r (N, C) the sample minus its point's weighted mean, J (N, C) dr/dz of the point's
    height, w (N,) the robust weights (0 where the sample is unusable)."""

    r: torch.Tensor
    J: torch.Tensor
    w: torch.Tensor


def residuals(st: ViewStack, pt: torch.Tensor, view: torch.Tensor, xy: torch.Tensor, z: torch.Tensor,
              n_points: int, huber: float = 1.5) -> Residuals:
    """The consistency residuals of points xy (P, 2), z (P,) over the pairs ``pt``, ``view`` (N,), with
    analytic height derivatives and Huber weights at ``huber`` x the median absolute residual. The views'
    log-colour offsets (:func:`_view_offsets`) are removed first and held fixed in the derivative."""
    uv, duv, _ = project(st.P[view], xy[pt], z[pt])
    val, grad, ok = sample(st, view, uv)
    J = (grad * duv[:, :, None]).sum(1)  # (N, C)
    if VIEW_OFFSETS:
        val = val - _view_offsets(val.detach(), pt, view, ok, n_points, st.P.shape[0])[view]
    w = ok.float()
    for k in range(3):  # the mean, then Huber weights around it, then the mean with those weights
        ws = torch.zeros(n_points, device=z.device).index_add_(0, pt, w).clamp(min=1e-9)
        mean = torch.zeros(n_points, val.shape[1], device=z.device).index_add_(0, pt, w[:, None] * val) / ws[:, None]
        jm = torch.zeros(n_points, J.shape[1], device=z.device).index_add_(0, pt, w[:, None] * J) / ws[:, None]
        r = val - mean[pt]
        if k == 2:
            break
        a = r.norm(dim=1)
        scale = huber * a[ok].median().clamp(min=1e-6) if ok.any() else torch.ones((), device=z.device)
        w = ok.float() * torch.where(a <= scale, torch.ones_like(a), scale / a.clamp(min=1e-9))
    return Residuals(r, J - jm[pt], w)


def _view_offsets(val: torch.Tensor, pt: torch.Tensor, view: torch.Tensor, ok: torch.Tensor, n_points: int,
                  n_views: int) -> torch.Tensor:
    """(V, C) each view's mean difference from the other views at the points they share: its exposure and white
    balance in log colour (constant over the view), which the comparison must not count as a height error."""
    w = ok.float()
    ws = torch.zeros(n_points, device=val.device).index_add_(0, pt, w).clamp(min=1e-9)
    mean = torch.zeros(n_points, val.shape[1], device=val.device).index_add_(0, pt, w[:, None] * val) / ws[:, None]
    d = val - mean[pt]
    wv = torch.zeros(n_views, device=val.device).index_add_(0, view, w).clamp(min=1e-9)
    return torch.zeros(n_views, val.shape[1], device=val.device).index_add_(0, view, w[:, None] * d) / wv[:, None]


def consistency_loss(st: ViewStack, pt: torch.Tensor, view: torch.Tensor, xy: torch.Tensor, z: torch.Tensor,
                     w: torch.Tensor) -> torch.Tensor:
    """The reference loss, differentiable w.r.t. z (P,) by autograd: sum over pairs of w (N,) x the squared
    difference of the sample from its point's w-weighted mean (what :func:`residuals` linearises)."""
    uv, _, _ = project(st.P[view], xy[pt], z[pt])
    val, _, ok = sample(st, view, uv)
    n = z.shape[0]
    if VIEW_OFFSETS:
        val = val - _view_offsets(val.detach(), pt, view, ok, n, st.P.shape[0])[view]
    ws = torch.zeros(n, device=z.device).index_add(0, pt, w).clamp(min=1e-9)
    mean = torch.zeros(n, val.shape[1], device=z.device).index_add(0, pt, w[:, None] * val) / ws[:, None]
    return (w[:, None] * (val - mean[pt]) ** 2).sum()
