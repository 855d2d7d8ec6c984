"""Measures from the 3D surface (issue 16): pothole depth / volume, crack length / orientation.

Inputs are stage 1's height field and stage 3's instance label image on the same vertex grid
(vertex ``(j, i)`` at ``(x0 + i*res, y0 + j*res)``). Everything is written into
``DefectInstance.extra`` under the keys of :data:`pavemap.export.geojson.PROPERTY_SCHEMA`.

Potholes (D40): a robust local road surface is fitted to a ring of road around the instance
(between ``ring_inner_m`` and ``ring_outer_m`` outside its footprint; other instances' vertices,
invalid and unobserved vertices left out) by least squares with iterative trimming of residuals
beyond ``trim_k`` robust sigmas, so a ring that grazes the dent's wall or a kerb does not tilt it.
It is a plane plus quadratic terms by default (``order``): the road's crown would otherwise read as
1-2 mm of depth under a 1 m ring.
Depth is the plane minus the surface over the footprint dilated by ``foot_dilate_m`` (detection
boxes can be smaller than the pothole), or, where enough height samples fall inside, from those samples;
with ``surface_floor`` False (stage 1's mesh) only from the samples, else "not measurable".
Vertices deeper than the noise floor (twice the ring's residual sigma) form the dent: its mean depth
and its volume. A footprint on unobserved ground, at
the mesh edge, or with too few ring vertices is "not measurable": the depths are None and
``measure_note`` says why, never a made-up number.

Cracks (D00, D10): length along the skeleton of the instance mask (geodesic diameter of each
skeleton piece, 1 cell orthogonal / sqrt 2 diagonal, so spurs do not count), plus the mask's
half-width at both ends (thinning stops that far short of a thick mask's ends). Orientation is the
mask's principal axis against the route direction at the defect (0 along, 90 across).
Alligator cracking (D20) keeps the instance's ``area_m2`` (vertex count x cell area).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy import ndimage
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components, dijkstra

from pavemap.geometry.chainage import chainage, cumulative_length
from pavemap.types import DefectInstance

POTHOLE, CRACK_CLASSES = 3, (0, 1)


@dataclass(frozen=True)
class MeasureConfig:
    """Ring, footprint and robustness settings of :func:`measure_instances` (metres unless said)."""

    foot_dilate_m: float = 0.1  # measure depth this far outside the instance footprint too
    ring_inner_m: float = 0.25  # the plane's ring starts this far outside the footprint ...
    ring_outer_m: float = 0.65  # ... and ends here
    min_ring_vertices: int = 12
    min_ring_share: float = 0.5  # of the geometric ring that must be valid mesh (else: at the mesh edge)
    min_observed_share: float = 0.5  # of footprint / ring vertices that must be observed
    max_invalid_share: float = 0.1  # of the footprint outside the valid mesh (else: at the mesh edge)
    trim_k: float = 2.5  # residuals beyond trim_k robust sigmas leave the plane fit
    iterations: int = 6
    noise_floor_m: float = 0.002  # dent threshold floor (a perfect mesh has zero ring residual)
    # 2: plane plus quadratic terms, so a road crown (curvature ~0.01 /m) under a 1 m ring does not read
    # as 1-2 mm of depth; the ring surrounds the dent, so the fit interpolates rather than extrapolates
    order: int = 2
    # Height samples (depth pixels, ground points) inside the footprint measure the floor itself where there
    # are at least this many: the surface is smoother than a pothole (its relief lattice is 0.5 m along the road)
    min_samples: int = 5
    sample_quantile: float = 0.99  # the deepest sample is noise-prone: depth_max is this quantile of them
    # ... and the ring plane from the samples around it where at least this many fall in the ring: the surface
    # there is pulled into the dent by its smoothing (the depths came out 7 mm short with the surface's ring)
    min_ring_samples: int = 20
    # Whether the surface itself measures a pothole's floor where too few samples fall inside (a dense scan,
    # the true surface). False for stage 1's mesh (pavemap.maintain.assess): its relief lattice is 0.5 m along
    # the road, so without samples its dent is an interpolation between the rims (3-27 mm for 11 potholes 47-100
    # mm deep on the bench's no-depth drives), and the depth is "not measurable", never that number.
    surface_floor: bool = True


def measure_instances(instances: list[DefectInstance], surface, labels: np.ndarray | None,  # noqa: ANN001
                      observed=None, route: np.ndarray | None = None,  # noqa: ANN001
                      config: MeasureConfig | None = None, samples: np.ndarray | None = None) -> None:
    """Write the surface measures of every instance into ``inst.extra`` (in place).

    surface: HeightField-like (``heights`` (ny, nx) and ``valid`` (ny, nx) bool torch or numpy, ``x0``,
    ``y0``, ``res``); labels (ny, nx) int instance id per vertex (0 none), e.g.
    ``FusionResult.instance_labels``; observed (ny, nx) bool or None (all observed); route (M, 2) from
    :func:`pavemap.geometry.chainage.route_polyline` or None (then no orientation); samples (N, 3) world
    height measurements (depth pixels, ground points) or None: where enough fall inside a pothole they
    give its depth instead of the (smoother) surface. A pothole's own ``extra["floor_samples"]`` (points (N, 3),
    road plane (point, normal)) (the floor sweep's, :mod:`pavemap.maintain.floor_sweep`; taken out of
    ``extra``) measure its floor wherever they lie, below that plane; its ``extra["floor_sweep_note"]`` says
    why the sweep found none (taken out too).
    Potholes get depth_max_mm, depth_mean_mm, volume_l, depth_sigma_mm, measurable, measure_note;
    cracks crack_length_m, orientation_deg, orientation_ok.
    """
    if not instances:
        return
    cfg = config or MeasureConfig()
    z = _np(surface.heights).astype(np.float64)
    valid = _np(surface.valid).astype(bool) & np.isfinite(z)
    obs = None if observed is None else _np(observed).astype(bool)
    grid = (float(surface.x0), float(surface.y0), float(surface.res))
    lab = None if labels is None else np.asarray(labels)
    if lab is not None and lab.shape != z.shape:
        raise ValueError(f"instance labels {lab.shape} do not match the surface grid {z.shape}")
    slices = ndimage.find_objects(lab) if lab is not None and lab.max() > 0 else []
    for inst in instances:
        sl = slices[inst.id - 1] if 0 < inst.id <= len(slices) else None
        if inst.cls == POTHOLE:
            own = inst.extra.pop("floor_samples", None)  # the floor sweep's, for this pothole only ...
            why = inst.extra.pop("floor_sweep_note", None) or None  # ... or why it found none
            inst.extra.update(_pothole(inst.id, sl, z, valid, obs, lab, grid, cfg, samples, own, why))
        elif inst.cls in CRACK_CLASSES:
            inst.extra.update(_crack(inst, sl, lab, grid, route))


def _np(a) -> np.ndarray:  # noqa: ANN001
    return a.detach().cpu().numpy() if hasattr(a, "detach") else np.asarray(a)


def _disk(r: int) -> np.ndarray:
    yy, xx = np.mgrid[-r:r + 1, -r:r + 1]
    return xx * xx + yy * yy <= r * r + r  # a little rounder than the strict disk at small r


def _crop(a: np.ndarray, j0: int, j1: int, i0: int, i1: int, fill: object) -> np.ndarray:
    """a[j0:j1, i0:i1] with the part outside the grid filled with ``fill`` (so rings stay whole)."""
    out = np.full((j1 - j0, i1 - i0), fill, dtype=a.dtype)
    ny, nx = a.shape
    sj0, sj1, si0, si1 = max(j0, 0), min(j1, ny), max(i0, 0), min(i1, nx)
    if sj1 > sj0 and si1 > si0:
        out[sj0 - j0:sj1 - j0, si0 - i0:si1 - i0] = a[sj0:sj1, si0:si1]
    return out


def _not_measurable(note: str) -> dict:
    return {"measurable": False, "measure_note": note, "depth_max_mm": None, "depth_mean_mm": None,
            "volume_l": None, "depth_sigma_mm": None}


def _design(x: np.ndarray, y: np.ndarray, order: int) -> np.ndarray:
    cols = [np.ones_like(x), x, y] + ([x * x, x * y, y * y] if order >= 2 else [])
    return np.stack(cols, axis=1)


def robust_plane(x: np.ndarray, y: np.ndarray, z: np.ndarray, trim_k: float = 2.5, iterations: int = 6,
                 order: int = 1) -> tuple[np.ndarray, float, np.ndarray]:
    """Plane z = a + b x + c y (order 2: plus x², xy, y²) by least squares with iterative trimming.

    x, y, z (N,) float64. Each pass refits on the points within ``trim_k`` robust sigmas (1.4826 MAD)
    of the previous fit. Returns (coef (3,) or (6,), robust sigma of the inliers' residuals, inlier mask (N,)).
    Evaluate with ``surface_at(coef, x, y)``.
    """
    A = _design(x, y, order)
    keep = np.ones(len(z), dtype=bool)
    coef = np.zeros(3)
    for _ in range(iterations):
        coef = np.linalg.lstsq(A[keep], z[keep], rcond=None)[0]
        r = z - A @ coef
        med = np.median(r[keep])
        s = max(1.4826 * float(np.median(np.abs(r[keep] - med))), 1e-5)
        new = np.abs(r - med) <= trim_k * s
        if new.sum() < A.shape[1] or np.array_equal(new, keep):
            break
        keep = new
    r = z - A @ coef
    sigma = 1.4826 * float(np.median(np.abs(r[keep] - np.median(r[keep]))))
    return coef, sigma, keep


def _pothole(iid: int, sl: tuple | None, z: np.ndarray, valid: np.ndarray, obs: np.ndarray | None,
             lab: np.ndarray | None, grid: tuple[float, float, float], cfg: MeasureConfig,
             samples: np.ndarray | None = None, own: tuple | None = None, own_why: str | None = None) -> dict:
    """The pothole measures of instance ``iid`` (see module doc)."""
    if sl is None or lab is None:
        return _not_measurable("no footprint on the surface grid")
    res = grid[2]
    r_foot = max(1, round(cfg.foot_dilate_m / res))
    r_in, r_out = round(cfg.ring_inner_m / res), max(round(cfg.ring_outer_m / res), round(cfg.ring_inner_m / res) + 1)
    pad = r_out + 1
    j0, j1, i0, i1 = sl[0].start - pad, sl[0].stop + pad, sl[1].start - pad, sl[1].stop + pad
    mask = _crop(lab, j0, j1, i0, i1, 0) == iid
    zc, vc = _crop(z, j0, j1, i0, i1, np.nan), _crop(valid, j0, j1, i0, i1, False)
    lc = _crop(lab, j0, j1, i0, i1, 0)
    oc = np.ones_like(vc) if obs is None else _crop(obs, j0, j1, i0, i1, False)
    foot = ndimage.binary_dilation(mask, _disk(r_foot))
    ring_geo = ndimage.binary_dilation(mask, _disk(r_out)) & ~ndimage.binary_dilation(mask, _disk(r_in))
    # Checks in order of what a road engineer can act on: the mesh ends, nobody saw it, crowded ring.
    if (foot & ~vc).sum() > cfg.max_invalid_share * foot.sum():
        return _not_measurable("at the mesh edge")
    if (ring_geo & vc).sum() < cfg.min_ring_share * ring_geo.sum():
        return _not_measurable("at the mesh edge (ring cut off)")
    fv = foot & vc
    obs_share = float((fv & oc).sum()) / max(int(fv.sum()), 1)
    if obs_share < cfg.min_observed_share:
        return _not_measurable("unobserved ground")
    ring_free = ring_geo & vc & (lc == 0)
    ring = ring_free & oc
    if ring.sum() < cfg.min_observed_share * max(int(ring_free.sum()), 1):
        return _not_measurable("unobserved ground around it")
    if ring.sum() < cfg.min_ring_vertices:
        return _not_measurable(f"too few ring vertices ({int(ring.sum())} < {cfg.min_ring_vertices})")
    jj, ii = np.nonzero(mask)
    cj, ci = jj.mean(), ii.mean()  # plane coordinates about the footprint's centre: well conditioned
    rj, ri = np.nonzero(ring)
    coef, sigma, inl = robust_plane((ri - ci) * res, (rj - cj) * res, zc[rj, ri], cfg.trim_k, cfg.iterations,
                                    cfg.order)
    n_in = int(inl.sum())
    if n_in < cfg.min_ring_vertices:
        return _not_measurable(f"too few ring vertices agree on a plane ({n_in})")
    fj, fi = np.nonzero(fv)
    floor = max(2.0 * sigma, cfg.noise_floor_m)
    if own is not None and len(own[0]) >= cfg.min_samples:  # the sweep's road: its ring, not the fused mask's
        (p0, n) = own[1]
        plane = np.array([p0[2], -n[0] / n[2], -n[1] / n[2]])
        return _pothole_from_samples(np.asarray(own[0], np.float64), (float(p0[0]), float(p0[1])), plane, sigma,
                                     n_in, int(fv.sum()) * res * res, cfg, "floor-sweep samples (images)")
    n_inside = 0
    if samples is not None and len(samples):
        found, n_inside = _pothole_in_samples(samples, fv, ring, (j0, i0), (cj, ci), grid, (coef, sigma, n_in), cfg)
        if found is not None:
            return found
    if own_why and not cfg.surface_floor:
        return _not_measurable(f"floor not measured ({own_why})")
    if not cfg.surface_floor:
        return _not_measurable(f"floor not measured ({n_inside} height samples inside it, {cfg.min_samples} needed)"
                               if samples is not None else "floor not measured (no depth measurements)")
    d = surface_at(coef, (fi - ci) * res, (fj - cj) * res) - zc[fj, fi]  # + below the plane
    dent = d > floor
    # plane offset error at the centre ~ sigma * sqrt(p / n) (p parameters), plus one vertex's own noise;
    # a footprint partly unobserved widens it (fewer views fixed those heights)
    sig = math.sqrt(sigma * sigma * (1.0 + len(coef) / n_in)) / math.sqrt(max(obs_share, 1e-3))
    return {
        "measurable": True, "measure_note": "",
        "depth_max_mm": round(max(float(d.max()), 0.0) * 1000.0, 1),
        "depth_mean_mm": round(float(d[dent].mean()) * 1000.0, 1) if dent.any() else 0.0,
        "volume_l": round(float(d[dent].sum()) * res * res * 1000.0, 3),
        "depth_sigma_mm": round(sig * 1000.0, 1),
    }


def _pothole_in_samples(samples: np.ndarray, fv: np.ndarray, ring: np.ndarray, crop0: tuple[int, int],
                        c: tuple[float, float], grid: tuple[float, float, float],
                        fit: tuple[np.ndarray, float, int], cfg: MeasureConfig) -> tuple[dict | None, int]:
    """Pothole measures from the height ``samples`` (n, 3) world x, y, z inside the footprint ``fv`` (h, w) bool,
    a crop whose cell (0, 0) is grid cell ``crop0`` (j, i), with the footprint's centre ``c`` (row, col) in it;
    ``fit`` the surface ring's plane (coef, sigma, inliers). With ``min_ring_samples`` of them in ``ring``
    (h, w) bool, the plane is refitted on those. (measures, or None with fewer than ``min_samples`` inside;
    the count inside)."""
    (j0, i0), (cj, ci), res = crop0, c, grid[2]
    coef, sigma, n_in = fit
    # the samples inside the footprint: grid cells (j0 + row, i0 + col) of the crop
    si = np.rint((samples[:, 0] - grid[0]) / res).astype(np.int64) - i0
    sj = np.rint((samples[:, 1] - grid[1]) / res).astype(np.int64) - j0
    inb = (si >= 0) & (sj >= 0) & (si < fv.shape[1]) & (sj < fv.shape[0])
    inside, around = np.zeros(len(samples), bool), np.zeros(len(samples), bool)
    inside[inb] = fv[sj[inb], si[inb]]
    around[inb] = ring[sj[inb], si[inb]]
    centre = (grid[0] + (i0 + ci) * res, grid[1] + (j0 + cj) * res)
    if inside.sum() < cfg.min_samples:
        return None, int(inside.sum())
    if around.sum() >= cfg.min_ring_samples:  # the plane from the same kind of measurement as the floor
        a = samples[around]
        c2, s2, inl2 = robust_plane(a[:, 0] - centre[0], a[:, 1] - centre[1], a[:, 2], cfg.trim_k,
                                    cfg.iterations, cfg.order)
        if s2 <= max(3.0 * sigma, 0.01):  # a ring on a kerb or a car's foot: the surface's ring stays
            coef, sigma, n_in = c2, s2, int(inl2.sum())
    found = _pothole_from_samples(samples[inside], centre, coef, sigma, n_in, int(fv.sum()) * res * res, cfg)
    return found, int(inside.sum())


def _pothole_from_samples(pts: np.ndarray, centre: tuple[float, float], coef: np.ndarray, sigma: float, n_ring: int,
                          foot_area: float, cfg: MeasureConfig, what: str = "height samples") -> dict:
    """Pothole measures from height samples pts (n, 3) inside its footprint, below the ring plane ``coef``
    (about ``centre``): depth_max the ``sample_quantile`` of their depths, depth_mean over those below the
    noise floor, volume their mean depth (negative as 0) over the footprint area ``foot_area`` m²; the note
    names them ``what``."""
    d = surface_at(coef, pts[:, 0] - centre[0], pts[:, 1] - centre[1]) - pts[:, 2]
    floor = max(2.0 * sigma, cfg.noise_floor_m)
    dent = d > floor
    spread = 1.4826 * float(np.median(np.abs(d - np.median(d)))) if len(d) > 1 else 0.0
    sig = math.sqrt(sigma * sigma * (1.0 + len(coef) / n_ring) + spread * spread / len(d))
    return {
        "measurable": True, "measure_note": f"from {len(d)} {what} inside it",
        "depth_max_mm": round(max(float(np.quantile(d, cfg.sample_quantile)), 0.0) * 1000.0, 1),
        "depth_mean_mm": round(float(d[dent].mean()) * 1000.0, 1) if dent.any() else 0.0,
        "volume_l": round(float(np.clip(d, 0.0, None).mean()) * foot_area * 1000.0, 3),
        "depth_sigma_mm": round(sig * 1000.0, 1),
    }


def surface_at(coef: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """The fitted plane (or quadratic) of :func:`robust_plane` at points x, y -> (N,) float64 (inputs ravelled)."""
    return _design(np.ravel(x).astype(np.float64), np.ravel(y).astype(np.float64), 2 if len(coef) > 3 else 1
                   ) @ coef


def skeleton_length(mask: np.ndarray, res: float) -> float:
    """Length (m) along the skeleton of a (h, w) bool mask; sum over its 8-connected pieces.

    Each piece: geodesic diameter of its skeleton graph (two Dijkstra passes; 1 cell orthogonal,
    sqrt 2 diagonal), plus the mask's half-width at both path ends less the end cells' own half cell.
    """
    from skimage.morphology import skeletonize

    if not mask.any():
        return 0.0
    sk = skeletonize(mask)
    edt = ndimage.distance_transform_edt(mask)
    idx = -np.ones(sk.shape, dtype=np.int64)
    jj, ii = np.nonzero(sk)
    n = len(jj)
    idx[jj, ii] = np.arange(n)
    rows, cols, wts = [], [], []
    h, w = sk.shape
    for dj, di, wt in ((0, 1, 1.0), (1, 0, 1.0), (1, 1, math.sqrt(2.0)), (1, -1, math.sqrt(2.0))):
        j2, i2 = jj + dj, ii + di
        ok = (j2 < h) & (i2 >= 0) & (i2 < w)
        tgt = np.full(n, -1)
        tgt[ok] = idx[j2[ok], i2[ok]]
        m = tgt >= 0
        rows.append(np.nonzero(m)[0])
        cols.append(tgt[m])
        wts.append(np.full(int(m.sum()), wt))
    g = coo_matrix((np.concatenate(wts), (np.concatenate(rows), np.concatenate(cols))), shape=(n, n)).tocsr()
    ncomp, comp = connected_components(g, directed=False)
    total = 0.0
    for c in range(ncomp):  # pieces of one instance: a handful
        nodes = np.nonzero(comp == c)[0]
        da = dijkstra(g, directed=False, indices=int(nodes[0]))
        a = int(nodes[np.argmax(da[nodes])])
        db = dijkstra(g, directed=False, indices=a)
        b = int(nodes[np.argmax(db[nodes])])
        ends = (edt[jj[a], ii[a]] - 1.0) + (edt[jj[b], ii[b]] - 1.0)  # a one-cell-wide line adds nothing
        total += (float(db[b]) + max(float(ends), 0.0)) * res
    return total


def route_direction(route: np.ndarray, xy: tuple[float, float], half_m: float = 1.0) -> np.ndarray | None:
    """(2,) unit direction of travel of the route at the foot of point ``xy`` (None: no route)."""
    if route is None or len(route) < 2:
        return None
    s, _ = chainage(route, np.asarray(xy, dtype=np.float64).reshape(1, 2))
    cum = cumulative_length(route)
    s0, s1 = np.clip([s[0] - half_m, s[0] + half_m], 0.0, cum[-1])
    p = np.stack([np.interp([s0, s1], cum, route[:, k]) for k in (0, 1)], axis=1)
    d = p[1] - p[0]
    n = float(np.hypot(*d))
    return d / n if n > 1e-9 else None


def _crack(inst: DefectInstance, sl: tuple | None, lab: np.ndarray | None, grid: tuple[float, float, float],
           route: np.ndarray | None) -> dict:
    """Crack length along the skeleton and orientation against the route (see module doc)."""
    if sl is None or lab is None:
        return {"crack_length_m": None, "orientation_deg": None, "orientation_ok": None}
    res = grid[2]
    j0, j1, i0, i1 = sl[0].start - 1, sl[0].stop + 1, sl[1].start - 1, sl[1].stop + 1
    mask = _crop(lab, j0, j1, i0, i1, 0) == inst.id
    out: dict = {"crack_length_m": round(skeleton_length(mask, res), 3), "orientation_deg": None,
                 "orientation_ok": None}
    jj, ii = np.nonzero(mask)
    if len(jj) < 2:
        return out
    pts = np.stack([ii, jj], axis=1).astype(np.float64) * res
    pts -= pts.mean(0)
    evals, evecs = np.linalg.eigh(pts.T @ pts)
    axis = evecs[:, int(np.argmax(evals))]
    t = route_direction(route, inst.centroid) if route is not None else None
    if t is None:
        return out
    deg = math.degrees(math.acos(min(1.0, abs(float(axis @ t)))))
    out["orientation_deg"] = round(deg, 1)
    out["orientation_ok"] = bool(deg <= 45.0) if inst.cls == 0 else bool(deg >= 45.0)
    return out


__all__ = ["MeasureConfig", "measure_instances", "robust_plane", "route_direction", "skeleton_length",
           "surface_at"]
