"""Detection -> surface-vertex association (SPEC §3, §5), vectorised over detections.

Three modes, all returning (detection, vertex) pairs:

- ``ray`` (paper): vertices whose distance to the box-centre ray is below
  ``d_thresh = beta0 * r + beta1 * (1 - conf)``. Candidates come only from grid cells near the
  ray's ground track where the ray passes within reach of the surface (spatial pruning), never
  from all vertices.
- ``hit``: intersect the centre ray with the surface, take the valid vertices within
  ``hit_radius_m`` (horizontal) of the hit point.
- ``footprint``: intersect a G x G grid of rays over the box; candidate vertices are those in
  the hits' bounding rectangle; a vertex is associated when it projects inside the box (exactly
  "the vertices under the box's footprint on the surface").

Per detection we also record whether it is mapped and its distance (``ray``: to the nearest
vertex from the ray; ``hit`` / ``footprint``: hit point to nearest associated vertex).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch

from pavemap.fuse.config import FusionConfig
from pavemap.fuse.footprint import footprint_quads, shoelace
from pavemap.geometry.camera import pixel_rays
from pavemap.types import Detection, Sequence

CHUNK = 2048  # detections per batch: bounds the candidate tensors to a few million entries


@dataclass
class Association:
    """det (P,) long and vid (P,) long flat vertex ids ``j*nx+i``, unique pairs;
    mapped (N,) bool; distance (N,) float64 (nan when unmapped); hit (N, 3) float64 (nan on a miss)."""

    det: torch.Tensor
    vid: torch.Tensor
    mapped: torch.Tensor
    distance: torch.Tensor
    hit: torch.Tensor


@dataclass
class DetectionBatch:
    """N detections as tensors on one device: boxes (N, 4) float64 ``x1 y1 x2 y2`` pixels, K (N, 3, 3)
    float64 and T (N, 4, 4) float64 camera-to-world of each detection's view, conf (N,) float64."""

    boxes: torch.Tensor
    K: torch.Tensor
    T: torch.Tensor
    conf: torch.Tensor

    def __len__(self) -> int:
        return int(self.boxes.shape[0])

    def centres(self) -> torch.Tensor:
        """(N, 2) float64 box centres ``(u, v)``."""
        b = self.boxes
        return torch.stack([(b[:, 0] + b[:, 2]) / 2, (b[:, 1] + b[:, 3]) / 2], 1)

    def centre_rays(self) -> tuple[torch.Tensor, torch.Tensor]:
        """Rays through the box centres: origins (N, 3), directions (N, 3) float64."""
        return pixel_rays(self.K, self.T, self.centres())


def detection_batch(seq: Sequence, dets: list[Detection], device: torch.device) -> DetectionBatch:
    """The tensors of ``dets`` (boxes, their views' K and camera-to-world poses, confidences)."""
    n = len(dets)
    frames = seq.frame_by_index()
    K = np.array([seq.cameras[d.camera].K for d in dets], dtype=np.float64).reshape(n, 3, 3)
    T = np.array([frames[d.frame].views[d.camera].T_world_cam for d in dets], dtype=np.float64).reshape(n, 4, 4)
    boxes = np.array([d.box for d in dets], dtype=np.float64).reshape(n, 4)
    conf = np.array([d.conf for d in dets], dtype=np.float64).reshape(n)
    return DetectionBatch(*(torch.as_tensor(a, device=device) for a in (boxes, K, T, conf)))


def window_pairs(i0: torch.Tensor, j0: torch.Tensor, i1: torch.Tensor, j1: torch.Tensor
                 ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """All grid cells of K inclusive rectangles [i0..i1] x [j0..j1] (K,) -> owner, i, j (P,) long.

    Ragged expansion without a Python loop (empty rectangles contribute nothing).
    """
    w = (i1 - i0 + 1).clamp(min=0)
    h = (j1 - j0 + 1).clamp(min=0)
    n = w * h
    owner = torch.repeat_interleave(torch.arange(len(n), device=n.device), n)
    start = torch.cumsum(n, 0) - n
    local = torch.arange(int(n.sum()), device=n.device) - start[owner]
    return owner, i0[owner] + local % w[owner], j0[owner] + local // w[owner]


def _grid_index(hf, xy: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:  # noqa: ANN001
    """Nearest vertex column/row of world points (N, 2), unclipped, long."""
    return (torch.round((xy[:, 0] - hf.x0) / hf.res).long(), torch.round((xy[:, 1] - hf.y0) / hf.res).long())


def _clip_window(hf, i0, j0, i1, j1):  # noqa: ANN001, ANN202
    return i0.clamp(0, hf.nx - 1), j0.clamp(0, hf.ny - 1), i1.clamp(max=hf.nx - 1), j1.clamp(max=hf.ny - 1)


def _vertex_xyz(hf, vid: torch.Tensor) -> torch.Tensor:  # noqa: ANN001
    """(P,) flat ids -> (P, 3) float64 world positions."""
    i = vid % hf.nx
    j = torch.div(vid, hf.nx, rounding_mode="floor")
    z = hf.heights.detach().reshape(-1)[vid].double()
    return torch.stack([hf.x0 + i.double() * hf.res, hf.y0 + j.double() * hf.res, z], 1)


def _min_per(owner: torch.Tensor, values: torch.Tensor, n: int) -> torch.Tensor:
    out = torch.full((n,), float("inf"), dtype=values.dtype, device=values.device)
    return out.scatter_reduce(0, owner, values, reduce="amin", include_self=True)


def _unique_pairs(det: torch.Tensor, vid: torch.Tensor, nv: int) -> tuple[torch.Tensor, torch.Tensor]:
    key = torch.unique(det * nv + vid)
    return torch.div(key, nv, rounding_mode="floor"), key % nv


def associate_ray(hf, dets: DetectionBatch, cfg: FusionConfig) -> Association:  # noqa: ANN001
    """Paper mode: vertices within d_thresh of the box-centre ray (3D point-to-ray distance, lam* >= 0)."""
    o, d = dets.centre_rays()
    conf = dets.conf
    n = o.shape[0]
    dev = o.device
    nv = hf.nx * hf.ny
    valid = hf.valid.reshape(-1)
    Hd = hf.heights.detach().double()
    zs = Hd[hf.valid]
    dth = cfg.beta0 * hf.res + cfg.beta1 * (1.0 - conf.double())  # (N,)
    reach = int(torch.ceil(dth.max() / hf.res).item()) + 1 if n else 1
    dets, vids = [], []
    mapped = torch.zeros(n, dtype=torch.bool, device=dev)
    dist = torch.full((n,), float("nan"), dtype=torch.float64, device=dev)
    if n == 0 or zs.numel() == 0:
        return Association(torch.zeros(0, dtype=torch.long, device=dev), torch.zeros(0, dtype=torch.long, device=dev),
                           mapped, dist, torch.full((n, 3), float("nan"), dtype=torch.float64, device=dev))
    z_lo, z_hi = float(zs.min()), float(zs.max())
    for s in range(0, n, CHUNK):
        e = min(n, s + CHUNK)
        oc, dc, th = o[s:e].double(), d[s:e].double(), dth[s:e]
        # Ray part within the surface's height band (+ threshold): only there can a vertex be near.
        dz = dc[:, 2]
        down = dz < -1e-9
        lam_a = torch.where(down, (z_hi + th - oc[:, 2]) / dz.clamp(max=-1e-9), torch.zeros_like(dz))
        lam_b = torch.where(down, (z_lo - th - oc[:, 2]) / dz.clamp(max=-1e-9), torch.zeros_like(dz))
        dnorm = dc.norm(dim=1)
        lam_a = lam_a.clamp(min=0.0)
        lam_b = torch.minimum(lam_b, cfg.max_dist_m / dnorm)
        dh = dc[:, :2].norm(dim=1).clamp(min=1e-9)
        # Ground-track samples every half cell; each sample's window of radius `reach` covers the track.
        ns = torch.where(down & (lam_b > lam_a), torch.ceil((lam_b - lam_a) * dh / (0.5 * hf.res)) + 1,
                         torch.zeros_like(dh)).clamp(max=20000).long()
        owner = torch.repeat_interleave(torch.arange(e - s, device=dev), ns)
        start = torch.cumsum(ns, 0) - ns
        k = torch.arange(int(ns.sum()), device=dev) - start[owner]
        lam = lam_a[owner] + k.double() * (0.5 * hf.res) / dh[owner]
        p = oc[owner] + lam[:, None] * dc[owner]
        # Prune samples where the ray is far above/below the local surface.
        hz, inside = hf.height_at(p[:, :2].to(hf.heights.dtype))
        near = inside & ((p[:, 2] - hz.double()).abs() <= th[owner] + 2 * hf.res)
        owner, p = owner[near], p[near]
        ci, cj = _grid_index(hf, p[:, :2])
        i0, j0, i1, j1 = _clip_window(hf, ci - reach, cj - reach, ci + reach, cj + reach)
        w_owner, wi, wj = window_pairs(i0, j0, i1, j1)
        det_local, vid = _unique_pairs(owner[w_owner], wj * hf.nx + wi, nv)
        keep = valid[vid]
        det_local, vid = det_local[keep], vid[keep]
        v = _vertex_xyz(hf, vid)
        oo, dd = oc[det_local], dc[det_local]
        lam_star = (((v - oo) * dd).sum(1) / (dd * dd).sum(1)).clamp(min=0.0)
        dv = (v - (oo + lam_star[:, None] * dd)).norm(dim=1)
        dmin = _min_per(det_local, dv, e - s)
        ok = dv < th[det_local]
        dets.append(det_local[ok] + s)
        vids.append(vid[ok])
        has = torch.isfinite(dmin)
        dist[s:e] = torch.where(has, dmin, dist[s:e])
        mapped[s:e] = dmin < th
    hit = torch.full((n, 3), float("nan"), dtype=torch.float64, device=dev)
    return Association(torch.cat(dets), torch.cat(vids), mapped, dist, hit)


def _hits(hf, o: torch.Tensor, d: torch.Tensor, cfg: FusionConfig) -> tuple[torch.Tensor, torch.Tensor]:  # noqa: ANN001
    from pavemap.geometry import intersect_rays

    # float64 rays: in float32 the march can step over the crossing of a perfectly flat surface
    # (its height band is only ~1e-6 wide, below float32 rounding of o_z + lam d_z).
    r = intersect_rays(hf, o.double(), d.double(), max_dist=cfg.max_dist_m)
    return r.points.detach().double(), r.hit


def footprint_centres(hf, boxes: torch.Tensor, K: torch.Tensor, T: torch.Tensor, pts: torch.Tensor,  # noqa: ANN001
                      hit: torch.Tensor) -> torch.Tensor:
    """Area centroid of each box's ground footprint (N, 3), from the centre hit ``pts`` (N, 3).

    The box corners' rays meet the local plane ``z = z_hit`` in a quadrilateral (a projective
    image of the box); its shoelace centroid is where the box's middle lies on the road. The
    centre ray is biased toward the camera: a box's middle row sees the harmonic, not the
    arithmetic, mean depth of its near and far edges. Boxes with a corner above the horizon, or
    without a centre hit, keep the centre hit.
    """
    q, ok = footprint_quads(boxes, K, T, pts[:, 2])
    ok = ok & hit
    qx, qy = q[..., 0], q[..., 1]
    nx_, ny_ = qx.roll(-1, 1), qy.roll(-1, 1)
    cross = qx * ny_ - nx_ * qy
    area = shoelace(q)
    ok = ok & (area.abs() > 1e-12)
    safe = torch.where(ok, area, torch.ones_like(area))
    cx = ((qx + nx_) * cross).sum(1) / (6 * safe)
    cy = ((qy + ny_) * cross).sum(1) / (6 * safe)
    out = pts.clone()
    # Stay with the centre hit where the quad centroid falls off the crop (a box straddling the edge).
    z, inside = hf.height_at(torch.stack([cx, cy], 1).to(hf.heights.dtype))
    ok = ok & inside
    out[ok] = torch.stack([cx, cy, z.double()], 1)[ok]
    return out


def associate_hit(hf, dets: DetectionBatch, cfg: FusionConfig) -> Association:  # noqa: ANN001
    """Vertices within ``hit_radius_m`` (horizontal) of the detection's surface point.

    The point is the centre ray's hit, or with ``cfg.hit_point == "footprint"`` the centroid of
    the box's ground footprint (:func:`footprint_centres`).
    """
    o, d = dets.centre_rays()
    n = o.shape[0]
    pts, hit = _hits(hf, o, d, cfg)
    if cfg.hit_point == "footprint":
        pts = footprint_centres(hf, dets.boxes, dets.K, dets.T, pts, hit)
    radius = max(cfg.hit_radius_m, 0.75 * hf.res)  # never smaller than the cell: a hit always maps
    reach = int(radius / hf.res) + 1
    idx = torch.nonzero(hit).squeeze(1)
    ci, cj = _grid_index(hf, pts[idx, :2])
    i0, j0, i1, j1 = _clip_window(hf, ci - reach, cj - reach, ci + reach, cj + reach)
    w_owner, wi, wj = window_pairs(i0, j0, i1, j1)
    vid = wj * hf.nx + wi
    det = idx[w_owner]
    v = _vertex_xyz(hf, vid)
    dxy = (v[:, :2] - pts[det, :2]).norm(dim=1)
    ok = hf.valid.reshape(-1)[vid] & (dxy <= radius)
    det, vid, dxy = det[ok], vid[ok], dxy[ok]
    dmin = _min_per(det, dxy, n)
    mapped = torch.isfinite(dmin)
    dist = torch.where(mapped, dmin, torch.full_like(dmin, float("nan")))
    hits = torch.where(hit[:, None], pts, torch.full_like(pts, float("nan")))
    return Association(det, vid, mapped, dist, hits)


def _footprint_windows(hf, dets: DetectionBatch, cfg: FusionConfig, cp: torch.Tensor,  # noqa: ANN001
                       ch: torch.Tensor) -> tuple[torch.Tensor, ...]:
    """Candidate vertex rectangles of the boxes whose centre ray hit (``cp`` (N, 3) hits, ``ch`` (N,) bool).

    Returns idx (M,) the detections with a hit and their inclusive windows i0, j0, i1, j1 (M,) long.
    """
    boxes, K, T = dets.boxes, dets.K, dets.T
    n = boxes.shape[0]
    max_cells = max(2, int(round(cfg.footprint_max_m / hf.res)))
    G = max(2, cfg.footprint_grid)
    g = torch.linspace(0.0, 1.0, G, device=boxes.device, dtype=torch.float64)
    gu, gv = torch.meshgrid(g, g, indexing="xy")
    fu, fv = gu.reshape(-1), gv.reshape(-1)
    x1, y1, x2, y2 = boxes.unbind(1)
    u = x1[:, None] + fu[None] * (x2 - x1)[:, None]
    v = y1[:, None] + fv[None] * (y2 - y1)[:, None]
    o, d = pixel_rays(K.repeat_interleave(G * G, 0), T.repeat_interleave(G * G, 0),
                      torch.stack([u.reshape(-1), v.reshape(-1)], 1))
    o, d = o.reshape(n, G * G, 3), d.reshape(n, G * G, 3)
    # Grid rays on the plane z = z_hit; rays that never reach it (above the horizon) stop at the cap.
    cap = max_cells * hf.res / d[..., :2].norm(dim=-1).clamp(min=1e-9)
    lam = (cp[:, None, 2] - o[..., 2]) / d[..., 2].clamp(max=-1e-12)
    lam = torch.where(d[..., 2] < -1e-12, lam.clamp(min=0.0), cap).clamp(max=cap)
    gp = o + lam[..., None] * d
    xmin = torch.minimum(gp[..., 0].amin(1), cp[:, 0])
    xmax = torch.maximum(gp[..., 0].amax(1), cp[:, 0])
    ymin = torch.minimum(gp[..., 1].amin(1), cp[:, 1])
    ymax = torch.maximum(gp[..., 1].amax(1), cp[:, 1])
    idx = torch.nonzero(ch).squeeze(1)
    i0 = torch.floor((xmin[idx] - hf.x0) / hf.res).long() - 2
    i1 = torch.ceil((xmax[idx] - hf.x0) / hf.res).long() + 2
    j0 = torch.floor((ymin[idx] - hf.y0) / hf.res).long() - 2
    j1 = torch.ceil((ymax[idx] - hf.y0) / hf.res).long() + 2
    ri, rj = _grid_index(hf, cp[idx, :2])
    half = max_cells // 2
    i0, i1 = torch.maximum(i0, ri - half), torch.minimum(i1, ri + half)
    j0, j1 = torch.maximum(j0, rj - half), torch.minimum(j1, rj + half)
    return (idx, *_clip_window(hf, i0, j0, i1, j1))


def associate_footprint(hf, dets: DetectionBatch, cfg: FusionConfig) -> Association:  # noqa: ANN001
    """Vertices whose projection falls inside the box: the box's footprint on the surface.

    The centre ray is intersected with the surface; the box's ``footprint_grid`` x ``footprint_grid``
    edge-inclusive ray grid is then intersected with the local plane ``z = z_hit`` (analytic, so no
    extra surface casts: casting 64 rays per box was 20x slower for the same candidates) to bound the
    candidate rectangle,
    padded by 2 cells. Membership itself is exact: a valid vertex is associated when it
    projects inside the box with positive depth. A box too small to contain a vertex maps to
    the vertex nearest its centre hit. ``cfg.footprint_max_m`` caps the rectangle's side: a far box
    one pixel tall covers metres of road at grazing angles, more than any defect.
    """
    boxes, K, T = dets.boxes, dets.K, dets.T
    n = boxes.shape[0]
    dev = boxes.device
    cp, ch = _hits(hf, *dets.centre_rays(), cfg)
    idx, i0, j0, i1, j1 = _footprint_windows(hf, dets, cfg, cp, ch)
    ref = cp
    # Projection matrices P = K [R^T | -R^T t], so a candidate's projection is one small gather.
    Rt = T[:, :3, :3].transpose(1, 2)
    Pm = K @ torch.cat([Rt, -(Rt @ T[:, :3, 3:])], 2)
    pair_dets, vids = [], []
    dmin = torch.full((n,), float("inf"), dtype=torch.float64, device=dev)
    near_d = torch.full((n,), float("inf"), dtype=torch.float64, device=dev)
    near_v = torch.full((n,), -1, dtype=torch.long, device=dev)
    valid = hf.valid.reshape(-1)
    for s in range(0, len(idx), max(1, CHUNK // 8)):
        e = min(len(idx), s + max(1, CHUNK // 8))
        w_owner, wi, wj = window_pairs(i0[s:e], j0[s:e], i1[s:e], j1[s:e])
        det = idx[s:e][w_owner]
        vid = wj * hf.nx + wi
        keep = valid[vid]
        det, vid = det[keep], vid[keep]
        X = _vertex_xyz(hf, vid)
        Pd = Pm[det]  # (P, 3, 4) projection rows of each candidate's view
        uvw = (Pd[:, :, :3] * X[:, None, :]).sum(-1) + Pd[:, :, 3]
        zc = uvw[:, 2]
        uu = uvw[:, 0] / zc.clamp(min=1e-9)
        vv = uvw[:, 1] / zc.clamp(min=1e-9)
        b = boxes[det]
        inside = (zc > 0) & (uu >= b[:, 0]) & (uu <= b[:, 2]) & (vv >= b[:, 1]) & (vv <= b[:, 3])
        dxy = (X[:, :2] - ref[det, :2]).norm(dim=1)
        # Nearest candidate per detection (fallback for boxes smaller than a cell).
        dn = _min_per(det, dxy, n)
        better = dn < near_d
        near_d = torch.where(better, dn, near_d)
        is_min = dxy == dn[det]
        cand_v = torch.full((n,), -1, dtype=torch.long, device=dev).scatter_reduce(
            0, det[is_min], vid[is_min], reduce="amax", include_self=True)
        near_v = torch.where(better, cand_v, near_v)
        pair_dets.append(det[inside])
        vids.append(vid[inside])
        dmin = torch.minimum(dmin, _min_per(det[inside], dxy[inside], n))
    det = torch.cat(pair_dets) if pair_dets else torch.zeros(0, dtype=torch.long, device=dev)
    vid = torch.cat(vids) if vids else torch.zeros(0, dtype=torch.long, device=dev)
    # Boxes with hits but no vertex inside: the nearest valid vertex within one cell of the reference.
    lone = ch & ~torch.isfinite(dmin) & (near_v >= 0) & (near_d <= hf.res)
    det = torch.cat([det, torch.nonzero(lone).squeeze(1)])
    vid = torch.cat([vid, near_v[lone]])
    dmin = torch.where(lone, near_d, dmin)
    mapped = torch.isfinite(dmin)
    dist = torch.where(mapped, dmin, torch.full_like(dmin, float("nan")))
    centres = footprint_centres(hf, boxes, K, T, cp, ch)
    hits = torch.where(ch[:, None], centres, torch.full_like(cp, float("nan")))
    return Association(det, vid, mapped, dist, hits)


# The association modes: one signature, ``(surface, detections, config) -> Association``.
ASSOCIATIONS: dict[str, Callable[..., Association]] = {
    "ray": associate_ray,
    "hit": associate_hit,
    "footprint": associate_footprint,
}


def associate_detections(seq: Sequence, dets: list[Detection], surface, config: FusionConfig  # noqa: ANN001
                         ) -> Association:
    """Run ``config.association`` for (already filtered) detections on ``surface`` (a HeightField)."""
    return ASSOCIATIONS[config.association](surface, detection_batch(seq, dets, surface.heights.device), config)
