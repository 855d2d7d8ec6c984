"""Pinhole camera rays and projection (SPEC §0: OpenCV axes, ``T_world_cam`` camera-to-world).

Pixel coordinates follow the pixel-centre convention of :meth:`pavemap.types.Camera.scaled`:
the centre of pixel column ``c`` is ``u = c``. Functions accept numpy or torch ``K`` / poses and
return torch tensors on the device and dtype of the tensor argument, so a pose held as a torch
tensor that requires grad (pose refinement) gets gradients.
"""

from __future__ import annotations

import numpy as np
import torch


def as_tensor(a: np.ndarray | torch.Tensor, like: torch.Tensor) -> torch.Tensor:
    """``a`` as a tensor with the dtype and device of ``like`` (keeps autograd when already a tensor)."""
    if isinstance(a, torch.Tensor):
        return a.to(dtype=like.dtype, device=like.device)
    return torch.as_tensor(np.asarray(a, dtype=np.float64), dtype=like.dtype, device=like.device)


def pixel_grid(width: int, height: int, device: torch.device | str = "cpu",
               dtype: torch.dtype = torch.float32) -> torch.Tensor:
    """(H*W, 2) pixel centres ``(u, v)`` in row-major order (row = v)."""
    v, u = torch.meshgrid(
        torch.arange(height, device=device, dtype=dtype),
        torch.arange(width, device=device, dtype=dtype),
        indexing="ij",
    )
    return torch.stack([u.reshape(-1), v.reshape(-1)], dim=1)


def pixel_rays(
    K: np.ndarray | torch.Tensor, T_world_cam: np.ndarray | torch.Tensor, pixels: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Rays through pixels: the project's one pixel-ray function.

    K: (3, 3) or (N, 3, 3); T_world_cam: (4, 4) or (N, 4, 4) camera-to-world; pixels: (N, 2) ``(u, v)``.
    Returns origins (N, 3) (the camera centres) and directions (N, 3) ``d = R K^-1 [u, v, 1]``
    (not normalised: the ray parameter of a point is its camera depth). A batched K / T gives
    each pixel its own camera, so detections of many views go through in one call.
    """
    K_t = as_tensor(K, pixels)
    T = as_tensor(T_world_cam, pixels)
    if K_t.shape[-2:] != (3, 3) or T.shape[-2:] != (4, 4):
        raise ValueError(f"pixel_rays: K must be (..., 3, 3) and T (..., 4, 4), got {tuple(K_t.shape)}, "
                         f"{tuple(T.shape)}")
    if pixels.ndim != 2 or pixels.shape[1] != 2:
        raise ValueError(f"pixel_rays: pixels must be (N, 2), got {tuple(pixels.shape)}")
    fx, fy, cx, cy, s = K_t[..., 0, 0], K_t[..., 1, 1], K_t[..., 0, 2], K_t[..., 1, 2], K_t[..., 0, 1]
    # K^-1 of an upper-triangular pinhole matrix in closed form (a batched solve is ~50x slower).
    y = (pixels[:, 1] - cy) / fy
    x = (pixels[:, 0] - cx - s * y) / fx
    d_cam = torch.stack([x, y, torch.ones_like(x)], dim=1)
    if T.ndim == 2:
        dirs = d_cam @ T[:3, :3].T
        origins = T[:3, 3].expand_as(dirs)
    else:
        dirs = (T[:, :3, :3] @ d_cam.unsqueeze(-1)).squeeze(-1)
        origins = T[:, :3, 3]
    return origins, dirs


def project(
    K: np.ndarray | torch.Tensor, T_world_cam: np.ndarray | torch.Tensor, points: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Project world points (N, 3) to pixels. Returns uv (N, 2) and camera depth (N,).

    Points behind the camera get depth <= 0 and meaningless uv; callers mask them with ``depth > 0``.
    """
    K_t = as_tensor(K, points)
    T = as_tensor(T_world_cam, points)
    R, t = T[:3, :3], T[:3, 3]
    pc = (points - t) @ R  # X_c = R^T (X_w - t), row-vector form
    z = pc[:, 2]
    safe = torch.where(z.abs() > 1e-12, z, torch.full_like(z, 1e-12))
    uvw = pc @ K_t.T
    uv = uvw[:, :2] / safe[:, None]
    return uv, z
