"""Chainage: distance along the driven route, and the signed lateral offset from it.

The route is the rig's trajectory (``Sequence.trajectory()``), a polyline in world metres. A point's
chainage is the path length from the first frame to the point's foot on the polyline; its offset is
the signed distance to that foot (+ left of the direction of travel, - right). A standing vehicle
repeats positions: zero-length pieces are dropped before projecting.
"""

from __future__ import annotations

import numpy as np


def route_polyline(trajectory: np.ndarray, min_step_m: float = 0.05) -> np.ndarray:
    """(F, 2|3) camera centres -> (M, 2) float64 route vertices without repeats closer than ``min_step_m``."""
    xy = np.asarray(trajectory, dtype=np.float64)[:, :2]
    if len(xy) == 0:
        return xy.reshape(0, 2)
    keep = [0]
    for k in range(1, len(xy)):  # O(F) once per run; F is frames, not pixels
        if np.hypot(*(xy[k] - xy[keep[-1]])) >= min_step_m:
            keep.append(k)
    return xy[keep]


def cumulative_length(route: np.ndarray) -> np.ndarray:
    """(M, 2) route -> (M,) float64 chainage of each route vertex (0 at the first)."""
    if len(route) < 2:
        return np.zeros(len(route))
    return np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(route, axis=0).T))])


def chainage(route: np.ndarray, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Chainage and lateral offset of points on a route.

    route (M, 2) float64 from :func:`route_polyline`; points (N, 2) world metres.
    Returns (chainage_m (N,), offset_m (N,)) float64; offset + left of the travel direction.
    Points beyond either end project onto the end piece (chainage < 0 or > length is clipped to it).
    A route of one vertex gives chainage 0 and the distance to it as offset.
    """
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    if len(route) == 0:
        raise ValueError("chainage needs a route with at least one vertex")
    if len(route) == 1 or len(pts) == 0:
        return np.zeros(len(pts)), np.hypot(*(pts - route[0]).T) if len(pts) else np.zeros(0)
    a, b = route[:-1], route[1:]  # (S, 2) pieces
    d = b - a
    L2 = np.maximum((d * d).sum(1), 1e-12)
    cum = cumulative_length(route)
    cand = _candidate_pieces(route, cum, pts)  # (N, K) piece indices; every piece when the route is short
    s_out = np.empty(len(pts))
    o_out = np.empty(len(pts))
    step = max(1, 2_000_000 // cand.shape[1])  # chunks of N*K that stay cache-sized
    for i0 in range(0, len(pts), step):
        p = pts[i0:i0 + step, None, :]
        c = cand[i0:i0 + step]
        t = np.clip(((p - a[c]) * d[c]).sum(-1) / L2[c], 0.0, 1.0)
        foot = a[c] + t[..., None] * d[c]
        dist2 = ((p - foot) ** 2).sum(-1)
        j = np.argmin(dist2, axis=1)
        rows = np.arange(len(j))
        k = c[rows, j]
        s_out[i0:i0 + step] = cum[k] + t[rows, j] * np.sqrt(L2[k])
        v = p[:, 0, :] - foot[rows, j]
        cross = d[k, 0] * v[:, 1] - d[k, 1] * v[:, 0]
        o_out[i0:i0 + step] = np.sign(cross) * np.sqrt(dist2[rows, j])
    return s_out, o_out


def _candidate_pieces(route: np.ndarray, cum: np.ndarray, pts: np.ndarray, spacing: float = 0.5,
                      k: int = 8) -> np.ndarray:
    """(N, K) int64 indices of the route pieces that can hold each point's foot: all of them for a route of
    few pieces; otherwise the pieces of the ``k`` route samples (every ``spacing`` m) nearest the point and
    their neighbours, so a long route costs points x 3k, not points x pieces."""
    n_pieces = len(route) - 1
    if n_pieces <= 3 * k:
        return np.broadcast_to(np.arange(n_pieces), (len(pts), n_pieces))
    from scipy.spatial import cKDTree

    at = np.arange(0.0, cum[-1] + spacing, spacing)
    piece = np.clip(np.searchsorted(cum, at, side="right") - 1, 0, n_pieces - 1)
    xy = np.stack([np.interp(at, cum, route[:, i]) for i in range(2)], axis=1)
    _, near = cKDTree(xy).query(pts, k=min(k, len(xy)))
    near = piece[np.asarray(near).reshape(len(pts), -1)]
    return np.clip(np.concatenate([near - 1, near, near + 1], axis=1), 0, n_pieces - 1)


__all__ = ["chainage", "cumulative_length", "route_polyline"]
