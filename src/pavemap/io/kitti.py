"""KITTI odometry → sequence folder.

Layout read (the official one; ``poses`` may also sit inside the sequence folder)::

    ROOT/sequences/00/image_2/000000.png    colour left   (--camera 2)
    ROOT/sequences/00/image_0/000000.png    grey left     (--camera 0, stored as 3 channels)
    ROOT/sequences/00/calib.txt             P0..P3 (3x4), Tr (velodyne -> cam0)
    ROOT/sequences/00/times.txt             optional, seconds
    ROOT/sequences/00/velodyne/000000.bin   optional, float32 x y z reflectance
    ROOT/poses/00.txt                       or ROOT/sequences/00/poses.txt

``calib.txt`` lines are either labelled (``P0: 12 numbers``, ``Tr: 12 numbers``) or bare
3×4 rows in the order P0, P1[, P2, P3][, Tr] (2, 4 or 5 rows). ``poses.txt`` has one row
of 12 numbers per frame: the 3×4 camera-to-world pose of the left grey camera (cam0) in
KITTI's frame, which is cam0 at frame 0 (x right, y down, z forward).

Conversions:

- world: ``X_ours = A X_kitti`` with ``A = [[0,0,1],[-1,0,0],[0,-1,0]]`` (x forward, y left,
  z up; a proper rotation, det +1). The origin stays at cam0 of frame 0, so the road lies
  near z = -1.65 m (the camera height).
- camera i of the rectified rig: ``P_i = K [I | t_i]`` with ``t_i = K⁻¹ P_i[:, 3]``, so
  ``X_cam_i = X_cam0 + t_i`` and ``T_world_cam_i = A4 · T_kitti_cam0 · [I | -t_i]``.
  Camera axes stay OpenCV (KITTI's already are).
- LiDAR: ``X_cam0 = Tr X_velo``; points are projected into camera i and the nearest depth
  per pixel is written as uint16 millimetres (``depth/<cam>/<frame>.png``).
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pavemap.geometry.valid import check_intrinsics, check_pose
from pavemap.io.gps import A_KITTI_TO_WORLD
from pavemap.io.sequence import SequenceError

#: Odometry sequence -> (raw drive, raw frame of odometry frame 0, raw frame of its last frame), the table of
#: the odometry devkit's readme (checked against several public copies of it): the OXTS (GPS/IMU) records of
#: ``--oxts`` are the raw drive's, offset by the start. 03's raw drive is not published.
KITTI_RAW: dict[str, tuple[str, int, int]] = {
    "00": ("2011_10_03_drive_0027", 0, 4540), "01": ("2011_10_03_drive_0042", 0, 1100),
    "02": ("2011_10_03_drive_0034", 0, 4660), "03": ("2011_09_26_drive_0067", 0, 800),
    "04": ("2011_09_30_drive_0016", 0, 270), "05": ("2011_09_30_drive_0018", 0, 2760),
    "06": ("2011_09_30_drive_0020", 0, 1100), "07": ("2011_09_30_drive_0027", 0, 1100),
    "08": ("2011_09_30_drive_0028", 1100, 5170), "09": ("2011_09_30_drive_0033", 0, 1590),
    "10": ("2011_09_30_drive_0034", 0, 1200),
}


@dataclass
class KittiCalib:
    P: dict[int, np.ndarray]  # camera index -> (3, 4) float64 projection of rectified camera
    Tr: np.ndarray | None  # (4, 4) float64 velodyne -> cam0, None when absent

    def intrinsics(self, cam: int) -> np.ndarray:
        return self.P[cam][:, :3].copy()

    def t_cam0_to_cam(self, cam: int) -> np.ndarray:
        """(3,) t_i with X_cam_i = X_cam0 + t_i."""
        return np.linalg.solve(self.P[cam][:, :3], self.P[cam][:, 3])


def _numbers(text: str, file: Path, line: int) -> np.ndarray:
    try:
        return np.array([float(x) for x in text.split()], dtype=np.float64)
    except ValueError:
        raise SequenceError(file, f"line {line}: expected numbers, got {text.strip()[:60]!r}") from None


def read_calib(path: str | os.PathLike) -> KittiCalib:
    """Parse an odometry ``calib.txt``, labelled or bare (see module docstring)."""
    path = Path(path)
    if not path.is_file():
        raise SequenceError(path, "calib.txt not found (KITTI odometry: sequences/NN/calib.txt)")
    labelled: dict[str, np.ndarray] = {}
    bare: list[np.ndarray] = []
    for ln, raw in enumerate(path.read_text(encoding="utf-8").splitlines(), 1):
        if not raw.strip():
            continue
        m = re.match(r"^\s*([A-Za-z_][\w]*)\s*:(.*)$", raw)
        if m:
            labelled[m.group(1)] = _numbers(m.group(2), path, ln)
        else:
            bare.append(_numbers(raw, path, ln))
    P: dict[int, np.ndarray] = {}
    Tr = None
    if labelled:
        for k, v in labelled.items():
            if re.fullmatch(r"P[0-3]", k):
                P[int(k[1])] = v
            elif k in ("Tr", "Tr_velo_cam", "Tr_velo_to_cam"):
                Tr = v
    else:
        if len(bare) not in (2, 3, 4, 5):
            raise SequenceError(path, f"expected 2, 4 or 5 bare rows (P0, P1[, P2, P3][, Tr]), found {len(bare)}")
        n_p = 4 if len(bare) >= 4 else 2
        P = dict(enumerate(bare[:n_p]))
        if len(bare) in (3, 5):
            Tr = bare[-1]
    for k, v in P.items():
        if v.size != 12:
            raise SequenceError(path, f"P{k} has {v.size} numbers, expected 12 (a 3x4 matrix)")
        P[k] = v.reshape(3, 4)
        why = check_intrinsics(P[k][:, :3])
        if why:
            raise SequenceError(path, f"P{k}: left 3x3 is not a camera matrix ({why})")
    if Tr is not None:
        if Tr.size != 12:
            raise SequenceError(path, f"Tr has {Tr.size} numbers, expected 12 (a 3x4 matrix)")
        Tr = np.vstack([Tr.reshape(3, 4), [0, 0, 0, 1]])
    if not P:
        raise SequenceError(path, "no projection matrices P0..P3 found")
    return KittiCalib(P, Tr)


def read_poses(path: str | os.PathLike) -> np.ndarray:
    """KITTI ``poses.txt`` → (N, 4, 4) float64 cam0-to-world in KITTI's frame. A row whose rotation is not
    orthonormal within 1e-4 (file rounding), or that holds NaN / infinity, raises SequenceError naming the line."""
    path = Path(path)
    rows = []
    for ln, raw in enumerate(path.read_text(encoding="utf-8").splitlines(), 1):
        if not raw.strip():
            continue
        v = _numbers(raw, path, ln)
        if v.size != 12:
            raise SequenceError(path, f"line {ln}: {v.size} numbers, expected 12 (a 3x4 pose)")
        T = np.eye(4)
        T[:3] = v.reshape(3, 4)
        # rounding (~1e-6 in KITTI's files) is cleaned later (kitti_to_world); a scaled or NaN row is an error
        why = check_pose(T)
        if why:
            raise SequenceError(path, f"line {ln}: {why}")
        rows.append(T)
    if not rows:
        raise SequenceError(path, "no poses")
    return np.stack(rows)


def kitti_to_world(T_kitti_cam0: np.ndarray, t_cam: np.ndarray) -> np.ndarray:
    """(N, 4, 4) KITTI cam0 poses and the camera's offset t_i → (N, 4, 4) T_world_cam in pavemap's z-up world."""
    A4 = np.eye(4)
    A4[:3, :3] = A_KITTI_TO_WORLD
    T_cam0_cam = np.eye(4)
    T_cam0_cam[:3, 3] = -t_cam
    T = A4 @ T_kitti_cam0 @ T_cam0_cam
    U, _, Vt = np.linalg.svd(T[:, :3, :3])  # rows of poses.txt carry ~1e-6 rounding
    T[:, :3, :3] = U @ Vt
    return T


def read_velodyne(path: str | os.PathLike) -> np.ndarray:
    """(N, 3) float32 points of a KITTI ``.bin`` (float32 x, y, z, reflectance)."""
    path = Path(path)
    raw = np.fromfile(path, dtype=np.float32)
    if raw.size % 4:
        raise SequenceError(path, f"size {raw.size * 4} bytes is not a multiple of 16 (x, y, z, r float32)")
    return raw.reshape(-1, 4)[:, :3]


def lidar_depth(points_velo: np.ndarray, Tr: np.ndarray, t_cam: np.ndarray, K: np.ndarray,
                width: int, height: int) -> np.ndarray:
    """Sparse depth (H, W) float32 metres (0 = none): nearest projected LiDAR point per pixel.

    ``points_velo`` (N, 3); ``Tr`` (4, 4) velodyne → cam0; camera i sits at X_cam0 + t_cam.
    """
    X = points_velo.astype(np.float64) @ Tr[:3, :3].T + Tr[:3, 3] + t_cam  # (N, 3) in camera i
    X = X[X[:, 2] > 0.1]
    uvw = X @ K.T
    u = np.floor(uvw[:, 0] / uvw[:, 2] + 0.5).astype(np.int64)  # pixel centres at integers
    v = np.floor(uvw[:, 1] / uvw[:, 2] + 0.5).astype(np.int64)
    ok = (u >= 0) & (u < width) & (v >= 0) & (v < height)
    flat = np.full(width * height, np.inf)
    np.minimum.at(flat, v[ok] * width + u[ok], X[ok, 2])
    flat[~np.isfinite(flat)] = 0.0
    return flat.reshape(height, width).astype(np.float32)
