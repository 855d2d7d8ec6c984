"""Fusion settings (SPEC §3): association mode, accumulator, instance and map parameters.

The road filter's thresholds (``tau_conf``, ``tau_road``, the mask source) are stage 2's:
:class:`pavemap.detect.config.FilterConfig`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

from pavemap.device import CHOICES as DEVICE_CHOICES
from pavemap.device import is_device_name
from pavemap.errors import PavemapError

AssociationMode = Literal["ray", "hit", "footprint"]
HitPoint = Literal["centre", "footprint"]
ProbForm = Literal["tanh", "sigmoid"]
CentroidMode = Literal["detections", "vertices"]
ASSOCIATION_MODES: tuple[str, ...] = ("ray", "hit", "footprint")
PROBS: tuple[str, ...] = ("tanh", "sigmoid")


@dataclass
class FusionConfig:
    """Every knob of stage 3. Defaults are the benchmark's choice (see bench/results/fusion.json).

    - ``association``: ``ray`` (paper point-to-ray distance, ``d = beta0*r + beta1*(1-conf)``),
      ``hit`` (vertices within ``hit_radius_m`` of the detection's surface point: the centre ray's
      hit, or by default, ``hit_point="footprint"``, the centroid of the box's ground footprint,
      which removes the centre ray's bias toward the camera), ``footprint``
      (vertices whose projection lies inside the box; candidates from a ``footprint_grid``² grid of
      rays over the box, the rectangle capped at ``footprint_max_m``).
      The modes are the table :data:`pavemap.fuse.associate.ASSOCIATIONS`.
    - ``alpha``: EMA weight of a new observation in the severity (paper 0.3).
    - ``prob``: ``tanh`` = 2σ(x)-1 (SPEC erratum, 0 when unobserved) or ``sigmoid`` (paper).
    - ``n_min``: a vertex is a defect vertex when observed at least this often.
    - ``splat_res`` / ``splat_sigma``: BEV map cell size and Gaussian σ in metres.
    - ``min_instance_obs``: drop instances seen by fewer distinct detections (outlier guard).
    - ``merge_gap_m``: defect-vertex pieces closer than this form one instance (views of one
      long crack land as separate blobs on an imperfect surface).
    - ``crack_join_m``: pieces of one longitudinal or transverse crack (same class, in line) up to this
      far apart along it form one instance (0: off).
    - ``centroid``: instance centre = inverse-variance weighted mean of its detections' surface
      points (``detections``; weight 1/(road metres per pixel)^2) or the vertex mean (``vertices``).
    - ``severity_weights``: severity of D00, D10, D20, D40 in the EMA.
    - ``device``: ``auto`` = the surface's device, else a name for :func:`pavemap.device.resolve_device`.
    """

    association: AssociationMode = "hit"
    alpha: float = 0.3
    beta0: float = 2.5
    beta1: float = 0.0
    hit_radius_m: float = 0.3
    hit_point: HitPoint = "footprint"
    footprint_grid: int = 4
    footprint_max_m: float = 6.0
    max_dist_m: float = 200.0
    prob: ProbForm = "tanh"
    centroid: CentroidMode = "detections"
    n_min: int = 2
    min_instance_obs: int = 2
    merge_gap_m: float = 0.4
    crack_join_m: float = 1.0
    splat_res: float = 0.1
    splat_sigma: float = 0.15
    severity_weights: tuple[float, ...] = (0.3, 0.4, 0.7, 1.0)
    device: str = "auto"

    def __post_init__(self) -> None:
        self.severity_weights = tuple(float(w) for w in self.severity_weights)
        self.validate()

    def validate(self) -> None:
        """Raise PavemapError naming the first bad field."""
        for name, value, allowed in (("association", self.association, ASSOCIATION_MODES),
                                     ("hit_point", self.hit_point, ("centre", "footprint")),
                                     ("centroid", self.centroid, ("detections", "vertices")),
                                     ("prob", self.prob, PROBS)):
            if value not in allowed:
                raise PavemapError(f"fusion.{name} must be one of {', '.join(allowed)}, got {value!r}")
        if not 0.0 < self.alpha <= 1.0:
            raise PavemapError(f"fusion.alpha must be in (0, 1], got {self.alpha}")
        if len(self.severity_weights) != 4 or not all(0.0 <= w <= 1.0 for w in self.severity_weights):
            raise PavemapError(f"fusion.severity_weights needs 4 values in [0, 1] (D00 D10 D20 D40), "
                               f"got {self.severity_weights}")
        for name in ("hit_radius_m", "splat_res", "max_dist_m", "footprint_max_m"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise PavemapError(f"fusion.{name} must be positive, got {v}")
        for name in ("merge_gap_m", "crack_join_m", "splat_sigma", "beta0", "beta1"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0):
                raise PavemapError(f"fusion.{name} must be >= 0, got {v}")
        for name in ("n_min", "footprint_grid", "min_instance_obs"):
            if getattr(self, name) < 1:
                raise PavemapError(f"fusion.{name} must be >= 1, got {getattr(self, name)}")
        if not is_device_name(self.device):
            raise PavemapError(f"fusion.device must be {DEVICE_CHOICES}, got {self.device!r}")

    @classmethod
    def preset(cls, name: str) -> FusionConfig:
        """Paper Table 2 fusion parameters (α 0.3, β0 2.5) for ``nuscenes`` and ``kitti``.

        The two presets differ only in the filter's τ_conf (:meth:`FilterConfig.preset`).
        """
        if name not in ("nuscenes", "kitti"):
            raise PavemapError(f"unknown fusion preset {name!r}; choose nuscenes or kitti")
        return cls()
