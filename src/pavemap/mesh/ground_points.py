"""Ground points triangulated from a sequence's images with its poses held fixed, and the camera height
they imply: the road's geometry when there is no depth sensor (issue 12).

Each reference view's corners on the ground are matched into later views (the same camera's next
``max_gap`` frames and other cameras of the rig where their ground overlaps) by a *patch sweep* along the
epipolar line (:mod:`pavemap.mesh.ground_sweep`): every depth hypothesis of a corner's ray puts a horizontal
plane through that point, the plane's homography warps the corner's patch into the partner, and zero-mean NCC
scores it (coarse 2 px steps over the whole depth range, then 1 px, then sub-pixel parabola fits). A far pass
matches the road 20-60 m ahead of the path's ends into partners 2 and 4 m on, three views a point, so the
mesh over the road the last frames see is observed too (issue 12 item 4). It is exact for a locally flat
road, immune to exposure changes between frames, and rejects patches whose NCC peak is flat or repeated
along the line (an edge running with the epipolar line: lane markings in forward motion; why not pyramidal
LK: docs/history, Geometry without LiDAR). The prior camera height only centres the search; triangulation
(:mod:`pavemap.geometry.triangulate`) uses the matched pixels and the poses. The stage-1 side (camera height,
sparse depth, self-check) is :mod:`pavemap.mesh.geometry`.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace

import cv2
import numpy as np

from pavemap.geometry.range_mask import range_mask
from pavemap.geometry.road_height import HeightEstimate, camera_heights, height_estimate
from pavemap.geometry.triangulate import (
    agrees_with_neighbours,
    plane_homography,
    triangulate_tracks,
    within_corridor,
)
from pavemap.io.egomask import ego_mask_at
from pavemap.io.sequence import load_rgb, load_semantics
from pavemap.mesh.config import GroundConfig
from pavemap.mesh.ground_sweep import Z_UP, Patches, ViewData, moved_points, sweep_match
from pavemap.mesh.init_surface import travel_direction
from pavemap.types import Camera, Sequence, View

RgbHook = Callable[[View, np.ndarray], None]


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


def _range_mask(cam: Camera, T: np.ndarray, cfg: GroundConfig, far: bool = False) -> np.ndarray:
    """(H, W) bool: pixels below the horizon margin whose ray meets the prior plane within the range
    (``far``: the far pass's margin and range)."""
    margin = cfg.far_horizon_deg if far else cfg.horizon_margin_deg
    lo, hi = (0.8 * cfg.max_range, cfg.far_range) if far else (cfg.min_range, cfg.max_range)
    return range_mask(cam.K, T[:3, :3], (cam.height, cam.width), cfg.prior_height, margin, lo, hi)


def _load(seq: Sequence, vd: ViewData, view: View, cfg: GroundConfig, ground_lut, road_lut, far: bool = False,
          on_rgb: RgbHook | None = None) -> None:
    cam = vd.cam
    size = (cam.width, cam.height)
    rgb = load_rgb(seq.path(view.image))
    if on_rgb is not None:
        on_rgb(view, rgb)
    grey = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)
    if grey.shape[::-1] != size:
        grey = cv2.resize(grey, size, interpolation=cv2.INTER_AREA)
    # a light blur makes bilinear samples at any sub-pixel phase alike, else NCC peaks lock onto whole pixels
    # (an image pyramid for the coarse search was tried: the road's fine texture is gone two levels up)
    vd.img = cv2.GaussianBlur(grey.astype(np.float32), (0, 0), 0.8)
    mask = np.ones((cam.height, cam.width), bool)
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
    if far:
        vd.far_mask = mask & _range_mask(cam, vd.T, cfg, far=True)
    vd.grey, vd.mask = grey, mask & _range_mask(cam, vd.T, cfg)


# ---------------------------------------------------------------------------- pairs, filters, driver


def _overlap(a: ViewData, b: ViewData, H: np.ndarray, step: int = 16) -> float:
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


def _overlap_between(a: ViewData, b: ViewData, cfg: GroundConfig) -> float:
    """:func:`_overlap` of a's ground in b through the prior road plane under a."""
    return _overlap(a, b, plane_homography(a.cam.K, a.T, b.cam.K, b.T, Z_UP, float(a.T[2, 3] - cfg.prior_height)))


def _partners(vds: list[ViewData], i: int, cfg: GroundConfig,
              overlaps: dict[tuple[int, int], float] | None = None) -> list[int]:
    """Views within ``max_gap`` frames, earlier or later (same frame other cameras too), that see enough of i's
    ground and whose pair is i's to match: each pair is matched once, from the view whose ground the other sees
    more of. Going forwards that is the view ahead: its near road, sharp and textured, lies in the view behind,
    farther off, while the view behind sees its own near road not at all from ahead (on a 2 Hz synthetic
    nuScenes-like drive matching from the view behind found 347 points, from the view ahead 1,949). A clip
    numbered backwards, a reversing car and a rear camera get the same pairs. ``overlaps`` caches
    :func:`_overlap_between` by (from, to) view: each pair is judged from both of its views."""
    a = vds[i]
    lo = hi = i  # views are in frame order
    while lo > 0 and a.pos - vds[lo - 1].pos <= cfg.max_gap:
        lo -= 1
    while hi + 1 < len(vds) and vds[hi + 1].pos - a.pos <= cfg.max_gap:
        hi += 1
    cands = [j for j in range(lo, hi + 1) if j != i]
    overlaps, out = {} if overlaps is None else overlaps, []
    for j in sorted(cands, key=lambda j: (abs(vds[j].pos - a.pos), j)):
        b = vds[j]
        if len(out) >= cfg.max_partners:
            break
        if np.linalg.norm(b.T[:3, 3] - a.T[:3, 3]) < 0.05 or b.img is None or b.mask is None:
            continue  # no baseline: a stationary vehicle gives no depth
        for key in ((i, j), (j, i)):
            if key not in overlaps:
                overlaps[key] = _overlap_between(vds[key[0]], vds[key[1]], cfg)
        mine, theirs = overlaps[i, j], overlaps[j, i]
        if mine >= cfg.min_overlap and (mine > theirs or (mine == theirs and i < j)):
            out.append(j)
    return out


def _far_partners(vds: list[ViewData], i: int, cfg: GroundConfig) -> list[int]:
    """The far pass's two partners of view i: the first later views of its camera half ``far_baseline_m`` and
    ``far_baseline_m`` away (the next one when both are the same), or none: a far point must be seen thrice."""
    a = vds[i]
    out: list[int] = []
    for j in range(i + 1, len(vds)):
        b = vds[j]
        if b.pos - a.pos > cfg.far_max_gap or b.img is None:
            break
        if b.key[1] == a.key[1]:
            base = np.linalg.norm(b.T[:3, 3] - a.T[:3, 3])
            if (not out and base >= cfg.far_baseline_m / 2) or (out and base >= cfg.far_baseline_m):
                out.append(j)
                if len(out) == 2:
                    return out
    return []


@dataclass
class _Tracks:
    """Observations (track, view, uv) gathered by :func:`_match_all`, the road flag of each track's
    reference pixel, the track count and counters."""

    stats: dict
    obs: dict[str, list[np.ndarray]] = field(default_factory=lambda: {"track": [], "view": [], "uv": []})
    road: list[np.ndarray] = field(default_factory=list)
    far: list[np.ndarray] = field(default_factory=list)  # the far pass's track ids
    moved: list[np.ndarray] = field(default_factory=list)  # track ids the other views contradict
    n: int = 0

    def add(self, track: np.ndarray, view: int, uv: np.ndarray) -> None:
        for k, x in (("track", track), ("view", np.full(len(track), view)), ("uv", uv)):
            self.obs[k].append(x)


def _corners(grey: np.ndarray, mask: np.ndarray, n: int, cfg: GroundConfig, pad: int = 4) -> np.ndarray | None:
    """(N, 2) float64 Shi-Tomasi corners of ``grey`` (H, W) within ``mask``, or None. Found in the rows the mask
    spans (plus ``pad``, so every masked pixel's response is the full image's): the far mask is a thin band."""
    rows = np.flatnonzero(mask.any(1))
    if len(rows) == 0:
        return None
    r0, r1 = max(rows[0] - pad, 0), min(rows[-1] + 1 + pad, len(mask))
    c = cv2.goodFeaturesToTrack(grey[r0:r1], n, cfg.quality, cfg.min_distance, mask=mask[r0:r1].astype(np.uint8))
    return None if c is None else c.reshape(-1, 2).astype(np.float64) + [0.0, r0]


def _match_corners(vds: list[ViewData], i: int, mask: np.ndarray, n_corners: int, partners: list[int],
                   cfg: GroundConfig, acc: _Tracks, normal: np.ndarray = Z_UP, check: bool = True) -> None:
    """View i's corners within ``mask`` (H, W) bool matched into ``partners``, added to ``acc``; the sweep's
    planes have the world ``normal`` (3,). ``check``: single matches the other views contradict go to
    ``acc.moved`` (the far pass keeps only points seen thrice anyway)."""
    a = vds[i]
    corners = _corners(a.grey, mask, n_corners, cfg)
    if corners is None:
        return
    tid = acc.n + np.arange(len(corners))
    ci = np.rint(corners).astype(np.int64)
    acc.road.append(np.ones(len(corners), bool) if a.road is None else a.road[ci[:, 1], ci[:, 0]])
    acc.add(tid, i, corners)
    tau = np.full(len(corners), np.nan)  # log depth found so far (narrows later partners' search)
    patches = Patches(a, corners, cfg, normal)
    matched = np.zeros((len(corners), len(partners)), bool)
    for k, j in enumerate(partners):
        idx, uv_b, t = sweep_match(a, vds[j], corners, cfg, tau, patches)
        tau[idx] = np.where(np.isfinite(tau[idx]), tau[idx], t)
        matched[idx, k] = True
        acc.stats["pairs"] += 1
        acc.stats["matches"] += len(idx)
        acc.add(tid[idx], j, uv_b)
    if check and cfg.static_ncc > 0:
        moved = moved_points(vds, i, corners, tau, matched, partners, cfg, patches)
        acc.moved.append(tid[moved])
        acc.stats["moved"] = acc.stats.get("moved", 0) + int(moved.sum())
    acc.n += len(corners)


@dataclass
class _FarPlan:
    """The far pass: its reference views ref (V,) bool, each one's sweep plane normal (V, 3) (the road's
    grade at the end it looks out of), and the path's ends {0: first, -1: last} as (end point (2,), unit
    direction out of the path (2,))."""

    ref: np.ndarray
    normal: np.ndarray
    ends: dict[int, tuple[np.ndarray, np.ndarray]]


def _far_plan(vds: list[ViewData], traj: np.ndarray, cfg: GroundConfig, grade_m: float = 10.0) -> _FarPlan:
    """The far pass serves the road beyond the path's ends (traj (F, 3)), which no later view comes nearer to:
    its references are every ``far_every``-th frame within ``far_range`` of path of an end, cameras looking
    out of it (within 45 degrees); its points are kept beyond an end only (nearer road has the near pass's).
    Its planes follow the grade of the last ``grade_m`` of path: 30 m ahead a patch spans ~10 m of road, and
    a level plane on a 2 % grade put the points 5 cm low."""
    plan = _FarPlan(np.zeros(len(vds), bool), np.tile(Z_UP, (len(vds), 1)), {})
    if cfg.far_range <= cfg.max_range or len(traj) < 2:
        return plan
    along = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(traj[:, :2], axis=0), axis=1))])
    pos = np.array([vd.pos for vd in vds])
    axis = np.stack([vd.T[:2, 2] for vd in vds])
    level = np.linalg.norm(axis, axis=1)
    for end in (0, -1):
        out = travel_direction(traj[:, :2], end)
        if out is None:
            continue
        plan.ends[end] = (traj[end, :2], out)
        near = np.abs(along - along[end]) <= grade_m
        rise = np.polyfit(along[near], traj[near, 2], 1)[0] * (1 if end == -1 else -1) if near.sum() >= 2 else 0.0
        n = np.array([-rise * out[0], -rise * out[1], 1.0])
        mine = ((np.abs(along[pos] - along[end]) <= cfg.far_range) & (pos % cfg.far_every == 0) & (level > 0.5)
                & (axis @ out >= np.cos(np.pi / 4) * level))
        plan.ref |= mine
        plan.normal[mine] = n / np.linalg.norm(n)
    return plan


def _match_all(seq: Sequence, vds: list[ViewData], views: list[View], cfg: GroundConfig, far: _FarPlan,
               on_rgb: RgbHook | None) -> _Tracks:
    """Corners of every view matched into its partners and, for the far pass's references, far corners into
    two partners up to ``far_baseline_m`` away. Views are loaded lazily and dropped once no later
    reference needs them."""
    luts = (seq.class_lut("ground") & ~seq.class_lut("movable"), seq.class_lut("road"))
    acc = _Tracks({"views": len(vds), "pairs": 0, "matches": 0, "far_pairs": 0})
    overlaps: dict[tuple[int, int], float] = {}  # a pair's overlaps, judged from both of its views
    loaded = dropped = 0
    for i, a in enumerate(vds):
        while loaded < len(vds) and (
                vds[loaded].pos - a.pos <= cfg.max_gap
                or (far.ref[i] and vds[loaded].pos - a.pos <= cfg.far_max_gap
                    and np.linalg.norm(vds[loaded - 1].T[:3, 3] - a.T[:3, 3]) < cfg.far_baseline_m)):
            _load(seq, vds[loaded], views[loaded], cfg, *luts, far=bool(far.ref[loaded]), on_rgb=on_rgb)
            loaded += 1
        while vds[dropped].pos < a.pos - cfg.max_gap:  # an image is kept while a later reference checks in it
            vds[dropped].img = vds[dropped].mask = None
            for key in [k for k in overlaps if dropped in k]:  # no later view pairs with it
                del overlaps[key]
            dropped += 1
        _match_corners(vds, i, a.mask, cfg.max_corners, _partners(vds, i, cfg, overlaps), cfg, acc)
        if a.far_mask is not None and (partners := _far_partners(vds, i, cfg)):
            first = acc.n
            _match_corners(vds, i, a.far_mask, cfg.far_corners, partners, cfg, acc, far.normal[i], check=False)
            acc.far.append(np.arange(first, acc.n))
            acc.stats["far_pairs"] += 1
        a.grey = a.label_ok = a.road = a.far_mask = None  # the mask stays while a later view may pair with a
    for vd in vds[dropped:]:
        vd.img = vd.mask = None
    return acc


def find_ground_points(seq: Sequence, cfg: GroundConfig | None = None, min_points: int = 50,
                       on_rgb: RgbHook | None = None) -> GroundPoints:
    """Triangulated ground points of ``seq`` (poses fixed). See the module docstring for the method.
    ``on_rgb(view, rgb)`` receives every view's decoded full-resolution image (H, W, 3) uint8.

    Without semantics (or ``use_semantics=False``) ground is what lies below the horizon, within
    ``max_range`` on the prior plane, below its cameras and within ``corridor_m`` of the trajectory.
    ``observable`` is False (with the reason) below ``min_points`` points.

    A road far from the prior height (poses with a wrong scale) enters the searched ``sweep_range`` only in part,
    and those points pull the height to the prior (poses x2: 2.3 m for 3.3 m); a height in the outer half of
    the range repeats the search centred on it (``stats["recentred_from_m"]``: the prior it left).
    """
    cfg = cfg or GroundConfig()
    gp = _find_ground_points(seq, cfg, min_points, on_rgb)
    if not gp.observable:
        return gp
    found = [e.median for e in estimate_camera_height(seq, gp).values() if e.observable]
    h = float(np.median(found)) if found else float("nan")
    if not (np.isfinite(h) and h > 0 and abs(np.log(h / cfg.prior_height)) > cfg.sweep_range / 2):
        return gp
    again = _find_ground_points(seq, replace(cfg, prior_height=h), min_points, None)
    again.stats["recentred_from_m"] = round(cfg.prior_height, 3)
    return again


def _find_ground_points(seq: Sequence, cfg: GroundConfig, min_points: int, on_rgb: RgbHook | None
                        ) -> GroundPoints:
    """One search of :func:`find_ground_points`, centred on ``cfg.prior_height``."""
    t0 = time.perf_counter()
    vds, views = [], []
    for pos, f in enumerate(seq.frames):
        for name, v in f.views.items():
            vds.append(ViewData((f.index, name), pos, seq.cameras[name].scaled(cfg.scale), v.T_world_cam))
            views.append(v)
    semantic = cfg.use_semantics and any(v.semantics for v in views)
    traj = seq.trajectory()
    traj_xy = traj[:, :2]
    far = _far_plan(vds, traj, cfg)
    ends = far.ends
    acc = _match_all(seq, vds, views, cfg, far, on_rgb)
    obs, road, n_tracks, stats = acc.obs, acc.road, acc.n, acc.stats
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
    if acc.moved:
        ok[np.concatenate(acc.moved)] = False
    # a ground point lies below every camera that sees it (catches mismatches on walls and trees)
    np.minimum.at(cam_z := np.full(n_tracks, np.inf), track, Tall[vid, 2, 3])
    ok &= tri.points[:, 2] < cam_z - 0.3
    if acc.far:  # the far pass's points beyond the path's ends only
        far = np.zeros(n_tracks, bool)
        far[np.concatenate(acc.far)] = True
        beyond = np.zeros(n_tracks, bool)
        for p, out in ends.values():
            beyond |= (tri.points[:, :2] - p) @ out > 0
        ok &= ~far | (beyond & (tri.n_views >= 3))
    if not semantic and ok.any():  # the corridor continues straight beyond the ends, as the far pass looks
        ext = {end: p + np.arange(cfg.far_range, 0, -1.0)[:, None] * out for end, (p, out) in ends.items()}
        path = np.concatenate([ext.get(0, np.zeros((0, 2))), traj_xy, ext.get(-1, np.zeros((0, 2)))[::-1]])
        ok[ok] &= within_corridor(tri.points[ok], np.c_[path, np.zeros(len(path))], cfg.corridor_m)
    stats["triangulated"] = int(ok.sum())
    if cfg.neighbour_m > 0 and ok.any():
        ok[ok] &= agrees_with_neighbours(tri.points[ok], 1.0, cfg.neighbour_m)
    stats.update(tracks=int(n_tracks), t_total_s=round(time.perf_counter() - t0, 2))
    sxy = view_scale_xy(seq.cameras, keys, cfg.scale)
    gp = _assemble(keys, tri, ok, np.concatenate(road), track, vid, uv, semantic, cfg.scale, sxy, stats)
    if len(gp) < min_points:
        gp.observable = False
        gp.reason = (f"only {len(gp)} ground points triangulated (need {min_points}): too little baseline or "
                     "road texture to observe the geometry")
    return gp


def view_scale_xy(cameras: dict[str, Camera], views: list, scale: float) -> np.ndarray:
    """(V, 2) float64 each view's true (x, y) factor of an image resize by ``scale`` (:meth:`Camera.scale_xy`);
    ``views``: (frame, camera name) keys."""
    return np.array([cameras[k[1]].scale_xy(scale) for k in views], np.float64).reshape(-1, 2)


def _empty(keys, semantic, reason, stats) -> GroundPoints:
    z, i = np.zeros(0), np.zeros(0, np.int64)
    return GroundPoints(keys, np.zeros((0, 3)), i, z, z, z.astype(bool), i, i, np.zeros((0, 2)), z, semantic,
                        False, reason, stats)


def _assemble(keys, tri, ok, road, track, vid, uv, semantic, scale, sxy, stats) -> GroundPoints:
    keep_obs = ok[track] & tri.used
    new_id = np.cumsum(ok) - 1
    # each axis by its true factor sxy (V, 2) of the view (Camera.scale_xy: the scaled K's), not ``scale``
    uv_full = (uv[keep_obs] + 0.5) / sxy[vid[keep_obs]] - 0.5
    return GroundPoints(keys, tri.points[ok], tri.n_views[ok], tri.rms_px[ok] / scale, tri.angle_deg[ok],
                        road[ok], new_id[track[keep_obs]], vid[keep_obs], uv_full, tri.depth[keep_obs], semantic,
                        True, "", stats)


def estimate_camera_height(seq: Sequence, gp: GroundPoints, *, min_points: int = 30,
                           road_only: bool = True) -> dict[str, HeightEstimate]:
    """Height of each camera above the road it drives over, per camera name, from ground points ``gp``
    (:func:`pavemap.geometry.road_height.camera_heights` along the camera's own path; the camera's height is
    the median over its frames). ``road_only`` uses the road's points when at least ``min_points`` are (a
    camera's height is above the road, and kerbs / sidewalks sit 0.1-0.2 m higher)."""
    pts = gp.points[gp.road] if road_only and gp.road.sum() >= min_points else gp.points
    out: dict[str, HeightEstimate] = {}
    for name in seq.cameras:
        centres = np.array([f.views[name].T_world_cam[:3, 3] for f in seq.frames if name in f.views])
        if not gp.observable:
            est = height_estimate(np.full(len(centres), np.nan))
            est.reason = gp.reason
        else:
            est = height_estimate(camera_heights(pts, centres, Z_UP))
        out[name] = est
    return out

