"""COLMAP's model -> a metric, z-up path of the car: its longest consistent part, steps that skid repaired onto
the car's heading, the road's "up", the sparse road points' scale (or a provisional one) and the heights along it.
"""

from __future__ import annotations

import logging

import numpy as np

from pavemap.errors import PavemapError
from pavemap.geometry.road_height import camera_heights
from pavemap.sfm.parts import PartLimits, consistent_parts, repair_skids, step_flags
from pavemap.sfm.result import SfmResult
from pavemap.sfm.sparse import heights_below_path, road_candidates
from pavemap.types import Camera

log = logging.getLogger(__name__)


def _model_poses(rec, names: list[str], keyframes: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray,
                                                                          np.ndarray]:
    """SfM-frame camera-to-world poses (N, 4, 4) (NaN where not registered), ``registered`` (N,) bool (keyframes
    only), K (3, 3) (pixel-centre convention) and the model's points (P, 3)."""
    by_name = {img.name: img for img in rec.images.values()}
    registered = np.array([n in by_name for n in names]) & keyframes
    T_wc = np.full((len(names), 4, 4), np.nan)
    for i in np.flatnonzero(registered):
        T = np.eye(4)
        T[:3, :4] = by_name[names[i]].cam_from_world().matrix()
        T_wc[i] = np.linalg.inv(T)
    cam = rec.cameras[next(iter(by_name.values())).camera_id] if by_name else None
    fx, fy, cx, cy = (float(v) for v in cam.params[:4]) if cam is not None else (np.nan,) * 4
    K = np.array([[fx, 0.0, cx - 0.5], [0.0, fy, cy - 0.5], [0.0, 0.0, 1.0]])
    P = np.array([p.xyz for p in rec.points3D.values()], dtype=np.float64).reshape(-1, 3)
    return T_wc, registered, K, P


def _up(T_wc: np.ndarray, min_turn_deg: float = 30.0) -> np.ndarray:
    """The road's "up" (3,) in the SfM frame from registered poses (R, 4, 4).

    A car turns about the road's normal, which is fixed in the camera (the mount does not move): where the
    path turns by ``min_turn_deg`` or more, up is the camera-frame axis that all the rotations map to one world
    direction (the least-squares common axis; it does not need the translations, which forward-motion SfM gets
    wrong first). On a straighter drive: the cameras' mean -y axis with the component along the drive removed
    (the mount's pitch tilts -y forward or back; the drive is near-level on average)."""
    C, R_wc = T_wc[:, :3, 3], T_wc[:, :3, :3]
    f = R_wc[:, :, 2]
    turned = np.degrees(np.arccos(np.clip(f @ f.T, -1.0, 1.0))).max() if len(f) > 1 else 0.0
    if turned >= min_turn_deg:
        dev = R_wc - R_wc.mean(0)
        w, V = np.linalg.eigh(np.einsum("kji,kjl->il", dev, dev))  # sum_k dev_kᵀ dev_k
        n_cam = V[:, 0] if V[1, 0] < 0 else -V[:, 0]  # up is the camera's -y side
        up = (R_wc @ n_cam).mean(0)
        return up / np.linalg.norm(up)
    up = -R_wc[:, :, 1].mean(0)
    _, _, Vt = np.linalg.svd(C - C.mean(0), full_matrices=False)
    along = Vt[0]
    up = up - (up @ along) * along if len(C) > 2 and np.ptp(C @ along) > 0 else up
    return up / np.linalg.norm(up)


def _keep_consistent(T_wc: np.ndarray, registered: np.ndarray, keyframes: np.ndarray, limits: PartLimits,
                     info: dict) -> np.ndarray:
    """``registered`` narrowed to the longest consistent part of the keyframes' path and the steps that skid
    repaired onto the car's heading (in place in ``T_wc``) (:mod:`pavemap.sfm.parts`). ``info["dropped"]``
    {frame: reason}, ``info["parts"]`` and ``info["steps"]`` say what was left out, repaired and why."""
    kf = np.flatnonzero(keyframes)
    reg_kf = registered[kf]
    up = _up(T_wc[registered])
    keep_kf, dropped, figures = consistent_parts(reg_kf, np.nan_to_num(T_wc[kf, :3, 3]),
                                                 np.nan_to_num(T_wc[kf, :3, 2]), up, limits)
    info["dropped"] = {int(kf[i]): why for i, why in sorted(dropped.items())}
    info["parts"] = [[int(kf[a]), int(kf[b]), bool(k)] for a, b, k in figures["parts"]]
    out = np.zeros_like(registered)
    out[kf[keep_kf]] = True
    if out.sum() < limits.min_frames:
        longest = "none" if not out.any() else f"frames {kf[keep_kf][0]}-{kf[keep_kf][-1]}"
        raise PavemapError(f"SfM: no consistent part of at least {limits.min_frames} keyframes to keep (longest: "
                           f"{longest}, {int(out.sum())} keyframes; {int(reg_kf.sum())} of {len(kf)} registered)")
    kept = np.flatnonzero(out)
    flags = step_flags(T_wc[kept, :3, 3], T_wc[kept, :3, 2], up, limits)
    moving = np.array([x is not None for x in flags["skid_deg"]], dtype=bool)
    if flags["skids"].sum() > 0.5 * max(1, moving.sum()):
        # most steps off the heading: SfM's translations are wrong as a whole, not here and there
        flags["skids"] = np.ones_like(flags["skids"])
        info["translations_rejected"] = True
    T_wc[kept, :3, 3] = repair_skids(T_wc[kept, :3, 3], T_wc[kept, :3, 2], up, flags["skids"],
                                     flags["mount_yaw_deg"], flags["reverse"])
    if flags["reverse"]:
        log.warning("SfM: the camera moves backwards along its view in most steps: are the frames numbered in "
                    "reverse? (mapped as given: a reversing car)")
    info["steps"] = {k: (v.tolist() if isinstance(v, np.ndarray) else v) for k, v in flags.items() if k != "why"}
    info["steps"]["repaired"] = np.flatnonzero(flags["skids"]).tolist()  # step k: kept frame k -> k+1
    return out


def metric_result(rec, names: list[str], keyframes: np.ndarray, camera: Camera, camera_height: float,
                   limits: PartLimits, hint: str, info: dict) -> SfmResult:
    """Keep the longest consistent part, scale it by the camera height, turn it z-up, and pack the result.

    The scale here comes from the sparse road points under the path; where there are too few of them (SIFT
    rarely lands on smooth asphalt) it is provisional and the road's step lengths or the dense road points
    set it afterwards (:func:`sfm_poses`); ``info["scale_source"]`` says which."""
    T_all, registered, K, P = _model_poses(rec, names, keyframes)
    info.update(registered_by_sfm=int(registered.sum()), points=len(P),
                reproj_px=float(rec.compute_mean_reprojection_error()))
    info["_poses_sfm"] = T_all
    if registered.sum() < 3:
        raise PavemapError(f"SfM registered only {int(registered.sum())} of {int(keyframes.sum())} keyframes "
                           f"({hint})")
    registered = _keep_consistent(T_all, registered, keyframes, limits, info)
    reg = np.flatnonzero(registered)
    T_wc = T_all[reg]
    C, R_wc = T_wc[:, :3, 3], T_wc[:, :3, :3]
    up = _up(T_wc)
    cand = road_candidates(P, C, R_wc, K, camera.width, camera.height, up)
    heights, drive_over = heights_below_path(P[cand], C, up)
    info.update(road_candidates=int(cand.sum()), road_points_under_path=int(drive_over.sum()))
    if drive_over.sum() >= 3 and np.median(heights[drive_over]) > 0 and not info.get("translations_rejected"):
        h_sfm = float(np.median(heights[drive_over]))
        info["scale_source"] = "sparse road points under the path"
        info["height_spread"] = float(np.median(np.abs(heights[drive_over] - h_sfm)) / h_sfm)
    else:
        # a provisional scale: a step of the median length taken as 5 m (a car at 36 km/h, 2 Hz); the road's
        # step lengths replace it, and without them the import stops (sfm_poses)
        steps = np.linalg.norm(np.diff(C, axis=0), axis=1)
        h_sfm = camera_height * float(np.median(steps[steps > 0])) / 5.0 if (steps > 0).any() else 1.0
        info["scale_source"] = ("provisional (SfM's translations rejected)" if info.get("translations_rejected")
                                else "provisional (too few sparse road points)")
    s = camera_height / h_sfm
    n = up
    # metric z-up world: z = n, x = driving direction in the plane, origin under camera 0
    travel = C[-1] - C[0]
    x = travel - (travel @ n) * n
    if np.linalg.norm(x) < 1e-9:
        x = R_wc[0][:, 2] - (R_wc[0][:, 2] @ n) * n
    x /= np.linalg.norm(x)
    A = np.stack([x, np.cross(n, x), n])  # rows: new axes in SfM coordinates
    origin = C[0] - h_sfm * n
    out = np.full((len(names), 4, 4), np.nan)
    M = np.tile(np.eye(4), (len(reg), 1, 1))
    M[:, :3, :3] = A @ R_wc
    M[:, :3, 3] = s * (C - origin) @ A.T
    U, _, Vt = np.linalg.svd(M[:, :3, :3])
    M[:, :3, :3] = U @ Vt
    out[reg] = M
    # the dropped parts in the same frame, for the diagnosis figure only
    moved = np.isfinite(T_all[:, 0, 0])
    info["_poses_sfm"] = np.full_like(T_all, np.nan)
    info["_poses_sfm"][moved, :3, 3] = s * (T_all[moved, :3, 3] - origin) @ A.T
    pts = s * (P - origin) @ A.T
    info.update(registered=int(registered.sum()), images=len(names), keyframes=int(keyframes.sum()))
    info["K_refined"] = {k: round(float(v), 2) for k, v in zip(("fx", "fy", "cx", "cy"),
                                                               (K[0, 0], K[1, 1], K[0, 2], K[1, 2]), strict=True)}
    road = pts[cand][drive_over]
    info["_heights"] = camera_heights(road, M[:, :3, 3], np.array([0.0, 0.0, 1.0]), lateral=1.5 * camera_height)
    return SfmResult(out, registered, float(s), int(drive_over.sum()), pts, info, K)


__all__ = ["metric_result"]
