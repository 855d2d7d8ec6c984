"""Is it a camera? Is it a pose? The checks every reader of intrinsics and poses applies, one line saying why not."""

from __future__ import annotations

import numpy as np


def check_intrinsics(K: np.ndarray) -> str | None:
    """Return why ``K`` is not a valid pinhole matrix, or None."""
    if K.shape != (3, 3):
        return f"K must be 3x3, got shape {list(K.shape)}"
    if not np.all(np.isfinite(K)):
        return "K contains NaN or infinity"
    if abs(K[1, 0]) > 1e-9 or abs(K[2, 0]) > 1e-9 or abs(K[2, 1]) > 1e-9:
        return "K is not upper-triangular"
    if abs(K[2, 2] - 1.0) > 1e-6:
        return f"K[2][2] must be 1, got {K[2, 2]:g}"
    if K[0, 0] <= 0 or K[1, 1] <= 0:
        return f"K focal lengths must be positive, got fx={K[0, 0]:g}, fy={K[1, 1]:g}"
    return None


def check_pose(T: np.ndarray, tol: float = 1e-4) -> str | None:
    """Return why ``T`` (4x4) is not a rigid camera-to-world transform, or None."""
    if T.shape != (4, 4):
        return f"pose must be 4x4, got shape {list(T.shape)}"
    if not np.all(np.isfinite(T)):
        return "pose contains NaN or infinity"
    R = T[:3, :3]
    err = np.abs(R @ R.T - np.eye(3)).max()
    if err > tol:  # the tolerance covers values rounded to a few digits in a file, not a scaled matrix
        scale = np.sqrt(np.linalg.eigvalsh(R @ R.T).clip(0))
        return (f"pose rotation is not orthonormal (max |R R^T - I| = {err:.2e}, allowed {tol:.0e}; its axes are "
                f"scaled by {scale.min():.4g}..{scale.max():.4g}, a rotation's by 1)")
    det = np.linalg.det(R)
    if abs(det - 1.0) > tol:
        return f"pose rotation has det {det:.4f}, expected 1 (a reflection?)"
    if np.abs(T[3] - np.array([0, 0, 0, 1.0])).max() > 1e-9:
        return "pose bottom row must be [0, 0, 0, 1]"
    return None


__all__ = ["check_intrinsics", "check_pose"]
