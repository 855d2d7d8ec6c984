"""Fusion settings (SPEC §2-§3): thresholds, association mode, accumulator and map parameters."""

from __future__ import annotations

from dataclasses import dataclass

from pavemap.errors import PavemapError

ASSOCIATIONS = ("ray", "hit", "footprint")
MASKS = ("frame", "mesh", "both")
PROBS = ("tanh", "sigmoid")


@dataclass
class FusionConfig:
    """Every knob of stages 2-3. Defaults are the benchmark's choice (see bench/results/fusion.json).

    - ``tau_conf``: keep detections with ``conf >= tau_conf`` (paper 0.05 nuScenes / 0.10 KITTI).
    - ``tau_road``: keep detections whose box road share ``R_road > tau_road`` (paper 0.5).
    - ``mask``: road mask source for ``R_road``: ``frame`` (the view's semantic PNG), ``mesh``
      (road rendered from the mesh), ``both`` (both ratios must pass).
    - ``association``: ``ray`` (paper point-to-ray distance, ``d = beta0*r + beta1*(1-conf)``),
      ``hit`` (vertices within ``hit_radius_m`` of the detection's surface point: the centre ray's
      hit, or by default, ``hit_point="footprint"``, the centroid of the box's ground footprint,
      which removes the centre ray's bias toward the camera), ``footprint``
      (vertices whose projection lies inside the box; candidates from a ``footprint_grid``² grid of
      rays over the box, the rectangle capped at ``footprint_max_m``).
    - ``alpha``: EMA weight of a new observation in the severity (paper 0.3).
    - ``prob``: ``tanh`` = 2σ(x)-1 (SPEC erratum, 0 when unobserved) or ``sigmoid`` (paper).
    - ``n_min``: a vertex is a defect vertex when observed at least this often.
    - ``splat_res`` / ``splat_sigma``: BEV map cell size and Gaussian σ in metres.
    - ``min_instance_obs``: drop instances seen by fewer distinct detections (outlier guard).
    - ``merge_gap_m``: defect-vertex pieces closer than this form one instance (views of one
      long crack land as separate blobs on an imperfect surface).
    - ``centroid``: instance centre = inverse-variance weighted mean of its detections' surface
      points (``detections``; weight 1/(road metres per pixel)^2) or the vertex mean (``vertices``).
    """

    tau_conf: float = 0.05
    tau_road: float = 0.5
    mask: str = "frame"
    association: str = "hit"
    alpha: float = 0.3
    beta0: float = 2.5
    beta1: float = 0.0
    hit_radius_m: float = 0.3
    hit_point: str = "footprint"  # hit mode: "centre" ray hit or the box "footprint" centroid
    footprint_grid: int = 4
    footprint_max_m: float = 6.0
    max_dist_m: float = 200.0
    prob: str = "tanh"
    centroid: str = "detections"  # instance centre: mean of its detections' surface points, or "vertices"
    n_min: int = 2
    min_instance_obs: int = 2
    merge_gap_m: float = 0.4  # defect-vertex pieces closer than this form one instance
    splat_res: float = 0.1
    splat_sigma: float = 0.15
    severity_weights: tuple[float, ...] = (0.3, 0.4, 0.7, 1.0)
    mesh_mask_scale: float = 0.25  # render scale when the mesh mask comes from render_view
    mesh_mask_grid: int = 8  # rays per box side when the mesh mask is sampled from the mesh surface
    device: str = "auto"  # auto = the surface's device

    def __post_init__(self) -> None:
        self.validate()

    def validate(self) -> None:
        """Raise PavemapError naming the first bad field."""
        if self.association not in ASSOCIATIONS:
            raise PavemapError(f"fusion.association must be one of {', '.join(ASSOCIATIONS)}, got {self.association!r}")
        if self.mask not in MASKS:
            raise PavemapError(f"fusion.mask must be one of {', '.join(MASKS)}, got {self.mask!r}")
        if self.hit_point not in ("centre", "footprint"):
            raise PavemapError(f"fusion.hit_point must be centre or footprint, got {self.hit_point!r}")
        if self.centroid not in ("detections", "vertices"):
            raise PavemapError(f"fusion.centroid must be detections or vertices, got {self.centroid!r}")
        if self.prob not in PROBS:
            raise PavemapError(f"fusion.prob must be tanh or sigmoid, got {self.prob!r}")
        if not 0.0 < self.alpha <= 1.0:
            raise PavemapError(f"fusion.alpha must be in (0, 1], got {self.alpha}")
        if not 0.0 <= self.tau_road < 1.0:
            raise PavemapError(f"fusion.tau_road must be in [0, 1), got {self.tau_road}")
        if not 0.0 <= self.tau_conf <= 1.0:
            raise PavemapError(f"fusion.tau_conf must be in [0, 1], got {self.tau_conf}")
        if len(self.severity_weights) != 4:
            raise PavemapError(f"fusion.severity_weights needs 4 values (D00 D10 D20 D40), got {self.severity_weights}")
        for name in ("hit_radius_m", "splat_res", "max_dist_m", "mesh_mask_scale", "footprint_max_m"):
            if not getattr(self, name) > 0:
                raise PavemapError(f"fusion.{name} must be positive, got {getattr(self, name)}")
        if self.merge_gap_m < 0:
            raise PavemapError(f"fusion.merge_gap_m must be >= 0, got {self.merge_gap_m}")
        if self.splat_sigma < 0 or self.beta0 < 0 or self.beta1 < 0:
            raise PavemapError("fusion.splat_sigma, beta0 and beta1 must be >= 0")
        if self.n_min < 1 or self.footprint_grid < 1 or self.min_instance_obs < 1 or self.mesh_mask_grid < 1:
            raise PavemapError("fusion.n_min, footprint_grid and min_instance_obs must be >= 1")

    @classmethod
    def preset(cls, name: str) -> FusionConfig:
        """Paper Table 2 thresholds: nuscenes τ_conf 0.05, kitti τ_conf 0.10 (τ_road 0.5, α 0.3, β0 2.5)."""
        if name == "nuscenes":
            return cls(tau_conf=0.05)
        if name == "kitti":
            return cls(tau_conf=0.10)
        raise PavemapError(f"unknown fusion preset {name!r}; choose nuscenes or kitti")
