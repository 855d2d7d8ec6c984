"""Where the closed form's height error lies (issue 47, ``refine_bench.py --parts error_parts``).

Over the observed vertices of the closed-form surface of a bench drive (no depth), the error against the truth
split three ways: near a height step of the truth (a kerb: the truth's max - min within 0.3 m above a threshold)
and away from one; by distance from the drive's path; and by spatial scale (the error smoothed by a Gaussian of
sigma 0.5-4 m, a normalised convolution over the observed vertices, and what is left). A refinement that moves
the surface by offsets on cells of a given size can remove at most the smoothed part at that size.
"""

from __future__ import annotations

import numpy as np

STEPS_M = (0.03, 0.05, 0.10)
SIGMAS_M = (0.5, 1.0, 2.0, 4.0)
BANDS_M = ((0, 2), (2, 4), (4, 6), (6, 10), (10, 1000))


def _rms(a: np.ndarray) -> float:
    return round(float(np.sqrt((a ** 2).mean())), 4) if a.size else None


def error_parts(mesh, seq) -> dict:  # noqa: ANN001
    """The split above for ``mesh`` (a stage-1 result with ``observed``) on ``seq`` (with a truth height)."""
    from scipy import ndimage
    from scipy.spatial import cKDTree

    from pavemap.io.truth import read_truth_height

    s, truth = mesh.surface, read_truth_height(seq.root)
    h = s.heights.double().cpu().numpy()
    xy = s.grid_xy().double().cpu().reshape(-1, 2)
    z, inside = truth.height_at(xy)
    z, inside = z.numpy().reshape(h.shape), inside.numpy().reshape(h.shape)
    mask = s.valid.cpu().numpy() & mesh.observed.cpu().numpy() & inside
    err = np.where(mask, h - z, 0.0)
    total = float((err[mask] ** 2).sum())
    r = max(1, round(0.3 / s.res))
    zmax = ndimage.maximum_filter(np.where(inside, z, -1e9), size=2 * r + 1)
    zmin = ndimage.minimum_filter(np.where(inside, z, 1e9), size=2 * r + 1)
    step = zmax - zmin
    out: dict = {"vertices": int(mask.sum()), "grid_m": s.res, "bias_m": round(float(err[mask].mean()), 4),
                 "rmse_m": _rms(err[mask]), "near_truth_step": [], "by_path_distance": [], "by_scale": []}
    for thr in STEPS_M:
        k = mask & (step > thr)
        out["near_truth_step"].append({"step_above_m": thr, "vertex_share": round(float(k.sum() / mask.sum()), 4),
                                       "squared_error_share": round(float((err[k] ** 2).sum()) / total, 4),
                                       "rmse_there_m": _rms(err[k]), "rmse_elsewhere_m": _rms(err[mask & ~k])})
    centres = np.array([v.T_world_cam[:3, 3] for f in seq.frames for v in f.views.values()])
    d = cKDTree(centres[:, :2]).query(xy.numpy())[0].reshape(h.shape)
    for a, b in BANDS_M:
        k = mask & (d >= a) & (d < b)
        if k.any():
            out["by_path_distance"].append({
                "from_m": a, "to_m": b, "vertex_share": round(float(k.sum() / mask.sum()), 4),
                "bias_m": round(float(err[k].mean()), 4), "rmse_m": _rms(err[k]),
                "squared_error_share": round(float((err[k] ** 2).sum()) / total, 4)})
    w = mask.astype(float)
    for sig in SIGMAS_M:
        px = sig / s.res
        low = ndimage.gaussian_filter(err, px) / np.maximum(ndimage.gaussian_filter(w, px), 1e-9)
        out["by_scale"].append({"sigma_m": sig, "smoothed_rmse_m": _rms(low[mask]),
                                "left_rmse_m": _rms((err - low)[mask])})
    return out
