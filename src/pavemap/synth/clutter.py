"""Clutter of the synthetic world: parked cars, buildings, walls, poles, trees and bushes, and their shadows.

Objects are oriented boxes ``(Nb, 12)`` and spheres ``(Ns, 8)`` (see :class:`pavemap.synth.scene.World`).
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np

from pavemap.synth.params import BUILDING, OBJECT_KINDS, TERRAIN, VEHICLE

if TYPE_CHECKING:
    from pavemap.synth.scene import World

# ---------------------------------------------------------------------------- clutter

CAR_COLOURS = np.array([
    [0.85, 0.85, 0.86], [0.62, 0.63, 0.65], [0.12, 0.12, 0.13], [0.35, 0.36, 0.38], [0.13, 0.2, 0.38],
    [0.55, 0.1, 0.08], [0.75, 0.72, 0.65], [0.2, 0.3, 0.22], [0.9, 0.9, 0.88], [0.45, 0.47, 0.5],
])
FACADE_COLOURS = np.array([
    [0.78, 0.72, 0.6], [0.62, 0.35, 0.27], [0.7, 0.7, 0.68], [0.85, 0.83, 0.78], [0.55, 0.5, 0.45],
    [0.66, 0.6, 0.52],
])


def make_clutter(w: World, rng: np.random.Generator):
    p = w.params
    w2 = p.width / 2
    boxes: list[list[float]] = []
    spheres: list[list[float]] = []
    skind: list[int] = []
    kind = {k: i for i, k in enumerate(OBJECT_KINDS)}
    L = p.road_length

    def place(s: float, t: float) -> tuple[float, float, float, float]:
        xy = w.xy_of_st(np.array([s]), np.array([t]))[0]
        z = float(w.height_at(xy[:1], xy[1:])[0])
        return float(xy[0]), float(xy[1]), z, float(w.heading_at(np.array([s]))[0])

    def box(s, t, length, width, z0, z1, colour, label, k, yaw_extra=0.0, base=None):
        x, y, z, yaw = place(s, t)
        if base is not None:
            z = base
        boxes.append([x, y, z + 0.5 * (z0 + z1), length / 2, width / 2, 0.5 * (z1 - z0), yaw + yaw_extra,
                      *colour, label, kind[k]])
        return z

    dens = p.clutter
    if dens <= 0:
        return np.zeros((0, 12), np.float32), np.zeros((0, 8), np.float32), np.zeros(0, np.int64)
    for side in (-1.0, 1.0):
        sw = p.sidewalk_left if side > 0 else p.sidewalk_right
        kerb_out = w2 + p.curb_width + sw  # outer edge of the sidewalk
        # parked cars: mostly at the kerb, half on the sidewalk or with 0.5 m on the road
        s = rng.uniform(0, 10)
        while s < L - 5:
            s += rng.exponential(14.0 / dens) + 5.0
            if s > L - 5:
                break
            length, width = rng.uniform(3.9, 4.9), rng.uniform(1.7, 1.95)
            height = rng.uniform(1.4, 1.75)
            r = rng.random()
            if r < 0.55:
                tc = side * (w2 - 0.5 + width / 2)  # 0.5 m of the car on the road edge
            elif r < 0.85:
                tc = side * (w2 + p.curb_width + 0.1)  # half on the kerb
            else:
                tc = side * (kerb_out + rng.uniform(1.5, 4.0))  # driveway / verge
            col = CAR_COLOURS[rng.integers(len(CAR_COLOURS))] * rng.uniform(0.9, 1.05)
            yaw_e = rng.normal(0, 0.03) + (math.pi if rng.random() < 0.5 else 0.0)
            z = box(s, tc, length, width, 0.3, 0.95, col, VEHICLE, "car_body", yaw_e)
            box(s, tc, length * 0.55, width * 0.88, 0.95, height, col, VEHICLE, "car_cabin", yaw_e, base=z)
            for ax_off in (-0.32, 0.32):
                xy = w.xy_of_st(np.array([s + ax_off * length * math.cos(yaw_e)]), np.array([tc]))[0]
                zz = float(w.height_at(xy[:1], xy[1:])[0])
                boxes.append([float(xy[0]), float(xy[1]), zz + 0.32, 0.33, width / 2 - 0.02, 0.34,
                              float(w.heading_at(np.array([s]))[0]) + yaw_e, 0.06, 0.06, 0.065, VEHICLE,
                              kind["car_wheels"]])
            s += length
        # buildings and walls beyond the sidewalk, with gaps
        s = rng.uniform(-5, 10)
        while s < L + 20:
            length = rng.uniform(8.0, 20.0)
            r = rng.random()
            if r < 0.55 * min(1.0, dens):
                depth = rng.uniform(8.0, 12.0)
                setback = rng.uniform(1.0, 6.0)
                tc = side * (kerb_out + setback + depth / 2)
                col = FACADE_COLOURS[rng.integers(len(FACADE_COLOURS))] * rng.uniform(0.9, 1.05)
                box(s + length / 2, tc, length, depth, -0.5, rng.uniform(4.0, 14.0), col, BUILDING, "building",
                    rng.normal(0, 0.02))
            elif r < 0.8:
                tc = side * (kerb_out + 0.2)
                col = np.array([0.6, 0.6, 0.58]) * rng.uniform(0.8, 1.1)
                box(s + length / 2, tc, length, 0.3, -0.3, rng.uniform(1.2, 2.4), col, BUILDING, "wall")
            s += length + rng.uniform(2.0, 12.0)
        # poles near the kerb
        s = rng.uniform(0, 20)
        while s < L:
            grey = np.array([0.45, 0.45, 0.47])
            box(s, side * (w2 + p.curb_width + 0.4), 0.2, 0.2, -0.2, rng.uniform(4.0, 8.0), grey, BUILDING, "pole")
            s += rng.uniform(20.0, 40.0) / max(dens, 0.2)
        # trees (trunk + canopy) and bushes on the outer sidewalk / verge
        s = rng.uniform(0, 10)
        while s < L:
            tc = side * (kerb_out - 0.6 + rng.uniform(0, 1.5))
            trunk_h = rng.uniform(2.0, 3.5)
            z = box(s, tc, 0.3, 0.3, -0.2, trunk_h + 0.5, np.array([0.3, 0.22, 0.15]), BUILDING, "trunk")
            x, y, _, _ = place(s, tc)
            rad = rng.uniform(1.4, 2.6)
            green = np.array([0.18, 0.34, 0.12]) * rng.uniform(0.8, 1.2)
            spheres.append([x, y, z + trunk_h + 0.6 * rad, rad, *green, BUILDING])
            skind.append(kind["canopy"])
            s += rng.uniform(12.0, 35.0) / max(dens, 0.2)
        s = rng.uniform(0, 10)
        while s < L:
            tc = side * (kerb_out + rng.uniform(0.5, 4.0))
            x, y, z, _ = place(s, tc)
            rad = rng.uniform(0.4, 1.0)
            green = np.array([0.22, 0.38, 0.14]) * rng.uniform(0.8, 1.2)
            spheres.append([x, y, z + 0.3 * rad, rad, *green, TERRAIN])
            skind.append(kind["bush"])
            s += rng.uniform(6.0, 20.0) / max(dens, 0.2)
    return (np.asarray(boxes, np.float32).reshape(-1, 12), np.asarray(spheres, np.float32).reshape(-1, 8),
            np.asarray(skind, np.int64))


def box_corners(boxes: np.ndarray) -> np.ndarray:
    """(Nb, 8, 3) world corners of oriented boxes."""
    sx = np.array([-1, 1, 1, -1, -1, 1, 1, -1], float)
    sy = np.array([-1, -1, 1, 1, -1, -1, 1, 1], float)
    sz = np.array([-1, -1, -1, -1, 1, 1, 1, 1], float)
    b = boxes.astype(np.float64)
    lx = sx[None] * b[:, 3:4]
    ly = sy[None] * b[:, 4:5]
    lz = sz[None] * b[:, 5:6]
    c, s = np.cos(b[:, 6:7]), np.sin(b[:, 6:7])
    return np.stack([b[:, 0:1] + c * lx - s * ly, b[:, 1:2] + s * lx + c * ly, b[:, 2:3] + lz], axis=-1)


def shadow_raster(w: World) -> np.ndarray:
    """Ground shadow coverage of all objects for the sun direction (projected hulls, softened edges)."""
    from scipy.ndimage import gaussian_filter
    from scipy.spatial import ConvexHull
    from skimage.draw import polygon as fill_polygon

    g = w.shadow_grid
    sh = np.zeros((g.ny, g.nx), np.float32)
    sun = w.sun
    shapes = []
    if len(w.boxes):
        shapes += list(box_corners(w.boxes))
    for sp in w.spheres:
        ang = np.linspace(0, 2 * np.pi, 12, endpoint=False)
        ring = [sp[:3] + sp[3] * np.array([np.cos(a) * np.cos(e), np.sin(a) * np.cos(e), np.sin(e)])
                for a in ang for e in (-0.6, 0.0, 0.6)]
        shapes.append(np.array(ring))
    for pts in shapes:
        zg = float(w.height_at(pts[:, 0].mean(keepdims=True), pts[:, 1].mean(keepdims=True))[0])
        h = np.clip(pts[:, 2] - zg, 0, None)
        proj = pts[:, :2] - (h / sun[2])[:, None] * sun[None, :2]
        allp = np.concatenate([proj, pts[:, :2]])
        try:
            hull = allp[ConvexHull(allp).vertices]
        except Exception:  # degenerate (flat) object: no shadow worth drawing
            continue
        rr, cc = fill_polygon((hull[:, 1] - g.y0) / g.res, (hull[:, 0] - g.x0) / g.res, shape=sh.shape)
        sh[rr, cc] = 1.0
    return gaussian_filter(sh, 1.0).astype(np.float32)
