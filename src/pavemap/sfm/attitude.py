"""The car body's attitude along the planar motion's path: each step's rotation in three angles, the path they
chain into, and the world's up from the axis the car turned about (:mod:`pavemap.sfm.planar`).

A car's body rolls and pitches on its springs and with the road's crossfall and grade, and the mount's up is only
known to a degree or two. Chaining each step's full rotation keeps every camera's orientation right; the world's
up is then the axis the turns were made about (the road's normal), not the mount's up.

Conventions: car frame x forward, y left, z up; world z up.
"""

from __future__ import annotations

import numpy as np

from pavemap.sfm.steps import rot_z


def step_rotation(yaw: float | np.ndarray, roll: float | np.ndarray = 0.0,
                  pitch: float | np.ndarray = 0.0) -> np.ndarray:
    """(..., 3, 3) rotation of the car's body over a step (the later body's axes in the earlier's): a turn ``yaw``
    about its up axis, after changes ``roll`` about its forward and ``pitch`` about its left axis (rad, (...,))."""
    yaw, roll, pitch = np.broadcast_arrays(*(np.asarray(v, float) for v in (yaw, roll, pitch)))
    cr, sr, cp, sp = np.cos(roll), np.sin(roll), np.cos(pitch), np.sin(pitch)
    one, zero = np.ones_like(roll), np.zeros_like(roll)
    Rx = np.stack([np.stack([one, zero, zero], -1), np.stack([zero, cr, -sr], -1), np.stack([zero, sr, cr], -1)], -2)
    Ry = np.stack([np.stack([cp, zero, sp], -1), np.stack([zero, one, zero], -1), np.stack([-sp, zero, cp], -1)], -2)
    return rot_z(yaw) @ Rx @ Ry


def unit_path(yaw: np.ndarray, R_cm: np.ndarray, reverse: bool, roll: np.ndarray | None = None,
              pitch: np.ndarray | None = None) -> np.ndarray:
    """(N, 4, 4) camera-to-world poses of a car on arcs: step i turns ``yaw[i]`` (N-1,) rad (NaN: 0), its body's
    roll and pitch change by ``roll[i]`` / ``pitch[i]`` (N-1,) rad (None: 0), and it is one unit long along its
    chord, horizontal in the earlier body half-way between the headings; ``R_cm`` (3, 3) camera -> car; backwards
    along the heading when ``reverse``. The world's up is the bodies' mean up."""
    n = len(yaw)
    th = np.nan_to_num(np.asarray(yaw, float))
    zeros = np.zeros(n)
    rel = step_rotation(th, zeros if roll is None else np.nan_to_num(roll), zeros if pitch is None else
                        np.nan_to_num(pitch))
    body = np.tile(np.eye(3), (n + 1, 1, 1))
    for i in range(n):
        body[i + 1] = body[i] @ rel[i]
    # unit steps: the road's sweep sizes them. Steps sized from the matches' parallax and the ground points under
    # them were tried and measured worse on every synthetic drive (bench/sfm_drives_bench.py: kitti-like turn
    # 0.88 -> 1.66 %, stop-and-go 0.91 -> 1.68 %, nuscenes-like turn 0.49 -> 2.51 %)
    chord = np.stack([np.cos(th / 2), np.sin(th / 2), zeros], -1)
    steps = np.einsum("nij,nj->ni", body[:-1], chord) * (-1.0 if reverse else 1.0)
    p = np.vstack([np.zeros(3), np.cumsum(steps, axis=0)])
    level = _leveller(road_up(body, rel, th))
    T = np.tile(np.eye(4), (n + 1, 1, 1))
    T[:, :3, :3] = level @ body @ R_cm  # world <- car <- camera
    T[:, :3, 3] = p @ level.T
    return T


def road_up(body: np.ndarray, rel: np.ndarray, yaw: np.ndarray, fallback_deg: float = 10.0) -> np.ndarray:
    """(3,) the road's up in the path's frame: the axis the car turned about, each step's rotation axis (in the
    frame of ``body`` (N, 3, 3), the steps' rotations ``rel`` (N-1, 3, 3)) weighted by its turn ``yaw`` (N-1,) rad
    and pointed up, with the bodies' mean up weighted as one turn of ``fallback_deg`` (a straight drive turns about
    nothing). The mount's up, tilted a degree or two from the true normal, would otherwise tilt the world by its
    error times the turn (3.7 deg of roll over the KITTI sample's 80 deg at 3.3 Hz)."""
    from scipy.spatial.transform import Rotation

    rv = Rotation.from_matrix(rel).as_rotvec()  # (N-1, 3) axis * angle, in the earlier body
    axes = np.einsum("nij,nj->ni", body[:-1], rv)
    # times the yaw: a right turn's axis points down, and a step that barely turns (its axis the springs' roll and
    # pitch, of either sign) weighs in quadratically less
    up = (axes * yaw[:, None]).sum(0) + np.radians(fallback_deg) ** 2 * body[:, :, 2].mean(0)
    return up / np.linalg.norm(up)


def _leveller(up: np.ndarray) -> np.ndarray:
    """(3, 3) the smallest rotation taking ``up`` (3,) onto the world's z."""
    from scipy.spatial.transform import Rotation

    u = up / np.linalg.norm(up)
    axis = np.cross(u, [0.0, 0.0, 1.0])
    s = np.linalg.norm(axis)
    if s < 1e-12:
        return np.eye(3)
    return Rotation.from_rotvec(axis / s * np.arctan2(s, u[2])).as_matrix()


__all__ = ["road_up", "step_rotation", "unit_path"]
