"""SfM's sparse points on the road under the driven path, and the frames between keyframes."""

from __future__ import annotations

import numpy as np

from pavemap.sfm.result import SfmResult


def heights_below_path(X: np.ndarray, C: np.ndarray, up: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Height of each camera path point above road points ``X`` (M, 3) it drives over.

    For each point the camera centre nearest *in the ground plane* is found among all
    frames (a later frame passes over what an earlier one saw ahead), so slopes along
    the road do not bias the height. Returns heights (M,) in SfM units and the mask of
    points within 1.5 typical heights, sideways, of the path (the road the car drove on).
    """
    from scipy.spatial import cKDTree

    def flat(a: np.ndarray) -> np.ndarray:
        return a - np.outer(a @ up, up)

    dist, k = cKDTree(flat(C)).query(flat(X))
    h = (C[k] - X) @ up
    first = np.median(h[h > 0]) if (h > 0).any() else 0.0
    return h, (h > 0) & (dist < 1.5 * first)


def road_candidates(P: np.ndarray, C: np.ndarray, R_wc: np.ndarray, K: np.ndarray, width: int, height: int,
                     up: np.ndarray) -> np.ndarray:
    """Mask of points ``P`` (M, 3) that look like road: below some camera and inside the lower-middle
    of its image (a forward car camera sees the road there). Points x cameras in blocks of 64 cameras."""
    hit = np.zeros(len(P), dtype=bool)
    for s0 in range(0, len(C), 64):
        Cb, Rb = C[s0 : s0 + 64], R_wc[s0 : s0 + 64]
        rel = P[None] - Cb[:, None]  # (B, M, 3)
        Xc = np.einsum("bji,bmj->bmi", Rb, rel)  # world -> camera: R^T (P - C)
        z = Xc[..., 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            u = K[0, 0] * Xc[..., 0] / z + K[0, 2]
            v = K[1, 1] * Xc[..., 1] / z + K[1, 2]
        ok = (z > 0) & ((rel @ up) < 0) & (v > K[1, 2] + 0.15 * height) & (v < height)
        ok &= np.abs(u - K[0, 2]) < 0.3 * width
        hit |= ok.any(0)
    return hit


def fill_between_keyframes(res: SfmResult, keyframes: np.ndarray) -> None:
    """Poses of frames that were not keyframes (the car hardly moved), interpolated in place.

    Position linearly and rotation by slerp between the registered keyframes either side (by frame
    number); frames outside the registered span stay unregistered. ``info["interpolated"]`` counts them.
    """
    from scipy.spatial.transform import Rotation, Slerp

    reg = np.flatnonzero(res.registered)
    todo = [i for i in np.flatnonzero(~keyframes) if reg.size >= 2 and reg[0] < i < reg[-1]]
    if todo:
        T = res.T_world_cam[reg]
        slerp = Slerp(reg.astype(float), Rotation.from_matrix(T[:, :3, :3]))
        for i in todo:
            res.T_world_cam[i] = np.eye(4)
            res.T_world_cam[i, :3, :3] = slerp([float(i)]).as_matrix()[0]
            res.T_world_cam[i, :3, 3] = [np.interp(i, reg, T[:, k, 3]) for k in range(3)]
            res.registered[i] = True
    res.info["interpolated"] = len(todo)


__all__ = ["fill_between_keyframes", "heights_below_path", "road_candidates"]
