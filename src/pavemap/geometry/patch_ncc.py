"""The plane-sweep NCC score of :class:`pavemap.mesh.ground_sweep.Sweep`: a compiled kernel and its numpy
reference.

:func:`sweep_scores_numpy` is the reference. It builds every hypothesis's warped patch as arrays of (rows,
hypotheses, patch pixels): a dozen passes over ~1.5 M-element temporaries per call, then ``cv2.remap``, and was
the largest part of stage 1 without training (docs/history, "The closed-form stage 1"). The kernel scores one
(corner, hypothesis) at a time, compiled by numba, on one thread: the patch pixel's depth on the
hypothesis's plane, its projection into the partner, a bilinear sample, and the zero-mean NCC against the
reference patch, without temporaries; a hypothesis stops at its first pixel outside the partner (score -1).

It computes in float64 with exact bilinear weights; the reference computes in float32 and ``cv2.remap`` rounds
sample positions to 1/32 px. The tests compare both: scores within 0.02, the best hypothesis within one step
where the reference finds a match, and the ground points found alike in number (3 %) and median height (2 mm).

Where numba is missing (:func:`available` False) or ``PAVEMAP_NCC=numpy`` asks for it, the reference runs.
"""

from __future__ import annotations

import os

import cv2
import numpy as np

from pavemap.geometry.march_cpu import available, compiled_on_first_use


def _score_py(e, ratio, KU, kt, img, ref, out):
    """out[r, s] = NCC of corner r's patch at plane depth scale e[r, s] (R, S) in ``img`` (H, W); -1 where the
    warped patch leaves the image. ratio (R, P), KU (R, P, 3), kt (3,), ref (R, P) zero-mean unit-norm rows."""
    R, S = e.shape
    P = ratio.shape[1]
    H, W = img.shape
    buf = np.empty(P)
    for r in range(R):
        for s in range(S):
            lam = e[r, s]
            total = 0.0
            inside = True
            for p in range(P):
                mu = lam * ratio[r, p]
                z = mu * KU[r, p, 2] + kt[2]
                if z <= 0.0:
                    inside = False
                    break
                u = (mu * KU[r, p, 0] + kt[0]) / z
                v = (mu * KU[r, p, 1] + kt[1]) / z
                if u < 0.0 or v < 0.0 or u > W - 1 or v > H - 1:
                    inside = False
                    break
                x0 = min(int(u), W - 2)
                y0 = min(int(v), H - 2)
                fx = u - x0
                fy = v - y0
                val = ((1.0 - fy) * ((1.0 - fx) * img[y0, x0] + fx * img[y0, x0 + 1])
                       + fy * ((1.0 - fx) * img[y0 + 1, x0] + fx * img[y0 + 1, x0 + 1]))
                buf[p] = val
                total += val
            if not inside:
                out[r, s] = -1.0
                continue
            mean = total / P
            ss = 0.0
            dot = 0.0
            for p in range(P):
                x = buf[p] - mean
                ss += x * x
                dot += x * ref[r, p]
            out[r, s] = dot / max(np.sqrt(ss), 1e-6)


_KERNEL = compiled_on_first_use(_score_py)


def zncc_rows(x: np.ndarray) -> np.ndarray:
    """(..., P) rows made zero-mean and unit-norm (a flat row stays ~0)."""
    x = x - x.mean(-1, keepdims=True)
    return x / np.maximum(np.linalg.norm(x, axis=-1, keepdims=True), 1e-6)


def sample_bilinear(img: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Bilinear samples (M,) of a float32 image at pixels uv (M, 2) (pixel centres at integers; cv2.remap,
    which rounds positions to 1/32 px; the border replicated)."""
    n = len(uv)
    if n == 0:
        return np.zeros(0, np.float32)
    w = 1024  # remap wants a 2D map of modest width
    m = np.zeros((-(-n // w) * w, 2), np.float32)
    m[:n] = uv
    m = m.reshape(-1, w, 2)
    return cv2.remap(img, m[..., 0], m[..., 1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE).ravel()[:n]


def sweep_scores_numpy(lam: np.ndarray, ratio: np.ndarray, KU: np.ndarray, kt: np.ndarray, img: np.ndarray,
                       ref: np.ndarray) -> np.ndarray:
    """:func:`sweep_scores` in numpy, float32 (the reference)."""
    mu = lam.astype(np.float32)[:, :, None] * ratio[:, None, :]
    z = mu * KU[..., 2][:, None] + kt[2]
    zs = np.maximum(z, 1e-6)
    u = (mu * KU[..., 0][:, None] + kt[0]) / zs
    v = (mu * KU[..., 1][:, None] + kt[1]) / zs
    W, H = img.shape[1] - 1, img.shape[0] - 1
    inside = ((z > 0) & (u >= 0) & (v >= 0) & (u <= W) & (v <= H)).all(-1)
    smp = zncc_rows(sample_bilinear(img, np.stack([u.ravel(), v.ravel()], 1)).reshape(u.shape))
    return np.where(inside, np.einsum("rsp,rp->rs", smp, ref), -1.0)


def sweep_scores(lam: np.ndarray, ratio: np.ndarray, KU: np.ndarray, kt: np.ndarray, img: np.ndarray,
                 ref: np.ndarray) -> np.ndarray:
    """(R, S) NCC scores; -1 where the warped patch leaves the image. lam (R, S): each hypothesis's depth of the
    corner's ray; ratio (R, P): a patch pixel's depth over the centre's on the plane; KU (R, P, 3): the pixels'
    rays through the partner's intrinsics (``uvw = mu KU + kt``); kt (3,); img (H, W) float32 partner image;
    ref (R, P) zero-mean, unit-norm reference patches. Compiled where numba is, else :func:`sweep_scores_numpy`."""
    if not available() or os.environ.get("PAVEMAP_NCC", "").lower() == "numpy":
        return sweep_scores_numpy(lam, ratio, KU, kt, img, ref)
    out = np.empty(lam.shape, np.float64)
    _KERNEL(np.ascontiguousarray(lam, np.float64), np.ascontiguousarray(ratio, np.float64),
                np.ascontiguousarray(KU, np.float64), np.ascontiguousarray(kt, np.float64),
                np.ascontiguousarray(img, np.float32), np.ascontiguousarray(ref, np.float64), out)
    return out


__all__ = ["available", "sample_bilinear", "sweep_scores", "sweep_scores_numpy", "zncc_rows"]
