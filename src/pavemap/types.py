"""Plain dataclasses at the boundaries between stages.

Conventions (SPEC §0): world frame metric, right-handed, z up. Cameras use OpenCV axes
(x right, y down, z forward). ``T_world_cam`` maps camera to world: ``X_w = R X_c + t``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

DEFECT_CODES: tuple[str, ...] = ("D00", "D10", "D20", "D40")
DEFECT_NAMES: dict[str, str] = {
    "D00": "longitudinal crack",
    "D10": "transverse crack",
    "D20": "alligator crack",
    "D40": "pothole",
}
NUM_DEFECT_CLASSES = len(DEFECT_CODES)
#: What fusion leaves in ``DefectInstance.priority`` until :func:`pavemap.maintain.assess` runs.
UNASSESSED = "unassessed"
#: Class names (normalised: lower case, ``_`` for separators) that are ground surface besides the road classes.
GROUND_NAMES: frozenset[str] = frozenset({
    "curb", "kerb", "sidewalk", "terrain", "ground", "parking", "crosswalk", "road_marking", "lane_marking",
    "driveable_surface", "drivable_surface", "other_flat", "flat", "grass", "manhole", "bike_lane",
})


@dataclass(frozen=True)
class SemanticClass:
    """One entry of a sequence's own label table; stages read road/movable from here."""

    id: int
    name: str
    road: bool = False
    movable: bool = False
    sky: bool = False

    @property
    def ground(self) -> bool:
        """Ground surface (measured depth there is the surface's): road classes and the names of
        ``GROUND_NAMES``, also as the last part of a dotted name such as nuScenes' ``flat.sidewalk``."""
        def norm(s: str) -> str:
            return "".join(ch if ch.isalnum() else "_" for ch in s.lower())

        full, last = norm(self.name), norm(self.name.rsplit(".", 1)[-1])
        return self.road or full in GROUND_NAMES or last in GROUND_NAMES or full.startswith("flat_")


@dataclass
class Camera:
    """A pinhole camera. ``K`` is (3, 3) float64, pixels of the full-resolution image."""

    name: str
    width: int
    height: int
    K: np.ndarray
    ego_mask: str | None = None  # sequence-relative PNG (255 = the ego vehicle: bonnet, dashboard), or None
    # the mount's height over the road (m) the import knew: SfM scaled the path to it, or the user gave it;
    # stage 1's camera-height prior when the config does not set one. None: not known
    height_m: float | None = None

    def scaled_size(self, scale: float) -> tuple[int, int]:
        """(width, height) of this camera's image resized by ``scale``: whole pixels, rounded."""
        return max(1, round(self.width * scale)), max(1, round(self.height * scale))

    def scale_xy(self, scale: float) -> tuple[float, float]:
        """The factors (x, y) by which a resize by ``scale`` really maps the image: the rounded size over the full
        one. A resize maps the whole image onto whole pixels, so an 800 x 450 image at 0.25 becomes 200 x 112 with
        rows 112 / 450 = 0.2489 of the full ones, not 0.25 (a 0.5 px error at the bottom row, which lifted the
        multi-view consistency of the nuScenes-like drive by 1.2 cm; docs/refine.md)."""
        w, h = self.scaled_size(scale)
        return w / self.width, h / self.height

    def scaled(self, scale: float) -> Camera:
        """The same camera for an image resized by ``scale`` to :meth:`scaled_size` (pixel-centre convention;
        each axis scaled by its true factor, :meth:`scale_xy`)."""
        sx, sy = self.scale_xy(scale)
        K = self.K.astype(np.float64).copy()
        K[0, :2] *= sx  # focal length and skew
        K[1, 1] *= sy
        K[0, 2] = (K[0, 2] + 0.5) * sx - 0.5
        K[1, 2] = (K[1, 2] + 0.5) * sy - 0.5
        return Camera(self.name, *self.scaled_size(scale), K)


@dataclass
class View:
    """One camera's image in one frame. Paths are relative to the sequence folder."""

    camera: str
    image: str
    T_world_cam: np.ndarray  # (4, 4) float64, camera-to-world
    semantics: str | None = None
    depth: str | None = None


@dataclass
class Frame:
    index: int
    timestamp: float
    views: dict[str, View]


@dataclass
class GeoOrigin:
    """WGS84 position of the world origin and compass heading of world +x (degrees from north).

    ``georef``: how the origin was found when it was fitted to GPS (source file, fixes, inliers,
    residual RMS in metres, scale, warnings; :func:`pavemap.geo.georef.georeference`), else None.
    """

    lat: float
    lon: float
    alt: float = 0.0
    heading_deg: float = 90.0
    georef: dict | None = None


@dataclass
class Sequence:
    """A drive: cameras, posed frames and the label table, rooted at ``root`` on disk."""

    name: str
    classes: list[SemanticClass]
    cameras: dict[str, Camera]
    frames: list[Frame]
    geo_origin: GeoOrigin | None = None
    root: Path | None = None

    @property
    def road_class_ids(self) -> list[int]:
        return [c.id for c in self.classes if c.road]

    @property
    def movable_class_ids(self) -> list[int]:
        return [c.id for c in self.classes if c.movable]

    @property
    def sky_class_ids(self) -> list[int]:
        return [c.id for c in self.classes if c.sky]

    def class_lut(self, flag: str) -> np.ndarray:
        """(256,) bool lookup table: ``lut[label]`` is True where the class has ``flag``."""
        lut = np.zeros(256, dtype=bool)
        for c in self.classes:
            if getattr(c, flag):
                lut[c.id] = True
        return lut

    def frame_by_index(self) -> dict[int, Frame]:
        return {f.index: f for f in self.frames}

    def path(self, relative: str) -> Path:
        if self.root is None:
            raise ValueError(f"sequence {self.name!r} has no root folder")
        return self.root / relative

    def camera_centres(self) -> np.ndarray:
        """(F*V, 3) float64 camera centres of all views, frame-major."""
        return np.array([v.T_world_cam[:3, 3] for f in self.frames for v in f.views.values()]).reshape(-1, 3)

    def trajectory(self) -> np.ndarray:
        """(F, 3) float64 mean camera centre per frame (the rig's path)."""
        return np.array([np.mean([v.T_world_cam[:3, 3] for v in f.views.values()], axis=0) for f in self.frames])


@dataclass
class Detection:
    """A 2D defect box in a view. ``box`` is x1, y1, x2, y2 in full-resolution pixels."""

    frame: int
    camera: str
    box: tuple[float, float, float, float]
    cls: int
    conf: float

    @property
    def centre(self) -> tuple[float, float]:
        x1, y1, x2, y2 = self.box
        return (0.5 * (x1 + x2), 0.5 * (y1 + y2))

    @property
    def code(self) -> str:
        return DEFECT_CODES[self.cls]


@dataclass
class DefectInstance:
    """A mapped defect: a polygon in world metres with its statistics (stage 3 output)."""

    id: int
    cls: int
    polygon: object  # shapely Polygon / MultiPolygon in world x, y metres
    severity_mean: float
    severity_max: float
    confidence: float
    observations: int
    probability: float
    area_m2: float
    length_m: float
    centroid: tuple[float, float]
    priority: str  # "repair now" | "inspect" | "no action"
    extra: dict = field(default_factory=dict)

    @property
    def code(self) -> str:
        return DEFECT_CODES[self.cls]

    @property
    def name(self) -> str:
        return DEFECT_NAMES[self.code]
