"""A pothole's floor from the images alone: a multi-view sweep of planes parallel to the road around it.

Without a depth layer nothing else measures a pothole's floor: stage 1's relief lattice is 0.5 m along the
road, and its ground points come from a sweep of level planes over the whole road, so inside a dent they sit
on the rims (:func:`pavemap.maintain._pothole_samples`). This sweep is local and dense instead. For each
pothole polygon:

1. the road plane around it: the surface's heights on a ring 0.25-0.65 m outside the polygon, a robust plane;
2. the reference view: the nearest view (any camera) that sees the polygon's whole box, within
   ``max_ref_range_m``; the partners: the next nearest ``partners`` views that see it from within
   ``max_view_angle_deg`` of the reference's direction and at most ``max_range_ratio`` times as far; of them
   only those whose view of a floor ``hidden_depth_m`` deep is not hidden by the near rim over more than
   ``max_hidden_share`` of the polygon's length (a flat, far view sees only the far wall); too coarse images
   (a pixel row longer than ``max_floor_pixel_m`` of road, or under ``min_px_per_cm`` of parallax per cm of
   depth) are not swept, and say so;
3. for each hypothesis depth δ (the road plane lowered by δ), each partner is warped onto the reference by
   the plane's homography, and each reference pixel of the pothole and its ring scores the zero-mean NCC of
   a ``window`` (rows x cols, wide: across the road the texture is not foreshortened), averaged over the
   partners;
4. each pixel keeps its best δ (a located peak, refined on a parabola, NCC at least ``min_ncc``); a median
   over ``median_px`` x ``median_px`` pixels takes out single wrong matches;
5. the road: the mode of the ring's δ; the floor's depths are taken relative to it;
6. the pixels whose ray enters the polygon and meets the floor in its interior give world points; their
   medians per ``cell_m`` cell of road, voted over 3 x 3 cells, are the samples.

It reads the images at their stored size: at 620 px wide (half KITTI's size) a pixel row covers 8-11 cm of the
road at a pothole 7-8 m away and a centimetre of depth moves it by 0.11-0.15 px, below what the floor's texture
can show; at 1241 px 3-5 cm and 0.22-0.48 px. What it measures against the truth and on the real samples:
``bench/floor_sweep_bench.py`` and docs/history's "Pothole depth from the images"; why it is off by default
(``maintenance.floor_sweep``) is there too.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import cv2
import numpy as np
import torch

from pavemap.geometry.camera import pixel_rays, project
from pavemap.io.sequence import load_gray
from pavemap.types import Sequence, View


@dataclass(frozen=True)
class FloorSweepConfig:
    """Settings of :func:`floor_samples` (metres and pixels of the stored images)."""

    window: tuple[int, int] = (3, 9)  # NCC window, rows x cols
    partners: int = 4
    max_ref_range_m: float = 12.0  # farther, a floor pixel covers more than its depth moves it
    max_partner_range_m: float = 25.0
    max_view_angle_deg: float = 25.0
    max_range_ratio: float = 2.0  # a partner this many times farther than the reference sees the floor blurred
    # the reference and its partners: with one partner a wrong match has no second view to disagree with it (on
    # plain road the nuScenes-like drive read up to 0.11 m of depth with 2 views, 28 mm with 3)
    min_views: int = 3
    # Each view must see the floor where it matters: a farther, flatter view sees a floor only beyond a strip behind
    # the near rim (depth x range / camera height), and averaging its matches in reads the floor short (docs/history's
    # "Pothole depth from the images"). A view is used only if it sees the middle of the polygon (the rim hides at
    # most half its length) on a floor 5 cm deep, FHWA's medium / high boundary.
    hidden_depth_m: float = 0.05
    max_hidden_share: float = 0.5
    depth_min_m: float = -0.03  # hypotheses: the road plane lowered by depth_min .. depth_max in depth_step
    depth_max_m: float = 0.15
    depth_step_m: float = 0.0025
    min_ncc: float = 0.5
    median_px: int = 5
    # The floor must be resolved: on half-size kitti-like frames (a pixel row 8-11 cm of road at the pothole,
    # 0.11-0.15 px of parallax per cm of depth) the depths came out 23 mm short (median) and half the potholes
    # got the wrong severity; at full size (3-5 cm, 0.22-0.48 px) 7 mm.
    max_floor_pixel_m: float = 0.06
    min_px_per_cm: float = 0.3
    cell_m: float = 0.04  # the samples' medians in cells of road this wide ...
    cell_min: int = 3  # ... holding at least this many
    cell_vote: int = 3
    min_ring_px: int = 50  # matched pixels of the road around it that place the road (else the surface does)
    margin_px: int = 10  # the polygon's box must lie this far inside the image
    ring_inner_m: float = 0.25
    ring_outer_m: float = 0.65
    # The samples keep to the polygon's interior: its outer ``interior_share`` of the equivalent radius (at least
    # ``interior_min_m``) holds the walls, which a level plane does not fit (a wall facing the camera matched up
    # to 0.1 m too deep on the nuScenes-like drive), and the road a mapped polygon takes in around the rim.
    interior_share: float = 0.3
    interior_min_m: float = 0.05


def floor_samples(seq: Sequence, polygons: list, surface, cfg: FloorSweepConfig | None = None  # noqa: ANN001
                  ) -> tuple[np.ndarray, list[str | None]]:
    """World points (N, 3) float64 on the floors of ``polygons`` (shapely polygons, world metres) measured by
    the sweep (module doc) on the road plane of ``surface`` (a :class:`~pavemap.geometry.HeightField`), and
    per polygon why none was measured (None where some were). Each point lies below its polygon's road plane
    (:func:`floor_sets`) by the floor's depth below the road as the images see it."""
    sets = floor_sets(seq, polygons, surface, cfg)
    return np.concatenate([np.zeros((0, 3))] + [p for p, _, _ in sets]), [w for _, w, _ in sets]


def floor_sets(seq: Sequence, polygons: list, surface, cfg: FloorSweepConfig | None = None  # noqa: ANN001
               ) -> list[tuple[np.ndarray, str | None, tuple[np.ndarray, np.ndarray] | None]]:
    """Per polygon: its floor points (N, 3), why none (or None), and the road plane they are measured from
    (point at the centroid (3,), unit upward normal (3,); None where no surface is around it)."""
    cfg = cfg or FloorSweepConfig()
    views = [v for f in seq.frames for v in f.views.values()]
    centres = np.array([np.asarray(v.T_world_cam)[:3, 3] for v in views]).reshape(-1, 3)
    images: dict[str, np.ndarray | None] = {}
    out = []
    none = np.zeros((0, 3))
    for poly in polygons:
        plane = _road_plane(poly, surface, cfg)
        seen = [] if plane is None else _views_seeing(seq, views, centres, poly, plane[0], cfg)
        if plane is None or len(seen) < 2:
            out.append((none, "no road surface around it" if plane is None else
                        f"no two views within {cfg.max_ref_range_m:g} m see it whole", plane))
            continue
        near = _partners(seen, plane[0], cfg)
        if len(near) < cfg.min_views:
            out.append((none, f"{len(near)} of {cfg.min_views} views needed see it from within "
                        f"{cfg.max_view_angle_deg:g} degrees of the nearest's direction and {cfg.max_range_ratio:g} "
                        "times its range", plane))
            continue
        vs = [v for v in near if _hidden_share(v, poly, plane, cfg.hidden_depth_m) <= cfg.max_hidden_share]
        if len(vs) < cfg.min_views or vs[0] is not near[0]:  # the partners were chosen around the nearest
            out.append((none, f"its near rim hides the middle of a {100 * cfg.hidden_depth_m:g} cm deep floor from "
                        f"{len(near) - len(vs)} of its {len(near)} views ({cfg.min_views} needed that see it)", plane))
            continue
        images = {v.image: images.get(v.image) for v in vs}  # the next pothole along the route shares most of them
        for v in vs:
            if images[v.image] is None:
                images[v.image] = load_gray(seq.path(v.image)).astype(np.float32)
        row_m = _floor_pixel_m(seq, vs[0], images[vs[0].image], plane)
        sens = _parallax_per_cm(seq, vs, images, plane)
        if row_m > cfg.max_floor_pixel_m or sens < cfg.min_px_per_cm:
            out.append((none, f"images too coarse: a pixel covers {100 * row_m:.0f} cm of it and 1 cm of depth moves "
                        f"it {sens:.2f} px (at most {100 * cfg.max_floor_pixel_m:g} cm, at least "
                        f"{cfg.min_px_per_cm:g} px)", plane))
            continue
        pts = _sweep_one(seq, vs, images, poly, plane, cfg)
        out.append((pts, None if len(pts) else "no view pair matched inside it", plane))
    return out


def _project(K: np.ndarray, T: np.ndarray, pts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """:func:`pavemap.geometry.camera.project` on numpy: pixels (N, 2) and camera depths (N,)."""
    uv, z = project(K, T, torch.from_numpy(np.asarray(pts, np.float64).reshape(-1, 3)))
    return uv.numpy(), z.numpy()


def _rays(K: np.ndarray, T: np.ndarray, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """:func:`pavemap.geometry.camera.pixel_rays` on numpy: origins (N, 3), directions (N, 3)."""
    o, d = pixel_rays(K, T, torch.from_numpy(np.asarray(uv, np.float64).reshape(-1, 2)))
    return o.numpy(), d.numpy()


def _on_plane(o: np.ndarray, d: np.ndarray, p0: np.ndarray, n: np.ndarray, depth: np.ndarray | float = 0.0
              ) -> np.ndarray:
    """(N, 3) where rays o + t d (N, 3) meet the plane through p0 with unit normal n, lowered by ``depth``
    (m, along n; a scalar or (N,))."""
    t = (n @ p0 - np.asarray(depth) - o @ n) / (d @ n)
    return o + t[:, None] * d


def _floor_pixel_m(seq: Sequence, ref: View, img: np.ndarray, plane: tuple[np.ndarray, np.ndarray]) -> float:
    """The road length (m) one reference pixel row covers at the polygon's centre: the plane points of the
    pixel there and of the one below it."""
    p0, n = plane
    T, K = np.asarray(ref.T_world_cam), _scaled_k(seq, ref, img)
    uv = _project(K, T, p0)[0][0]
    pts = _on_plane(*_rays(K, T, np.stack([uv, uv + [0.0, 1.0]])), p0, n)
    return float(np.linalg.norm(pts[1] - pts[0]))


def _parallax_per_cm(seq: Sequence, vs: list[View], images: dict[str, np.ndarray],
                     plane: tuple[np.ndarray, np.ndarray]) -> float:
    """Pixels (at the stored size) that 1 cm of depth at the polygon's centre moves its image in a partner,
    relative to the reference, at best over the partners."""
    p0, n = plane
    c = np.asarray(vs[0].T_world_cam)[:3, 3]
    deeper = _on_plane(c[None], (p0 - c)[None], p0, n, 0.01)[0]  # the reference ray through the centre, 1 cm down
    best = 0.0
    for v in vs[1:]:
        uv = _project(_scaled_k(seq, v, images[v.image]), np.asarray(v.T_world_cam), np.stack([p0, deeper]))[0]
        best = max(best, float(np.linalg.norm(uv[1] - uv[0])))
    return best


def _road_plane(poly, surface, cfg: FloorSweepConfig) -> tuple[np.ndarray, np.ndarray] | None:  # noqa: ANN001
    """(point on the plane at the polygon's centroid (3,), unit upward normal (3,)) from the surface's ring."""
    from shapely import contains_xy

    from pavemap.maintain.measure import robust_plane

    x0, y0, x1, y1 = poly.bounds
    r = cfg.ring_outer_m
    step = float(surface.res) / 2
    xs, ys = np.arange(x0 - r, x1 + r, step), np.arange(y0 - r, y1 + r, step)
    X, Y = (a.ravel() for a in np.meshgrid(xs, ys))
    ring = contains_xy(poly.buffer(cfg.ring_outer_m), X, Y) & ~contains_xy(poly.buffer(cfg.ring_inner_m), X, Y)
    if ring.sum() < 12:
        return None
    xy = torch.from_numpy(np.stack([X[ring], Y[ring]], 1)).to(surface.heights.dtype).to(surface.heights.device)
    z, inside = (t.detach().cpu().numpy() for t in surface.height_at(xy))
    if inside.sum() < 12:
        return None
    c = poly.centroid
    coef, _, _ = robust_plane(X[ring][inside] - c.x, Y[ring][inside] - c.y, z[inside].astype(np.float64))
    n = np.array([-coef[1], -coef[2], 1.0])
    return np.array([c.x, c.y, coef[0]]), n / np.linalg.norm(n)


def _box_corners(poly, p0: np.ndarray, n: np.ndarray) -> np.ndarray:  # noqa: ANN001
    """(4, 3) the polygon's box corners on the plane through p0 with normal n."""
    x0, y0, x1, y1 = poly.bounds
    xy = np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]], dtype=np.float64)
    z = p0[2] - (n[0] * (xy[:, 0] - p0[0]) + n[1] * (xy[:, 1] - p0[1])) / n[2]
    return np.c_[xy, z]


def _views_seeing(seq: Sequence, views: list[View], centres: np.ndarray, poly, p0: np.ndarray,  # noqa: ANN001
                  cfg: FloorSweepConfig) -> list[tuple[float, View]]:
    """(distance, view) of the views that see the polygon's whole box, nearest first; [] when the nearest is
    farther than ``max_ref_range_m``."""
    from pavemap.io.egomask import ego_mask_at

    dist = np.linalg.norm(centres - p0, axis=1) if len(centres) else np.zeros(0)
    corners = _box_corners(poly, p0, np.array([0.0, 0.0, 1.0]))
    seen, ego = [], {}
    for k in np.argsort(dist):
        if dist[k] > cfg.max_partner_range_m:
            break
        v = views[k]
        cam = seq.cameras[v.camera]
        T = np.asarray(v.T_world_cam)
        uv, depth = _project(cam.K, T, corners)
        if (depth < 1.0).any():
            continue
        m = cfg.margin_px
        if (uv < m).any() or (uv[:, 0] > cam.width - 1 - m).any() or (uv[:, 1] > cam.height - 1 - m).any():
            continue
        if v.camera not in ego:
            ego[v.camera] = ego_mask_at(seq, v.camera, cam.width, cam.height)
        if ego[v.camera] is not None:  # the bonnet hides it
            (c0, r0), (c1, r1) = np.floor(uv.min(0)).astype(int), np.ceil(uv.max(0)).astype(int)
            if ego[v.camera][r0:r1 + 1, c0:c1 + 1].any():
                continue
        seen.append((float(dist[k]), v))
    return seen if seen and seen[0][0] <= cfg.max_ref_range_m else []


def _hidden_share(v: View, poly, plane: tuple[np.ndarray, np.ndarray], depth_m: float) -> float:  # noqa: ANN001
    """The share of the polygon's length along the view's direction that its near rim hides from ``v`` on a floor
    ``depth_m`` below the road plane (steep walls): a view at range D and height h above the road sees such a floor
    only from depth_m * D / h past the rim. A pothole fused from parts: its largest part, whose own near rim
    hides its floor."""
    p0, n = plane
    c = np.asarray(v.T_world_cam)[:3, 3]
    along = p0[:2] - c[:2]
    dist = max(float(np.linalg.norm(along)), 1e-6)
    part = max(getattr(poly, "geoms", [poly]), key=lambda g: g.area)
    extent = np.asarray(part.exterior.coords)[:, :2] @ (along / dist)
    return depth_m * dist / max(float((c - p0) @ n), 1e-6) / max(float(extent.max() - extent.min()), 1e-6)


def _partners(seen: list[tuple[float, View]], p0: np.ndarray, cfg: FloorSweepConfig) -> list[View]:
    """The reference (nearest) and up to ``partners`` next nearest views that look at p0 from a direction within
    ``max_view_angle_deg`` of the reference's (a rig's camera looking back at it sees another road texture)."""
    dirs = np.array([p0 - np.asarray(v.T_world_cam)[:3, 3] for _, v in seen])
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    ok = (dirs @ dirs[0] >= np.cos(np.radians(cfg.max_view_angle_deg))) & (
        np.array([d for d, _ in seen]) <= cfg.max_range_ratio * seen[0][0])
    return [v for (_, v), k in zip(seen, ok, strict=True) if k][:cfg.partners + 1]


def _scaled_k(seq: Sequence, v: View, img: np.ndarray) -> np.ndarray:
    cam = seq.cameras[v.camera]
    return cam.K if img.shape[1] == cam.width else cam.scaled(img.shape[1] / cam.width).K


def _sweep_one(seq: Sequence, vs: list[View], images: dict[str, np.ndarray], poly,  # noqa: ANN001
               plane: tuple[np.ndarray, np.ndarray], cfg: FloorSweepConfig) -> np.ndarray:
    """World points (N, 3) on one pothole's floor: reference vs[0], partners vs[1:] (module doc, 3-5)."""
    from shapely import contains_xy

    p0, nW = plane
    ref, img_r = vs[0], images[vs[0].image]
    Kr = _scaled_k(seq, ref, img_r)
    T = np.asarray(ref.T_world_cam)
    Rr, tr = T[:3, :3], T[:3, 3]
    uv = _project(Kr, T, _box_corners(poly.buffer(cfg.ring_outer_m), p0, nW))[0]  # the pothole and its ring
    h, w = img_r.shape
    u0, v0 = np.maximum(np.floor(uv.min(0)).astype(int) - 8, 0)
    u1, v1 = np.minimum(np.ceil(uv.max(0)).astype(int) + 8, [w - 1, h - 1])
    crop = img_r[v0:v1 + 1, u0:u1 + 1]
    n_c = Rr.T @ nW  # the plane n_c . X = d in reference camera coordinates
    deltas = np.arange(cfg.depth_min_m, cfg.depth_max_m + 1e-9, cfg.depth_step_m)
    score, seen = _scores(seq, vs, images, crop, Kr, Rr, tr, n_c, p0, nW, deltas, (u0, v0), cfg)
    depth, ok = _best_depths(score, deltas, cfg)
    ok, depth = (ok & seen).ravel(), depth.ravel()
    uu, vv = np.meshgrid(np.arange(u0, u1 + 1), np.arange(v0, v1 + 1))
    o, d = _rays(Kr, T, np.stack([uu.ravel(), vv.ravel()], 1))  # (P, 3) world
    at0 = _on_plane(o, d, p0, nW)
    ring = ok & contains_xy(poly.buffer(cfg.ring_outer_m), at0[:, 0], at0[:, 1]) & ~contains_xy(
        poly.buffer(cfg.ring_inner_m), at0[:, 0], at0[:, 1])
    keep = ok & contains_xy(poly, at0[:, 0], at0[:, 1])
    dk = depth[keep] - _road_offset(depth[ring], cfg)
    pts = _on_plane(o[keep], d[keep], p0, nW, dk)
    # the ray enters the polygon and meets the floor in its interior: a match too deep on the far wall puts its
    # point past the far rim, and a window before the near rim that takes in the dark floor is left out
    inset = max(cfg.interior_min_m, cfg.interior_share * float(np.sqrt(poly.area / np.pi)))
    inner = contains_xy(poly.buffer(-inset), pts[:, 0], pts[:, 1])
    return _cell_medians(pts[inner], dk[inner], p0, nW, cfg)


def _road_offset(ring_depths: np.ndarray, cfg: FloorSweepConfig) -> float:
    """Where the images put the road around the pothole, below the surface's ring plane (m): the mode of the
    ring's depths (1 mm bins, smoothed), 0 with fewer than ``min_ring_px`` of them. The surface's ring sits a few
    mm into the dent (its smoothing: 1-9 mm on the bench's drives); the ring's matches have a long deep tail
    (p75 up to 44 mm on the nuScenes-like drive: other defects, kerbs, windows half outside a partner), which
    moves their median by up to 7 mm and their mode by under 2."""
    if len(ring_depths) < cfg.min_ring_px:
        return 0.0
    edges = np.arange(cfg.depth_min_m, cfg.depth_max_m + 0.001, 0.001)
    hist = np.histogram(ring_depths, bins=edges)[0].astype(np.float64)
    hist = np.convolve(hist, np.exp(-0.5 * (np.arange(-6, 7) / 2.0) ** 2), mode="same")
    return float(edges[int(hist.argmax())] + 0.0005)


def _cell_medians(pts: np.ndarray, depth: np.ndarray, p0: np.ndarray, n: np.ndarray, cfg: FloorSweepConfig
                  ) -> np.ndarray:
    """One point per ``cell_m`` square of road holding at least ``cell_min`` samples: at the median depth of its
    samples below the plane (p0, n), at their mean x, y. Wrong matches are scattered (2-10 % of the samples on
    the nuScenes-like drive, most on the far wall), so a quantile of the raw samples is theirs, not the floor's."""
    if not len(pts):
        return pts
    ij = np.floor((pts[:, :2] - p0[:2]) / cfg.cell_m).astype(np.int64)
    _, cell, count = np.unique(ij, axis=0, return_inverse=True, return_counts=True)
    cell = cell.ravel()
    order = np.lexsort((depth, cell))
    starts = np.r_[0, np.cumsum(count)[:-1]]
    med = 0.5 * (depth[order][starts + (count - 1) // 2] + depth[order][starts + count // 2])
    xy = np.stack([np.bincount(cell, pts[:, k], len(count)) / count for k in (0, 1)], 1)
    ok = count >= cfg.cell_min
    if not ok.any():
        return np.zeros((0, 3))
    u = np.unique(ij, axis=0)
    med, xy, u = med[ok], xy[ok], u[ok]
    # a floor is continuous: each cell takes the median of its ``cell_vote`` x ``cell_vote`` neighbourhood (more
    # than half of it measured), so a patch of wrong matches smaller than about half of it is voted down
    k = cfg.cell_vote
    lo = u.min(0) - k // 2
    grid = np.full(tuple(u.max(0) - lo + k), np.nan)
    grid[u[:, 0] - lo[0], u[:, 1] - lo[1]] = med
    nb = np.lib.stride_tricks.sliding_window_view(np.pad(grid, k // 2, constant_values=np.nan), (k, k))
    nb = nb.reshape(*grid.shape, k * k)[u[:, 0] - lo[0], u[:, 1] - lo[1]]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        smooth = np.nanmedian(nb, axis=1)
    keep = np.isfinite(nb).sum(1) > k * k // 2
    z = p0[2] - (n[0] * (xy[:, 0] - p0[0]) + n[1] * (xy[:, 1] - p0[1])) / n[2] - smooth / n[2]
    return np.c_[xy, z][keep]


def _scores(seq: Sequence, vs: list[View], images: dict[str, np.ndarray], crop: np.ndarray, Kr: np.ndarray,
            Rr: np.ndarray, tr: np.ndarray, n_c: np.ndarray, p0: np.ndarray, nW: np.ndarray, deltas: np.ndarray,
            origin: tuple[int, int], cfg: FloorSweepConfig) -> tuple[np.ndarray, np.ndarray]:
    """(S, h, w) float32 NCC of each reference pixel's window, averaged over the partners, per hypothesis, and
    (h, w) bool whether the window lies inside every partner."""
    k = (cfg.window[1], cfg.window[0])  # OpenCV's (width, height)

    def box(a: np.ndarray) -> np.ndarray:
        return cv2.boxFilter(a, -1, k, borderType=cv2.BORDER_REFLECT)

    rm = box(crop)
    rv = box(crop * crop) - rm * rm
    to_crop = np.array([[1.0, 0.0, origin[0]], [0.0, 1.0, origin[1]], [0.0, 0.0, 1.0]])
    Kinv = np.linalg.inv(Kr) @ to_crop
    partners = []
    for v in vs[1:]:
        img = images[v.image]
        T2 = np.asarray(v.T_world_cam)
        partners.append((img, _scaled_k(seq, v, img), T2[:3, :3].T @ Rr, T2[:3, :3].T @ (tr - T2[:3, 3])))
    score = np.zeros((len(deltas), *crop.shape), np.float32)
    seen = np.ones(crop.shape, bool)  # the window lies inside every partner (at the middle hypothesis)
    d_mid = float(n_c @ (Rr.T @ (p0 - deltas[len(deltas) // 2] * nW - tr)))
    for img, K2, R21, t21 in partners:
        H = K2 @ (R21 + np.outer(t21, n_c) / d_mid) @ Kinv
        inside = cv2.warpPerspective(np.ones(img.shape, np.float32), H, (crop.shape[1], crop.shape[0]),
                                     flags=cv2.INTER_NEAREST | cv2.WARP_INVERSE_MAP, borderValue=0.0)
        seen &= box(inside) > 0.999
    for s, dl in enumerate(deltas):
        d_c = float(n_c @ (Rr.T @ (p0 - dl * nW - tr)))
        for img, K2, R21, t21 in partners:
            H = K2 @ (R21 + np.outer(t21, n_c) / d_c) @ Kinv
            warped = cv2.warpPerspective(img, H, (crop.shape[1], crop.shape[0]),
                                         flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP, borderMode=cv2.BORDER_REPLICATE)
            wm = box(warped)
            cov = box(crop * warped) - rm * wm
            score[s] += cov / np.sqrt(np.maximum(rv * (box(warped * warped) - wm * wm), 1e-6))
    return score / max(len(partners), 1), seen


def _best_depths(score: np.ndarray, deltas: np.ndarray, cfg: FloorSweepConfig) -> tuple[np.ndarray, np.ndarray]:
    """Per pixel: the best depth (h, w), parabola-refined and median-filtered, and whether it is kept."""
    best = score.argmax(0)
    b = np.clip(best, 1, len(deltas) - 2)
    s0, s1, s2 = (np.take_along_axis(score, (b + o)[None], 0)[0] for o in (-1, 0, 1))
    den = s0 - 2 * s1 + s2
    off = np.where(den < -1e-6, 0.5 * (s0 - s2) / np.where(den < -1e-6, den, -1.0), 0.0)
    depth = deltas[b] + np.clip(off, -1, 1) * (deltas[1] - deltas[0])
    # a best score at either end of the range is no located peak
    located = (best > 0) & (best < len(deltas) - 1)
    depth = np.where((np.take_along_axis(score, best[None], 0)[0] >= cfg.min_ncc) & located, depth, np.nan)
    r = cfg.median_px // 2
    padded = np.pad(depth, r, mode="edge")
    win = np.lib.stride_tricks.sliding_window_view(padded, (cfg.median_px, cfg.median_px))
    with warnings.catch_warnings():  # all-NaN windows warn; they are expected, and dropped
        warnings.simplefilter("ignore", RuntimeWarning)
        med = np.nanmedian(win.reshape(*depth.shape, -1), axis=-1)
    ok = np.isfinite(depth) & np.isfinite(med)
    return np.where(ok, med, 0.0), ok


__all__ = ["FloorSweepConfig", "floor_samples", "floor_sets"]
