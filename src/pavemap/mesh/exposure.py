"""Per-view exposure: a gain and an offset between the texture's reference brightness and each view.

Real cameras change exposure along a drive (auto-exposure, and the sun behind a tree): on the real KITTI
sample the road's mean grey level goes 0.60 -> 0.25 -> 0.42 over 51 frames. A texture averaged over such
views is right for none of them. Each view ``v`` is modelled as ``I = a_v c + b_v`` (one gain and offset for
all channels; c the texture's colour), fitted in closed form by ridge least squares towards (1, 0), and the
bake averages the compensated colours ``(I - b_v) / a_v``. Held-out views get the (a, b) of their camera's
training views interpolated in time: nothing of a held-out view enters its own exposure.

Tensors: exposure (V, 2) float64, columns gain and offset, one row per view of a pool.
"""

from __future__ import annotations

import numpy as np
import torch

from pavemap.mesh.data import ViewKey

# Pseudo-pixels of the prior (a, b) = (1, 0): a view with a few hundred road pixels keeps nearly its prior.
PRIOR_PIXELS = 200.0
GAIN_RANGE = (0.25, 4.0)  # a fitted gain outside this is a failed fit, not an exposure
OFFSET_RANGE = (-0.5, 0.5)  # ... and an offset of half the colour range (images in [0, 1])


def identity(n_views: int, device: torch.device | None = None) -> torch.Tensor:
    """(V, 2) float64: gain 1, offset 0."""
    out = torch.zeros(n_views, 2, dtype=torch.float64, device=device)
    out[:, 0] = 1.0
    return out


def apply(rgb: torch.Tensor, exposure: torch.Tensor | None, view: torch.Tensor) -> torch.Tensor:
    """Texture colours rgb (M, 3) as the views ``view`` (M,) long see them: ``a rgb + b``."""
    if exposure is None:
        return rgb
    e = exposure.to(rgb.dtype)[view]
    return e[:, :1] * rgb + e[:, 1:]


def compensate(obs: torch.Tensor, exposure: torch.Tensor | None, view: torch.Tensor) -> torch.Tensor:
    """Observed colours obs (M, 3) in the texture's reference: ``(obs - b) / a``."""
    if exposure is None:
        return obs
    e = exposure.to(obs.dtype)[view]
    return (obs - e[:, 1:]) / e[:, :1]


def fit(view: torch.Tensor, pred: torch.Tensor, obs: torch.Tensor, n_views: int,
        prior_pixels: float = PRIOR_PIXELS) -> torch.Tensor:
    """(V, 2) the ridge least-squares (a_v, b_v) of ``obs ~ a pred + b`` per view.

    view (M,) long; pred, obs (M, 3) float64 (the texture where each pixel lands, and the pixel). The prior
    (1, 0) weighs ``prior_pixels`` pixels at the pool's mean level and spread; views without pixels keep it.
    The result is normalised (:func:`normalise`)."""
    x, y = pred.reshape(-1), obs.reshape(-1)
    v = view.repeat_interleave(pred.shape[1])
    s = torch.zeros(n_views, 5, dtype=torch.float64, device=pred.device)
    s.index_add_(0, v, torch.stack([torch.ones_like(x), x, x * x, y, x * y], 1))
    n, sx, sxx, sy, sxy = s.unbind(1)
    mean, var = float(x.mean()), float(x.var()) if x.numel() > 1 else 1.0
    lam = prior_pixels * 3
    # prior pseudo-data: lam pixels at mean +- sqrt(var) observed as exactly themselves (a = 1, b = 0)
    n, sx, sy = n + lam, sx + lam * mean, sy + lam * mean
    sxx, sxy = sxx + lam * (mean ** 2 + var), sxy + lam * (mean ** 2 + var)
    det = n * sxx - sx * sx
    a = (n * sxy - sx * sy) / det
    b = (sy - a * sx) / n
    out = torch.stack([a, b], 1)
    bad = (~torch.isfinite(out).all(1) | (a < GAIN_RANGE[0]) | (a > GAIN_RANGE[1]) | (b < OFFSET_RANGE[0])
           | (b > OFFSET_RANGE[1]))
    out[bad] = identity(1, out.device)
    return normalise(out, s[:, 0])


def normalise(exposure: torch.Tensor, weight: torch.Tensor) -> torch.Tensor:
    """Fix the gauge: texture and exposures trade ``c -> alpha c + beta``; choose the weighted mean gain 1
    and mean offset 0 so that the texture sits at the drive's average exposure."""
    w = weight.to(exposure.dtype).clamp_min(0)
    if float(w.sum()) <= 0:
        return exposure
    a_mean = float((w * exposure[:, 0]).sum() / w.sum())
    b_mean = float((w * exposure[:, 1]).sum() / w.sum())
    a = exposure[:, 0] / a_mean
    b = exposure[:, 1] - exposure[:, 0] * b_mean / a_mean
    return torch.stack([a, b], 1)


def interpolate(train_keys: list[ViewKey], exposure: torch.Tensor, keys: list[ViewKey]) -> torch.Tensor:
    """(len(keys), 2): each view's exposure linearly interpolated in frame index between the training views
    of its camera (held constant past the ends); identity for a camera without training views."""
    out = identity(len(keys), exposure.device)
    e = exposure.detach().cpu().numpy()
    for cam in {k.camera for k in keys}:
        rows = [i for i, k in enumerate(train_keys) if k.camera == cam]
        if not rows:
            continue
        frames = np.array([train_keys[i].frame for i in rows], np.float64)
        order = np.argsort(frames)
        at = [i for i, k in enumerate(keys) if k.camera == cam]
        fq = np.array([keys[i].frame for i in at], np.float64)
        for c in range(2):
            vals = np.interp(fq, frames[order], e[rows][order, c])
            out[at, c] = torch.as_tensor(vals, dtype=out.dtype, device=out.device)
    return out


def summary(exposure: torch.Tensor | None) -> dict | None:
    """The spread of the fitted exposures for metrics.json (None when not fitted)."""
    if exposure is None:
        return None
    a, b = exposure[:, 0].cpu().numpy(), exposure[:, 1].cpu().numpy()
    return {"gain_min": round(float(a.min()), 4), "gain_max": round(float(a.max()), 4),
            "offset_min": round(float(b.min()), 4), "offset_max": round(float(b.max()), 4)}
