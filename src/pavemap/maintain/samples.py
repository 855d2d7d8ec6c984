"""Height samples around mapped defects: the measured depth pixels of the sequence, read when needed.

Stage 1 keeps its height measurements with the mesh (:attr:`pavemap.mesh.model.RoadMesh.samples`: every
ground point and a subsample of the depth pixels at its training scale). A pothole of 0.3 m² holds few of
those, so where the sequence has depth maps the maintenance stage reads them at full resolution, but only
the pixels that land in a defect's box on the road, from the views near it.
"""

from __future__ import annotations

import numpy as np
import torch

from pavemap.geometry.camera import pixel_rays
from pavemap.io.sequence import load_depth
from pavemap.types import Sequence


def depth_samples(seq: Sequence, boxes: np.ndarray, max_range_m: float = 25.0) -> np.ndarray:
    """(N, 3) float64 world points of the depth pixels of ``seq`` that fall in any of ``boxes`` (B, 4)
    ``x_min, y_min, x_max, y_max`` (world metres), from views whose camera is within ``max_range_m`` of a box;
    an empty (0, 3) array without depth layers or boxes."""
    boxes = np.asarray(boxes, dtype=np.float64).reshape(-1, 4)
    out = [np.zeros((0, 3))]
    if not len(boxes):
        return out[0]
    centres = np.stack([(boxes[:, 0] + boxes[:, 2]) / 2, (boxes[:, 1] + boxes[:, 3]) / 2], 1)
    for f in seq.frames:
        for v in f.views.values():
            if not v.depth:
                continue
            c = np.asarray(v.T_world_cam)[:3, 3]
            near = np.hypot(*(centres - c[:2]).T) <= max_range_m
            if not near.any():
                continue
            d = load_depth(seq.path(v.depth))
            rows, cols = np.nonzero(d > 0)
            if not len(rows):
                continue
            K = seq.cameras[v.camera].K
            sx, sy = d.shape[1] / seq.cameras[v.camera].width, d.shape[0] / seq.cameras[v.camera].height
            uv = torch.from_numpy(np.stack([(cols + 0.5) / sx - 0.5, (rows + 0.5) / sy - 0.5], 1).astype(np.float64))
            o, dirs = pixel_rays(K, v.T_world_cam, uv)
            p = (o + torch.from_numpy(d[rows, cols].astype(np.float64))[:, None] * dirs).numpy()
            b = boxes[near]
            hit = ((p[:, None, 0] >= b[None, :, 0]) & (p[:, None, 0] <= b[None, :, 2])
                   & (p[:, None, 1] >= b[None, :, 1]) & (p[:, None, 1] <= b[None, :, 3])).any(1)
            out.append(p[hit])
    return np.concatenate(out)


__all__ = ["depth_samples"]
