"""The ``maintenance`` section of the run config (:class:`MaintenanceConfig`), kept apart from the policy
(:mod:`pavemap.maintain.policy`), which it names."""

from __future__ import annotations

import math
from dataclasses import dataclass

from pavemap.errors import PavemapError
from pavemap.maintain.policy import load_policy


@dataclass
class MaintenanceConfig:
    """The ``maintenance`` section of the run config (:mod:`pavemap.config`).

    - ``policy``: a maintenance policy YAML (:func:`load_policy`), "" for the built-in one;
    - ``segment_m``: length of the road segments along the route (m);
    - ``lane_width_m``: lane width for the lane position; None: the policy's ``lanes.lane_width_m``;
    - ``floor_sweep``: without a depth layer, measure potholes' floors by a multi-view sweep of the images
      around each (:mod:`pavemap.maintain.floor_sweep`; full-size images); False (default): their depth is not
      measured without depth. Off by default: it measures few potholes, and plain road on the real nuScenes
      clip read as a dent (docs/history, "Pothole depth from the images").
    """

    policy: str = ""
    segment_m: float = 100.0
    lane_width_m: float | None = None
    floor_sweep: bool = False

    def validate(self) -> None:
        """Raise PavemapError naming the first bad field (a bad policy file names its entry)."""
        if not (math.isfinite(self.segment_m) and 1.0 <= self.segment_m <= 100_000.0):
            raise PavemapError(f"maintenance.segment_m must be in [1, 100000] m, got {self.segment_m}")
        if self.lane_width_m is not None and not (math.isfinite(self.lane_width_m) and 1.5 <= self.lane_width_m <= 8):
            raise PavemapError(f"maintenance.lane_width_m must be in [1.5, 8] m or none, got {self.lane_width_m}")
        load_policy(self.policy)


__all__ = ["MaintenanceConfig"]
