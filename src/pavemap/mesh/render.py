"""Differentiable rendering of the height-field road mesh (pure torch, CPU and CUDA).

Every pixel's ray is intersected exactly with the triangulated height field
(:mod:`pavemap.geometry.heightfield`); RGB, semantic logits and camera depth are the barycentric
interpolation of the hit triangle's vertex attributes, exactly as a rasterizer would give.
"""

from __future__ import annotations

import numpy as np
import torch

from pavemap.geometry import HeightField, intersect_rays, pixel_grid, pixel_rays
from pavemap.mesh.model import RoadMesh
from pavemap.types import Camera


def view_rays(K: torch.Tensor, T: torch.Tensor, view: torch.Tensor, uv: torch.Tensor
              ) -> tuple[torch.Tensor, torch.Tensor]:
    """Rays of pixels from many views at once (:func:`pavemap.geometry.pixel_rays`, batched).

    K (V, 3, 3), T (V, 4, 4) camera-to-world, view (N,) long, uv (N, 2) -> origins, dirs (N, 3) with
    ``d = R K^-1 [u, v, 1]`` (lam = camera depth). Differentiable w.r.t. T (pose refinement).
    """
    return pixel_rays(K[view], T[view], uv)


def shade(hit, mesh: RoadMesh) -> dict:  # noqa: ANN001 - a heightfield RayHit
    """The mesh's per-vertex attributes at ray hits -> rgb (N, 3), sem_logits (N, C), depth (N,), valid (N,)."""
    return {"rgb": mesh.at_hits(hit, mesh.rgb.float()), "sem_logits": mesh.at_hits(hit, mesh.sem_logits.float()),
            "depth": hit.lam * hit.hit.to(hit.lam.dtype), "valid": hit.hit}


@torch.no_grad()
def render_view(mesh: RoadMesh, camera: Camera, T_world_cam: np.ndarray | torch.Tensor, scale: float = 1.0,
                max_dist: float = 200.0) -> dict:
    """Render a whole view of the mesh at ``scale`` of the camera's image size.

    Returns {"rgb": (H, W, 3) float in [0, 1], "sem_logits": (H, W, C), "labels": (H, W) long class ids
    (-1 where the ray misses the mesh or the mesh has no semantics), "depth": (H, W) camera depth in
    metres (0 on misses), "valid": (H, W) bool}; tensors on the mesh's device.
    """
    cam = camera.scaled(scale) if scale != 1.0 else camera
    surf = mesh.surface
    dev = surf.heights.device
    px = pixel_grid(cam.width, cam.height, device=dev, dtype=torch.float32)
    o, d = pixel_rays(np.asarray(cam.K, dtype=np.float64), T_world_cam, px)
    hit = intersect_rays(HeightField(surf.x0, surf.y0, surf.res, surf.heights.float(), surf.valid),
                         o, d, max_dist=max_dist)
    C = mesh.sem_logits.shape[-1]
    r = shade(hit, mesh)
    H, W = cam.height, cam.width
    ids = torch.tensor(mesh.class_ids, dtype=torch.long, device=dev)
    if C and mesh.has_semantics:
        labels = torch.where(hit.hit, ids[r["sem_logits"].argmax(1)], torch.full_like(hit.vertex_ids[:, 0], -1))
    else:
        labels = torch.full((px.shape[0],), -1, dtype=torch.long, device=dev)
    return {
        "rgb": r["rgb"].clamp(0, 1).reshape(H, W, 3),
        "sem_logits": r["sem_logits"].reshape(H, W, C),
        "labels": labels.reshape(H, W),
        "depth": r["depth"].reshape(H, W),
        "valid": hit.hit.reshape(H, W),
    }
