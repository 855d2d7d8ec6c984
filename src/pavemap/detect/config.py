"""Stage 2 settings: which detector runs (``DetectorConfig``) and which detections go on (``FilterConfig``).

Both are sections of :class:`pavemap.config.RunConfig` (``detector:`` and ``filter:``); their field
types are the schema the config loader checks YAML and ``--set`` overrides against.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

from pavemap.errors import PavemapError

Backend = Literal["auto", "sim", "yolo", "file"]
MaskSource = Literal["frame", "mesh", "both"]
BACKENDS: tuple[str, ...] = ("auto", "sim", "yolo", "file")
MASKS: tuple[str, ...] = ("frame", "mesh", "both")
#: paper Table 2's τ_conf per preset: the simulated detector is calibrated to them, and a detector whose operating
#: point pavemap has not measured gets them
PAPER_TAU_CONF: dict[str, float] = {"nuscenes": 0.05, "kitti": 0.10}


@dataclass
class DetectorConfig:
    """The detection backend of ``pavemap run``.

    - ``backend``: ``auto`` (``sim`` where the sequence has synthetic truth ``truth/defects.geojson``,
      else ``yolo`` with the shipped weights), ``sim`` (simulated detector, synthetic sequences only),
      ``yolo`` (ultralytics weights), ``file`` (a detections JSONL or a folder of YOLO txt files).
    - ``weights``: yolo weights (.pt); None = the shipped
      ``pavemap/weights/pavemap-yolov5n-rdd2022.pt`` (inside the package).
    - ``file``: file backend input; None = ``SEQ/detections.jsonl``.
    - ``seed``: sim random seed. ``imgsz`` / ``conf`` / ``batch`` / ``class_map``: yolo inference
      (``conf`` keeps nearly everything: the filter's ``tau_conf`` decides later).
    - ``paint_fp``: sim only: share of all detections that are false positives on lane paint (a real
      detector's mistake on lane lines), in [0, 0.5].
    """

    backend: Backend = "auto"
    weights: str | None = None
    file: str | None = None
    seed: int = 0
    # 800, not the 640 it was trained at: on the car-mounted Czech val the shipped detector scores mAP50 0.282 at
    # 800 vs 0.242 at 640 (thin cracks gain from the upscaled 600 px photos; a dashcam frame is downscaled less),
    # China's motorbike photos 0.806 vs 0.879, 138 vs 115 ms a frame (bench/results/detector.json)
    imgsz: int = 800
    conf: float = 0.01
    batch: int = 8
    class_map: str | None = None
    paint_fp: float = 0.0

    def __post_init__(self) -> None:
        self.validate()

    def validate(self) -> None:
        """Raise PavemapError naming the first bad field."""
        if self.backend not in BACKENDS:
            raise PavemapError(f"detector.backend must be one of {', '.join(BACKENDS)}, got {self.backend!r}")
        if self.imgsz < 32:
            raise PavemapError(f"detector.imgsz must be >= 32, got {self.imgsz}")
        if self.batch < 1:
            raise PavemapError(f"detector.batch must be >= 1, got {self.batch}")
        if not (math.isfinite(self.conf) and 0.0 <= self.conf < 1.0):
            raise PavemapError(f"detector.conf must be in [0, 1), got {self.conf}")
        if self.seed < 0:
            raise PavemapError(f"detector.seed must be >= 0, got {self.seed}")
        ok = isinstance(self.paint_fp, int | float) and math.isfinite(self.paint_fp)
        if not (ok and 0.0 <= self.paint_fp <= 0.5):
            raise PavemapError(f"detector.paint_fp must be in [0, 0.5], got {self.paint_fp!r}")


@dataclass
class FilterConfig:
    """The road filter of stage 2 (SPEC §2).

    - ``tau_conf``: keep ``conf >= tau_conf``; none = the detector's operating point (shipped 0.20, sim 0.05 / 0.10):
      :func:`pavemap.detect.backends.resolve_tau_conf` gives the measured one of weights the registry knows, else
      the paper's for the preset (:data:`PAPER_TAU_CONF`), which the simulated detector is calibrated to.
    - ``tau_road``: keep detections whose box road share ``R_road > tau_road`` (paper 0.5).
    - ``mask``: road mask for ``R_road``: ``frame`` (the view's semantic PNG), ``mesh`` (the road
      mesh's semantics seen through the box), ``both`` (both ratios must pass).
    - ``mesh_mask_grid``: rays per box side when the mesh mask is sampled from the mesh surface.
    - ``mesh_mask_scale``: render scale when the mesh mask comes from a rendered view instead.
    - ``tau_paint``: drop an on-road detection that lane paint spans (min of the shares of its rows and
      columns holding paint ≥ ``tau_paint``; paint from the semantics' paint class, else the image;
      :mod:`pavemap.detect.paint`). 1 turns the rule off.
    """

    tau_conf: float | None = None
    tau_road: float = 0.5
    mask: MaskSource = "frame"
    mesh_mask_scale: float = 0.25
    mesh_mask_grid: int = 8
    tau_paint: float = 0.7

    def __post_init__(self) -> None:
        self.validate()

    def validate(self) -> None:
        """Raise PavemapError naming the first bad field."""
        if not (isinstance(self.tau_paint, int | float) and math.isfinite(self.tau_paint)
                and 0.0 < self.tau_paint <= 1.0):
            raise PavemapError(f"filter.tau_paint must be in (0, 1], got {self.tau_paint!r}")
        if self.mask not in MASKS:
            raise PavemapError(f"filter.mask must be one of {', '.join(MASKS)}, got {self.mask!r}")
        if self.tau_conf is not None and not (isinstance(self.tau_conf, int | float) and 0.0 <= self.tau_conf <= 1.0):
            raise PavemapError(f"filter.tau_conf must be in [0, 1] or none (the detector's operating point), "
                               f"got {self.tau_conf}")
        if not 0.0 <= self.tau_road < 1.0:
            raise PavemapError(f"filter.tau_road must be in [0, 1), got {self.tau_road}")
        if not (math.isfinite(self.mesh_mask_scale) and 0.0 < self.mesh_mask_scale <= 1.0):
            raise PavemapError(f"filter.mesh_mask_scale must be in (0, 1], got {self.mesh_mask_scale}")
        if self.mesh_mask_grid < 1:
            raise PavemapError(f"filter.mesh_mask_grid must be >= 1, got {self.mesh_mask_grid}")

    @classmethod
    def preset(cls, name: str) -> FilterConfig:
        """The filter of a preset: τ_road 0.5 for both (paper Table 2); τ_conf is left to the detector (None),
        whose default for the paper's detector is the preset's :data:`PAPER_TAU_CONF`."""
        if name not in PAPER_TAU_CONF:
            raise PavemapError(f"unknown filter preset {name!r}; choose nuscenes or kitti")
        return cls()


__all__ = ["BACKENDS", "MASKS", "PAPER_TAU_CONF", "Backend", "DetectorConfig", "FilterConfig", "MaskSource"]
