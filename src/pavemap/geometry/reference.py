"""Brute-force reference rasterizer (numpy): every triangle against every ray.

The test oracle for :func:`pavemap.geometry.heightfield.intersect_rays`; O(rays x triangles), so
only for small height fields.
"""

from __future__ import annotations

import numpy as np

from pavemap.geometry.heightfield import HeightField


def reference_intersect(
    hf: HeightField, origins: np.ndarray, dirs: np.ndarray, max_dist: float = 200.0, block: int = 256
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Moeller-Trumbore over all kept triangles; nearest hit with ``0 <= lam <= max_dist``.

    origins, dirs: (N, 3). Returns lam (N,) (inf on a miss), hit (N,) bool, vertex_ids (N, 3) long
    and bary (N, 3) float64 in the vertex order of ``HeightField.faces``.
    """
    verts = hf.vertices().detach().cpu().double().numpy()
    faces = hf.faces(valid_only=True).cpu().numpy()
    o = np.asarray(origins, dtype=np.float64)
    d = np.asarray(dirs, dtype=np.float64)
    n = o.shape[0]
    lam_best = np.full(n, np.inf)
    face_best = np.full(n, -1)
    bary_best = np.zeros((n, 3))
    p0, p1, p2 = verts[faces[:, 0]], verts[faces[:, 1]], verts[faces[:, 2]]
    e1, e2 = p1 - p0, p2 - p0
    for s in range(0, n, block):
        oo, dd = o[s:s + block, None, :], d[s:s + block, None, :]
        pv = np.cross(dd, e2[None])
        det = np.einsum("rfk,fk->rf", pv, e1)
        ok = np.abs(det) > 1e-15
        inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
        tv = oo - p0[None]
        bu = np.einsum("rfk,rfk->rf", tv, pv) * inv
        qv = np.cross(tv, e1[None])
        bv = np.einsum("rk,rfk->rf", dd[:, 0], qv) * inv
        lam = np.einsum("fk,rfk->rf", e2, qv) * inv
        eps = 1e-10
        good = ok & (bu >= -eps) & (bv >= -eps) & (bu + bv <= 1 + eps) & (lam >= 0) & (lam <= max_dist)
        lam = np.where(good, lam, np.inf)
        f = np.argmin(lam, axis=1)
        r = np.arange(lam.shape[0])
        lb = lam[r, f]
        lam_best[s:s + block] = lb
        face_best[s:s + block] = np.where(np.isfinite(lb), f, -1)
        b1, b2 = bu[r, f], bv[r, f]
        bary_best[s:s + block] = np.stack([1 - b1 - b2, b1, b2], 1)
    hit = face_best >= 0
    ids = np.where(hit[:, None], faces[np.maximum(face_best, 0)], 0)
    return lam_best, hit, ids, np.where(hit[:, None], bary_best, 0.0)
