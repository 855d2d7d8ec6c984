"""The patch sweep of :mod:`pavemap.mesh.ground_points`: one reference view's corners matched into one partner.

Every depth hypothesis of a corner's ray puts a horizontal plane through that point; the plane's homography
warps the corner's patch into the partner, and zero-mean NCC scores it (:mod:`pavemap.geometry.patch_ncc`):
coarse 2 px steps over the whole depth range, then 1 px, then sub-pixel parabola fits. Patches whose NCC
peak is flat or repeated along the epipolar line are rejected (an edge running with the line).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from pavemap.geometry import patch_ncc
from pavemap.geometry.triangulate import parabola_vertex, second_peak
from pavemap.types import Camera

if TYPE_CHECKING:
    from pavemap.mesh.config import GroundConfig

Z_UP = np.array([0.0, 0.0, 1.0])


@dataclass
class ViewData:
    """A view as the ground points read it: its key (frame index, camera), frame position, camera at the
    matching scale and pose; the images and masks while it is loaded."""

    key: tuple[int, str]
    pos: int
    cam: Camera  # at the matching scale
    T: np.ndarray
    grey: np.ndarray | None = None  # uint8 (corners)
    img: np.ndarray | None = None  # float32, lightly blurred (what the sweep samples)
    mask: np.ndarray | None = None  # candidate ground pixels
    label_ok: np.ndarray | None = None  # semantic ground (None without semantics)
    road: np.ndarray | None = None
    far_mask: np.ndarray | None = None  # candidate ground pixels of the far pass (far references only)


class Patches:
    """What a sweep needs of its reference view a and corners c (N, 2), whatever the partner: the patch pixels'
    rays (N, P, 3), their depth ratios on the plane through the corner's point, the reference patches."""

    def __init__(self, a: ViewData, c: np.ndarray, cfg: GroundConfig, normal: np.ndarray = Z_UP):
        r = cfg.patch // 2
        dv, du = np.mgrid[-r:r + 1, -r:r + 1]
        off = np.stack([du.ravel(), dv.ravel()], 1).astype(np.float64)
        Ra = a.T[:3, :3]
        n_a = Ra.T @ normal
        q = c[:, None, :] + off[None]  # (N, P, 2) reference patch pixels
        Kinv = np.linalg.inv(a.cam.K)
        self.x_a = np.concatenate([q, np.ones(q.shape[:2] + (1,))], -1) @ Kinv.T  # (N, P, 3) rays, z = 1
        self.xc = np.c_[c, np.ones(len(c))] @ Kinv.T
        # a patch pixel's depth on the plane through the centre's point: mu(p) = lam * ratio(p)
        self.ratio = ((self.xc @ n_a)[:, None] / (self.x_a @ n_a)).astype(np.float32)
        ref = patch_ncc.sample_bilinear(a.img, q.reshape(-1, 2)).reshape(len(c), -1)
        self.contrast = ref.std(-1)
        self.sparse = np.nonzero(((off[:, 0] % 2) == 0) & ((off[:, 1] % 2) == 0))[0]
        self.ref = patch_ncc.zncc_rows(ref).astype(np.float32)
        self.ref_sparse = patch_ncc.zncc_rows(ref[:, self.sparse]).astype(np.float32)
        self.lam0 = -cfg.prior_height / (self.xc @ Ra.T)[:, 2]


class Sweep:
    """One (reference a, partner b) pair for N corners (N, 2). Hypotheses are log depths ``tau`` of a
    corner's ray relative to the prior plane's depth ``lam0``. ``patches``: a's :class:`Patches` of these
    corners, when already made for another partner."""

    def __init__(self, a: ViewData, b: ViewData, c: np.ndarray, cfg: GroundConfig, patches: Patches | None = None):
        pa = patches if patches is not None else Patches(a, c, cfg)
        Kb = b.cam.K
        Ra, Rb = a.T[:3, :3], b.T[:3, :3]
        R_ba, t_ba = Rb.T @ Ra, Rb.T @ (a.T[:3, 3] - b.T[:3, 3])
        self.ratio, self.contrast, self.sparse, self.ref, self.ref_sparse, self.lam0 = (
            pa.ratio, pa.contrast, pa.sparse, pa.ref, pa.ref_sparse, pa.lam0)
        self.KU = (pa.x_a @ (Kb @ R_ba).T).astype(np.float32)  # uvw = mu KU + K t
        self.kt = (Kb @ t_ba).astype(np.float32)
        self.xb, self.t_ba, self.Kb = pa.xc @ R_ba.T, t_ba, Kb
        self.img = b.img
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


def sweep_match(a: ViewData, b: ViewData, corners: np.ndarray, cfg: GroundConfig, tau_prior: np.ndarray,
                 patches: Patches | None = None, budget: int = 1_500_000
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Match a's corners (N, 2) into b, coarse (``coarse_px`` spacing over the whole range) to fine (1 px,
    then two parabola fits at 0.5 and 0.25 px). ``tau_prior`` (N,): a corner's log depth from an earlier
    partner (NaN if none); known corners are searched only within +-4 px of it. Returns kept corner
    indices, their pixels in b (on the epipolar line, so a 2-view reprojection error is ~0), log depths."""
    sw = Sweep(a, b, corners.astype(np.float64), cfg, patches)
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


def moved_points(vds: list[ViewData], i: int, corners: np.ndarray, tau: np.ndarray, matched: np.ndarray,
                 partners: list[int], cfg: GroundConfig, patches: Patches) -> np.ndarray:
    """(N,) bool: view i's corners (N, 2) matched into exactly one of ``partners`` (``matched`` (N, K) bool, at
    log depth ``tau`` (N,)) that every other loaded view of i's camera within ``cfg.max_gap`` frames
    contradicts (:func:`contradicted`)."""
    a = vds[i]
    near = []  # views are in frame order: only the neighbours within max_gap frames are looked at
    for step in (-1, 1):
        j = i + step
        while 0 <= j < len(vds) and abs(vds[j].pos - a.pos) <= cfg.max_gap:
            if vds[j].img is not None and vds[j].key[1] == a.key[1]:
                near.append(j)
            j += step
    seen = np.zeros((len(corners), len(near)), bool)
    for k, j in enumerate(partners):
        if j in near:
            seen[:, near.index(j)] = matched[:, k]
    once = matched.sum(1) == 1
    return once & contradicted(a, [vds[j] for j in near], corners, np.where(once, tau, np.nan), seen, cfg, patches)


def contradicted(a: ViewData, others: list[ViewData], corners: np.ndarray, tau: np.ndarray, matched: np.ndarray,
                 cfg: GroundConfig, patches: Patches) -> np.ndarray:
    """(N,) bool: a's corners (N, 2) whose patch, put at the log depth ``tau`` (N,; NaN: not checked), scores
    below ``cfg.static_ncc`` (best within +-1 px along the epipolar line) in every one of the ``others`` views
    that did not match it (``matched`` (N, K) bool) and sees the spot. The static road scores there about as
    it did where it matched; a moving vehicle's flank, matched between two neighbouring frames, does not. A view
    whose semantics or ego mask put something else there counts too: leaving those out kept points that were
    wrong (docs/history, "Points on moving vehicles")."""
    rows_all = np.flatnonzero(np.isfinite(tau))
    best = np.full(len(corners), -np.inf)  # the best NCC over the views that see it (-inf: none does)
    for k, b in enumerate(others):
        rows = rows_all[~matched[rows_all, k]]
        if len(rows) == 0:
            continue
        sw = Sweep(a, b, corners.astype(np.float64), cfg, patches)
        px = np.where(sw.g[rows] > 1.0, 1.0 / np.maximum(sw.g[rows], 1.0), 0.0)  # < 1 px of parallax: depth alone
        ncc = sw.score(tau[rows, None] + np.array([-1.0, 0.0, 1.0])[None] * px[:, None], rows, sparse=False)
        best[rows] = np.maximum(best[rows], np.where(ncc.min(1) > -1, ncc.max(1), -np.inf))  # -1: leaves b
    return np.isfinite(best) & (best < cfg.static_ncc)
