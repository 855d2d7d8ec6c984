"""Ground points triangulated from a sequence's images with its poses held fixed, and the camera height
they imply: the road's geometry when there is no depth sensor (issue 12).

Each reference view's corners on the ground are matched into later views (the same camera's next
``max_gap`` frames and other cameras of the rig where their ground overlaps) by a *patch sweep* along the
epipolar line: every depth hypothesis of a corner's ray puts a horizontal plane through that point, the
plane's homography warps the corner's patch into the partner, and zero-mean NCC scores it (coarse 2 px
steps over the whole depth range, then 1 px, then sub-pixel parabola fits). It is exact for a locally flat
road, immune to exposure changes between frames, and rejects patches whose NCC peak is flat or repeated
along the line (an edge running with the epipolar line: lane markings in forward motion; why not pyramidal
LK: README, Geometry without LiDAR). The prior camera height only centres the search; triangulation
(:mod:`pavemap.geometry.triangulate`) uses the matched pixels and the poses. The stage-1 side (camera height,
sparse depth, self-check) is :mod:`pavemap.mesh.geometry`.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace

import cv2
import numpy as np

from pavemap.geometry import patch_ncc
from pavemap.geometry.triangulate import (
    HeightEstimate,
    agrees_with_neighbours,
    camera_height,
    local_ground,
    parabola_vertex,
    plane_homography,
    second_peak,
    triangulate_tracks,
    within_corridor,
)
from pavemap.io.egomask import ego_mask_at
from pavemap.io.sequence import load_rgb, load_semantics
from pavemap.types import Camera, Sequence, View

Z_UP = np.array([0.0, 0.0, 1.0])


@dataclass
class GroundConfig:
    """Knobs of :func:`find_ground_points` (defaults chosen on the synthetic and KITTI benches)."""

    scale: float = 1.0  # image scale for matching
    prior_height: float = 1.5  # m: centres the depth search and the range mask, never enters the geometry
    min_range: float = 2.0  # m, ground distance of usable pixels on the prior plane
    max_range: float = 25.0
    horizon_margin_deg: float = 3.0  # pixels must look at least this far below the horizon
    max_gap: int = 3  # frames between a reference view and its partners
    max_partners: int = 4
    min_overlap: float = 0.15  # fraction of the reference's ground that a partner must see
    max_corners: int = 400
    min_distance: int = 7  # px between corners
    quality: float = 0.003  # goodFeaturesToTrack quality level (road texture is weak)
    patch: int = 11  # sweep patch side (px)
    sweep_range: float = 0.5  # +- log depth around the prior plane's depth (prior height x0.6 .. x1.65)
    coarse_px: float = 2.0  # coarse hypothesis spacing along the epipolar line (px)
    sweep_max_steps: int = 200  # at most this many coarse hypotheses (the spacing grows beyond)
    sparse_coarse: bool = True  # coarse sweep on every other pixel of the patch (3x faster, same points)
    min_ncc: float = 0.8
    min_drop: float = 0.05  # NCC must fall by this much 2 px either side of the peak (edges along the line)
    min_contrast: float = 2.0  # grey levels (std of the reference patch)
    max_err_px: float = 1.0  # reprojection error allowed per observation
    min_angle_deg: float = 1.0
    min_views: int = 2
    neighbour_m: float = 0.15  # drop points this far off the robust surface of their neighbours
    corridor_m: float = 8.0  # without semantics: ground must lie this close to the trajectory
    use_semantics: bool = True


@dataclass
class GroundPoints:
    """Triangulated ground points of a sequence.

    views: the (frame index, camera) of every view id. points (N, 3) float64 world; per point n_views (N,),
    rms_px (N,) reprojection RMS in full-resolution pixels, angle_deg (N,) triangulation angle, road (N,)
    bool (on a road class; all True without semantics). Per observation (M,): obs_point, obs_view (view
    id), obs_uv (M, 2) full-resolution pixels, obs_depth (M,) camera z in metres (what a depth map holds).
    ``observable`` is False, with ``reason``, when the images did not give enough points to trust (one
    frame, no texture, no baseline).
    """

    views: list[tuple[int, str]]
    points: np.ndarray
    n_views: np.ndarray
    rms_px: np.ndarray
    angle_deg: np.ndarray
    road: np.ndarray
    obs_point: np.ndarray
    obs_view: np.ndarray
    obs_uv: np.ndarray
    obs_depth: np.ndarray
    semantic: bool
    observable: bool
    reason: str
    stats: dict = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.points)

    def subset(self, keep: np.ndarray) -> GroundPoints:
        """The points where ``keep`` (N,) bool holds, with their observations (re-indexed)."""
        new = np.cumsum(keep) - 1
        obs = keep[self.obs_point] if len(self.obs_point) else np.zeros(0, bool)
        return replace(
            self, points=self.points[keep], n_views=self.n_views[keep], rms_px=self.rms_px[keep],
            angle_deg=self.angle_deg[keep], road=self.road[keep], obs_point=new[self.obs_point[obs]],
            obs_view=self.obs_view[obs], obs_uv=self.obs_uv[obs], obs_depth=self.obs_depth[obs])

    def split(self, every: int) -> tuple[GroundPoints, GroundPoints]:
        """(fit, check): every ``every``-th point held out as the self-check's unseen evidence."""
        held = (np.arange(len(self)) % every) == every // 2
        return self.subset(~held), self.subset(held)


@dataclass
class _ViewData:
    key: tuple[int, str]
    pos: int
    cam: Camera  # at the matching scale
    T: np.ndarray
    grey: np.ndarray | None = None  # uint8 (corners)
    img: np.ndarray | None = None  # float32, lightly blurred (what the sweep samples)
    mask: np.ndarray | None = None  # candidate ground pixels
    label_ok: np.ndarray | None = None  # semantic ground (None without semantics)
    road: np.ndarray | None = None


def _range_mask(cam: Camera, T: np.ndarray, cfg: GroundConfig) -> np.ndarray:
    """(H, W) bool: pixels below the horizon whose ray meets the prior plane within the range (row and column
    terms broadcast: 4x faster than an (H, W, 3) ray array per view, 8.7 s of a nuScenes-like drive's setup)."""
    R = T[:3, :3]
    y = ((np.arange(cam.height) - cam.K[1, 2]) / cam.K[1, 1])[:, None]  # (H, 1)
    x = (np.arange(cam.width)[None, :] - cam.K[0, 2] - cam.K[0, 1] * y) / cam.K[0, 0]  # (H, W)
    dx, dy, dz = (R[k, 0] * x + (R[k, 1] * y + R[k, 2]) for k in range(3))
    horiz = np.sqrt(dx * dx + dy * dy)
    below = dz < -np.sin(np.radians(cfg.horizon_margin_deg)) * np.sqrt(horiz * horiz + dz * dz)
    with np.errstate(divide="ignore", invalid="ignore"):
        dist = cfg.prior_height / -dz * horiz
    return below & (dist >= cfg.min_range) & (dist <= cfg.max_range)


def _load(seq: Sequence, vd: _ViewData, view: View, cfg: GroundConfig, ground_lut, road_lut) -> None:
    cam = vd.cam
    size = (cam.width, cam.height)
    grey = cv2.cvtColor(load_rgb(seq.path(view.image)), cv2.COLOR_RGB2GRAY)
    if grey.shape[::-1] != size:
        grey = cv2.resize(grey, size, interpolation=cv2.INTER_AREA)
    # a light blur makes bilinear samples at any sub-pixel phase alike, else NCC peaks lock onto whole pixels
    # (an image pyramid for the coarse search was tried: the road's fine texture is gone two levels up)
    vd.img = cv2.GaussianBlur(grey.astype(np.float32), (0, 0), 0.8)
    mask = _range_mask(cam, vd.T, cfg)
    if cfg.use_semantics and view.semantics:
        lab = load_semantics(seq.path(view.semantics))
        if lab.shape[::-1] != size:
            lab = cv2.resize(lab, size, interpolation=cv2.INTER_NEAREST)
        # erode: a corner on a class edge straddles a car's bumper and the road
        vd.label_ok = cv2.erode(ground_lut[lab].astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)
        vd.road = road_lut[lab]
        mask &= vd.label_ok
    if (ego := ego_mask_at(seq, view.camera, size[0], size[1])) is not None:  # the bonnet moves with the camera
        mask &= ~cv2.dilate(ego.astype(np.uint8), np.ones((9, 9), np.uint8)).astype(bool)
    vd.grey, vd.mask = grey, mask


# ---------------------------------------------------------------------------- the patch sweep


class _Sweep:
    """One (reference a, partner b) pair for N corners (N, 2). Hypotheses are log depths ``tau`` of a
    corner's ray relative to the prior plane's depth ``lam0``."""

    def __init__(self, a: _ViewData, b: _ViewData, c: np.ndarray, cfg: GroundConfig):
        Ka, Kb = a.cam.K, b.cam.K
        r = cfg.patch // 2
        dv, du = np.mgrid[-r:r + 1, -r:r + 1]
        off = np.stack([du.ravel(), dv.ravel()], 1).astype(np.float64)
        Ra, Rb = a.T[:3, :3], b.T[:3, :3]
        R_ba, t_ba = Rb.T @ Ra, Rb.T @ (a.T[:3, 3] - b.T[:3, 3])
        n_a = Ra.T @ Z_UP
        q = c[:, None, :] + off[None]  # (N, P, 2) reference patch pixels
        Kinv = np.linalg.inv(Ka)
        x_a = np.concatenate([q, np.ones(q.shape[:2] + (1,))], -1) @ Kinv.T  # (N, P, 3) rays, z = 1
        xc = np.c_[c, np.ones(len(c))] @ Kinv.T
        # a patch pixel's depth on the plane through the centre's point: mu(p) = lam * ratio(p)
        self.ratio = ((xc @ n_a)[:, None] / (x_a @ n_a)).astype(np.float32)
        self.KU = (x_a @ R_ba.T @ Kb.T).astype(np.float32)  # uvw = mu KU + K t
        self.kt = (Kb @ t_ba).astype(np.float32)
        self.xb, self.t_ba, self.Kb = xc @ R_ba.T, t_ba, Kb
        self.img = b.img
        ref = patch_ncc.sample_bilinear(a.img, q.reshape(-1, 2)).reshape(len(c), -1)
        self.contrast = ref.std(-1)
        self.sparse = np.nonzero(((off[:, 0] % 2) == 0) & ((off[:, 1] % 2) == 0))[0]
        self.ref = patch_ncc.zncc_rows(ref).astype(np.float32)
        self.ref_sparse = patch_ncc.zncc_rows(ref[:, self.sparse]).astype(np.float32)
        self.lam0 = -cfg.prior_height / (xc @ Ra.T)[:, 2]
        # px per unit tau along the epipolar line
        self.g = np.linalg.norm(self.centre_px(0.01) - self.centre_px(-0.01), axis=-1) / 0.02

    def centre_px(self, tau: np.ndarray | float, rows: np.ndarray | slice = slice(None)) -> np.ndarray:
        lam = self.lam0[rows] * np.exp(tau)
        uvw = (lam[:, None] * self.xb[rows] + self.t_ba) @ self.Kb.T
        return uvw[:, :2] / uvw[:, 2:3]

    def score(self, tau: np.ndarray, rows: np.ndarray, sparse: bool, reference: bool = False) -> np.ndarray:
        """NCC (R, S) of hypotheses tau (R, S) of corners ``rows``; -1 where the patch leaves b
        (:func:`pavemap.geometry.patch_ncc.sweep_scores`; ``reference``: its numpy reference)."""
        pix = self.sparse if sparse else slice(None)
        ref = self.ref_sparse if sparse else self.ref
        f = patch_ncc.sweep_scores_numpy if reference else patch_ncc.sweep_scores
        return f(self.lam0[rows, None] * np.exp(tau), self.ratio[rows][:, pix], self.KU[rows][:, pix], self.kt,
                 self.img, ref[rows])

    def best(self, tau: np.ndarray, rows: np.ndarray, sparse: bool, margin: float = 0.1):
        """Best hypothesis per row of tau (R, S) refined by a parabola: (tau, peak NCC, distinct peak)."""
        ncc = self.score(tau, rows, sparse)
        k = np.argmax(ncc, 1)
        r = np.arange(len(rows))
        peak = ncc[r, k]
        second = second_peak(ncc, k)
        S = tau.shape[1]
        kk = np.clip(k, 1, S - 2)
        off = parabola_vertex(ncc[r, kk - 1], ncc[r, kk], ncc[r, kk + 1])
        return tau[r, kk] + off * (tau[r, 1] - tau[r, 0]), peak, (k > 0) & (k < S - 1) & (second < peak - margin)


def _sweep_match(a: _ViewData, b: _ViewData, corners: np.ndarray, cfg: GroundConfig, tau_prior: np.ndarray,
                 budget: int = 1_500_000) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Match a's corners (N, 2) into b, coarse (``coarse_px`` spacing over the whole range) to fine (1 px,
    then two parabola fits at 0.5 and 0.25 px). ``tau_prior`` (N,): a corner's log depth from an earlier
    partner (NaN if none); known corners are searched only within +-4 px of it. Returns kept corner
    indices, their pixels in b (on the epipolar line, so a 2-view reprojection error is ~0), log depths."""
    sw = _Sweep(a, b, corners.astype(np.float64), cfg)
    span = 2 * cfg.sweep_range
    P = len(sw.sparse) if cfg.sparse_coarse else len(sw.ref[0])
    t_hat, ok = np.zeros(len(corners)), np.zeros(len(corners), bool)
    usable = (sw.contrast >= cfg.min_contrast) & (sw.g * span >= 2.0)  # else: no texture / no parallax
    known = np.isfinite(tau_prior)
    unknown = np.nonzero(usable & ~known)[0]
    unknown = unknown[np.argsort(sw.g[unknown])]  # chunks of alike parallax need alike hypothesis counts
    start = 0
    while start < len(unknown):
        S = min(int(np.ceil(span * sw.g[unknown[start]] / cfg.coarse_px)) + 1, cfg.sweep_max_steps + 1)
        n = max(1, budget // (S * P))
        S = min(int(np.ceil(span * sw.g[unknown[start:start + n]].max() / cfg.coarse_px)) + 1,
                cfg.sweep_max_steps + 1)
        rows = unknown[start:start + n]
        tau = np.broadcast_to(np.linspace(-cfg.sweep_range, cfg.sweep_range, S), (len(rows), S))
        t_hat[rows], peak, distinct = sw.best(tau, rows, cfg.sparse_coarse)
        ok[rows] = distinct & (peak >= cfg.min_ncc - 0.1)
        start += n
    rows = np.nonzero(usable & known)[0]
    if len(rows):
        tau = tau_prior[rows, None] + np.arange(-4.0, 5.0)[None] / sw.g[rows, None]
        t_hat[rows], peak, ok[rows] = sw.best(tau, rows, False)
    rows = np.nonzero(ok)[0]
    if len(rows):
        t_hat[rows], _, good = sw.best(t_hat[rows, None] + np.arange(-2.0, 3.0)[None] / sw.g[rows, None], rows,
                                       False)
        rows = rows[good]
    for h in (0.5, 0.25):  # two parabola fits at sub-pixel spacing
        hh = h / sw.g[rows]
        ncc = sw.score(t_hat[rows, None] + np.stack([-hh, 0 * hh, hh], 1), rows, sparse=False)
        t_hat[rows] += hh * parabola_vertex(ncc[:, 0], ncc[:, 1], ncc[:, 2])
        rows = rows[(ncc.min(1) > -1) & (ncc[:, 1] >= cfg.min_ncc)]
    if cfg.min_drop > 0 and len(rows):
        # a sharp peak: an edge running nearly with the epipolar line gives a broad one, and a wrong depth
        hh = 2.0 / sw.g[rows]
        ncc = sw.score(t_hat[rows, None] + np.stack([-hh, 0 * hh, hh], 1), rows, sparse=False)
        rows = rows[ncc[:, 1] - np.maximum(ncc[:, 0], ncc[:, 2]) >= cfg.min_drop]
    uv = sw.centre_px(t_hat[rows], rows)
    if b.label_ok is not None and len(rows):
        ui = np.clip(np.rint(uv).astype(np.int64), 0, [b.cam.width - 1, b.cam.height - 1])
        on = b.label_ok[ui[:, 1], ui[:, 0]]
        rows, uv = rows[on], uv[on]
    return rows, uv, t_hat[rows]


# ---------------------------------------------------------------------------- pairs, filters, driver


def _overlap(a: _ViewData, b: _ViewData, H: np.ndarray, step: int = 16) -> float:
    """Fraction of a's candidate ground pixels (sampled) that land on b's through homography H."""
    ys, xs = np.nonzero(a.mask[::step, ::step])
    if len(xs) == 0:
        return 0.0
    q = np.c_[xs * step, ys * step, np.ones(len(xs))] @ H.T
    front = q[:, 2] > 0
    q = q[:, :2] / np.where(front, q[:, 2], 1.0)[:, None]
    W, Hh = b.cam.width, b.cam.height
    inside = front & (q[:, 0] >= 0) & (q[:, 1] >= 0) & (q[:, 0] < W - 1) & (q[:, 1] < Hh - 1)
    qi = np.clip(np.rint(q).astype(np.int64), 0, [W - 1, Hh - 1])
    return float((inside & b.mask[qi[:, 1], qi[:, 0]]).mean())


def _partners(vds: list[_ViewData], i: int, cfg: GroundConfig) -> list[int]:
    """Later views (same frame other cameras, next ``max_gap`` frames) that see enough of i's ground."""
    a = vds[i]
    out = []
    for j in range(i + 1, len(vds)):
        b = vds[j]
        if b.pos - a.pos > cfg.max_gap or len(out) >= cfg.max_partners:
            break
        if np.linalg.norm(b.T[:3, 3] - a.T[:3, 3]) < 0.05 or b.img is None:
            continue  # no baseline: a stationary vehicle gives no depth
        H = plane_homography(a.cam.K, a.T, b.cam.K, b.T, Z_UP, float(a.T[2, 3] - cfg.prior_height))
        if _overlap(a, b, H) >= cfg.min_overlap:
            out.append(j)
    return out


def _match_all(seq: Sequence, vds: list[_ViewData], views: list[View], cfg: GroundConfig):
    """Corners of every view matched into its partners: observations (track, view, uv), per track the road
    flag of its reference pixel, the track count and counters."""
    luts = (seq.class_lut("ground") & ~seq.class_lut("movable"), seq.class_lut("road"))
    stats: dict = {"views": len(vds), "pairs": 0, "matches": 0}
    obs: dict[str, list[np.ndarray]] = {"track": [], "view": [], "uv": []}
    road: list[np.ndarray] = []
    n_tracks, loaded = 0, 0  # views are loaded lazily and dropped once no later reference needs them
    for i, a in enumerate(vds):
        while loaded < len(vds) and vds[loaded].pos - a.pos <= cfg.max_gap:
            _load(seq, vds[loaded], views[loaded], cfg, *luts)
            loaded += 1
        corners = cv2.goodFeaturesToTrack(a.grey, cfg.max_corners, cfg.quality, cfg.min_distance,
                                          mask=a.mask.astype(np.uint8))
        if corners is not None:
            corners = corners.reshape(-1, 2).astype(np.float64)
            tid = n_tracks + np.arange(len(corners))
            ci = np.rint(corners).astype(np.int64)
            road.append(np.ones(len(corners), bool) if a.road is None else a.road[ci[:, 1], ci[:, 0]])
            for k, x in (("track", tid), ("view", np.full(len(corners), i)), ("uv", corners)):
                obs[k].append(x)
            tau = np.full(len(corners), np.nan)  # log depth found so far (narrows later partners' search)
            for j in _partners(vds, i, cfg):
                idx, uv_b, t = _sweep_match(a, vds[j], corners, cfg, tau)
                tau[idx] = np.where(np.isfinite(tau[idx]), tau[idx], t)
                stats["pairs"] += 1
                stats["matches"] += len(idx)
                for k, x in (("track", tid[idx]), ("view", np.full(len(idx), j)), ("uv", uv_b)):
                    obs[k].append(x)
            n_tracks += len(corners)
        a.grey = a.img = a.mask = a.label_ok = a.road = None
    return obs, road, n_tracks, stats


def find_ground_points(seq: Sequence, cfg: GroundConfig | None = None, min_points: int = 50) -> GroundPoints:
    """Triangulated ground points of ``seq`` (poses fixed). See the module docstring for the method.

    Without semantics (or ``use_semantics=False``) ground is what lies below the horizon, within
    ``max_range`` on the prior plane, below its cameras and within ``corridor_m`` of the trajectory.
    ``observable`` is False (with the reason) below ``min_points`` points.
    """
    cfg = cfg or GroundConfig()
    t0 = time.perf_counter()
    vds, views = [], []
    for pos, f in enumerate(seq.frames):
        for name, v in f.views.items():
            vds.append(_ViewData((f.index, name), pos, seq.cameras[name].scaled(cfg.scale), v.T_world_cam))
            views.append(v)
    semantic = cfg.use_semantics and any(v.semantics for v in views)
    obs, road, n_tracks, stats = _match_all(seq, vds, views, cfg)
    stats["t_match_s"] = round(time.perf_counter() - t0, 2)
    keys = [vd.key for vd in vds]
    if stats["matches"] == 0:
        return _empty(keys, semantic, "no view pair with a baseline and overlapping, textured ground: "
                      "geometry not observable from the images", stats)
    track, vid, uv = (np.concatenate(obs[k]) for k in ("track", "view", "uv"))
    Kall = np.stack([vd.cam.K for vd in vds])
    Tall = np.stack([vd.T for vd in vds])
    tri = triangulate_tracks(Kall[vid], Tall[vid], uv, track, n_tracks, max_err_px=cfg.max_err_px,
                             min_angle_deg=cfg.min_angle_deg, min_views=cfg.min_views)
    ok = tri.ok.copy()
    # a ground point lies below every camera that sees it (catches mismatches on walls and trees)
    np.minimum.at(cam_z := np.full(n_tracks, np.inf), track, Tall[vid, 2, 3])
    ok &= tri.points[:, 2] < cam_z - 0.3
    if not semantic and ok.any():
        ok[ok] &= within_corridor(tri.points[ok], seq.trajectory(), cfg.corridor_m)
    stats["triangulated"] = int(ok.sum())
    if cfg.neighbour_m > 0 and ok.any():
        ok[ok] &= agrees_with_neighbours(tri.points[ok], 1.0, cfg.neighbour_m)
    stats.update(tracks=int(n_tracks), t_total_s=round(time.perf_counter() - t0, 2))
    gp = _assemble(keys, tri, ok, np.concatenate(road), track, vid, uv, semantic, cfg.scale, stats)
    if len(gp) < min_points:
        gp.observable = False
        gp.reason = (f"only {len(gp)} ground points triangulated (need {min_points}): too little baseline or "
                     "road texture to observe the geometry")
    return gp


def _empty(keys, semantic, reason, stats) -> GroundPoints:
    z, i = np.zeros(0), np.zeros(0, np.int64)
    return GroundPoints(keys, np.zeros((0, 3)), i, z, z, z.astype(bool), i, i, np.zeros((0, 2)), z, semantic,
                        False, reason, stats)


def _assemble(keys, tri, ok, road, track, vid, uv, semantic, scale, stats) -> GroundPoints:
    keep_obs = ok[track] & tri.used
    new_id = np.cumsum(ok) - 1
    uv_full = (uv[keep_obs] + 0.5) / scale - 0.5
    return GroundPoints(keys, tri.points[ok], tri.n_views[ok], tri.rms_px[ok] / scale, tri.angle_deg[ok],
                        road[ok], new_id[track[keep_obs]], vid[keep_obs], uv_full, tri.depth[keep_obs], semantic,
                        True, "", stats)


def estimate_camera_height(seq: Sequence, gp: GroundPoints, *, radius: float = 4.0, max_radius: float = 12.0,
                           min_points: int = 30, road_only: bool = True) -> dict[str, HeightEstimate]:
    """Height of each camera above its local ground, per camera name, from ground points ``gp``.

    Each view's centre gets a robust local plane (RANSAC + Tukey IRLS over points within ``radius``,
    widened up to ``max_radius``); the camera's height is its median over frames. ``road_only`` fits the
    road's points (a camera's height is above the road, and kerbs / sidewalks sit 0.1-0.2 m higher).
    """
    pts = gp.points[gp.road] if road_only and gp.road.sum() >= min_points else gp.points
    out: dict[str, HeightEstimate] = {}
    for name in seq.cameras:
        centres = np.array([f.views[name].T_world_cam[:3, 3] for f in seq.frames if name in f.views])
        if not gp.observable:
            est = camera_height(centres, local_ground(np.zeros((0, 3)), centres))
            est.reason = gp.reason
        else:
            est = camera_height(centres, local_ground(pts, centres, radius=radius, max_radius=max_radius,
                                                      min_points=min_points))
        out[name] = est
    return out

