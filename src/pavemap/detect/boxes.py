"""How much of a mask lies inside each box: a summed-area table, four gathers per box.

Shared by the road filter (:mod:`pavemap.detect.filter`: the road share of a box) and the paint and ego rules
(:mod:`pavemap.detect.paint`: the ego-mask share of a box).
"""

from __future__ import annotations

import numpy as np
from skimage.transform import integral_image as integral


def integral_image(mask: np.ndarray) -> np.ndarray:
    """(H, W) bool -> (H+1, W+1) int64 summed-area table with a zero first row and column."""
    ii = np.zeros((mask.shape[0] + 1, mask.shape[1] + 1), dtype=np.int64)
    ii[1:, 1:] = integral(mask, dtype=np.int64)  # the same sums as two cumsums, 3x faster on 1600 x 900
    return ii


def box_ratio(mask: np.ndarray, boxes: np.ndarray, scale: float = 1.0) -> np.ndarray:
    """Share of True pixels of ``mask`` (H, W) inside each box (N, 4) x1 y1 x2 y2 -> (N,) float64.

    Boxes are in full-resolution pixels, pixel-centre convention (column ``c`` has its centre at
    ``u = c``, as :meth:`Camera.scaled`); a pixel counts when its centre lies in the box.
    ``scale`` maps boxes onto a mask of a reduced size. Every box covers at least one pixel.
    """
    H, W = mask.shape
    b = (np.asarray(boxes, dtype=np.float64).reshape(-1, 4) + 0.5) * scale - 0.5
    c0 = np.clip(np.ceil(b[:, 0]), 0, W - 1).astype(np.int64)
    r0 = np.clip(np.ceil(b[:, 1]), 0, H - 1).astype(np.int64)
    c1 = np.clip(np.floor(b[:, 2]) + 1, c0 + 1, W).astype(np.int64)
    r1 = np.clip(np.floor(b[:, 3]) + 1, r0 + 1, H).astype(np.int64)
    ii = integral_image(mask)
    inside = ii[r1, c1] - ii[r0, c1] - ii[r1, c0] + ii[r0, c0]
    return inside / ((r1 - r0) * (c1 - c0))


__all__ = ["box_ratio", "integral_image"]
