"""Defect instances: connected components of defect vertices -> polygons with statistics (SPEC §3).

Each vertex stands for its grid cell (a square of side ``r`` centred on it), so an instance's
polygon is the union of its vertices' cells (traced by rasterio's polygoniser, 8-connected), its
area is ``count * r^2`` and its length is the extent along the component's principal axis.
All per-component statistics are bincount / scatter reductions over the labelled vertices.
"""

from __future__ import annotations

import numpy as np
from affine import Affine
from rasterio.features import shapes
from scipy import ndimage
from shapely.geometry import MultiPolygon, Polygon, shape
from shapely.ops import unary_union

from pavemap.types import NUM_DEFECT_CLASSES, UNASSESSED, DefectInstance


def label_components(mask: np.ndarray, gap_cells: int = 0) -> tuple[np.ndarray, int]:
    """(ny, nx) bool -> (labels (ny, nx) int32, 0 = background, 1..K 8-connected components; K).

    With ``gap_cells`` > 0, pieces closer than about ``2 * gap_cells`` cells are one component
    (labelled on the mask dilated by ``gap_cells``, then restricted to the mask's own vertices):
    the views of one long crack can land as separate blobs on an imperfect surface.
    """
    st = np.ones((3, 3), dtype=bool)
    if gap_cells <= 0:
        labels, k = ndimage.label(mask, structure=st)
        return labels.astype(np.int32), int(k)
    grown = ndimage.binary_dilation(mask, structure=st, iterations=gap_cells)
    labels, _ = ndimage.label(grown, structure=st)
    labels = np.where(mask, labels, 0)
    # Dense ids 1..K over the labels that kept a vertex.
    ids = np.unique(labels)
    ids = ids[ids > 0]
    lut = np.zeros(int(labels.max()) + 1, dtype=np.int32)
    lut[ids] = np.arange(1, len(ids) + 1, dtype=np.int32)
    return lut[labels], len(ids)


def component_polygons(labels: np.ndarray, k: int, x0: float, y0: float, res: float) -> list:
    """Polygon (world metres) of each component 1..k: the union of its vertices' cells."""
    transform = Affine(res, 0.0, x0 - res / 2, 0.0, res, y0 - res / 2)
    parts: list[list[Polygon]] = [[] for _ in range(k + 1)]
    for geom, value in shapes(labels, mask=labels > 0, connectivity=8, transform=transform):
        parts[int(value)].append(shape(geom))
    polys = []
    for lab in range(1, k + 1):
        p = parts[lab][0] if len(parts[lab]) == 1 else unary_union(parts[lab])
        if not p.is_valid:
            p = p.buffer(0)
        polys.append(p)
    return polys


def principal_extent(labels_flat: np.ndarray, x: np.ndarray, y: np.ndarray, k: int, res: float) -> np.ndarray:
    """Extent (k,) in metres of each component along its principal axis (vertex spread + one cell)."""
    cnt = np.bincount(labels_flat, minlength=k + 1).astype(np.float64)
    safe = np.maximum(cnt, 1)
    mx = np.bincount(labels_flat, x, k + 1) / safe
    my = np.bincount(labels_flat, y, k + 1) / safe
    dx, dy = x - mx[labels_flat], y - my[labels_flat]
    sxx = np.bincount(labels_flat, dx * dx, k + 1)
    syy = np.bincount(labels_flat, dy * dy, k + 1)
    sxy = np.bincount(labels_flat, dx * dy, k + 1)
    theta = 0.5 * np.arctan2(2 * sxy, sxx - syy)  # principal axis angle of the 2x2 covariance
    t = dx * np.cos(theta)[labels_flat] + dy * np.sin(theta)[labels_flat]
    hi = np.full(k + 1, -np.inf)
    lo = np.full(k + 1, np.inf)
    np.maximum.at(hi, labels_flat, t)
    np.minimum.at(lo, labels_flat, t)
    return (hi - lo + res)[1:]


def join_crack_pieces(labels: np.ndarray, k: int, cls: np.ndarray, res: float, gap_m: float,
                      max_deg: float = 20.0, min_ratio: float = 2.0, crack_classes: tuple[int, ...] = (0, 1)
                      ) -> tuple[np.ndarray, int]:
    """Components 1..k of ``labels`` (ny, nx) int32 that are pieces of one crack, joined. Two pieces join when
    they have the same class ``cls`` (k,) (majority class) among ``crack_classes``, come within ``gap_m`` of
    each other, are together a line (their union's principal extent at least ``min_ratio`` times its width, from
    its second moments) and lie along it (the line between their centres within ``max_deg`` of its axis, not
    side by side), and neither piece is a line of its own across that axis. Pieces too short to have a direction
    of their own (shorter than ``gap_m``) join whenever together they form a line. Returns the new labels (ids
    1..K') and K'.

    Why: a longitudinal or transverse crack is a line, and where a stretch of it is faint in every view its
    fused vertices fall apart into pieces 0.4-0.9 m apart along the line (8 of ~700 true cracks on the
    KITTI-00 drive), which an isotropic merge distance that large would also join across neighbouring cracks.
    """
    from scipy.spatial import cKDTree

    if k < 2 or gap_m <= 0:
        return labels, k
    flat = labels.reshape(-1)
    sel = np.flatnonzero(flat)
    L = flat[sel]
    order = np.argsort(L, kind="stable")
    y, x = np.divmod(sel[order], labels.shape[1])
    pts, L = np.stack([x, y], 1) * res, L[order]
    start = np.searchsorted(L, np.arange(k + 2))  # component c's vertices: pts[start[c]:start[c + 1]]
    n = np.diff(start).astype(np.float64)  # (k + 1,), index 0 the background (no vertices)
    m1 = np.stack([np.bincount(L, pts[:, i], k + 1) for i in range(2)], 1)
    m2 = np.stack([np.bincount(L, pts[:, i] * pts[:, j], k + 1) for i, j in ((0, 0), (1, 1), (0, 1))], 1)
    centre = m1 / np.maximum(n, 1)[:, None]
    reach = np.zeros(k + 1)
    np.maximum.at(reach, L, np.linalg.norm(pts - centre[L], axis=1))
    crack = np.concatenate([[False], np.isin(cls, crack_classes)])
    ids = np.flatnonzero(crack)
    parent = np.arange(k + 1)
    trees: dict[int, cKDTree] = {}
    cos_max = float(np.cos(np.radians(max_deg)))

    def root(a: int) -> int:
        while parent[a] != a:
            parent[a] = parent[parent[a]]
            a = parent[a]
        return a

    def near(a: int, b: int) -> bool:
        if a not in trees:
            trees[a] = cKDTree(pts[start[a]:start[a + 1]])
        d, _ = trees[a].query(pts[start[b]:start[b + 1]], distance_upper_bound=gap_m + 1e-9)
        return bool(np.isfinite(d).any())

    if len(ids) < 2:
        return labels, k
    for i, j in cKDTree(centre[ids]).query_pairs(2 * float(reach[ids].max()) + gap_m, output_type="ndarray"):
        a, b = int(ids[i]), int(ids[j])
        if cls[a - 1] != cls[b - 1] or np.linalg.norm(centre[a] - centre[b]) > reach[a] + reach[b] + gap_m:
            continue
        u, ratio, _ = _union_axis(n[[a, b]], m1[[a, b]], m2[[a, b]], res)
        d = centre[b] - centre[a]
        if ratio < min_ratio ** 2 or abs(float(d @ u)) < cos_max * float(np.linalg.norm(d)):
            continue
        # a piece that is a line of its own (elongated, and at least gap_m long: a wisp of a few cells has no
        # direction) running across the pair's line: side by side, not one crack
        if any(r >= min_ratio ** 2 and length >= gap_m and abs(float(v @ u)) < cos_max for v, r, length in
               (_union_axis(n[[c]], m1[[c]], m2[[c]], res) for c in (a, b))):
            continue
        if root(a) != root(b) and near(a, b):
            parent[root(a)] = root(b)
    roots = np.array([root(a) for a in range(k + 1)])
    _, dense = np.unique(roots[1:], return_inverse=True)
    lut = np.concatenate([[0], dense + 1]).astype(np.int32)
    return lut[labels], int(dense.max()) + 1


def _union_axis(n: np.ndarray, m1: np.ndarray, m2: np.ndarray, res: float) -> tuple[np.ndarray, float, float]:
    """Principal axis (2,) of the union of pieces with vertex counts n (P,), coordinate sums m1 (P, 2) and
    second-moment sums m2 (P, 3: xx, yy, xy), the ratio of its variances along and across it (the
    across-variance at least that of one cell, res^2 / 12) and its length along the axis (m; a uniform line's
    from its variance, sqrt(12 var))."""
    tot = float(n.sum())
    mx, my = m1.sum(0) / tot
    sxx, syy, sxy = m2.sum(0) / tot - np.array([mx * mx, my * my, mx * my])
    half, mid = np.hypot(0.5 * (sxx - syy), sxy), 0.5 * (sxx + syy)
    theta = 0.5 * np.arctan2(2 * sxy, sxx - syy)
    return (np.array([np.cos(theta), np.sin(theta)]), float((mid + half) / max(mid - half, res * res / 12)),
            float(np.sqrt(12.0 * max(mid + half, 0.0))))


def _distinct_detections(lab: np.ndarray, k: int, pair_det: np.ndarray, pair_vid: np.ndarray) -> np.ndarray:
    """(k + 1,) int: the distinct detections per component of the flat label image ``lab`` (0 background),
    from the (P,) (detection, vertex) associations ``pair_det`` / ``pair_vid``."""
    pl = lab[pair_vid] if len(pair_vid) else np.zeros(0, dtype=np.int64)
    m = pl > 0
    # 1-D keys: np.unique on rows (axis=0) is an order of magnitude slower.
    uniq = np.unique(pair_det[m].astype(np.int64) * (k + 1) + pl[m])
    return np.bincount(uniq % (k + 1), minlength=k + 1)


def _max_by(labels: np.ndarray, values: np.ndarray, k: int) -> np.ndarray:
    """(k + 1,) the largest of ``values`` (N,) per label of ``labels`` (N,) in 0..k, starting from 0 (a label
    without values gets 0)."""
    out = np.zeros(k + 1)
    np.maximum.at(out, labels, values)
    return out


def build_instances(
    shape: tuple[int, int], vertices: np.ndarray, defect: np.ndarray, prob: np.ndarray, counts: np.ndarray,
    sev: np.ndarray, conf: np.ndarray, pair_det: np.ndarray, pair_vid: np.ndarray, x0: float, y0: float,
    res: float, min_obs: int = 1, merge_gap_m: float = 0.0, crack_join_m: float = 0.0,
) -> tuple[list[DefectInstance], np.ndarray]:
    """Instances from the defect vertices.

    shape ``(ny, nx)`` of the vertex grid; vertices (M,) int64 sorted flat ids ``j*nx+i`` of the observed
    vertices, with per vertex: defect (M,) bool, prob / sev / conf (M,), counts (M, 4); pair_det / pair_vid
    (P,) the (detection, vertex) associations (for the distinct-detection count ``observations``).
    Components seen by fewer than ``min_obs`` distinct detections are dropped; pieces within
    ``merge_gap_m`` of each other form one instance (a MultiPolygon when they do not touch), and so do
    pieces of one crack up to ``crack_join_m`` apart along it (:func:`join_crack_pieces`).
    Returns the instances (ids 1..K in order) and the (ny, nx) int32 label image of the kept ones.
    """
    ny, nx = shape
    mask = np.zeros(ny * nx, dtype=bool)
    mask[vertices[defect]] = True
    labels, k = label_components(mask.reshape(ny, nx), int(round(merge_gap_m / (2 * res))))
    del mask
    if k == 0:
        return [], labels
    if crack_join_m > 0 and k > 1:
        sel = np.flatnonzero(labels.reshape(-1))
        L, at = labels.reshape(-1)[sel], np.searchsorted(vertices, sel)
        votes = np.stack([np.bincount(L, counts[at, c], k + 1) for c in range(NUM_DEFECT_CLASSES)], 1)[1:]
        labels, k = join_crack_pieces(labels, k, votes.argmax(1), res, crack_join_m)
    lab = labels.reshape(-1)
    sel = np.nonzero(lab)[0]
    L = lab[sel]
    jj, ii = np.divmod(sel, nx)
    x, y = x0 + ii * res, y0 + jj * res
    cnt = np.bincount(L, minlength=k + 1)
    n_det = _distinct_detections(lab, k, pair_det, pair_vid)
    keep = n_det >= min_obs
    keep[0] = False
    if not keep[1:].any():
        return [], np.zeros_like(labels)
    # Relabel the kept components 1..K' so ids are dense.
    new = np.zeros(k + 1, dtype=np.int32)
    new[keep] = np.arange(1, int(keep.sum()) + 1, dtype=np.int32)
    labels = new[labels]
    k2 = int(keep.sum())
    old_ids = np.nonzero(keep)[0]
    lab2 = labels.reshape(-1)[sel]
    in_kept = lab2 > 0
    sel, L2, x, y = sel[in_kept], lab2[in_kept], x[in_kept], y[in_kept]
    cnt = cnt[old_ids]
    at = np.searchsorted(vertices, sel)  # labelled cells are defect vertices, so observed ones
    cls_counts = np.stack([np.bincount(L2, counts[at, c], k2 + 1) for c in range(NUM_DEFECT_CLASSES)], 1)[1:]
    sev_f, conf_f, prob_f = sev[at], conf[at], prob[at]
    sev_mean = np.bincount(L2, sev_f, k2 + 1)[1:] / cnt
    sev_max, conf_max, prob_max = _max_by(L2, sev_f, k2), _max_by(L2, conf_f, k2), _max_by(L2, prob_f, k2)
    cx = np.bincount(L2, x, k2 + 1)[1:] / cnt
    cy = np.bincount(L2, y, k2 + 1)[1:] / cnt
    length = principal_extent(L2, x, y, k2, res)
    polys = component_polygons(labels, k2, x0, y0, res)
    n_obs = n_det[old_ids]
    out = []
    for t in range(k2):
        cls = int(np.argmax(cls_counts[t]))
        poly = polys[t]
        out.append(DefectInstance(
            id=t + 1, cls=cls, polygon=poly if isinstance(poly, Polygon | MultiPolygon) else poly,
            severity_mean=float(sev_mean[t]), severity_max=float(sev_max[t + 1]),
            confidence=float(conf_max[t + 1]), observations=int(n_obs[t]), probability=float(prob_max[t + 1]),
            area_m2=float(cnt[t] * res * res), length_m=float(length[t]),
            centroid=(float(cx[t]), float(cy[t])), priority=UNASSESSED,  # urgency: pavemap.maintain.assess
            extra={"vertices": int(cnt[t]), "vertex_observations": int(cls_counts[t].sum()),
                   "class_votes": [int(v) for v in cls_counts[t]]},
        ))
    return out, labels
