"""The synthetic road world: a curved road with exact height field, materials, defects and clutter.

Geometry lives in two coordinate systems:

* world ``(x, y, z)`` metres, z up (SPEC §0);
* road ``(s, t)``: arc length along the centreline and signed lateral offset (t > 0 left of the
  direction of travel). ``st_of_xy`` maps world to road coordinates through a coarse 0.5 m raster
  of the exact nearest-point projection, bilinearly interpolated (error < 1 mm inside the
  corridor because s and t are smooth there).

The surface *is* the float32 raster ``World.height`` at 0.05 m (exported as ``truth/height.npy``),
read with bilinear interpolation: the renderer, the clutter placement and the truth export all use
the same surface, so "the height field is exact" holds by construction. It is computed from an
analytic profile (crown, superelevation, grade, curb, sidewalk, verge) plus potholes.
"""

from __future__ import annotations

import contextlib
import math
from collections.abc import Iterator
from dataclasses import asdict, dataclass, field, fields

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

    @property
    def width(self) -> float:
        return self.lanes * self.lane_width

    @property
    def road_length(self) -> float:
        ego = self.speed * max(self.frames - 1, 0) / self.hz
        return self.road_before + ego + self.road_after


PRESETS: dict[str, dict] = {
    "nuscenes-like": dict(frames=40, hz=2.0, speed=8.0, road_before=35.0, road_after=70.0, lanes=2,
                          lane_width=3.6),
    "kitti-like": dict(frames=80, hz=10.0, speed=10.0, road_before=15.0, road_after=70.0, lanes=2,
                       lane_width=3.5, min_radius=90.0),
}


# ---------------------------------------------------------------------------- world


@dataclass
class Grid:
    """A raster ``(ny, nx)``: cell (row j, col i) centre at ``(x_min + i*res, y_min + j*res)``."""

    x_min: float
    y_min: float
    res: float
    ny: int
    nx: int

    def to_json(self) -> dict:
        return {"x_min": self.x_min, "y_min": self.y_min, "resolution": self.res, "shape": [self.ny, self.nx]}


@dataclass
class World:
    """A generated world. Arrays are numpy; ``tensors(device)`` gives the torch view the renderer uses."""

    params: WorldParams
    # centreline samples (Nc,) every CENTRELINE_DS metres
    cl_s: np.ndarray
    cl_xy: np.ndarray  # (Nc, 2)
    cl_theta: np.ndarray  # (Nc,)
    cl_kappa: np.ndarray  # (Nc,)
    st_grid: Grid
    st: np.ndarray  # (2, ny, nx) float32: s and t of each coarse cell
    height_grid: Grid
    height: np.ndarray  # (ny, nx) float32, the exact surface
    shadow_grid: Grid
    shadow: np.ndarray  # (ny, nx) float32 in [0, 1], 1 = fully shadowed
    defects: list[dict]  # one dict per defect (see _make_defects), id = index
    decoys: list[dict]  # off-road streaks, same layout as cracks
    boxes: np.ndarray  # (Nb, 12) float32: cx, cy, cz, hx, hy, hz, yaw, r, g, b, label, kind
    spheres: np.ndarray  # (Ns, 8) float32: cx, cy, cz, radius, r, g, b, label ; kind via sphere_kind
    sphere_kind: np.ndarray  # (Ns,) int: index into OBJECT_KINDS
    noise_tiles: np.ndarray  # (T, 128, 128) float32 value-noise tiles
    sun: np.ndarray  # (3,) unit vector towards the sun
    _cache: dict = field(default_factory=dict, repr=False)

    # -- cheap numpy queries (used for placement, poses and tests) ---------------------------
    def height_at(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """(N,) float64 exact surface height at world (x, y) (bilinear on the 0.05 m raster)."""
        return bilinear_np(self.height, self.height_grid, np.asarray(x, float), np.asarray(y, float))

    def st_at(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Road coordinates (s, t) of world points, each (N,) float64."""
        x = np.asarray(x, float)
        y = np.asarray(y, float)
        return (bilinear_np(self.st[0], self.st_grid, x, y), bilinear_np(self.st[1], self.st_grid, x, y))

    def label_at(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """(N,) uint8 ground material class (road, lane_marking, curb, sidewalk, terrain) at world (x, y)."""
        s, t = self.st_at(x, y)
        st = torch.as_tensor(np.stack([s, t]), dtype=torch.float32)
        cov, _ = markings(self.params, st[0], st[1], torch.full_like(st[0], 1e-3))
        lab = ground_label(self.params, st[0], st[1], cov)
        return lab.numpy().astype(np.uint8)

    def xy_of_st(self, s: np.ndarray, t: np.ndarray) -> np.ndarray:
        """(N, 2) world points at road coordinates (s, t) (linear interpolation of the centreline)."""
        s = np.asarray(s, float)
        t = np.asarray(t, float)
        x = np.interp(s, self.cl_s, self.cl_xy[:, 0])
        y = np.interp(s, self.cl_s, self.cl_xy[:, 1])
        th = np.interp(s, self.cl_s, np.unwrap(self.cl_theta))
        return np.stack([x - t * np.sin(th), y + t * np.cos(th)], axis=-1)

    def heading_at(self, s: np.ndarray) -> np.ndarray:
        return np.interp(np.asarray(s, float), self.cl_s, self.cl_theta)

    def tensors(self, device: str | torch.device = "cpu") -> dict:
        """Torch tensors of everything the renderer reads, cached per device."""
        key = str(torch.device(device))
        if key not in self._cache:
            self._cache[key] = _to_tensors(self, torch.device(device))
        return self._cache[key]

    def to_json(self) -> dict:
        p = asdict(self.params)
        p["class_mix"] = list(self.params.class_mix)
        return {
            "generator": "pavemap.synth",
            "params": p,
            "height_grid": self.height_grid.to_json(),
            "classes": CLASSES,
            "defects": len(self.defects),
            "decoys": len(self.decoys),
            "objects": {"boxes": int(len(self.boxes)), "spheres": int(len(self.spheres))},
            "sun": self.sun.tolist(),
            "instance_encoding": {
                "file": "truth/instances/<camera>/<frame>.png (uint16)",
                "low_14_bits": f"0 none; 1..{DECOY_ID_OFFSET - 1} defect id + 1; "
                f">= {DECOY_ID_OFFSET}: off-road streak (decoy) index + {DECOY_ID_OFFSET}",
                "bit_14": "ground pixel in cast shadow",
            },
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


def make_world(preset: str = "nuscenes-like", seed: int = 0, threads: int | None = DEFAULT_THREADS,
               **overrides: object) -> World:
    """Build the world of ``preset`` with ``seed``; ``overrides`` set any WorldParams field."""
    p = world_params(preset, seed, **overrides)
    with torch_threads(threads):
        return _build_world(p)


def _build_world(p: WorldParams) -> World:
    rng = _rngs(p.seed)
    cl_s, cl_xy, cl_theta, cl_kappa = _centreline(p, rng["road"])
    tiles = rng["tex"].random((6, 128, 128)).astype(np.float32)
    st_grid, st = _st_raster(cl_s, cl_xy, cl_theta, margin=45.0)
    hgrid = _grid_around(cl_xy, margin=28.0, res=HEIGHT_RES)
    w = World(
        params=p, cl_s=cl_s, cl_xy=cl_xy, cl_theta=cl_theta, cl_kappa=cl_kappa, st_grid=st_grid, st=st,
        height_grid=hgrid, height=np.zeros((hgrid.ny, hgrid.nx), np.float32),
        shadow_grid=_grid_around(cl_xy, margin=28.0, res=SHADOW_RES), shadow=np.zeros((1, 1), np.float32),
        defects=[], decoys=[], boxes=np.zeros((0, 12), np.float32), spheres=np.zeros((0, 8), np.float32),
        sphere_kind=np.zeros(0, np.int64), noise_tiles=tiles, sun=_sun(p),
    )
    w.defects = _make_defects(w, rng["defects"])
    w.height = _height_raster(w)
    w._cache.clear()
    w.decoys = _make_decoys(w, rng["decoys"])
    w.boxes, w.spheres, w.sphere_kind = _make_clutter(w, rng["clutter"])
    w.shadow = _shadow_raster(w) if p.shadows else np.zeros((1, 1), np.float32)
    w._cache.clear()
    return w


def _rngs(seed: int) -> dict[str, np.random.Generator]:
    # Independent streams: changing the defect density does not move the road or the cars.
    names = ("road", "tex", "defects", "decoys", "clutter", "rig")
    return {n: np.random.default_rng([int(seed), i]) for i, n in enumerate(names)}


def _sun(p: WorldParams) -> np.ndarray:
    az = math.radians(p.sun_azimuth_deg)
    el = math.radians(p.sun_elevation_deg)
    return np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])


# ---------------------------------------------------------------------------- centreline


def _centreline(p: WorldParams, rng: np.random.Generator):
    """Straights and arcs with curvature ramps; origin at the first ego position, heading +x there."""
    L = p.road_length + 10.0
    ds = CENTRELINE_DS
    n = int(math.ceil(L / ds)) + 1
    s = np.arange(n) * ds - 5.0  # a little before s = 0 so lookups near the ends stay inside
    kappa = np.zeros(n)
    pos = -5.0
    sign = rng.choice([-1.0, 1.0])
    while pos < s[-1]:
        if rng.random() < p.straight_fraction:
            seg = rng.uniform(25.0, 70.0)
        else:
            radius = rng.uniform(p.min_radius, p.max_radius)
            angle = math.radians(rng.uniform(15.0, 60.0))
            seg = radius * angle
            m = (s >= pos) & (s < pos + seg)
            kappa[m] = sign / radius
            sign = -sign if rng.random() < 0.7 else sign
        pos += seg
    # curvature ramps (clothoid-like transitions) by smoothing over ~20 m
    k = int(20.0 / ds)
    ker = np.hanning(2 * k + 1)
    ker /= ker.sum()
    kappa = np.convolve(np.pad(kappa, k, mode="edge"), ker, mode="valid")
    theta = np.concatenate([[0.0], np.cumsum(0.5 * (kappa[1:] + kappa[:-1]) * ds)])
    xy = np.zeros((n, 2))
    xy[1:, 0] = np.cumsum(0.5 * (np.cos(theta[1:]) + np.cos(theta[:-1])) * ds)
    xy[1:, 1] = np.cumsum(0.5 * (np.sin(theta[1:]) + np.sin(theta[:-1])) * ds)
    # put the ego start (s = road_before) at the origin with heading 0
    s0 = p.road_before
    th0 = np.interp(s0, s, theta)
    c0 = np.array([np.interp(s0, s, xy[:, 0]), np.interp(s0, s, xy[:, 1])])
    rot = np.array([[math.cos(-th0), -math.sin(-th0)], [math.sin(-th0), math.cos(-th0)]])
    xy = (xy - c0) @ rot.T
    theta = theta - th0
    return s, xy, theta, kappa


def _grid_around(xy: np.ndarray, margin: float, res: float) -> Grid:
    lo = np.floor((xy.min(0) - margin) / res) * res
    hi = np.ceil((xy.max(0) + margin) / res) * res
    nx = int(round((hi[0] - lo[0]) / res)) + 1
    ny = int(round((hi[1] - lo[1]) / res)) + 1
    return Grid(float(lo[0]), float(lo[1]), res, ny, nx)


def _st_raster(s: np.ndarray, xy: np.ndarray, theta: np.ndarray, margin: float) -> tuple[Grid, np.ndarray]:
    """Exact nearest-point (s, t) on a coarse raster: KD-tree to the nearest sample, then tangent projection."""
    from scipy.spatial import cKDTree

    g = _grid_around(xy, margin, ST_RES)
    gx = g.x_min + np.arange(g.nx) * g.res
    gy = g.y_min + np.arange(g.ny) * g.res
    X, Y = np.meshgrid(gx, gy)
    P = np.stack([X.ravel(), Y.ravel()], axis=1)
    _, k = cKDTree(xy).query(P)
    d = P - xy[k]
    T = np.stack([np.cos(theta[k]), np.sin(theta[k])], axis=1)
    N = np.stack([-T[:, 1], T[:, 0]], axis=1)
    ss = s[k] + (d * T).sum(1)
    tt = (d * N).sum(1)
    return g, np.stack([ss.reshape(g.ny, g.nx), tt.reshape(g.ny, g.nx)]).astype(np.float32)


# ---------------------------------------------------------------------------- rasters / lookups


def bilinear_np(a: np.ndarray, g: Grid, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Bilinear lookup in raster ``a`` (ny, nx) at world points; clamps to the edge."""
    fx = np.clip((x - g.x_min) / g.res, 0, g.nx - 1.000001)
    fy = np.clip((y - g.y_min) / g.res, 0, g.ny - 1.000001)
    i = np.floor(fx).astype(np.int64)
    j = np.floor(fy).astype(np.int64)
    ax = fx - i
    ay = fy - j
    v00, v01 = a[j, i].astype(np.float64), a[j, i + 1].astype(np.float64)
    v10, v11 = a[j + 1, i].astype(np.float64), a[j + 1, i + 1].astype(np.float64)
    return (1 - ay) * ((1 - ax) * v00 + ax * v01) + ay * ((1 - ax) * v10 + ax * v11)


def bilinear_t(a: torch.Tensor, g: tuple[float, float, float, int, int], x: torch.Tensor, y: torch.Tensor,
               grad: bool = False):
    """Bilinear lookup in a flattened raster ``a`` ((ny*nx,) or (C, ny*nx)); optional x/y gradient.

    Indices are int32 + index_select: several times faster than int64 advanced indexing on CPU.
    """
    x_min, y_min, res, ny, nx = g
    fx = ((x - x_min) / res).clamp(0, nx - 1.01)
    fy = ((y - y_min) / res).clamp(0, ny - 1.01)
    i = fx.floor()
    j = fy.floor()
    ax = fx - i
    ay = fy - j
    idx = j.int() * nx + i.int()
    dim = a.dim() - 1
    v00 = a.index_select(dim, idx)
    v01 = a.index_select(dim, idx + 1)
    v10 = a.index_select(dim, idx + nx)
    v11 = a.index_select(dim, idx + (nx + 1))
    top = v00 + ax * (v01 - v00)
    bot = v10 + ax * (v11 - v10)
    val = top + ay * (bot - top)
    if not grad:
        return val
    dx = ((1 - ay) * (v01 - v00) + ay * (v11 - v10)) / res
    dy = (bot - top) / res
    return val, dx, dy


def value_noise(tile: torch.Tensor, x: torch.Tensor, y: torch.Tensor, scale: float) -> torch.Tensor:
    """Smooth value noise in [0, 1] with feature size ``scale`` metres from a periodic (128, 128) tile."""
    u = x / scale
    v = y / scale
    i = u.floor()
    j = v.floor()
    fu = u - i
    fv = v - j
    fu = fu * fu * (3 - 2 * fu)
    fv = fv * fv * (3 - 2 * fv)
    i0 = i.int() & 127
    j0 = (j.int() & 127) * 128
    i1 = (i0 + 1) & 127
    j1 = (j0 + 128) & 16383
    flat = tile.reshape(-1)
    a = flat.index_select(0, j0 + i0)
    b = flat.index_select(0, j0 + i1)
    c = flat.index_select(0, j1 + i0)
    d = flat.index_select(0, j1 + i1)
    top = a + fu * (b - a)
    bot = c + fu * (d - c)
    return top + fv * (bot - top)


def _to_tensors(w: World, dev: torch.device) -> dict:
    f32 = torch.float32
    p = w.params

    def ten(a, dtype=f32):
        return torch.as_tensor(np.ascontiguousarray(a), dtype=dtype, device=dev)

    hg, sg, shg = w.height_grid, w.st_grid, w.shadow_grid
    out = {
        "device": dev,
        "params": p,
        "height": ten(w.height).reshape(-1),
        "hgrid": (hg.x_min, hg.y_min, hg.res, hg.ny, hg.nx),
        "st": ten(w.st).reshape(2, -1),
        "stgrid": (sg.x_min, sg.y_min, sg.res, sg.ny, sg.nx),
        "shadow": ten(w.shadow).reshape(-1),
        "shgrid": (shg.x_min, shg.y_min, shg.res, shg.ny, shg.nx) if w.shadow.size > 1 else None,
        "tiles": ten(w.noise_tiles),
        "kappa": ten(w.cl_kappa),
        "cl_s0": float(w.cl_s[0]),
        "sun": ten(w.sun),
        "boxes": ten(w.boxes),
        "spheres": ten(w.spheres),
        "sphere_kind": ten(w.sphere_kind, torch.long),
    }
    out["items"] = _item_tables(w, dev)
    return out


# ---------------------------------------------------------------------------- ground profile


def ground_label(p: WorldParams, s: torch.Tensor, t: torch.Tensor, marking: torch.Tensor) -> torch.Tensor:
    """(N,) long ground class from road coordinates; ``marking`` (N,) paint coverage in [0, 1]."""
    a = t.abs()
    w2 = p.width / 2
    sw = torch.where(t > 0, torch.full_like(t, p.sidewalk_left), torch.full_like(t, p.sidewalk_right))
    lab = torch.full_like(s, TERRAIN, dtype=torch.long)
    lab = torch.where(a < w2 + p.curb_width + sw, torch.full_like(lab, SIDEWALK), lab)
    lab = torch.where(a < w2 + p.curb_width, torch.full_like(lab, CURB), lab)
    lab = torch.where(a < w2, torch.full_like(lab, ROAD), lab)
    return torch.where((lab == ROAD) & (marking > 0.5), torch.full_like(lab, MARKING), lab)


WHITE_PAINT = (0.92, 0.92, 0.9)
YELLOW_PAINT = (0.92, 0.74, 0.22)


def marking_lines(p: WorldParams) -> list[tuple[float, float, bool, tuple[float, float, float]]]:
    """Painted lines as (t centre, width, dashed, colour): edge lines, lane dividers, double yellow centre."""
    w2 = p.width / 2
    out = [(-(w2 - 0.3), 0.15, False, WHITE_PAINT), (w2 - 0.3, 0.15, False, WHITE_PAINT)]
    for k in range(1, p.lanes):
        tk = -w2 + k * p.lane_width
        if p.lanes % 2 == 0 and k == p.lanes // 2:
            out += [(tk - 0.1, 0.1, False, YELLOW_PAINT), (tk + 0.1, 0.1, False, YELLOW_PAINT)]
        else:
            out.append((tk, 0.12, True, WHITE_PAINT))
    return out


def markings(p: WorldParams, s: torch.Tensor, t: torch.Tensor, fp: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Paint coverage (N,) in [0, 1] and paint colour (N, 3), anti-aliased over the pixel footprint ``fp`` (m)."""
    cov = torch.zeros_like(s)
    col = torch.zeros(s.shape + (3,), dtype=s.dtype, device=s.device)
    fpc = fp.clamp(min=1e-3)
    for i, (tc, wid, dashed, colour) in enumerate(marking_lines(p)):
        c = ((wid / 2 - (t - tc).abs()) / fpc + 0.5).clamp(0, 1) * (wid / fpc).clamp(max=1)
        if dashed:
            m = torch.remainder(s + 2.1 * i, 9.0)
            d = torch.where(m < 3.0, torch.minimum(m, 3.0 - m), -torch.minimum(m - 3.0, 9.0 - m))
            c = c * (d / fpc + 0.5).clamp(0, 1)
        upd = c > cov
        cov = torch.where(upd, c, cov)
        col = torch.where(upd[..., None], torch.tensor(colour, dtype=s.dtype, device=s.device), col)
    return cov, col


def profile_height(p: WorldParams, tiles: torch.Tensor, kappa: torch.Tensor, cl_s0: float,
                   x: torch.Tensor, y: torch.Tensor, s: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
    """Analytic height without potholes: grade + vertical curve + cross-section + small unevenness."""
    a = t.abs()
    w2 = p.width / 2
    k = ((s - cl_s0) / CENTRELINE_DS).round().clamp(0, kappa.numel() - 1).int()
    # superelevation: the road banks into turns (inner side lower), capped
    e = (kappa.index_select(0, k) * 3.0).clamp(-p.max_superelevation, p.max_superelevation)
    z = p.grade * s + p.vert_amp * torch.sin(2 * math.pi * s / p.vert_wavelength)
    road = p.crown * (1 - (a / w2) ** 2) + e * t
    edge = e * t.sign() * w2
    sw = torch.where(t > 0, torch.full_like(t, p.sidewalk_left), torch.full_like(t, p.sidewalk_right))
    d = a - w2
    curb = (d / HEIGHT_RES).clamp(0, 1) * p.curb_height
    walk = 0.02 * (d - p.curb_width).clamp(min=0).minimum(sw)
    dv = (d - p.curb_width - sw).clamp(min=0)
    verge = (0.06 * dv).clamp(max=0.35) + 0.06 * (value_noise(tiles[4], x, y, 3.0) - 0.5) * (dv / 2).clamp(max=1)
    off = edge + curb + walk + verge
    uneven = 0.012 * (value_noise(tiles[5], x, y, 4.0) - 0.5) + 0.004 * (value_noise(tiles[5], x, y, 0.7) - 0.5)
    return z + torch.where(a <= w2, road, off) + uneven


def st_lookup(tw: dict, x: torch.Tensor, y: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    st = bilinear_t(tw["st"], tw["stgrid"], x, y)
    return st[0], st[1]


def _height_raster(w: World) -> np.ndarray:
    """The exact surface on the 0.05 m grid: profile everywhere, potholes carved in their footprints."""
    tw = _to_tensors(w, torch.device("cpu"))
    g = w.height_grid
    out = np.empty((g.ny, g.nx), np.float32)
    xs = torch.as_tensor(g.x_min + np.arange(g.nx) * g.res, dtype=torch.float32)
    rows = max(1, 262_144 // g.nx)  # cache-sized chunks: large temporaries are slow
    for j0 in range(0, g.ny, rows):
        j1 = min(g.ny, j0 + rows)
        ys = torch.as_tensor(g.y_min + np.arange(j0, j1) * g.res, dtype=torch.float32)
        Y, X = torch.meshgrid(ys, xs, indexing="ij")
        X = X.reshape(-1)
        Y = Y.reshape(-1)
        s, t = st_lookup(tw, X, Y)
        z = profile_height(w.params, tw["tiles"], tw["kappa"], tw["cl_s0"], X, Y, s, t)
        out[j0:j1] = z.reshape(j1 - j0, g.nx).numpy()
    for d in w.defects:
        if d["cls"] != 3:
            continue
        i0 = max(0, int((d["aabb"][0] - g.x_min) / g.res))
        i1 = min(g.nx, int((d["aabb"][2] - g.x_min) / g.res) + 2)
        j0 = max(0, int((d["aabb"][1] - g.y_min) / g.res))
        j1 = min(g.ny, int((d["aabb"][3] - g.y_min) / g.res) + 2)
        X, Y = np.meshgrid(g.x_min + np.arange(i0, i1) * g.res, g.y_min + np.arange(j0, j1) * g.res)
        q = blob_q_np(d, X, Y)
        # flat-ish bottom with walls over the outer 30 % of the radius, plus a rough bottom
        depth = d["depth_m"] * np.clip((1 - q) / 0.3, 0, 1) ** 1.5
        rough = 0.006 * np.sin(X * 37.0 + d["phase"][0]) * np.sin(Y * 41.0 + d["phase"][1])
        out[j0:j1, i0:i1] -= (depth + np.where(q < 1, rough, 0.0)).astype(np.float32)
    return out


# ---------------------------------------------------------------------------- defects


def blob_q_np(d: dict, X: np.ndarray, Y: np.ndarray) -> np.ndarray:
    """Normalised radius of points in a blob defect: < 1 inside, 1 on the boundary."""
    c, r = math.cos(d["rot"]), math.sin(d["rot"])
    dx = X - d["centre"][0]
    dy = Y - d["centre"][1]
    u = (c * dx + r * dy) / d["ax"]
    v = (-r * dx + c * dy) / d["ay"]
    rho = np.hypot(u, v)
    phi = np.arctan2(v, u)
    h = d["harm"]
    return rho / (1 + h[0] * np.cos(2 * phi + d["phase"][0]) + h[1] * np.cos(3 * phi + d["phase"][1]))


def blob_polygon(d: dict, n: int = 48) -> np.ndarray:
    """(n, 2) boundary of a blob defect (the q = 1 curve)."""
    phi = np.linspace(0, 2 * np.pi, n, endpoint=False)
    h = d["harm"]
    r = 1 + h[0] * np.cos(2 * phi + d["phase"][0]) + h[1] * np.cos(3 * phi + d["phase"][1])
    u = r * np.cos(phi) * d["ax"]
    v = r * np.sin(phi) * d["ay"]
    c, s = math.cos(d["rot"]), math.sin(d["rot"])
    return np.stack([d["centre"][0] + c * u - s * v, d["centre"][1] + s * u + c * v], axis=1)


def _crack_polyline(w: World, rng: np.random.Generator, s0: float, t0: float, length: float,
                    along: bool, n: int = 12) -> np.ndarray:
    """(n, 2) world vertices of a wandering crack in road coordinates (along s or across t)."""
    u = np.linspace(0, length, n)
    wander = np.cumsum(rng.normal(0, 0.035, n)) + 0.05 * np.sin(u * rng.uniform(2, 5) + rng.uniform(0, 6))
    wander -= wander[0]
    if along:
        s, t = s0 + u, t0 + wander
    else:
        ang = math.radians(rng.uniform(-15, 15))
        s = s0 + u * math.sin(ang) + wander
        t = t0 + u * math.cos(ang)
    return w.xy_of_st(s, t)


def _make_defects(w: World, rng: np.random.Generator) -> list[dict]:
    p = w.params
    s_lo, s_hi = 3.0, p.road_length - 3.0
    n = int(rng.poisson(p.defect_density * (s_hi - s_lo) / 100.0))
    mix = np.asarray(p.class_mix, float)
    mix = mix / mix.sum()
    placed: list[tuple[float, float, float, float]] = []  # (s0, s1, t0, t1) boxes, to avoid overlaps
    out: list[dict] = []
    for _ in range(n):
        cls = int(rng.choice(4, p=mix))
        _place_defect(w, rng, cls, placed, out, s_lo, s_hi)
    if p.survey > 0:
        _later_survey(w, out, placed, s_lo, s_hi)
    return out


def _later_survey(w: World, out: list[dict], placed: list, s_lo: float, s_hi: float) -> None:
    """Survey k of the same road: grow a share of the existing defects, add new ones (own random stream)."""
    p = w.params
    rng = np.random.default_rng([int(p.seed), 1000 + int(p.survey)])
    g = p.survey_growth
    for d in out:
        if rng.random() >= p.survey_grow_share:
            continue
        d["grown"] = True
        if d["kind"] == "blob":
            d["ax"] *= g
            d["ay"] *= g
            if "depth_m" in d:
                d["depth_m"] = min(d["depth_m"] * 1.3, 0.12)
            poly = blob_polygon(d)
            d["aabb"] = [*(poly.min(0) - 0.02), *(poly.max(0) + 0.02)]
            d["length_m"] = float(np.ptp(poly @ [math.cos(d["rot"]), math.sin(d["rot"])]))
        else:  # a crack grows longer about its middle
            line = np.asarray(d["line"], dtype=float)
            mid = line.mean(0)
            line = mid + (line - mid) * g
            d["line"] = line.tolist() if isinstance(d["line"], list) else line
            d["length_m"] = float(np.linalg.norm(np.diff(line, axis=0), axis=1).sum())
            d["aabb"] = [*(line.min(0) - d["band_m"]), *(line.max(0) + d["band_m"])]
    mix = np.asarray(p.class_mix, float)
    mix = mix / mix.sum()
    n_new = int(rng.poisson(p.survey_new_per_100m * (s_hi - s_lo) / 100.0))
    for _ in range(n_new):
        before = len(out)
        _place_defect(w, rng, int(rng.choice(4, p=mix)), placed, out, s_lo, s_hi)
        if len(out) > before:
            out[-1]["new_in_survey"] = int(p.survey)


def _place_defect(w: World, rng: np.random.Generator, cls: int, placed: list, out: list[dict],
                  s_lo: float, s_hi: float) -> None:
    p = w.params
    w2 = p.width / 2
    sz = p.defect_size
    for _try in range(30):
        sc = rng.uniform(s_lo, s_hi)
        if cls == 0:
            length = rng.uniform(1.0, 4.0) * sz
            ext_s, ext_t = length, 0.3
        elif cls == 1:
            length = min(rng.uniform(1.0, 3.5) * sz, p.width - 1.0)
            ext_s, ext_t = 0.8, length
        elif cls == 2:
            ax, ay = rng.uniform(0.5, 1.25) * sz, rng.uniform(0.4, 1.0) * sz
            ext_s, ext_t = 2.6 * ax, 2.6 * ay
        else:
            rad = rng.uniform(0.15, 0.75) * sz
            ax, ay = rad * rng.uniform(1.0, 1.3), rad
            ext_s, ext_t = 2.6 * ax, 2.6 * ax
        half_t = w2 - 0.35 - ext_t / 2
        if half_t <= 0:
            continue
        tc = rng.uniform(-half_t, half_t)
        box = (sc - ext_s / 2 - 0.3, sc + ext_s / 2 + 0.3, tc - ext_t / 2 - 0.3, tc + ext_t / 2 + 0.3)
        if any(b[0] < box[1] and box[0] < b[1] and b[2] < box[3] and box[2] < b[3] for b in placed):
            continue
        placed.append(box)
        did = len(out)
        if cls in (0, 1):
            if cls == 0:
                line = _crack_polyline(w, rng, sc - length / 2, tc, length, along=True)
            else:
                line = _crack_polyline(w, rng, sc, tc - length / 2, length, along=False)
            d = {"id": did, "cls": cls, "kind": "line", "line": line, "width_m": rng.uniform(0.012, 0.03),
                 "band_m": 0.10, "length_m": float(np.linalg.norm(np.diff(line, axis=0), axis=1).sum()),
                 "darkness": rng.uniform(0.55, 0.8)}
            d["centre"] = line[len(line) // 2].tolist()
            d["aabb"] = [*(line.min(0) - d["band_m"]), *(line.max(0) + d["band_m"])]
        else:
            centre = w.xy_of_st(np.array([sc]), np.array([tc]))[0]
            rot = float(w.heading_at(np.array([sc]))[0]) + rng.uniform(-0.35, 0.35)
            d = {"id": did, "cls": cls, "kind": "blob", "centre": centre.tolist(), "ax": ax, "ay": ay,
                 "rot": rot, "harm": [rng.uniform(0, 0.12), rng.uniform(0, 0.08)],
                 "phase": [rng.uniform(0, 6.283), rng.uniform(0, 6.283)],
                 "darkness": rng.uniform(0.5, 0.8)}
            if cls == 2:
                d["cell_m"] = rng.uniform(0.14, 0.28)
                d["width_m"] = rng.uniform(0.01, 0.022)
            else:
                d["depth_m"] = rng.uniform(0.03, 0.10)
            poly = blob_polygon(d)
            d["aabb"] = [*(poly.min(0) - 0.02), *(poly.max(0) + 0.02)]
            d["length_m"] = float(np.ptp(poly @ [math.cos(rot), math.sin(rot)]))
        d["s_range"] = [box[0], box[1]]
        out.append(d)
        break


def _make_decoys(w: World, rng: np.random.Generator) -> list[dict]:
    """Crack-like dark streaks off the road (sidewalk, curb, verge): classic detector false positives."""
    p = w.params
    w2 = p.width / 2
    n = int(rng.poisson(p.decoy_density * p.road_length / 100.0))
    out = []
    for i in range(n):
        side = rng.choice([-1.0, 1.0])
        sw = p.sidewalk_left if side > 0 else p.sidewalk_right
        t0 = side * (w2 + p.curb_width + rng.uniform(0.3, sw + 3.0))
        s0 = rng.uniform(2.0, p.road_length - 6.0)
        length = rng.uniform(0.8, 3.0)
        line = _crack_polyline(w, rng, s0, t0, length, along=rng.random() < 0.6)
        d = {"id": i, "cls": -1, "kind": "line", "line": line, "width_m": rng.uniform(0.015, 0.035), "band_m": 0.10,
             "darkness": rng.uniform(0.5, 0.75), "s_range": [s0 - 1.5, s0 + length + 1.5]}
        d["aabb"] = [*(line.min(0) - 0.1), *(line.max(0) + 0.1)]
        d["centre"] = line[len(line) // 2].tolist()
        out.append(d)
    return out


def _item_tables(w: World, dev: torch.device) -> dict:
    """Pack defects + decoys into padded tensors and an s-bin index (2 m bins → up to K items)."""
    items = list(w.defects) + list(w.decoys)
    n = len(items)
    M = 12
    lines = np.zeros((max(n, 1), M, 2), np.float32)
    prm = np.zeros((max(n, 1), 16), np.float32)
    aabb = np.zeros((max(n, 1), 4), np.float32)
    aabb[:] = [1e9, 1e9, -1e9, -1e9]
    for k, d in enumerate(items):
        aabb[k] = d["aabb"]
        decoy = k >= len(w.defects)
        code = (d["id"] + DECOY_ID_OFFSET) if decoy else (d["id"] + 1)
        cls = 4 if decoy else d["cls"]
        if d["kind"] == "line":
            ln = np.asarray(d["line"], np.float32)
            lines[k, : len(ln)] = ln
            lines[k, len(ln):] = ln[-1]
            prm[k, :5] = [cls, code, d["width_m"], d["band_m"], d["darkness"]]
        else:
            prm[k, :16] = [cls, code, d.get("width_m", 0.0), 0.0, d["darkness"], d["centre"][0], d["centre"][1],
                           d["ax"], d["ay"], d["rot"], d["harm"][0], d["harm"][1], d["phase"][0], d["phase"][1],
                           d.get("cell_m", 0.2), float(d["id"] % 997)]
    bin_m = 2.0
    s_min = float(w.cl_s[0]) - 60.0
    nb = int((float(w.cl_s[-1]) + 60.0 - s_min) / bin_m) + 1
    lists: list[list[int]] = [[] for _ in range(nb)]
    for k, d in enumerate(items):
        b0 = int((d["s_range"][0] - 1.0 - s_min) / bin_m)
        b1 = int((d["s_range"][1] + 1.0 - s_min) / bin_m)
        for b in range(max(0, b0), min(nb - 1, b1) + 1):
            lists[b].append(k)
    K = max(1, max((len(x) for x in lists), default=1))
    table = np.full((nb, K), -1, np.int64)
    for b, x in enumerate(lists):
        table[b, : len(x)] = x
    return {
        "n": n, "lines": torch.as_tensor(lines, device=dev), "prm": torch.as_tensor(prm, device=dev),
        "aabb": torch.as_tensor(aabb, device=dev), "table": torch.as_tensor(table, device=dev),
        "bin_m": bin_m, "s_min": s_min,
    }


# ---------------------------------------------------------------------------- clutter

CAR_COLOURS = np.array([
    [0.85, 0.85, 0.86], [0.62, 0.63, 0.65], [0.12, 0.12, 0.13], [0.35, 0.36, 0.38], [0.13, 0.2, 0.38],
    [0.55, 0.1, 0.08], [0.75, 0.72, 0.65], [0.2, 0.3, 0.22], [0.9, 0.9, 0.88], [0.45, 0.47, 0.5],
])
FACADE_COLOURS = np.array([
    [0.78, 0.72, 0.6], [0.62, 0.35, 0.27], [0.7, 0.7, 0.68], [0.85, 0.83, 0.78], [0.55, 0.5, 0.45],
    [0.66, 0.6, 0.52],
])


def _make_clutter(w: World, rng: np.random.Generator):
    p = w.params
    w2 = p.width / 2
    boxes: list[list[float]] = []
    spheres: list[list[float]] = []
    skind: list[int] = []
    kind = {k: i for i, k in enumerate(OBJECT_KINDS)}
    L = p.road_length

    def place(s: float, t: float) -> tuple[float, float, float, float]:
        xy = w.xy_of_st(np.array([s]), np.array([t]))[0]
        z = float(w.height_at(xy[:1], xy[1:])[0])
        return float(xy[0]), float(xy[1]), z, float(w.heading_at(np.array([s]))[0])

    def box(s, t, length, width, z0, z1, colour, label, k, yaw_extra=0.0, base=None):
        x, y, z, yaw = place(s, t)
        if base is not None:
            z = base
        boxes.append([x, y, z + 0.5 * (z0 + z1), length / 2, width / 2, 0.5 * (z1 - z0), yaw + yaw_extra,
                      *colour, label, kind[k]])
        return z

    dens = p.clutter
    if dens <= 0:
        return np.zeros((0, 12), np.float32), np.zeros((0, 8), np.float32), np.zeros(0, np.int64)
    for side in (-1.0, 1.0):
        sw = p.sidewalk_left if side > 0 else p.sidewalk_right
        kerb_out = w2 + p.curb_width + sw  # outer edge of the sidewalk
        # parked cars: mostly at the kerb, half on the sidewalk or with 0.5 m on the road
        s = rng.uniform(0, 10)
        while s < L - 5:
            s += rng.exponential(14.0 / dens) + 5.0
            if s > L - 5:
                break
            length, width = rng.uniform(3.9, 4.9), rng.uniform(1.7, 1.95)
            height = rng.uniform(1.4, 1.75)
            r = rng.random()
            if r < 0.55:
                tc = side * (w2 - 0.5 + width / 2)  # 0.5 m of the car on the road edge
            elif r < 0.85:
                tc = side * (w2 + p.curb_width + 0.1)  # half on the kerb
            else:
                tc = side * (kerb_out + rng.uniform(1.5, 4.0))  # driveway / verge
            col = CAR_COLOURS[rng.integers(len(CAR_COLOURS))] * rng.uniform(0.9, 1.05)
            yaw_e = rng.normal(0, 0.03) + (math.pi if rng.random() < 0.5 else 0.0)
            z = box(s, tc, length, width, 0.3, 0.95, col, VEHICLE, "car_body", yaw_e)
            box(s, tc, length * 0.55, width * 0.88, 0.95, height, col, VEHICLE, "car_cabin", yaw_e, base=z)
            for ax_off in (-0.32, 0.32):
                xy = w.xy_of_st(np.array([s + ax_off * length * math.cos(yaw_e)]), np.array([tc]))[0]
                zz = float(w.height_at(xy[:1], xy[1:])[0])
                boxes.append([float(xy[0]), float(xy[1]), zz + 0.32, 0.33, width / 2 - 0.02, 0.34,
                              float(w.heading_at(np.array([s]))[0]) + yaw_e, 0.06, 0.06, 0.065, VEHICLE,
                              kind["car_wheels"]])
            s += length
        # buildings and walls beyond the sidewalk, with gaps
        s = rng.uniform(-5, 10)
        while s < L + 20:
            length = rng.uniform(8.0, 20.0)
            r = rng.random()
            if r < 0.55 * min(1.0, dens):
                depth = rng.uniform(8.0, 12.0)
                setback = rng.uniform(1.0, 6.0)
                tc = side * (kerb_out + setback + depth / 2)
                col = FACADE_COLOURS[rng.integers(len(FACADE_COLOURS))] * rng.uniform(0.9, 1.05)
                box(s + length / 2, tc, length, depth, -0.5, rng.uniform(4.0, 14.0), col, BUILDING, "building",
                    rng.normal(0, 0.02))
            elif r < 0.8:
                tc = side * (kerb_out + 0.2)
                col = np.array([0.6, 0.6, 0.58]) * rng.uniform(0.8, 1.1)
                box(s + length / 2, tc, length, 0.3, -0.3, rng.uniform(1.2, 2.4), col, BUILDING, "wall")
            s += length + rng.uniform(2.0, 12.0)
        # poles near the kerb
        s = rng.uniform(0, 20)
        while s < L:
            grey = np.array([0.45, 0.45, 0.47])
            box(s, side * (w2 + p.curb_width + 0.4), 0.2, 0.2, -0.2, rng.uniform(4.0, 8.0), grey, BUILDING, "pole")
            s += rng.uniform(20.0, 40.0) / max(dens, 0.2)
        # trees (trunk + canopy) and bushes on the outer sidewalk / verge
        s = rng.uniform(0, 10)
        while s < L:
            tc = side * (kerb_out - 0.6 + rng.uniform(0, 1.5))
            trunk_h = rng.uniform(2.0, 3.5)
            z = box(s, tc, 0.3, 0.3, -0.2, trunk_h + 0.5, np.array([0.3, 0.22, 0.15]), BUILDING, "trunk")
            x, y, _, _ = place(s, tc)
            rad = rng.uniform(1.4, 2.6)
            green = np.array([0.18, 0.34, 0.12]) * rng.uniform(0.8, 1.2)
            spheres.append([x, y, z + trunk_h + 0.6 * rad, rad, *green, BUILDING])
            skind.append(kind["canopy"])
            s += rng.uniform(12.0, 35.0) / max(dens, 0.2)
        s = rng.uniform(0, 10)
        while s < L:
            tc = side * (kerb_out + rng.uniform(0.5, 4.0))
            x, y, z, _ = place(s, tc)
            rad = rng.uniform(0.4, 1.0)
            green = np.array([0.22, 0.38, 0.14]) * rng.uniform(0.8, 1.2)
            spheres.append([x, y, z + 0.3 * rad, rad, *green, TERRAIN])
            skind.append(kind["bush"])
            s += rng.uniform(6.0, 20.0) / max(dens, 0.2)
    return (np.asarray(boxes, np.float32).reshape(-1, 12), np.asarray(spheres, np.float32).reshape(-1, 8),
            np.asarray(skind, np.int64))


def box_corners(boxes: np.ndarray) -> np.ndarray:
    """(Nb, 8, 3) world corners of oriented boxes."""
    sx = np.array([-1, 1, 1, -1, -1, 1, 1, -1], float)
    sy = np.array([-1, -1, 1, 1, -1, -1, 1, 1], float)
    sz = np.array([-1, -1, -1, -1, 1, 1, 1, 1], float)
    b = boxes.astype(np.float64)
    lx = sx[None] * b[:, 3:4]
    ly = sy[None] * b[:, 4:5]
    lz = sz[None] * b[:, 5:6]
    c, s = np.cos(b[:, 6:7]), np.sin(b[:, 6:7])
    return np.stack([b[:, 0:1] + c * lx - s * ly, b[:, 1:2] + s * lx + c * ly, b[:, 2:3] + lz], axis=-1)


def _shadow_raster(w: World) -> np.ndarray:
    """Ground shadow coverage of all objects for the sun direction (projected hulls, softened edges)."""
    from scipy.ndimage import gaussian_filter
    from scipy.spatial import ConvexHull
    from skimage.draw import polygon as fill_polygon

    g = w.shadow_grid
    sh = np.zeros((g.ny, g.nx), np.float32)
    sun = w.sun
    shapes = []
    if len(w.boxes):
        shapes += list(box_corners(w.boxes))
    for sp in w.spheres:
        ang = np.linspace(0, 2 * np.pi, 12, endpoint=False)
        ring = [sp[:3] + sp[3] * np.array([np.cos(a) * np.cos(e), np.sin(a) * np.cos(e), np.sin(e)])
                for a in ang for e in (-0.6, 0.0, 0.6)]
        shapes.append(np.array(ring))
    for pts in shapes:
        zg = float(w.height_at(pts[:, 0].mean(keepdims=True), pts[:, 1].mean(keepdims=True))[0])
        h = np.clip(pts[:, 2] - zg, 0, None)
        proj = pts[:, :2] - (h / sun[2])[:, None] * sun[None, :2]
        allp = np.concatenate([proj, pts[:, :2]])
        try:
            hull = allp[ConvexHull(allp).vertices]
        except Exception:  # degenerate (flat) object: no shadow worth drawing
            continue
        rr, cc = fill_polygon((hull[:, 1] - g.y_min) / g.res, (hull[:, 0] - g.x_min) / g.res, shape=sh.shape)
        sh[rr, cc] = 1.0
    return gaussian_filter(sh, 1.0).astype(np.float32)
