"""Parameters and fixed tables of the synthetic world: classes, object kinds, resolutions, presets.

Same :class:`WorldParams` + seed → the same world, byte for byte (``truth/world.json`` stores them).
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from dataclasses import dataclass, fields

import numpy as np
import torch

from pavemap.errors import PavemapError
from pavemap.palette import PAVEMAP_CLASSES

# ---------------------------------------------------------------------------- class table

#: Semantic classes of the synthetic world (ids fixed here only; stages read flags from sequence.json).
CLASSES: list[dict] = [
    {"id": c.id, "name": c.name, "road": c.road, "movable": c.movable, "sky": c.sky} for c in PAVEMAP_CLASSES
]
ROAD, MARKING, CURB, SIDEWALK, TERRAIN, VEHICLE, BUILDING, SKY = range(8)

#: Object kinds of the clutter (box/sphere primitives); used as FP sources by the simulated detector.
OBJECT_KINDS = ("car_body", "car_cabin", "car_wheels", "building", "wall", "pole", "trunk", "canopy", "bush")
OBJECT_SOURCE = {
    "car_body": "vehicle", "car_cabin": "vehicle", "car_wheels": "vehicle", "building": "building",
    "wall": "building", "pole": "pole", "trunk": "vegetation", "canopy": "vegetation", "bush": "vegetation",
}

HEIGHT_RES = 0.05  # m, resolution of the exact surface raster and of truth/height.npy
ST_RES = 0.5  # m, resolution of the (s, t) lookup raster
SHADOW_RES = 0.1  # m
CENTRELINE_DS = 0.25  # m
DECOY_ID_OFFSET = 10000  # instance codes >= this are off-road crack-like streaks (decoys), not defects


#: torch CPU threads for world building and rendering. On the shared 2-core machine one thread
#: measured several times faster than two (OpenMP threads spin against other processes).
DEFAULT_THREADS = 1


@contextlib.contextmanager
def torch_threads(n: int | None) -> Iterator[None]:
    """Temporarily set torch's intra-op CPU threads (None: leave as is)."""
    old = torch.get_num_threads()
    change = bool(n) and n != old
    if change:
        torch.set_num_threads(int(n))  # type: ignore[arg-type]
    try:
        yield
    finally:
        if change:
            torch.set_num_threads(old)


# ---------------------------------------------------------------------------- parameters


@dataclass
class WorldParams:
    """Everything that defines a world; saved to ``truth/world.json``. Same params + seed → same world."""

    preset: str = "nuscenes-like"
    seed: int = 0
    # ego drive (defines the road length)
    frames: int = 40
    hz: float = 2.0
    speed: float = 8.0  # m/s
    road_before: float = 30.0  # m of road behind the first frame
    road_after: float = 80.0  # m of road ahead of the last frame
    ego_lane: int = 0  # 0 = rightmost lane
    # road cross-section
    lanes: int = 2
    lane_width: float = 3.5
    crown: float = 0.05  # m, centre above the edges
    max_superelevation: float = 0.02  # lateral slope in turns
    grade: float = 0.015  # longitudinal slope
    vert_amp: float = 0.3  # m, vertical curve amplitude
    vert_wavelength: float = 400.0  # m
    curb_height: float = 0.12
    curb_width: float = 0.25
    sidewalk_left: float = 2.5
    sidewalk_right: float = 2.0
    # horizontal alignment
    min_radius: float = 70.0
    max_radius: float = 220.0
    straight_fraction: float = 0.45
    # defects
    defect_density: float = 25.0  # per 100 m of road
    class_mix: tuple[float, float, float, float] = (0.35, 0.25, 0.2, 0.2)  # D00, D10, D20, D40
    defect_size: float = 1.0  # scale on all defect sizes
    # no defects before this chainage (m along the drive from the first frame; None: defects everywhere),
    # e.g. half the drive length for a clean first half and a damaged second half (segment benchmark)
    defect_free_until_m: float | None = None
    # repeat surveys of the same road: survey k > 0 keeps every defect of survey 0, enlarges a
    # share of them and adds new ones (for testing change detection between surveys)
    survey: int = 0
    survey_new_per_100m: float = 6.0
    survey_grow_share: float = 0.4
    survey_growth: float = 1.6  # linear scale on grown defects (area grows by its square)
    # clutter and lighting
    clutter: float = 1.0  # scale on clutter density (0 = none)
    decoy_density: float = 8.0  # off-road crack-like streaks per 100 m
    shadows: bool = True
    sun_azimuth_deg: float = 215.0
    sun_elevation_deg: float = 42.0
    # A given trajectory (pavemap.synth.trajectory): the camera centres (F, 3), z up, origin at the first; the
    # road follows it and ``frames`` is its length (None: a generated road at ``speed``)
    path: list | None = None

    def validate(self) -> None:
        if self.preset not in PRESETS:
            raise PavemapError(f"unknown preset {self.preset!r}; choose one of {sorted(PRESETS)}")
        if not 2 <= self.lanes <= 4:
            raise PavemapError(f"lanes must be 2..4, got {self.lanes}")
        width = self.lanes * self.lane_width
        if not 7.0 <= width <= 12.0 + 1e-9:
            raise PavemapError(f"road width lanes*lane_width must be 7..12 m, got {width:.2f}")
        if self.frames < 1:
            raise PavemapError(f"frames must be >= 1, got {self.frames}")
        if self.defect_density < 0 or self.clutter < 0 or self.decoy_density < 0:
            raise PavemapError("defect_density, clutter and decoy_density must be >= 0")
        mix = np.asarray(self.class_mix, dtype=float)
        if mix.shape != (4,) or np.any(mix < 0) or mix.sum() <= 0:
            raise PavemapError(f"class_mix needs 4 non-negative weights, got {self.class_mix}")
        if not 0 <= self.ego_lane < self.lanes:
            raise PavemapError(f"ego_lane must be 0..{self.lanes - 1}")
        if self.path is not None:
            a = np.asarray(self.path, dtype=float)
            if a.ndim != 2 or a.shape[1] != 3 or len(a) < 2 or not np.all(np.isfinite(a)):
                raise PavemapError("path must be at least 2 finite (x, y, z) camera centres")
            if len(a) != self.frames:
                raise PavemapError(f"frames ({self.frames}) must equal the trajectory's poses ({len(a)})")
        if self.defect_free_until_m is not None and not np.isfinite(self.defect_free_until_m):
            raise PavemapError(f"defect_free_until_m must be a finite number or None, got {self.defect_free_until_m}")

    @property
    def width(self) -> float:
        return self.lanes * self.lane_width

    @property
    def road_length(self) -> float:
        if self.path is not None:
            xy = np.asarray(self.path, dtype=float)[:, :2]
            return self.road_before + float(np.linalg.norm(np.diff(xy, axis=0), axis=1).sum()) + self.road_after
        ego = self.speed * max(self.frames - 1, 0) / self.hz
        return self.road_before + ego + self.road_after


PRESETS: dict[str, dict] = {
    "nuscenes-like": dict(frames=40, hz=2.0, speed=8.0, road_before=35.0, road_after=70.0, lanes=2,
                          lane_width=3.6),
    "kitti-like": dict(frames=80, hz=10.0, speed=10.0, road_before=15.0, road_after=70.0, lanes=2,
                       lane_width=3.5, min_radius=90.0),
}


def world_params(preset: str, seed: int = 0, **overrides: object) -> WorldParams:
    """Preset defaults with ``overrides`` applied; unknown keys raise PavemapError."""
    if preset not in PRESETS:
        raise PavemapError(f"unknown preset {preset!r}; choose one of {sorted(PRESETS)}")
    names = {f.name for f in fields(WorldParams)}
    bad = sorted(k for k in overrides if k not in names)
    if bad:
        raise PavemapError(f"unknown world parameter(s) {bad}; known: {sorted(names)}")
    kw = dict(PRESETS[preset])
    kw.update({k: v for k, v in overrides.items() if v is not None})
    if "class_mix" in kw:
        kw["class_mix"] = tuple(float(v) for v in kw["class_mix"])  # type: ignore[union-attr]
    p = WorldParams(preset=preset, seed=int(seed), **kw)
    p.validate()
    return p
