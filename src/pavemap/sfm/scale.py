"""Metric scale of an SfM trajectory from the road the camera looks at.

:func:`road_relength` sets each step's length from the road's image motion (:mod:`pavemap.sfm.steps`).
:func:`dense_rescale` measures the cameras' heights over densely matched road points, which check that
scale, or set it where the road's steps could not. SIFT finds few points on smooth asphalt (the nuScenes
clip: a dozen under the driven path), too few to fix the scale from sparse SfM points, so the road is matched
densely, with the SfM poses held fixed (:func:`pavemap.mesh.ground_points.find_ground_points`: plane-sweep
NCC of corners, exact for a locally flat road), and the height of every camera over the road it drives over
(:func:`pavemap.geometry.road_height.camera_heights`) is compared with the known mounting height. The
sweep's depth search is centred on a provisional scale, so this refines a scale that is within a factor ~1.6
already (the sparse estimate); two passes make it converge.
"""

from __future__ import annotations

import dataclasses
import logging
from pathlib import Path

import numpy as np

from pavemap.sfm.result import SfmResult
from pavemap.types import Camera, Frame, Sequence, View

log = logging.getLogger(__name__)


def _in_mask(uv: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """(M,) bool: full-resolution pixels ``uv`` (M, 2) on True pixels of ``mask`` (H, W)."""
    H, W = mask.shape
    x = np.clip(np.round(uv[:, 0]).astype(int), 0, W - 1)
    y = np.clip(np.round(uv[:, 1]).astype(int), 0, H - 1)
    return mask[y, x]


def road_heights(images: list[Path], T_world_cam: np.ndarray, camera: Camera, camera_height: float,
                 ego_mask: np.ndarray | None = None, scale: float = 0.5) -> tuple[np.ndarray, dict]:
    """Per-camera height (R,) over the road it drives over (:func:`pavemap.geometry.road_height.camera_heights`), in
    the units of ``T_world_cam`` (R, 4, 4) (z up, metric-ish).

    ``images`` (R,) are the registered frames in order. Ground points seen on the ego vehicle
    (``ego_mask`` (H, W), True = ego) are dropped. Returns the heights (NaN where unobserved) and stats.
    """
    import tempfile

    from pavemap.geometry.road_height import camera_heights, height_estimate
    from pavemap.io.egomask import write_ego_mask
    from pavemap.mesh.ground_points import GroundConfig, find_ground_points
    from pavemap.palette import PAVEMAP_CLASSES

    frames = [Frame(i, float(i), {camera.name: View(camera.name, str(Path(p).resolve()), T)})
              for i, (p, T) in enumerate(zip(images, T_world_cam, strict=True))]
    with tempfile.TemporaryDirectory(prefix="pavemap-egomask-") as tmp:
        # the matcher leaves the ego vehicle's pixels out from the start (corners on a textured bonnet that
        # moves with the camera are mismatches waiting to happen); the points seen on it are dropped below too
        cam = camera if ego_mask is None or not ego_mask.any() else dataclasses.replace(
            camera, ego_mask=write_ego_mask(ego_mask, tmp, camera.name))
        seq = Sequence("sfm", list(PAVEMAP_CLASSES), {camera.name: cam}, frames, None, Path(tmp))
        gp = find_ground_points(seq, GroundConfig(scale=scale, prior_height=camera_height), min_points=30)
    stats = {"ground_points": len(gp), "observable": gp.observable, "reason": gp.reason}
    if ego_mask is not None and ego_mask.any() and len(gp):
        bad = np.zeros(len(gp), dtype=bool)
        bad[gp.obs_point[_in_mask(gp.obs_uv, ego_mask)]] = True
        gp = dataclasses.replace(gp, points=gp.points[~bad], road=gp.road[~bad])
        stats["dropped_on_ego"] = int(bad.sum())
    if not gp.observable:
        return np.full(len(images), np.nan), stats
    heights = camera_heights(gp.points, T_world_cam[:, :3, 3], np.array([0.0, 0.0, 1.0]))
    est = height_estimate(heights, min_centres=1)
    if est.observable:
        stats.update(median=est.median, spread=est.spread, centres=est.n_centres)
    return heights, stats


def refine_scale(images: list[Path], T_world_cam: np.ndarray, camera: Camera, camera_height: float,
                 ego_mask: np.ndarray | None = None, passes: int = 2) -> tuple[float, np.ndarray, dict]:
    """Factor that makes the median camera height over the road ``camera_height``, per-camera heights after it.

    ``T_world_cam`` (R, 4, 4) z-up, already roughly metric. Returns (factor, heights (R,) m, stats);
    factor is NaN when the road could not be matched.
    """
    factor = 1.0
    T = T_world_cam.copy()
    heights, stats = np.full(len(T), np.nan), {}
    for k in range(passes):
        heights, stats = road_heights(images, T, camera, camera_height, ego_mask)
        h = heights[np.isfinite(heights)]
        if h.size < 3:
            if stats.get("observable", True):  # points were found, but not under the path's cameras
                stats["reason"] = (f"{stats.get('ground_points', 0)} road points, under only {h.size} of {len(T)} "
                                   "cameras (need 3)")
            return float("nan"), heights, stats
        f = camera_height / float(np.median(h))
        factor *= f
        heights = heights * f
        T[:, :3, 3] *= f
        log.info("SfM scale pass %d: x%.4f (%d cameras measured)", k + 1, f, h.size)
        if abs(f - 1.0) < 0.01:
            break
    stats["factor"] = factor
    return factor, heights, stats


def road_relength(res: SfmResult, images: list[Path], camera: Camera, camera_height: float,
                   ego_mask: np.ndarray | None, min_share: float = 0.5) -> bool:
    """Each registered step of ``res`` re-measured on the road (in place); ``info["road_steps"]`` says how.

    True when the road measured at least ``min_share`` of the steps: the path's scale is then the road's.
    """
    from pavemap.sfm.steps import relength_path, road_steps

    reg = np.flatnonzero(res.registered)
    T = res.T_world_cam[reg]
    est = road_steps([images[i] for i in reg], T, camera, camera_height, ego_mask)
    C = T[:, :3, 3]
    L = np.linalg.norm(np.diff(C, axis=0), axis=1)
    # COLMAP's step lengths carry the images' geometry and drift slowly: the road's noisy readings are smoothed
    # along them; the planar motion's are all one unit (no length of their own), so each step takes its reading
    if res.info.get("method") == "pycolmap SfM":
        guessed = np.zeros(len(est), bool)
        guessed[[k for k in res.info.get("steps", {}).get("repaired", []) if k < len(est)]] = True
        C_new, factor = relength_path(C, est, guessed_length=guessed)
    else:
        C_new, factor = relength_path(C, est, window=0)
    trusted = np.array([e.trusted for e in est], dtype=bool)
    road = np.array([e.length_m for e in est])
    moving = trusted & (L > 0.25) & (road > 0.25)
    ratio = L[moving] / road[moving]
    res.info["road_steps"] = {
        "measured": int(trusted.sum()), "steps": len(est),
        "sfm_m": L.round(2).tolist(), "road_m": [round(e.length_m, 2) if e.trusted else None for e in est],
        "peak_ncc": [round(e.peak, 3) for e in est],
        # the SfM's own camera height along the path, as the road's step lengths read it
        "sfm_height_m": (camera_height * ratio).round(3).tolist(),
        # the lengths written: the road's reading, or the measured neighbours' ratio on SfM's length
        "path_m": np.linalg.norm(np.diff(C_new, axis=0), axis=1).round(3).tolist(),
        "own_reading": [bool(t and abs(f * lk - e.length_m) < 1e-6) for t, f, lk, e in zip(trusted, factor, L, est,
                                                                                           strict=True)],
    }
    if not trusted.any():
        log.warning("SfM: no step could be measured on the road; keeping the SfM's step lengths")
        return False
    overall = float(np.linalg.norm(np.diff(C_new, axis=0), axis=1).sum() / max(L.sum(), 1e-9))
    T[:, :3, 3] = C_new
    res.T_world_cam[reg] = T
    # the sparse points cannot follow a change of scale along the path; they take its overall factor
    res.points *= overall
    res.scale *= overall
    res.info["_heights"] = res.info["_heights"] * overall
    log.info("SfM: %d of %d steps measured on the road; path length x%.3f", int(trusted.sum()), len(est), overall)
    return bool(trusted.mean() >= min_share)


def dense_rescale(res: SfmResult, images: list[Path], camera: Camera, camera_height: float,
                   ego_mask: np.ndarray | None, apply: bool = True, max_disagreement: float = 0.05) -> None:
    """Refine ``res``'s scale in place from densely matched road points; keeps the sparse scale if that fails.

    ``apply`` False: the scale stays; the per-camera heights are measured (for the checks), the road is
    put at z = 0 and the factor the points would have applied is reported, with a warning past
    ``max_disagreement`` (the KITTI sample: 3.6 %; the nuScenes clip: 10 %).
    """
    reg = np.flatnonzero(res.registered)
    T = res.T_world_cam[reg]
    factor, heights, stats = refine_scale([images[i] for i in reg], T, camera, camera_height, ego_mask)
    res.info["dense_scale"] = {k: (round(v, 4) if isinstance(v, float) else v) for k, v in stats.items()}
    if not np.isfinite(factor):
        log.warning("SfM: dense road matching failed (%s); %s", stats.get("reason") or "no reason given",
                    "keeping the sparse scale" if apply else "the road's step lengths keep the scale unchecked")
        return
    res.info["dense_scale"]["applied"] = apply
    if not apply and abs(factor - 1.0) > max_disagreement:
        # two measurements of one scale: the road's image motion and the ground points' heights
        log.warning("SfM: the road's step lengths and the dense ground points disagree on the scale by %+.0f %% "
                    "(the camera %.2f m over the road by the points, %.2f m by the steps): the path's scale is "
                    "uncertain by that much", 100 * (factor - 1.0), camera_height / factor, camera_height)
        res.info["dense_scale"]["disagrees"] = True
    if apply:
        T[:, :3, 3] *= factor
        res.points *= factor
        res.scale *= factor
    else:
        heights = heights / factor
    ok = np.isfinite(heights)
    # the road at z = 0: shift by the median road level under the cameras
    T[:, 2, 3] -= float(np.median(T[ok, 2, 3] - heights[ok]))
    res.T_world_cam[reg] = T
    res.info["_heights"] = heights


__all__ = ["dense_rescale", "refine_scale", "road_heights", "road_relength"]
