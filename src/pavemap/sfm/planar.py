"""A car's path from consecutive frames by its planar, non-holonomic motion (no SfM model needed).

Forward-motion SfM on 2 Hz frames can mistake a turn for a sideways slide (the bas-relief ambiguity: a small
rotation about the vertical and a sideways translation move far points alike). On a clip into an open car
park COLMAP registered every frame with 1 px reprojection error, 8.5 deg of yaw where the frames' own
essential matrix saw 2.5, and steps pointing 115 deg off the camera's heading. A car cannot do that: it
turns about the road's normal and moves along its heading, on a circular arc between two frames
(Ackermann steering; Scaramuzza et al., IJCV 2009). With the camera's mount to the car known, the motion
between two frames has **one** unknown besides its length, the yaw ``theta``, with the step along the
chord at ``theta / 2``:

1. Features (SIFT, OpenCV) of each frame with the ego vehicle masked; matches between consecutive frames.
2. The mount: the camera's yaw and pitch on the car (the road's normal is the camera's -y made square to
   the car's forward axis: the car drives parallel to the road) that let the arc model explain the
   matches of all pairs best, each pair's yaw free.
3. Each pair's yaw: a 1D search of ``theta`` minimising a robust epipolar error over all matches (no
   RANSAC needed: one parameter); the sign of the step (forwards or reversing) from the triangulated
   points' depths, decided for the whole clip by majority.
4. The step lengths, and so the metric scale, are the road's (:mod:`pavemap.sfm.steps`): the homography of
   the road plane at the known camera height, swept along the step.

Conventions: car frame x forward, y left, z up; camera OpenCV (x right, y down, z forward); world z up.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pavemap.errors import PavemapError
from pavemap.sfm.attitude import step_rotation, unit_path
from pavemap.sfm.result import SfmResult
from pavemap.sfm.road_yaw import road_yaw_offsets
from pavemap.sfm.steps import rot_z
from pavemap.types import Camera

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class PlanarConfig:
    """Feature matching and the yaw search of :func:`planar_motion`."""

    width: int = 960  # px, images are matched at about this width
    features: int = 4000
    ratio: float = 0.75  # Lowe's ratio test
    max_yaw_deg: float = 35.0  # per step
    inlier_px: float = 2.0  # epipolar error (px at ``width``) counted as a match
    min_inliers: int = 12
    refine_mount: bool = False  # the arc-model search moved KITTI's mount 2 deg away from the truth
    attitude: bool = True  # each step's change of the body's roll and pitch fitted with its yaw
    max_tilt_deg: float = 3.0  # bound on a step's change of roll, of pitch, and on its yaw's move from the 1D search


@dataclass
class PairMotion:
    """One step i -> i+1: yaw (rad, left positive), matches and inliers, the majority sign of its depths
    (+1 forwards, -1 reversing, 0 undecided), and the change of the body's roll and pitch (rad; 0 unless fitted)."""

    yaw: float
    matches: int
    inliers: int
    sign: int
    roll: float = 0.0
    pitch: float = 0.0


def _features(images: list[Path], K: np.ndarray, width: int, ego: np.ndarray | None, n: int,  # noqa: ANN202
              masks: list[Path | None] | None = None):
    """Keypoints (pixels at the matching width) and descriptors of each image; ``ego`` (H, W) True = ego vehicle,
    ``masks`` per image a PNG whose black pixels are left out (a vehicle that moves), or None."""
    import cv2

    from pavemap.io.sequence import load_gray

    sift = cv2.SIFT_create(nfeatures=n)
    out = []
    for p in images:
        g = load_gray(p, width)
        s = g.shape[1] / float(width if width else g.shape[1])
        m = None
        if ego is not None:
            m = (cv2.resize((~ego).astype(np.uint8), (g.shape[1], g.shape[0]), interpolation=cv2.INTER_NEAREST)
                 * 255)
        mp = masks[len(out)] if masks is not None else None
        if mp is not None:
            own = cv2.resize(cv2.imread(str(mp), cv2.IMREAD_GRAYSCALE), (g.shape[1], g.shape[0]),
                             interpolation=cv2.INTER_NEAREST)
            m = own if m is None else np.minimum(m, own)
        kp, des = sift.detectAndCompute(g, m)
        full = np.array([k.pt for k in kp], dtype=np.float64).reshape(-1, 2)
        out.append((full, des, s))
    return out


def _match(a, b, ratio: float) -> tuple[np.ndarray, np.ndarray]:  # noqa: ANN001
    """Matched pixel pairs (M, 2), (M, 2) at the matching scale (ratio test, mutual)."""
    import cv2

    if a[1] is None or b[1] is None or len(a[1]) < 2 or len(b[1]) < 2:
        return np.zeros((0, 2)), np.zeros((0, 2))
    bf = cv2.BFMatcher(cv2.NORM_L2)
    fwd = bf.knnMatch(a[1], b[1], k=2)
    back = {m.queryIdx: m.trainIdx for m, *_ in bf.knnMatch(b[1], a[1], k=1)}
    keep = [m for m, n2 in (x for x in fwd if len(x) == 2) if m.distance < ratio * n2.distance
            and back.get(m.trainIdx) == m.queryIdx]
    return (np.array([a[0][m.queryIdx] for m in keep]).reshape(-1, 2),
            np.array([b[0][m.trainIdx] for m in keep]).reshape(-1, 2))


def _bearings(uv: np.ndarray, K: np.ndarray) -> np.ndarray:
    """(M, 3) unit camera rays of pixels ``uv`` (M, 2)."""
    r = np.linalg.solve(K, np.vstack([uv.T, np.ones(len(uv))])).T
    return r / np.linalg.norm(r, axis=1, keepdims=True)


def _mount(yaw: float, pitch: float) -> np.ndarray:
    """(3, 3) camera -> car rotation (rows: the car's forward, left, up in camera coordinates) of a camera yawed
    ``yaw`` (rad, right positive) and pitched ``pitch`` (rad, down positive) on the car, no roll."""
    f = np.array([np.sin(yaw) * np.cos(pitch), -np.sin(pitch), np.cos(yaw) * np.cos(pitch)])
    up = np.array([0.0, -1.0, 0.0]) - (-f[1]) * f  # camera -y made square to the forward axis
    up /= np.linalg.norm(up)
    return np.stack([f, np.cross(up, f), up])


def _robust_cost(b1: np.ndarray, b2: np.ndarray, th: np.ndarray, tau: float) -> tuple[np.ndarray, np.ndarray]:
    """Truncated epipolar error of the arc model, (T,) summed over the matches, and the (T, M) inlier mask,
    for yaws ``th`` (T,) and car-frame bearings ``b1`` / ``b2`` (M, 3)."""
    t = np.stack([np.cos(th / 2), np.sin(th / 2), np.zeros_like(th)], -1)  # (T, 3)
    rb2 = np.einsum("tij,mj->tmi", rot_z(th), b2)  # (T, M, 3)
    r = np.abs(np.einsum("tmi,tmi->tm", rb2, np.cross(t[:, None, :], b1[None])))
    return np.minimum(r, tau).sum(1), r < tau


def _essential_forward(rays: list[tuple[np.ndarray, np.ndarray]], f_px: float) -> tuple[np.ndarray, int]:
    """The car's forward axis (3,) in the camera from the pairs' essential matrices (5-point RANSAC on rays):
    each pair's translation direction turned back by half its rotation (the chord of an arc lies half-way
    between the two headings), sign-aligned with the view, median over the pairs; and the pairs used."""
    import cv2
    from scipy.spatial.transform import Rotation

    dirs = []
    for a, b in rays:
        if len(a) < 15:
            continue
        pa, pb = a[:, :2] / a[:, 2:], b[:, :2] / b[:, 2:]
        E, inl = cv2.findEssentialMat(pa, pb, np.eye(3), cv2.RANSAC, 0.999, 1.0 / f_px)
        if E is None or E.shape != (3, 3):
            continue
        n, R, t, _ = cv2.recoverPose(E, pa, pb, np.eye(3), mask=inl)
        if n < 15:
            continue
        c = (-R.T @ t).ravel()  # the second camera's centre in the first's frame
        half = Rotation.from_matrix(R.T).as_rotvec() / 2  # first -> second camera, half-way
        c = Rotation.from_rotvec(half).inv().apply(c)
        dirs.append(c if c[2] >= 0 else -c)  # the car's forward axis looks the way the camera does
    f = np.median(np.array(dirs), axis=0) if dirs else np.array([0.0, 0.0, 1.0])
    return f / np.linalg.norm(f), len(dirs)


def mount_rotation(rays: list[tuple[np.ndarray, np.ndarray]], f_px: float, cfg: PlanarConfig) -> tuple[np.ndarray,
                                                                                                        dict]:
    """(3, 3) camera -> car rotation, and what was measured.

    ``rays``: unit camera rays (M, 3), (M, 3) of matched points of consecutive frames. The car's forward axis
    from the pairs' essential matrices (:func:`_essential_forward`), then the mount's yaw and pitch refined
    within 2 deg to let the arc model explain the matches best, each pair's yaw free."""
    f, used = _essential_forward(rays, f_px)
    yaw0, pitch0 = float(np.arctan2(f[0], f[2])), float(np.arcsin(-f[1]))
    rng = np.random.default_rng(0)
    sub = [(a[k], b[k]) for a, b in rays if len(a) >= cfg.min_inliers
           for k in [rng.permutation(len(a))[:150]]]
    tau = cfg.inlier_px / f_px
    lim = np.radians(cfg.max_yaw_deg)
    grid = np.linspace(-lim, lim, int(cfg.max_yaw_deg / 0.5) * 2 + 1)

    def cost(yaw: float, pitch: float) -> float:
        R = _mount(yaw, pitch)
        return float(sum(_robust_cost(a @ R.T, b @ R.T, grid, tau)[0].min() for a, b in sub))

    cands = [(yaw0 + np.radians(dy), pitch0 + np.radians(dp)) for dy in np.arange(-2, 2.01, 0.5)
             for dp in np.arange(-2, 2.01, 0.5)] if cfg.refine_mount else [(yaw0, pitch0)]
    best = cands[int(np.argmin([cost(y, p) for y, p in cands]))] if len(cands) > 1 else cands[0]
    info = {"pairs_used": used, "essential_yaw_deg": round(float(np.degrees(yaw0)), 2),
            "essential_pitch_deg": round(float(np.degrees(pitch0)), 2),
            "yaw_deg": round(float(np.degrees(best[0])), 2), "pitch_deg": round(float(np.degrees(best[1])), 2)}
    return _mount(*best), info


def pair_yaw(b1: np.ndarray, b2: np.ndarray, cfg: PlanarConfig, f_px: float) -> PairMotion:
    """The yaw of one step from car-frame bearings ``b1`` / ``b2`` (M, 3) of matched points (1D search).

    Epipolar constraint of the arc: the point seen along ``b1`` from the first car pose and ``b2`` from the
    second, ``t = (cos theta/2, sin theta/2, 0)``: ``(Rz(theta) b2) . (t x b1) = 0``."""
    M = len(b1)
    if cfg.min_inliers > M:
        return PairMotion(float("nan"), M, 0, 0)
    tau = cfg.inlier_px / f_px  # an angle

    def cost(th: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return _robust_cost(b1, b2, th, tau)

    lim = np.radians(cfg.max_yaw_deg)
    grid = np.linspace(-lim, lim, int(2 * cfg.max_yaw_deg / 0.1) + 1)
    c, _ = cost(grid)
    th0 = grid[int(np.argmin(c))]
    fine = np.linspace(th0 - np.radians(0.1), th0 + np.radians(0.1), 41)
    c2, inl = cost(fine)
    k = int(np.argmin(c2))
    th, inlier = float(fine[k]), inl[k]
    # which way along the chord: the triangulated depths are positive for one sign only
    t = np.array([np.cos(th / 2), np.sin(th / 2), 0.0])
    rb2 = b2[inlier] @ rot_z(np.array(th)).T
    votes = 0
    for s in (1.0, -1.0):
        # lambda1 b1 - lambda2 rb2 = s t, least squares per point
        A = np.stack([b1[inlier], -rb2], -1)  # (m, 3, 2)
        lam = _depths(A, s * t)
        votes += int(s) * int(((lam[:, 0] > 0) & (lam[:, 1] > 0)).sum())
    return PairMotion(th, M, int(inlier.sum()), int(np.sign(votes)))


def pair_attitude(b1: np.ndarray, b2: np.ndarray, m: PairMotion, cfg: PlanarConfig, f_px: float) -> PairMotion:
    """``m`` with the step's yaw, roll and pitch change fitted together (Cauchy-robust least squares on the
    epipolar error of the matches the 1D search left within 3 pixels), the chord still horizontal in the earlier
    body at half the yaw.

    A car's body rolls and pitches on its springs and with the road's crossfall and grade; the 1D search turns it
    about the mount's up axis only. On the eight synthetic 2 Hz drives of ``bench/sfm_drives_bench.py`` the planar
    path's error fell from 2.23 to 0.54 % of the path (mean; a step's turn 0.32 -> 0.20 deg off), on the KITTI
    sample's 51 frames from 0.77 to 0.68 % (a step's rotation 0.18 -> 0.05 deg off)."""
    from scipy.optimize import least_squares

    if not np.isfinite(m.yaw) or m.inliers < cfg.min_inliers:
        return m
    tau = cfg.inlier_px / f_px

    def resid(x: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
        t = np.array([np.cos(x[0] / 2), np.sin(x[0] / 2), 0.0])
        return np.einsum("mi,mi->m", b @ step_rotation(*x).T, np.cross(t, a))

    x0 = np.array([m.yaw, 0.0, 0.0])
    near = np.abs(resid(x0, b1, b2)) < 3 * tau
    if near.sum() < cfg.min_inliers:
        return m
    lim = np.radians(cfg.max_tilt_deg)
    sol = least_squares(resid, x0, args=(b1[near], b2[near]), loss="cauchy", f_scale=tau, x_scale=1e-2,
                        bounds=(x0 - lim, x0 + lim))
    if not sol.success:
        return m
    return PairMotion(float(sol.x[0]), m.matches, m.inliers, m.sign, float(sol.x[1]), float(sol.x[2]))


def _depths(A: np.ndarray, t: np.ndarray) -> np.ndarray:
    """(m, 2) least-squares depths of ``A`` (m, 3, 2) x = ``t`` (3,), per row."""
    AtA = np.einsum("mki,mkj->mij", A, A)
    Atb = np.einsum("mki,k->mi", A, t)
    det = AtA[:, 0, 0] * AtA[:, 1, 1] - AtA[:, 0, 1] ** 2
    det = np.where(np.abs(det) < 1e-12, np.nan, det)
    l1 = (AtA[:, 1, 1] * Atb[:, 0] - AtA[:, 0, 1] * Atb[:, 1]) / det
    l2 = (AtA[:, 0, 0] * Atb[:, 1] - AtA[:, 0, 1] * Atb[:, 0]) / det
    return np.stack([l1, l2], 1)


def planar_motion(images: list[Path], camera: Camera, ego_mask: np.ndarray | None = None,
                  cfg: PlanarConfig | None = None, masks: list[Path | None] | None = None
                  ) -> tuple[np.ndarray, list[PairMotion], dict]:
    """World camera-to-world poses (N, 4, 4) of ``images`` (video order) with **unit** steps along the car's
    arcs (z up, the camera 0 m over the road: lengths and height come from the road afterwards), the pairs'
    motions (N-1) and what was measured (``mount``, ``reverse``, ``yaw_deg`` per step).

    A pair with too few inliers gets no yaw (NaN): the path is cut there by the caller. ``masks``: per image a PNG
    of the pixels to match (black: a vehicle that moves), or None."""
    cfg = cfg or PlanarConfig()
    K = camera.K.astype(np.float64)
    width = min(cfg.width, camera.width)
    feats = _features(images, K, width, ego_mask, cfg.features, masks)
    s = width / camera.width
    Ks = K.copy()
    Ks[:2] *= s
    pairs = [_match(feats[i], feats[i + 1], cfg.ratio) for i in range(len(images) - 1)]
    rays = [(_bearings(a, Ks), _bearings(b, Ks)) for a, b in pairs]
    R_cm, mount = mount_rotation(rays, float(Ks[0, 0]), cfg)
    motions = [pair_yaw(a @ R_cm.T, b @ R_cm.T, cfg, float(Ks[0, 0])) for a, b in rays]
    if cfg.attitude:
        motions = [pair_attitude(a @ R_cm.T, b @ R_cm.T, m, cfg, float(Ks[0, 0])) for (a, b), m in
                   zip(rays, motions, strict=True)]
    signs = np.array([m.sign for m in motions])
    reverse = bool((signs < 0).sum() > (signs > 0).sum())
    T = unit_path(np.array([m.yaw for m in motions]), R_cm, reverse, np.array([m.roll for m in motions]),
                  np.array([m.pitch for m in motions]))
    info = {"mount": mount, "reverse": reverse, "yaw_deg": [round(float(np.degrees(m.yaw)), 2) for m in motions],
            "roll_deg": [round(float(np.degrees(m.roll)), 2) for m in motions],
            "pitch_deg": [round(float(np.degrees(m.pitch)), 2) for m in motions],
            "inliers": [m.inliers for m in motions], "matches": [m.matches for m in motions],
            "sign_votes": signs.tolist()}
    return T, motions, info




def _road_yaw(T: np.ndarray, pinfo: dict, images: list[Path], camera: Camera, camera_height: float,
              ego_mask: np.ndarray | None) -> np.ndarray:
    """The path ``T`` (K, 4, 4) with each turning step's yaw corrected on the road (:mod:`pavemap.sfm.road_yaw`);
    ``pinfo["yaw_deg"]`` updated and ``pinfo["road_yaw"]`` says what was changed."""
    yaw = np.radians(np.asarray(pinfo["yaw_deg"], float))
    offsets, records = road_yaw_offsets(images, T, yaw, camera, camera_height, ego_mask)
    pinfo["road_yaw"] = {"searched": len(records), "corrected": int((offsets != 0).sum()), "steps": records}
    if not offsets.any():
        return T
    pinfo["yaw_deg_matches"] = pinfo["yaw_deg"]
    yaw = yaw + offsets
    pinfo["yaw_deg"] = [round(float(np.degrees(y)), 2) for y in yaw]
    R_cm = _mount(*np.radians([pinfo["mount"]["yaw_deg"], pinfo["mount"]["pitch_deg"]]))
    return unit_path(yaw, R_cm, bool(pinfo["reverse"]), np.radians(np.asarray(pinfo["roll_deg"], float)),
                     np.radians(np.asarray(pinfo["pitch_deg"], float)))


def planar_result(images: list[Path], keyframes: np.ndarray, camera: Camera, camera_height: float,
                  ego_mask: np.ndarray | None, min_frames: int, info: dict, cfg: PlanarConfig | None = None,
                  masks: list[Path | None] | None = None) -> SfmResult:
    """An :class:`SfmResult` from the car's planar motion over the keyframes (unit steps, the camera
    ``camera_height`` m over the road at z = 0; the road sets the step lengths afterwards).

    The path is cut where a pair had too few matches to measure its yaw; the longest part is kept and the
    other frames are named in ``info["dropped"]``. Raises PavemapError when no part of ``min_frames`` is left."""
    kf = np.flatnonzero(keyframes)
    T, motions, pinfo = planar_motion([images[i] for i in kf], camera, ego_mask, cfg,
                                      None if masks is None else [masks[i] for i in kf])
    T = _road_yaw(T, pinfo, [images[i] for i in kf], camera, camera_height, ego_mask)
    info["planar"] = pinfo
    ok_step = np.array([np.isfinite(m.yaw) for m in motions], dtype=bool)
    # parts: runs of keyframes joined by measured steps
    bounds = [-1] + np.flatnonzero(~ok_step).tolist() + [len(kf) - 1]
    parts = [(bounds[j] + 1, bounds[j + 1]) for j in range(len(bounds) - 1)]
    best = max(range(len(parts)), key=lambda j: parts[j][1] - parts[j][0])
    a, b = parts[best]
    info["parts"] = [[int(kf[p0]), int(kf[p1]), j == best] for j, (p0, p1) in enumerate(parts)]
    why = "in a shorter part: too few feature matches between two frames to follow the car's motion across"
    info["dropped"] = {int(kf[i]): why for j, (p0, p1) in enumerate(parts) if j != best for i in range(p0, p1 + 1)}
    if b - a + 1 < min_frames:
        raise PavemapError(f"planar motion: no part of at least {min_frames} keyframes with enough feature matches "
                           f"between consecutive frames (longest: {b - a + 1})")
    keep = np.zeros(len(images), dtype=bool)
    keep[kf[a:b + 1]] = True
    out = np.full((len(images), 4, 4), np.nan)
    Tk = T[a:b + 1].copy()
    Tk[:, :3, 3] -= Tk[0, :3, 3]
    # world x along the drive, as SfM's paths have it (a reversing clip: along the way it went)
    travel = Tk[-1, :2, 3]
    a = -np.arctan2(travel[1], travel[0]) if np.linalg.norm(travel) > 0 else 0.0
    Tk[:, :3, :] = rot_z(np.array(a)) @ Tk[:, :3, :]
    Tk[:, 2, 3] += camera_height  # the path climbs with the body's pitch (a fixed height measured worse)
    out[keep] = Tk
    info.update(method="planar motion", registered=int(keep.sum()), images=len(images), keyframes=int(len(kf)),
                scale_source="provisional (planar motion: unit steps)", road_points_under_path=0,
                reproj_px=float("nan"))
    info["_heights"] = np.full(int(keep.sum()), np.nan)
    return SfmResult(out, keep, 1.0, 0, np.zeros((0, 3)), info, camera.K.astype(np.float64).copy())


__all__ = ["PairMotion", "PlanarConfig", "mount_rotation", "pair_attitude", "pair_yaw", "planar_motion",
           "planar_result"]
