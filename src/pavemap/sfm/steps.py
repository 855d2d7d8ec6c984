"""Step lengths of a driven path from the road's image motion (the ground-plane homography).

Forward-motion SfM fixes each camera's rotation and direction of travel well, but the length of
each step only through points whose depth the small forward baseline barely constrains, and its
scale drifts along a clip (+22 % over the KITTI sample's 50 steps). The road itself measures
them: for a camera ``h`` metres over a locally flat road, a step of ``d`` metres moves the road's
image by the homography ``K (R + t nᵀ / h) K⁻¹`` with ``t = d · t̂``. With R and t̂ from SfM, the
one unknown ``d / h`` is found by a 1D sweep of the windowed NCC between the later view's road and
the earlier view warped onto it (the earlier view saw the same road farther away). This is the
ground-plane scale of monocular visual odometry (Song & Chandraker 2014; Zhou et al. 2019).
On COLMAP's path one road reading is a noisy sample of a slowly drifting scale, so
:func:`relength_path` takes the neighbouring steps' median ratio unless a step's own is far off it
(the synthetic 2 Hz drives: 0.153 % mean path RMSE after a similarity alignment, 0.213 % per step).

Conventions: poses ``T_world_cam`` (N, 4, 4) camera-to-world, OpenCV camera axes (x right, y down,
z forward), world z up, metres or SfM units (only directions and rotations are used).
"""

from __future__ import annotations

import warnings
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from pavemap.types import Camera


@dataclass
class StepConfig:
    """Sweep of one step's length.

    - ``width``: images are matched at about this width (px; 800 of 1600 is ample for asphalt grain and paint).
    - ``near_m`` / ``far_m``: road compared in the later view, horizontal distance from its camera.
    - ``half_width_m``: and at most this far to either side of the camera's forward axis (parked cars,
      walls and verges stand above the road plane nearer than it and would pull the step long).
    - ``window``: side of the NCC window (px at ``scale``).
    - ``max_step_m``: longest step swept (a car at 130 km/h and 2 Hz covers 18 m).
    - ``coarse`` / ``fine``: candidates of the first pass (geometric, 0.05 m to ``max_step_m``) and of the
      second, between the best's neighbours.
    - ``min_peak`` / ``min_margin``: a step is trusted when its NCC peak reaches ``min_peak`` and beats
      the best candidate farther than 20 % (or 0.3 m) away by ``min_margin``.
    """

    width: int = 800
    near_m: float = 3.0
    far_m: float = 25.0
    half_width_m: float = 2.0
    window: int = 11
    max_step_m: float = 20.0
    coarse: int = 40
    fine: int = 11
    min_peak: float = 0.3
    min_margin: float = 0.03


@dataclass
class StepEstimate:
    """One pair's sweep: the step (m) at the NCC peak, its score, its margin, trusted or not, the curve."""

    length_m: float
    peak: float
    margin: float
    trusted: bool
    sweep_m: np.ndarray = field(repr=False)
    score: np.ndarray = field(repr=False)


def rot_z(theta: np.ndarray | float) -> np.ndarray:
    """(..., 3, 3) rotations by ``theta`` (...,) rad about the world's vertical (z up; left positive)."""
    c, s = np.cos(theta), np.sin(theta)
    R = np.zeros(np.shape(theta) + (3, 3))
    R[..., 0, 0], R[..., 0, 1], R[..., 1, 0], R[..., 1, 1], R[..., 2, 2] = c, -s, s, c, 1.0
    return R


def _pixel_rays(K: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """(H, W, 3) float64 camera-frame rays K⁻¹ (u, v, 1) of every pixel centre of an image ``shape`` (H, W)."""
    H, W = shape
    u, v = np.meshgrid(np.arange(W, dtype=np.float64), np.arange(H, dtype=np.float64))
    return np.stack([u, v, np.ones_like(u)], -1) @ np.linalg.inv(K).T


def _road_roi(rays: np.ndarray, n_cam: np.ndarray, h: float, cfg: StepConfig, ego: np.ndarray | None) -> np.ndarray:
    """(H, W) bool: pixels whose ray (``rays`` (H, W, 3)) meets the road ``near_m``..``far_m`` ahead and at most
    ``half_width_m`` to the side, not on the ego vehicle."""
    down = rays @ n_cam
    hit = down > 1e-6
    lam = np.where(hit, h / np.where(hit, down, 1.0), 0.0)
    # ground point in a frame with the road's normal removed: forward (camera z on the road) and lateral
    fwd = np.array([0.0, 0.0, 1.0]) - n_cam[2] * n_cam
    fwd /= np.linalg.norm(fwd)
    side = np.cross(n_cam, fwd)
    ahead = lam * (rays @ fwd)
    lateral = lam * (rays @ side)
    roi = hit & (ahead >= cfg.near_m) & (ahead <= cfg.far_m) & (np.abs(lateral) <= cfg.half_width_m)
    if ego is not None:
        roi &= ~ego
    return roi


def _ncc_score(ref: np.ndarray, warped: np.ndarray, valid: np.ndarray, win: int) -> float:
    """Mean windowed ZNCC (float) of ``ref`` and ``warped`` (H, W) over textured ``valid`` pixels."""
    import cv2

    k = (win, win)
    m = valid.astype(np.float32)
    cnt = cv2.boxFilter(m, -1, k, normalize=True)
    a, b = ref * m, warped * m
    with np.errstate(divide="ignore", invalid="ignore"):
        ma = cv2.boxFilter(a, -1, k) / cnt
        mb = cv2.boxFilter(b, -1, k) / cnt
        va = cv2.boxFilter(a * a, -1, k) / cnt - ma**2
        vb = cv2.boxFilter(b * b, -1, k) / cnt - mb**2
        cov = cv2.boxFilter(a * b, -1, k) / cnt - ma * mb
        z = cov / np.sqrt(np.maximum(va * vb, 1e-12))
    use = valid & (cnt > 0.75) & (va > 1e-4) & (vb > 1e-5)
    return float(np.mean(z[use])) if use.sum() > 200 else float("nan")


def road_scorer(img_src: np.ndarray, img_dst: np.ndarray, K: np.ndarray, T_src: np.ndarray, R_dst: np.ndarray,
                normal: np.ndarray, h: float, roi_dst: np.ndarray, ego: np.ndarray | None, cfg: StepConfig):  # noqa: ANN201
    """A function of the destination camera's centre (3,) (world) -> the windowed NCC (float) between
    ``img_dst``'s road pixels ``roi_dst`` and ``img_src`` warped onto them through the road plane (a pixel whose
    road point lies behind the source camera is not compared).

    ``img_*`` (H, W) float32 at the matching scale with ``K`` scaled to match; ``T_src`` (4, 4) the source
    camera-to-world pose, ``R_dst`` (3, 3) the destination's rotation; the road is the plane with upward unit
    ``normal`` (3,) ``h`` metres below the source camera; ``ego`` (H, W) True = ego.
    """
    import cv2

    H, W = img_dst.shape
    ys, xs = np.nonzero(roi_dst)
    y0, y1, x0, x1 = ys.min(), ys.max() + 1, xs.min(), xs.max() + 1
    u, v = np.meshgrid(np.arange(x0, x1, dtype=np.float64), np.arange(y0, y1, dtype=np.float64))
    pix = np.stack([u.ravel(), v.ravel(), np.ones(u.size)])
    ref = img_dst[y0:y1, x0:x1]
    roi = roi_dst[y0:y1, x0:x1]
    src_ok = None if ego is None else (~ego).astype(np.float32)
    offset = float(normal @ T_src[:3, 3]) - h  # the road: normal . X = offset
    rays = R_dst @ np.linalg.solve(K, pix)  # (3, M) world directions of the destination's pixels
    down = normal @ rays
    to_src = K @ T_src[:3, :3].T  # world -> source pixels (homogeneous, depth last)

    def score(centre: np.ndarray) -> float:
        # each destination pixel's road point, then into the source view. Not the plane's homography: that
        # loses the sign of the depth, and a road point behind the source camera (the destination the rear
        # view of a step, a clip numbered backwards) lands mirrored on the source's buildings and sky
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            lam = (offset - normal @ centre) / down
            q = to_src @ (centre[:, None] + lam * rays - T_src[:3, 3, None])
            front = (lam > 0) & (q[2] > 1e-9)
            mx = np.where(front, q[0] / q[2], np.nan).reshape(u.shape)
            my = np.where(front, q[1] / q[2], np.nan).reshape(u.shape)
        inside = np.isfinite(mx) & np.isfinite(my) & (mx >= 0) & (mx <= W - 1) & (my >= 0) & (my <= H - 1)
        mx = np.where(inside, mx, -1.0).astype(np.float32)
        my = np.where(inside, my, -1.0).astype(np.float32)
        warped = cv2.remap(img_src, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        valid = roi & inside
        if src_ok is not None:
            valid &= cv2.remap(src_ok, mx, my, cv2.INTER_NEAREST, borderValue=0) > 0.5
        return _ncc_score(ref, warped, valid, cfg.window)

    return score


def sweep_step(img_src: np.ndarray, img_dst: np.ndarray, K: np.ndarray, T_src: np.ndarray, R_dst: np.ndarray,
               direction: np.ndarray, normal: np.ndarray, h: float, roi_dst: np.ndarray, ego: np.ndarray | None,
               cfg: StepConfig) -> StepEstimate:
    """Length (m) of the step src → dst at which the road warped from ``img_src`` best matches ``img_dst``
    (:func:`road_scorer`; the destination camera sits at ``T_src``'s centre + d · ``direction`` (3,) unit).
    ``roi_dst`` (H, W) bool: road pixels of the destination view to compare.
    """
    score_at = road_scorer(img_src, img_dst, K, T_src, R_dst, normal, h, roi_dst, ego, cfg)

    def score(d: float) -> float:
        return score_at(T_src[:3, 3] + d * direction)

    coarse = np.r_[0.0, np.geomspace(0.05, cfg.max_step_m, cfg.coarse - 1)]
    s_coarse = np.array([score(d) for d in coarse])
    if not np.isfinite(s_coarse).any():
        return StepEstimate(float("nan"), float("nan"), 0.0, False, coarse, s_coarse)
    k = int(np.nanargmax(s_coarse))
    lo, hi = coarse[max(k - 1, 0)], coarse[min(k + 1, len(coarse) - 1)]
    fine = np.linspace(lo, hi, cfg.fine)
    s_fine = np.array([score(d) for d in fine])
    sweep = np.r_[coarse, fine]
    sc = np.r_[s_coarse, s_fine]
    order = np.argsort(sweep)
    sweep, sc = sweep[order], sc[order]
    j = int(np.nanargmax(sc))
    best = float(sweep[j])
    # (the coarse and fine candidates can coincide: the parabola needs three distinct abscissae)
    if 0 < j < len(sc) - 1 and np.isfinite(sc[j - 1 : j + 2]).all() and np.unique(sweep[j - 1 : j + 2]).size == 3:
        # parabola through the peak and its neighbours (unequal spacing)
        x, y = sweep[j - 1 : j + 2], sc[j - 1 : j + 2]
        A = np.stack([x**2, x, np.ones(3)], 1)
        a, b, _ = np.linalg.solve(A, y)
        if a < 0:
            best = float(np.clip(-b / (2 * a), x[0], x[2]))
    far = np.abs(sweep - best) > max(0.2 * best, 0.3)
    rival = float(np.nanmax(sc[far])) if np.isfinite(sc[far]).any() else -1.0
    peak = float(sc[j])
    margin = peak - rival
    return StepEstimate(best, peak, margin, bool(peak >= cfg.min_peak and margin >= cfg.min_margin), sweep, sc)


@dataclass
class _Pair:
    """One step i -> i+1 ready to sweep: the images (H, W) float32 at the matching scale, K (3, 3) scaled to
    them, the poses (4, 4), the direction of travel and the road's upward normal (3,) (world), the
    destination's road pixels (H, W) bool (None: too few to compare) and the ego mask (H, W) or None."""

    i: int
    src: np.ndarray
    dst: np.ndarray
    K: np.ndarray
    Ta: np.ndarray
    Tb: np.ndarray
    direction: np.ndarray
    normal: np.ndarray
    roi: np.ndarray | None
    ego: np.ndarray | None


def _pairs(images: list[Path], T_world_cam: np.ndarray, camera: Camera, camera_height: float,
           ego_mask: np.ndarray | None, cfg: StepConfig) -> Iterator[_Pair]:
    """The consecutive steps of a path as :class:`_Pair` (images read once, at ``cfg.width``)."""
    import cv2

    from pavemap.io.sequence import load_gray

    width = max(8, round(camera.width * min(1.0, cfg.width / camera.width)))
    grays = [load_gray(p, width).astype(np.float32) / 255.0 for p in images]
    Hs, Ws = max(8, round(camera.height * width / camera.width)), width
    for p, g in zip(images, grays, strict=True):
        if g.shape != (Hs, Ws):  # the camera's size, as load_gray resizes it
            from pavemap.errors import PavemapError

            raise PavemapError(f"{p}: image is not {camera.width}x{camera.height}, the size of camera {camera.name}")
    # K of the resized image, per axis (a rounded height scales rows slightly unlike columns: KITTI 0.16 %)
    K = camera.scaled(Ws / camera.width).K
    rays = _pixel_rays(K, (Hs, Ws))
    ego = None
    if ego_mask is not None and ego_mask.any():
        ego = cv2.resize(ego_mask.astype(np.uint8), (Ws, Hs), interpolation=cv2.INTER_NEAREST) > 0
        ego = cv2.dilate(ego.astype(np.uint8), np.ones((5, 5), np.uint8)) > 0
    up = np.array([0.0, 0.0, 1.0])
    for i in range(len(images) - 1):
        Ta, Tb = T_world_cam[i], T_world_cam[i + 1]
        step = Tb[:3, 3] - Ta[:3, 3]
        L = float(np.linalg.norm(step))
        # the direction of travel; a stopped car's SfM step has none, so take the camera's forward axis
        dir_w = step / L if L > 1e-6 else Ta[:3, 2] - (Ta[:3, 2] @ up) * up
        dir_w /= np.linalg.norm(dir_w)
        # the car drives on the road, so the road's normal is square to the direction of travel; the
        # world's up alone leaves the mount's pitch to the road in it (0.8 deg made KITTI's steps 20 % long)
        n_w = up - (up @ dir_w) * dir_w if L > 1e-6 else up
        n_w /= np.linalg.norm(n_w)
        roi = _road_roi(rays, -Tb[:3, :3].T @ n_w, camera_height, cfg, ego)
        yield _Pair(i, grays[i], grays[i + 1], K, Ta, Tb, dir_w, n_w, roi if roi.sum() >= 500 else None, ego)


def road_steps(images: list[Path], T_world_cam: np.ndarray, camera: Camera, camera_height: float,
               ego_mask: np.ndarray | None = None, cfg: StepConfig | None = None) -> list[StepEstimate]:
    """Length (m) of each step i → i+1 of the path (N-1 estimates) from the road's image motion.

    ``T_world_cam`` (N, 4, 4) z-up; rotations and the directions of travel are used, not the lengths.
    ``camera_height`` (m) is the mount's height over the road; ``ego_mask`` (H, W) True on the ego vehicle.
    """
    cfg = cfg or StepConfig()
    out = []
    for p in _pairs(images, T_world_cam, camera, camera_height, ego_mask, cfg):
        if p.roi is None:
            out.append(StepEstimate(float("nan"), float("nan"), 0.0, False, np.zeros(0), np.zeros(0)))
            continue
        out.append(sweep_step(p.src, p.dst, p.K, p.Ta, p.Tb[:3, :3], p.direction, p.normal, camera_height, p.roi,
                              p.ego, cfg))
    return out


def road_sideways(images: list[Path], T_world_cam: np.ndarray, camera: Camera, camera_height: float,
                  ego_mask: np.ndarray | None = None, cfg: StepConfig | None = None,
                  offsets_m: np.ndarray | None = None) -> list[dict]:
    """What the road says of each step's sideways component: with the step as ``T_world_cam`` has it (its
    length, its rotations), the destination camera moved by each of ``offsets_m`` (default -0.4..0.4 m by
    5 cm) square to the direction of travel on the road; per step ``{"step", "length_m", "best_offset_m",
    "peak", "at_zero", "margin"}`` (NCC; ``best_offset_m`` None where the road could not be compared).

    A check of a path's shape, not a correction: the lane lines and the asphalt's grain move sideways in
    the image with the camera, so an offset of 0 says the SfM's sideways motion is what the road shows.
    """
    cfg = cfg or StepConfig()
    offsets = np.round(np.linspace(-0.4, 0.4, 17), 3) if offsets_m is None else np.asarray(offsets_m, float)
    out = []
    for p in _pairs(images, T_world_cam, camera, camera_height, ego_mask, cfg):
        L = float(np.linalg.norm(p.Tb[:3, 3] - p.Ta[:3, 3]))
        row = {"step": p.i, "length_m": round(L, 3), "best_offset_m": None, "peak": None, "at_zero": None,
               "margin": None}
        if p.roi is not None and L > 0.25:  # a standing car has no direction of travel to be square to
            side = np.cross(p.normal, p.direction)
            score = road_scorer(p.src, p.dst, p.K, p.Ta, p.Tb[:3, :3], p.normal, camera_height, p.roi, p.ego, cfg)
            sc = np.array([score(p.Tb[:3, 3] + o * side) for o in offsets])
            if np.isfinite(sc).any():
                k = int(np.nanargmax(sc))
                far = np.abs(offsets - offsets[k]) > 0.15
                rival = float(np.nanmax(sc[far])) if np.isfinite(sc[far]).any() else float("nan")
                zero = int(np.argmin(np.abs(offsets)))
                row.update(best_offset_m=float(offsets[k]), peak=round(float(sc[k]), 3),
                           at_zero=round(float(sc[zero]), 3), margin=round(float(sc[k] - rival), 3))
        out.append(row)
    return out


def _score_at(e: StepEstimate, length: float) -> float:
    """The road's NCC (float) at ``length`` m on a step's sweep curve (linear between candidates; NaN off it)."""
    ok = np.isfinite(e.score)
    if ok.sum() < 2 or not e.sweep_m[ok].min() <= length <= e.sweep_m[ok].max():
        return float("nan")
    return float(np.interp(length, e.sweep_m[ok], e.score[ok]))


def relength_path(C: np.ndarray, steps: list[StepEstimate], window: int = 3, max_dev: float = 0.2,
                  guessed_length: np.ndarray | None = None,
                  contradiction: float = 0.1) -> tuple[np.ndarray, np.ndarray]:
    """Positions (R, 3) with each step's length from the road where trusted; the factors (R-1,) applied.

    ``C`` (R, 3) the path (directions kept), ``steps`` its R-1 road estimates. A step the road could not
    measure keeps its direction and takes the road-to-path ratio of the nearest measured steps (linear
    in the step index), so the path's scale follows the road along its whole length. ``window`` > 0: every
    moving step takes the median road-to-path ratio of the measured steps within ``window`` steps of it
    instead of its own (a path whose step lengths carry information, SfM's, drifts in scale slowly, while
    one step's road sweep is a noisy reading of it), unless its own ratio is more than ``max_dev`` (log) off
    theirs: there the path's own length is wrong (a forward-motion SfM failure), not the road's reading noisy,
    and the road's reading is taken, if the road contradicts the neighbours' length: its NCC there more than
    ``contradiction`` below its peak (a sweep with two near-equal peaks, one at the neighbours' length, does
    not: clip 1 read a 5 m step as 14 m on such a curve). ``guessed_length`` (R-1,) bool: steps whose length the
    path only guessed (a skid repaired onto the heading) take the road's reading too. A step of no length (a
    stopped car) stays one; with no measured step at all the path is returned unchanged.
    """
    d = np.diff(C, axis=0)
    L = np.linalg.norm(d, axis=1)
    road = np.array([e.length_m if e.trusted else np.nan for e in steps])
    ok = np.isfinite(road)
    if not ok.any():
        return C.copy(), np.ones(len(d))
    # ratios of moving steps only: a step of centimetres makes a ratio of noise
    long_ = ok & (L > 0.25) & (road > 0.25)
    idx = np.arange(len(d))
    ratio = (np.interp(idx, idx[long_], road[long_] / L[long_]) if long_.any()
             else np.full(len(d), float(np.nanmedian(road) / max(np.median(L), 1e-9))))
    own = ok & (L > 1e-6)  # steps that take the road's own reading
    if window > 0 and long_.any():
        r = np.where(long_, np.log(np.where(long_, road, 1.0) / np.maximum(L, 1e-9)), np.nan)
        guessed = np.zeros(len(d), bool) if guessed_length is None else np.asarray(guessed_length, bool)
        near = (np.abs(idx[:, None] - idx[None]) <= window) & ~guessed[None]  # (S, S) sound steps in the window
        with warnings.catch_warnings():  # a window without a measured step: its median is NaN
            warnings.simplefilter("ignore", RuntimeWarning)
            local = np.nanmedian(np.where(near, r[None], np.nan), axis=1)
        ratio = np.where(np.isfinite(local), np.exp(local), ratio)
        # the road's own reading where it says the car (nearly) stood, where the path only guessed the length,
        # and where the path's ratio is far off its neighbours'
        off = long_ & ~guessed & np.isfinite(local) & (np.abs(r - local) > max_dev)
        for i in np.flatnonzero(off):
            at_local = _score_at(steps[i], float(np.exp(local[i]) * L[i]))
            off[i] = not at_local >= steps[i].peak - contradiction  # NaN (off the curve): the road's own
        own &= ~long_ | guessed | ~np.isfinite(local) | off
    factor = np.where(own, road / np.maximum(L, 1e-9), ratio)
    out = np.vstack([C[:1], C[:1] + np.cumsum(d * factor[:, None], axis=0)])
    return out, factor


__all__ = ["StepConfig", "StepEstimate", "relength_path", "road_scorer", "road_sideways", "road_steps", "rot_z",
           "sweep_step"]
