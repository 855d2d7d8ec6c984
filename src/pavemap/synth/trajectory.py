"""Synthetic worlds along a given trajectory (``pavemap synth --trajectory FILE``, issue 17).

The trajectory is a KITTI odometry pose file (one 3 x 4 camera-to-world matrix per line, e.g.
``kitti-odometry-poses/00.txt``). The ego lane follows the camera path; the road's centre line is offset to the
left of it by the ego lane's offset, resampled every ``CENTRELINE_DS`` and continued straight beyond both ends.
Where the path comes back (a loop, a U-turn, a crossing), the road of both passes is one surface: the height of
the road is a function of the place, not of the arc length (the camera heights of every pass near a point,
smoothed), and defects, streaks and objects that would lie on the other pass's road are left out.
"""

from __future__ import annotations

import logging
import math
import os
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from pavemap.errors import PavemapError
from pavemap.geometry.grid import GridSpec
from pavemap.synth.params import CENTRELINE_DS, WorldParams
from pavemap.synth.rig import path_frames_s

log = logging.getLogger("pavemap")
BASE_RES = 1.0  # m, the raster of the road's height along its passes
BASE_SIGMA = 3.0  # m, smoothing of the camera heights into that raster


def read_trajectory(path: str | os.PathLike, frames: int | None = None, start: int = 0) -> np.ndarray:
    """(F, 3) float64 camera centres (z up, origin at the first one used) of the poses ``start ..
    start + frames`` of a KITTI pose file. Fewer poses than ``frames``: the ones there are, logged."""
    from pavemap.io.kitti import kitti_to_world, read_poses

    path = Path(path)
    if not path.is_file():
        raise PavemapError(f"{path}: trajectory file not found (KITTI odometry poses: 12 numbers per line)")
    T = kitti_to_world(read_poses(path), np.zeros(3))
    if not 0 <= start < len(T):
        raise PavemapError(f"{path}: start pose {start} is outside its {len(T)} poses")
    n = len(T) - start if frames is None else int(frames)
    if n < 2:
        raise PavemapError(f"{path}: a trajectory needs at least 2 poses, asked for {n}")
    if start + n > len(T):
        log.warning("trajectory %s has %d poses from pose %d; rendering %d frames, not the %d asked", path,
                    len(T) - start, start, len(T) - start, n)
        n = len(T) - start
    c = T[start:start + n, :3, 3]
    if not np.all(np.isfinite(c)):
        raise PavemapError(f"{path}: non-finite positions among poses {start}..{start + n - 1}")
    return c - c[0]


def ego_lane_t(p: WorldParams) -> float:
    """Signed lateral offset of the ego lane's centre from the road's centre line (right lanes < 0)."""
    return -p.width / 2 + (p.ego_lane + 0.5) * p.lane_width


def path_centreline(p: WorldParams) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The road of a trajectory world: centre-line samples s (N,), xy (N, 2), theta (N,), kappa (N,), and the
    ego path length of each sample (N,) (to place the frames: ``np.interp(frame_s, ego_s, s)``)."""
    xyz = np.asarray(p.path, dtype=np.float64)
    xy = xyz[:, :2]
    moving = np.concatenate([[True], np.linalg.norm(np.diff(xy, axis=0), axis=1) > 1e-3])
    q = xy[moving]
    sq = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(q, axis=0), axis=1))])
    if sq[-1] < 1.0:
        raise PavemapError("the trajectory moves less than 1 m: no road to build along it")
    ds = CENTRELINE_DS
    u = np.arange(0.0, sq[-1] + 0.5 * ds, ds)
    ex, ey = np.interp(u, sq, q[:, 0]), np.interp(u, sq, q[:, 1])
    k = max(1, int(round(2.0 / ds)))  # heading over +-2 m: pose noise would make the road wobble
    th = np.unwrap(np.arctan2(np.gradient(ey), np.gradient(ex)))
    ker = np.hanning(2 * k + 3)[1:-1]
    th = np.convolve(np.pad(th, k, mode="edge"), ker / ker.sum(), mode="valid")
    from pavemap.synth.rig import RIGS

    fwd = RIGS[p.preset][0].xyz[0]  # the poses are the camera's: the vehicle's reference point sits behind it
    ex, ey = ex - fwd * np.cos(th), ey - fwd * np.sin(th)
    # continue straight beyond both ends, as far as the world's road_before / road_after (+5 m for lookups)
    nb, na = int(math.ceil((p.road_before + 5.0) / ds)), int(math.ceil((p.road_after + 5.0) / ds))
    before = np.arange(-nb, 0) * ds
    after = u[-1] + np.arange(1, na + 1) * ds
    ego_u = np.concatenate([before, u, after])
    ex = np.concatenate([ex[0] + before * math.cos(th[0]), ex, ex[-1] + (after - u[-1]) * math.cos(th[-1])])
    ey = np.concatenate([ey[0] + before * math.sin(th[0]), ey, ey[-1] + (after - u[-1]) * math.sin(th[-1])])
    th = np.concatenate([np.full(nb, th[0]), th, np.full(na, th[-1])])
    lane = ego_lane_t(p)
    cx, cy = ex + lane * np.sin(th), ey - lane * np.cos(th)  # centre = ego - lane_t * left normal
    seg = np.linalg.norm(np.diff(np.stack([cx, cy], 1), axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)]) - 5.0  # as the generated worlds: a little before s = 0
    s = s - np.interp(0.0, ego_u, s) + p.road_before  # the first frame at s = road_before
    kappa = np.gradient(th) / np.maximum(np.gradient(s), 1e-6)
    return s, np.stack([cx, cy], 1), th, kappa, ego_u


def base_raster(p: WorldParams, ego_xy: np.ndarray, ego_u: np.ndarray, g: GridSpec) -> tuple[GridSpec, np.ndarray]:
    """The road's longitudinal height as a function of place: (grid at BASE_RES over ``g``'s box, (ny, nx)
    float32), the ground under every pass's camera (its height minus the mount height) within ~3 sigma,
    Gaussian-weighted; so a loop's two passes see one road height."""
    from pavemap.synth.rig import RIGS

    xyz = np.asarray(p.path, dtype=np.float64)
    frame_u = path_frames_s(xyz)
    mount_z = RIGS[p.preset][0].xyz[2]
    ground = xyz[:, 2] - mount_z
    on_path = (ego_u >= 0) & (ego_u <= frame_u[-1])
    pts = ego_xy[on_path]
    z = np.interp(ego_u[on_path], frame_u, ground)
    bg = GridSpec.covering((g.x0, g.y0), (g.x0 + (g.nx - 1) * g.res, g.y0 + (g.ny - 1) * g.res), BASE_RES)
    X, Y = bg.centres()
    cells = np.stack([X.ravel(), Y.ravel()], 1)
    d, i = cKDTree(pts).query(cells, k=min(24, len(pts)))
    d, i = d.reshape(len(cells), -1), i.reshape(len(cells), -1)
    w = np.exp(-0.5 * ((d - d[:, :1]) / BASE_SIGMA) ** 2)  # relative to the nearest: far cells keep a height
    out = (w * z[i]).sum(1) / w.sum(1)
    return bg, out.reshape(bg.ny, bg.nx).astype(np.float32)


def own_pass(w, s_ranges: np.ndarray, x: np.ndarray, y: np.ndarray, tol_m: float = 0.5) -> np.ndarray:
    """(N,) bool: points (x, y) whose nearest road is the pass they were placed on (their road coordinate s
    within ``s_ranges`` (N, 2) +- tol_m); elsewhere the other pass of a loop would cut them."""
    s, _ = w.st_at(x, y)
    return (s >= s_ranges[:, 0] - tol_m) & (s <= s_ranges[:, 1] + tol_m)


def on_some_road(w, x: np.ndarray, y: np.ndarray, margin_m: float) -> np.ndarray:
    """(N,) bool: points within ``margin_m`` beyond the carriageway of the nearest road."""
    _, t = w.st_at(x, y)
    return np.abs(t) < w.params.width / 2 + margin_m


def turn_path(step: float = 4.0, straight: int = 6, radius: float = 15.0, arc_steps: int = 6,
              angle_deg: float = 90.0) -> np.ndarray:
    """(F, 3) camera centres of a drive for ``WorldParams.path``: ``straight`` steps of ``step`` m, a left turn of
    ``angle_deg`` on a ``radius`` m arc in ``arc_steps`` steps, ``straight`` steps again (2 Hz at 8 m/s by
    default: the SfM tests' and benches' turn)."""
    pts = [np.zeros(2)]
    pts += [np.array([step * (k + 1), 0.0]) for k in range(straight)]
    c = pts[-1] + [0.0, radius]
    a = np.radians(angle_deg)
    arc = -np.pi / 2 + a * np.arange(1, arc_steps + 1) / arc_steps
    pts += [c + radius * np.array([np.cos(u), np.sin(u)]) for u in arc]
    d = np.array([np.cos(a), np.sin(a)])
    pts += [pts[-1] + step * (k + 1) * d for k in range(straight)]
    return np.c_[np.array(pts), np.zeros(len(pts))]

