"""What SfM hands back: metric poses, what was registered, the scale and the figures of its checks."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from pavemap.errors import PavemapError


@dataclass
class SfmResult:
    T_world_cam: np.ndarray  # (N, 4, 4) float64, metric z-up; rows of unregistered images are NaN
    registered: np.ndarray  # (N,) bool
    scale: float  # metres per SfM unit
    plane_inliers: int
    points: np.ndarray  # (P, 3) float64 SfM points in the metric world
    info: dict = field(default_factory=dict)
    K: np.ndarray | None = None  # (3, 3) intrinsics used (refined when asked), pixel-centre convention


class SfmRefusedError(PavemapError):
    """SfM could not give a usable path; ``info`` holds what it measured on the way (for ``sfm.json``)."""

    def __init__(self, message: str, info: dict) -> None:
        super().__init__(message)
        self.info = info
