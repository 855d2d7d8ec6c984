"""A tiny textured road scene for stage-1 tests, rendered exactly by ray casting a fine height field.

Not the synthetic world of pavemap.synth: it is small (tens of pixels), fast, and its texture is a
continuous function of world x, y (not vertex colours), so the mesh must actually fit it.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from PIL import Image

from pavemap.geometry import HeightField, intersect_rays, pixel_grid, pixel_rays
from pavemap.io.sequence import read_sequence, save_depth, write_sequence
from pavemap.io.truth import write_truth_height
from pavemap.types import Camera, Frame, SemanticClass, Sequence, View

CLASSES = [
    SemanticClass(0, "road", road=True), SemanticClass(1, "lane_marking", road=True), SemanticClass(2, "curb"),
    SemanticClass(3, "sidewalk"), SemanticClass(5, "vehicle", movable=True), SemanticClass(7, "sky", sky=True),
]
ROAD_HALF = 3.0
CURB = 0.12


def truth_field(res: float = 0.05) -> HeightField:
    x0, y0, nx, ny = -12.0, -8.0, int(48 / res) + 1, int(16 / res) + 1
    xs = x0 + res * np.arange(nx)
    ys = y0 + res * np.arange(ny)
    X, Y = np.meshgrid(xs, ys)
    h = 0.01 * X + 0.04 * np.sin(X / 3.0) - 0.02 * (Y / ROAD_HALF) ** 2
    a = np.abs(Y)
    h = h + np.clip((a - ROAD_HALF) / res, 0, 1) * CURB + 0.02 * np.clip(a - ROAD_HALF - res, 0, None)
    return HeightField(x0, y0, res, torch.tensor(h, dtype=torch.float64), torch.ones(ny, nx, dtype=torch.bool))


def texture(xy: np.ndarray) -> np.ndarray:
    """(N, 2) world -> (N, 3) colour in [0, 1]: asphalt pattern, dashed centre line, concrete sidewalk."""
    x, y = xy[:, 0], xy[:, 1]
    base = 0.35 + 0.12 * np.sin(3.1 * x) * np.cos(2.3 * y) + 0.08 * np.sin(1.7 * x + 2.9 * y) \
        + 0.05 * np.cos(5.3 * x - 1.1 * y)
    col = np.stack([base, base * 0.95 + 0.02, base * 0.9 + 0.05], 1)
    line = (np.abs(y) < 0.08) & (np.mod(x, 3.0) < 1.8)
    col[line] = (0.92, 0.92, 0.88)
    walk = np.abs(y) >= ROAD_HALF
    col[walk] = np.stack([0.62 + 0.05 * np.sin(4 * x[walk]), 0.6 + 0.0 * x[walk], 0.55 + 0.0 * x[walk]], 1)
    return np.clip(col, 0, 1)


def labels_of(xy: np.ndarray) -> np.ndarray:
    x, y = xy[:, 0], xy[:, 1]
    a = np.abs(y)
    lab = np.where(a < ROAD_HALF, 0, np.where(a < ROAD_HALF + 0.1, 2, 3))
    line = (a < 0.08) & (np.mod(x, 3.0) < 1.8)
    return np.where(line, 1, lab).astype(np.uint8)


def look(eye, yaw_deg: float, pitch_down_deg: float) -> np.ndarray:
    """Camera-to-world pose at ``eye`` looking along yaw (from +x, left positive), pitched down."""
    yaw, pitch = np.radians(yaw_deg), np.radians(pitch_down_deg)
    f = np.array([np.cos(yaw) * np.cos(pitch), np.sin(yaw) * np.cos(pitch), -np.sin(pitch)])
    x = np.cross(f, [0, 0, 1.0])
    x /= np.linalg.norm(x)
    y = np.cross(f, x)
    T = np.eye(4)
    T[:3, :3] = np.stack([x, y, f], 1)
    T[:3, 3] = eye
    return T


def make_scene(root: Path, frames: int = 8, width: int = 64, height: int = 40, step: float = 1.2,
               semantics: bool = True, vehicle: bool = True, cams: tuple = (0.0, 45.0, 180.0),
               depth_every: int = 0) -> Sequence:
    """Write a sequence folder with ``frames`` frames of len(cams) cameras and truth/height.*.

    ``depth_every`` > 0 adds sparse depth maps (a LiDAR-like return on every n-th pixel of every n-th row).
    """
    root.mkdir(parents=True, exist_ok=True)
    truth = truth_field()
    K = np.array([[0.8 * width, 0, (width - 1) / 2], [0, 0.8 * width, (height - 1) / 2], [0, 0, 1.0]])
    cameras = {f"CAM{i}": Camera(f"CAM{i}", width, height, K) for i in range(len(cams))}
    px = pixel_grid(width, height, dtype=torch.float64)
    seq_frames = []
    for f in range(frames):
        views = {}
        for ci, yaw in enumerate(cams):
            name = f"CAM{ci}"
            cx = f * step
            z0 = float(truth.height_at(torch.tensor([[cx, -1.5]], dtype=torch.float64))[0][0])
            T = look([cx, -1.5, z0 + 1.5], yaw, 12.0)
            o, d = pixel_rays(K, T, px)
            hit = intersect_rays(truth, o, d, max_dist=60.0)
            xy = hit.points[:, :2].numpy()
            col = texture(xy)
            lab = labels_of(xy)
            col[~hit.hit.numpy()] = (0.55, 0.7, 0.95)
            lab[~hit.hit.numpy()] = 7
            img = (col.reshape(height, width, 3) * 255 + 0.5).astype(np.uint8)
            lab = lab.reshape(height, width)
            if vehicle and ci == 0 and f % 3 == 1:
                img[height // 2:height // 2 + 8, width // 2:width // 2 + 10] = (200, 30, 30)
                lab[height // 2:height // 2 + 8, width // 2:width // 2 + 10] = 5
            (root / "images" / name).mkdir(parents=True, exist_ok=True)
            Image.fromarray(img).save(root / "images" / name / f"{f:06d}.png")
            sem_rel = None
            if semantics:
                (root / "semantics" / name).mkdir(parents=True, exist_ok=True)
                Image.fromarray(lab).save(root / "semantics" / name / f"{f:06d}.png")
                sem_rel = f"semantics/{name}/{f:06d}.png"
            dep_rel = None
            if depth_every:
                lam = np.where(hit.hit.numpy(), hit.lam.numpy(), 0.0).reshape(height, width)
                sparse = np.zeros_like(lam)
                sparse[::depth_every, ::depth_every] = lam[::depth_every, ::depth_every]
                (root / "depth" / name).mkdir(parents=True, exist_ok=True)
                save_depth(root / "depth" / name / f"{f:06d}.png", sparse)
                dep_rel = f"depth/{name}/{f:06d}.png"
            views[name] = View(name, f"images/{name}/{f:06d}.png", T, sem_rel, dep_rel)
        seq_frames.append(Frame(f, f * 0.1, views))
    seq = Sequence("tiny-mesh", list(CLASSES), cameras, seq_frames, None, root)
    write_sequence(seq, root)
    write_truth_height(root, truth.heights.numpy(), truth.grid)
    return seq


def read_scene(root: Path, **kw) -> Sequence:
    """:func:`make_scene` at ``root``, read back from disk (what a run sees)."""
    make_scene(root, **kw)
    return read_sequence(root)
