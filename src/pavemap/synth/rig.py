"""Camera rigs and the ego trajectory of the synthetic presets.

Vehicle frame: x forward, y left, z up, origin on the ground under the rig. Camera poses are
``T_world_cam`` camera-to-world with OpenCV camera axes (x right, y down, z forward).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from pavemap.synth.scene import World
from pavemap.types import Camera

# R_veh_cam for yaw 0, pitch 0: camera z = vehicle x, camera x = -vehicle y, camera y = -vehicle z
_R0 = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


@dataclass(frozen=True)
class Mount:
    name: str
    width: int
    height: int
    fx: float
    cx: float
    cy: float
    xyz: tuple[float, float, float]  # position in the vehicle frame (m)
    yaw_deg: float  # left positive
    pitch_down_deg: float


RIGS: dict[str, tuple[Mount, ...]] = {
    # nuScenes-like: 6 surround cameras, 1600x900, fx ~1266 (back camera wider, fx ~809)
    "nuscenes-like": (
        Mount("CAM_FRONT", 1600, 900, 1266.4, 816.3, 491.5, (1.70, 0.00, 1.51), 0.0, 1.5),
        Mount("CAM_FRONT_RIGHT", 1600, 900, 1260.8, 807.9, 495.3, (1.55, -0.49, 1.50), -55.0, 1.5),
        Mount("CAM_BACK_RIGHT", 1600, 900, 1259.5, 807.3, 501.2, (1.04, -0.48, 1.56), -110.0, 1.5),
        Mount("CAM_BACK", 1600, 900, 809.2, 829.2, 481.8, (0.05, 0.00, 1.52), 180.0, 1.5),
        Mount("CAM_BACK_LEFT", 1600, 900, 1256.7, 817.8, 451.9, (1.05, 0.48, 1.56), 110.0, 1.5),
        Mount("CAM_FRONT_LEFT", 1600, 900, 1257.9, 827.2, 450.9, (1.52, 0.49, 1.51), 55.0, 1.5),
    ),
    # KITTI-like: one front camera 1241x376 at 1.65 m
    "kitti-like": (Mount("CAM_FRONT", 1241, 376, 718.856, 607.193, 185.216, (0.27, 0.0, 1.65), 0.0, 0.8),),
}
DEFAULT_SCALE = {"nuscenes-like": 0.5, "kitti-like": 1.0}


def rig_cameras(preset: str, scale: float) -> dict[str, Camera]:
    """Cameras of a preset at image ``scale`` (K scaled with the pixel-centre convention)."""
    out = {}
    for m in RIGS[preset]:
        K = np.array([[m.fx, 0.0, m.cx], [0.0, m.fx, m.cy], [0.0, 0.0, 1.0]])
        cam = Camera(m.name, m.width, m.height, K)
        out[m.name] = cam.scaled(scale) if scale != 1.0 else cam
    return out


def _rot_z(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _rot_y(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def _rot_x(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def vehicle_poses(world: World, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Ego poses ``T_world_veh`` (F, 4, 4) and timestamps (F,) following the ego lane with small wobble."""
    p = world.params
    F = p.frames
    ts = np.arange(F) / p.hz
    speed = p.speed * (1 + 0.05 * np.sin(2 * np.pi * ts / max(ts[-1] + 1.0, 8.0) + rng.uniform(0, 6)))
    s = p.road_before + np.concatenate([[0.0], np.cumsum(speed[:-1] / p.hz)])
    lane_t = -p.width / 2 + (p.ego_lane + 0.5) * p.lane_width
    ph = rng.uniform(0, 6.28)
    t = lane_t + 0.15 * np.sin(s / 23.0 + ph)
    dt_ds = 0.15 / 23.0 * np.cos(s / 23.0 + ph)
    if p.path is not None:  # a given trajectory: its own spacing (stops, gaps) in the ego lane's centre
        s = np.interp(path_frames_s(np.asarray(p.path)), world.cl_ego_u, world.cl_s)
        t, dt_ds = np.full(F, lane_t), np.zeros(F)
    xy = world.xy_of_st(s, t)
    yaw = world.heading_at(s) + np.arctan(dt_ds)
    poses = np.zeros((F, 4, 4))
    for i in range(F):
        fwd = np.array([math.cos(yaw[i]), math.sin(yaw[i])])
        left = np.array([-fwd[1], fwd[0]])
        P = xy[i]
        zc = world.height_at(P[:1], P[1:])[0]
        zf = world.height_at(P[:1] + 1.4 * fwd[:1], P[1:] + 1.4 * fwd[1:])[0]
        zb = world.height_at(P[:1] - 1.4 * fwd[:1], P[1:] - 1.4 * fwd[1:])[0]
        zl = world.height_at(P[:1] + 0.8 * left[:1], P[1:] + 0.8 * left[1:])[0]
        zr = world.height_at(P[:1] - 0.8 * left[:1], P[1:] - 0.8 * left[1:])[0]
        pitch = math.atan2(zf - zb, 2.8) + math.radians(rng.normal(0, 0.25))  # nose up positive
        roll = math.atan2(zr - zl, 1.6) + math.radians(rng.normal(0, 0.2))
        R = _rot_z(yaw[i]) @ _rot_y(-pitch) @ _rot_x(roll)
        poses[i, :3, :3] = R
        poses[i, :3, 3] = [P[0], P[1], zc]
        poses[i, 3, 3] = 1.0
    return poses, ts


def path_frames_s(path_xyz: np.ndarray) -> np.ndarray:
    """(F,) ego path length of each frame (standing frames repeat it)."""
    xy = np.asarray(path_xyz, dtype=np.float64)[:, :2]
    return np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(xy, axis=0), axis=1))])


def camera_pose(T_world_veh: np.ndarray, m: Mount) -> np.ndarray:
    """(4, 4) camera-to-world pose of mount ``m`` on the vehicle, re-orthonormalised."""
    R_vc = _rot_z(math.radians(m.yaw_deg)) @ _R0 @ _rot_x(-math.radians(m.pitch_down_deg))
    T_vc = np.eye(4)
    T_vc[:3, :3] = R_vc
    T_vc[:3, 3] = m.xyz
    T = T_world_veh @ T_vc
    U, _, Vt = np.linalg.svd(T[:3, :3])
    T[:3, :3] = U @ Vt
    return T


def perturb_poses(seq, degrees: float = 0.3, metres: float = 0.2, seed: int = 0, per: str = "view"):
    """A deep copy of sequence ``seq`` with every view's pose moved by a rotation of exactly ``degrees``
    about a random axis (in the world frame) and a translation of exactly ``metres`` in a random direction;
    returns (copy, {"frame/camera": true 4x4 pose}).

    ``per="view"``: each camera on its own, rotating about its centre; ``per="frame"``: the cameras of a
    frame as one rigid rig, rotating about their mean centre (an ego-pose error).
    For testing pose refinement against a known error (SPEC §1: 0.3 deg / 0.2 m).
    """
    import copy

    if per not in ("view", "frame"):
        raise ValueError(f"perturb_poses: per must be 'view' or 'frame', got {per!r}")
    rng = np.random.default_rng(seed)
    out = copy.deepcopy(seq)
    truth: dict[str, np.ndarray] = {}
    ang = math.radians(degrees)

    def draw() -> tuple[np.ndarray, np.ndarray]:
        axis = rng.normal(size=3)
        axis /= np.linalg.norm(axis)
        K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
        t = rng.normal(size=3)
        return np.eye(3) + math.sin(ang) * K + (1 - math.cos(ang)) * K @ K, metres * t / np.linalg.norm(t)

    for f in out.frames:
        centre = np.mean([v.T_world_cam[:3, 3] for v in f.views.values()], axis=0)
        shared = draw() if per == "frame" else None
        for name, v in f.views.items():
            truth[f"{f.index}/{name}"] = v.T_world_cam.copy()
            R, t = shared if shared is not None else draw()
            T = v.T_world_cam.copy()
            pivot = centre if per == "frame" else T[:3, 3]
            T[:3, :3] = R @ T[:3, :3]
            T[:3, 3] = pivot + R @ (T[:3, 3] - pivot) + t
            v.T_world_cam = T
    return out, truth


def pose_errors(poses: dict[str, np.ndarray], truth: dict[str, np.ndarray]) -> dict[str, float]:
    """Mean and median translation (m) and rotation (deg) errors of ``poses`` against ``truth`` (same keys)."""
    dt, dr = [], []
    for k, T in poses.items():
        T, T0 = np.asarray(T, dtype=np.float64), truth[k]
        dt.append(float(np.linalg.norm(T[:3, 3] - T0[:3, 3])))
        c = (np.trace(T[:3, :3].T @ T0[:3, :3]) - 1) / 2
        dr.append(float(np.degrees(np.arccos(np.clip(c, -1, 1)))))
    return {"trans_mean_m": float(np.mean(dt)), "trans_median_m": float(np.median(dt)),
            "rot_mean_deg": float(np.mean(dr)), "rot_median_deg": float(np.median(dr)), "views": len(dt)}
