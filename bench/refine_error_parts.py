"""Where the closed form's height error lies (issue 47, ``refine_bench.py --parts error_parts``).

Over the observed vertices of the closed-form surface of a bench drive (no depth), the error against the truth
split three ways: near a height step of the truth (a kerb: the truth's max - min within 0.3 m above a threshold)
and away from one; by distance from the drive's path; and by spatial scale (the error smoothed by a Gaussian of
sigma 0.5-4 m, a normalised convolution over the observed vertices, and what is left). A refinement that moves
the surface by offsets on cells of a given size can remove at most the smoothed part at that size. At the kerbs
(truth step > 10 cm) the error is split again by the side of the step (the road's lower side, the higher
sidewalk side) and by the distance from the step's other side (0.1 / 0.2 / 0.3 m rings).

:func:`truth_sides` reruns the closed form with the kerb refit's road / off-road vertex sides replaced by the
truth's at the kerbs: what a perfect placement of the step would give.
"""

from __future__ import annotations

import json

import numpy as np

STEPS_M = (0.03, 0.05, 0.10)
KERB_M = 0.10
RINGS_M = (0.1, 0.2, 0.3)
SIGMAS_M = (0.5, 1.0, 2.0, 4.0)
BANDS_M = ((0, 2), (2, 4), (4, 6), (6, 10), (10, 1000))


def _rms(a: np.ndarray) -> float:
    return round(float(np.sqrt((a ** 2).mean())), 4) if a.size else None


def _truth_window(truth, xy, shape: tuple[int, int], res: float) -> tuple[np.ndarray, ...]:  # noqa: ANN001
    """The truth's height ``z`` and ``inside`` at the grid points ``xy`` (ny * nx, 2) float64 tensor, and its max
    and min over the square of +-0.3 m around each, each (ny, nx): where a kerb is and which side is lower."""
    from scipy import ndimage

    z, inside = truth.height_at(xy)
    z, inside = z.numpy().reshape(shape), inside.numpy().reshape(shape)
    r = max(1, round(0.3 / res))
    zmax = ndimage.maximum_filter(np.where(inside, z, -1e9), size=2 * r + 1)
    zmin = ndimage.minimum_filter(np.where(inside, z, 1e9), size=2 * r + 1)
    return z, inside, zmax, zmin


def error_parts(mesh, seq) -> dict:  # noqa: ANN001
    """The split above for ``mesh`` (a stage-1 result with ``observed``) on ``seq`` (with a truth height)."""
    from scipy import ndimage
    from scipy.spatial import cKDTree

    from pavemap.io.truth import read_truth_height

    s, truth = mesh.surface, read_truth_height(seq.root)
    h = s.heights.double().cpu().numpy()
    xy = s.grid_xy().double().cpu().reshape(-1, 2)
    z, inside, zmax, zmin = _truth_window(truth, xy, h.shape, s.res)
    mask = s.valid.cpu().numpy() & mesh.observed.cpu().numpy() & inside
    err = np.where(mask, h - z, 0.0)
    total = float((err[mask] ** 2).sum())
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
    out["kerb_sides"] = _kerb_sides(err, mask, z, zmax, zmin, s.res, total)
    w = mask.astype(float)
    for sig in SIGMAS_M:
        px = sig / s.res
        low = ndimage.gaussian_filter(err, px) / np.maximum(ndimage.gaussian_filter(w, px), 1e-9)
        out["by_scale"].append({"sigma_m": sig, "smoothed_rmse_m": _rms(low[mask]),
                                "left_rmse_m": _rms((err - low)[mask])})
    return out


def _part(err: np.ndarray, k: np.ndarray, mask: np.ndarray, total: float) -> dict:
    bias = round(float(err[k].mean()), 4) if k.any() else None
    return {"vertex_share": round(float(k.sum() / mask.sum()), 4), "bias_m": bias, "rmse_m": _rms(err[k]),
            "squared_error_share": round(float((err[k] ** 2).sum()) / total, 4)}


def _kerb_sides(err: np.ndarray, mask: np.ndarray, z: np.ndarray, zmax: np.ndarray, zmin: np.ndarray, res: float,
                total: float) -> dict:
    """The kerb vertices' error by side of the step: lower (the road) and higher (the sidewalk), and per ring of
    vertices 0-0.1, 0.1-0.2, 0.2-0.3 m from the nearest vertex of the other side."""
    from scipy import ndimage

    kerb = mask & (zmax - zmin > KERB_M)
    low = kerb & (z < 0.5 * (zmax + zmin))
    high = kerb & ~low
    to_high = ndimage.distance_transform_edt(~high) * res
    to_low = ndimage.distance_transform_edt(~low) * res
    rings = []
    for d in RINGS_M:
        ring_low = low & (to_high > d - 0.1 + 1e-6) & (to_high <= d + 1e-6)
        ring_high = high & (to_low > d - 0.1 + 1e-6) & (to_low <= d + 1e-6)
        rings.append({"to_m": d, "low": _part(err, ring_low, mask, total), "high": _part(err, ring_high, mask, total)})
    return {"step_above_m": KERB_M, "low": _part(err, low, mask, total), "high": _part(err, high, mask, total),
            "rings": rings}


def truth_sides(seq, cfg) -> tuple:  # noqa: ANN001
    """Stage 1 on ``seq`` with ``cfg``, the kerb refit given the truth's sides at the kerbs (the vertices that
    :func:`error_parts` counts as kerb: 1 on the step's lower side, 0 on its higher side; elsewhere the baked
    classes' sides)."""
    import torch

    import pavemap.mesh.train as train
    from pavemap.io.truth import read_truth_height
    from pavemap.mesh import reconstruct

    truth, inner = read_truth_height(seq.root), train.initial_heights

    def with_truth(pool, grid, *a, vertex_side=None, **k):  # noqa: ANN001, ANN202
        if vertex_side is not None:
            g = grid.spec
            jj, ii = np.mgrid[0:g.ny, 0:g.nx]
            xy = torch.from_numpy(np.stack([g.x0 + ii * g.res, g.y0 + jj * g.res], -1).reshape(-1, 2)).double()
            vid = np.flatnonzero(grid.valid.reshape(-1))
            z, inside, zmax, zmin = (arr.reshape(-1)[vid] for arr in _truth_window(truth, xy, (g.ny, g.nx), g.res))
            kerb = inside & (zmax - zmin > KERB_M)
            vertex_side = vertex_side.copy()
            vertex_side[kerb] = np.where(z[kerb] < 0.5 * (zmax[kerb] + zmin[kerb]), 1, 0)
        return inner(pool, grid, *a, vertex_side=vertex_side, **k)

    train.initial_heights = with_truth
    try:
        return reconstruct(seq, None, cfg, progress=False)
    finally:
        train.initial_heights = inner


ROUNDS = (2, 4, 8)
SEEDS = (0, 1, 2)


def relief_rounds(data, preset: str, cfg, seeds: tuple[int, ...] = SEEDS,  # noqa: ANN001
                  rounds: tuple[int, ...] = ROUNDS) -> list[dict]:
    """The closed form (``cfg``) on drives of seeds ``seeds`` (no depth; seed 0 is the bench drive), with the kerb
    refit running each of ``rounds`` robust rounds (``ReliefFit.refit_iterations``): bias, RMSE over observed
    vertices, stage-1 seconds. What chose the default."""
    import functools
    import time

    import pavemap.mesh.relief as relief
    from common import no_depth_copy
    from mesh_bench import bench_drive, height_bias
    from pavemap.io.sequence import read_sequence
    from pavemap.mesh import reconstruct
    from pavemap.synth import synthesize

    rows, default = [], relief.ReliefFit
    for seed in seeds:
        if seed == 0:
            seq_dir = bench_drive(data, preset, "none", "cpu")
        else:
            src = data / f"{preset}-seed{seed}-sparse"
            if not (src / "sequence.json").is_file():
                synthesize(src, preset, seed=seed, depth="sparse", device="cpu", progress=False)
            seq_dir = no_depth_copy(src, data / f"{preset}-seed{seed}-none")
        seq = read_sequence(seq_dir)
        for n in rounds:
            relief.ReliefFit = functools.partial(default, refit_iterations=n)  # what fit_relief builds when given none
            try:
                t = time.perf_counter()
                mesh, _ = reconstruct(seq, None, cfg, progress=False)
                secs = time.perf_counter() - t
            finally:
                relief.ReliefFit = default
            hb = height_bias(None, mesh, seq)
            rows.append({"seed": seed, "refit_iterations": n, "bias_observed_m": hb["height_bias_observed_m"],
                         "rmse_observed_m": hb["height_rmse_observed_m"], "stage1_seconds": round(secs, 1)})
            print(preset, json.dumps(rows[-1]), flush=True)
    return rows
