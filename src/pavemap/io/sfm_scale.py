"""Metric scale of an SfM trajectory from the road the camera looks at (dense ground points).

SIFT finds few points on smooth asphalt (the nuScenes clip: a dozen under the driven path), too
few to fix the scale from sparse SfM points. Here the road is matched densely instead, with the
SfM poses held fixed (:func:`pavemap.mesh.ground_points.find_ground_points`: plane-sweep NCC of
corners, exact for a locally flat road), and the height of every camera over its local road plane
(:func:`pavemap.mesh.ground_points.estimate_camera_height`) is compared with the known mounting
height. The sweep's depth search is centred on a provisional scale, so this refines a scale that is
within a factor ~1.6 already (the sparse estimate); two passes make it converge.
"""

from __future__ import annotations

import dataclasses
import logging
from pathlib import Path

import numpy as np

from pavemap.types import Camera, Frame, Sequence, View

log = logging.getLogger(__name__)


def _in_mask(uv: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """(M,) bool: full-resolution pixels ``uv`` (M, 2) on True pixels of ``mask`` (H, W)."""
    H, W = mask.shape
    x = np.clip(np.round(uv[:, 0]).astype(int), 0, W - 1)
    y = np.clip(np.round(uv[:, 1]).astype(int), 0, H - 1)
    return mask[y, x]


def road_heights(images: list[Path], T_world_cam: np.ndarray, camera: Camera, camera_height: float,
                 ego_mask: np.ndarray | None = None, scale: float = 0.5,
                 radius: float = 4.0) -> tuple[np.ndarray, dict]:
    """Per-camera height (R,) over the local road, in the units of ``T_world_cam`` (R, 4, 4) (z up, metric-ish).

    ``images`` (R,) are the registered frames in order. Ground points seen on the ego vehicle
    (``ego_mask`` (H, W), True = ego) are dropped. Returns the heights (NaN where unobserved) and stats.
    """
    import tempfile

    from pavemap.io.egomask import write_ego_mask
    from pavemap.mesh.ground_points import GroundConfig, estimate_camera_height, find_ground_points
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
    est = estimate_camera_height(seq, gp, radius=radius, max_radius=3 * radius)[camera.name]
    stats.update(median=float(est.median), spread=float(est.spread), centres=int(est.n_centres))
    return np.asarray(est.per_centre, dtype=np.float64), stats


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


__all__ = ["refine_scale", "road_heights"]
