"""Write a synthetic world as a sequence folder (SPEC §6) with its ground truth.

Layout written (on top of SPEC §6):
  truth/defects.geojson      ground-truth defect polygons (world metres) with id, cls, name, sizes;
                             potholes also depth_m (nominal), depth_max_m, depth_mean_m, volume_l
  truth/height.npy/.json     the exact surface raster (0.05 m; sample (j, i) at x0 + i*res, y0 + j*res)
  truth/world.json           parameters and seed (same params + seed → byte-identical folder)
  truth/instances/<camera>/<frame>.png   uint16 code map per view (see world.json instance_encoding)
"""

from __future__ import annotations

import json
import os
import shutil
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from PIL import Image

from pavemap.device import resolve_device
from pavemap.errors import PavemapError
from pavemap.geometry.camera import pixel_grid, pixel_rays
from pavemap.geometry.grid import GridSpec
from pavemap.io.atomic import atomic_write_json
from pavemap.io.owned import check_replaceable, mark_written
from pavemap.io.sequence import read_sequence, save_depth, write_sequence
from pavemap.io.truth import read_truth_grid, write_truth_height
from pavemap.synth.defects import blob_polygon, blob_q_np
from pavemap.synth.params import CLASSES, torch_threads
from pavemap.synth.render import render_view
from pavemap.synth.rig import DEFAULT_SCALE, RIGS, camera_pose, rig_cameras, vehicle_poses
from pavemap.synth.scene import World
from pavemap.synth.world import make_world, pothole_dent, pothole_window
from pavemap.types import DEFECT_CODES, DEFECT_NAMES, Frame, GeoOrigin, SemanticClass, Sequence, View

DEPTH_MODES = ("none", "sparse", "dense")
GEO_ORIGINS = {
    "nuscenes-like": GeoOrigin(lat=42.3505, lon=-71.0531, alt=5.0, heading_deg=72.0),  # Boston seaport
    "kitti-like": GeoOrigin(lat=49.0111, lon=8.4167, alt=115.0, heading_deg=105.0),  # Karlsruhe
}
PNG_LEVEL = 1  # zlib level: noisy renders barely compress better at higher levels, and cost 2-3x the time


@dataclass
class TruthDefect:
    """A ground-truth defect: shapely polygon in world metres with its class and properties."""

    id: int
    cls: int
    polygon: object  # shapely Polygon
    properties: dict = field(default_factory=dict)

    @property
    def code(self) -> str:
        return DEFECT_CODES[self.cls]


def synthesize(out: Path, preset: str = "nuscenes-like", seed: int = 0, frames: int | None = None,
               scale: float | None = None, depth: str = "sparse", overwrite: bool = False,
               device: str = "cpu", threads: int | None = 1, progress: bool = True,
               **overrides: object) -> Sequence:
    """Generate a synthetic drive into the sequence folder ``out`` and return its Sequence.

    ``overrides`` set any ``WorldParams`` field (e.g. ``defect_density=40``, ``shadows=False``).
    The folder is built under a temporary name and renamed at the end, so a half-written
    sequence never looks complete. ``threads`` (default 1) sets torch's CPU threads while
    rendering: on a shared 2-core machine one thread measured several times faster than two.
    """
    from tqdm import tqdm

    out = Path(out)
    if depth not in DEPTH_MODES:
        raise PavemapError(f"depth must be one of {DEPTH_MODES}, got {depth!r}")
    if preset not in RIGS:
        raise PavemapError(f"unknown preset {preset!r}; choose one of {sorted(RIGS)}")
    scale = DEFAULT_SCALE[preset] if scale is None else float(scale)
    if not 0.02 <= scale <= 4.0:
        raise PavemapError(f"scale must be in 0.02..4, got {scale}")
    check_replaceable(out, "sequence", overwrite)  # only a folder pavemap wrote, and all of it pavemap's
    dev = resolve_device(device)
    tmp = out.parent / f".{out.name}.partial-{os.getpid()}"
    try:
        with torch_threads(threads):
            if tmp.exists():
                shutil.rmtree(tmp)
            tmp.mkdir(parents=True)
            world = make_world(preset, seed, threads=None, frames=frames, **overrides)
            seq = _render_sequence(world, tmp, scale, depth, dev, progress, tqdm)
            _write_truth(world, tmp)
            write_sequence(seq, tmp)
            read_sequence(tmp)  # validate what we wrote before it can look complete
            mark_written(tmp, "sequence", {"source": f"pavemap synth {preset} seed {seed}"})
        if out.exists():
            shutil.rmtree(out) if out.is_dir() else out.unlink()
        out.parent.mkdir(parents=True, exist_ok=True)
        os.replace(tmp, out)
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)
    seq.root = out
    return seq


def exposure_drift(steps: np.ndarray, tau_frames: float = 100.0) -> np.ndarray:
    """(F,) exposure gains from per-frame log-gain steps (F,): an auto-exposure's lag, which drifts but keeps
    coming back (a mean-reverting AR(1) walk with a correlation time of ``tau_frames``; log-gain sd 0.28 for
    steps of 0.04), centred on a mean log-gain of 0.

    Why not a plain random walk: its spread grows with the drive, 0.04 x sqrt(4,541) = 2.7 in log-gain along
    KITTI-00, so frames came out 15x over- or under-exposed (road white, held-out PSNR 9 dB)."""
    from scipy.signal import lfilter

    steps = np.asarray(steps, dtype=np.float64)
    if not len(steps):
        return steps
    log_gain = lfilter([1.0], [1.0, -float(np.exp(-1.0 / tau_frames))], steps)  # x_k = rho x_(k-1) + e_k
    return np.exp(log_gain - log_gain.mean())


def _render_sequence(world: World, root: Path, scale: float, depth: str, dev, progress: bool, tqdm) -> Sequence:
    p = world.params
    cams = rig_cameras(p.preset, scale)
    mounts = RIGS[p.preset]
    rng = np.random.default_rng([p.seed, 5])
    poses, ts = vehicle_poses(world, rng)
    # exposure drifts smoothly from frame to frame; each camera has its own white balance
    exposure = exposure_drift(rng.normal(0, 0.04, len(ts)))
    wb = {m.name: tuple(float(v) for v in 1 + rng.normal(0, 0.015, 3)) for m in mounts}
    frames: list[Frame] = []
    rings: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    bar = tqdm(total=len(ts) * len(mounts), desc=f"synth {p.preset}", unit="view", disable=not progress)
    for fi in range(len(ts)):
        views: dict[str, View] = {}
        for ci, m in enumerate(mounts):
            cam = cams[m.name]
            T = camera_pose(poses[fi], m)
            r = render_view(world, cam, T, exposure=float(exposure[fi]), white_balance=wb[m.name],
                            noise_seed=fi * 16 + ci, device=dev, threads=None)
            name = f"{fi:06d}.png"
            img = f"images/{m.name}/{name}"
            sem = f"semantics/{m.name}/{name}"
            _save_png(root / img, r.rgb)
            _save_png(root / sem, r.label)
            _save_png(root / "truth" / "instances" / m.name / name, r.code)
            dpath = None
            if depth != "none":
                dpath = f"depth/{m.name}/{name}"
                if depth == "dense":
                    dm = r.depth
                else:
                    if m.name not in rings:
                        R_veh_cam = poses[fi][:3, :3].T @ T[:3, :3]
                        rings[m.name] = lidar_rings(cam.K, R_veh_cam, cam.height, cam.width)
                    dm = lidar_mask(r.depth, rings[m.name], p.seed, fi, ci)
                (root / dpath).parent.mkdir(parents=True, exist_ok=True)
                save_depth(root / dpath, dm)
            views[m.name] = View(m.name, img, T, sem, dpath)
            bar.update(1)
        frames.append(Frame(fi, float(round(ts[fi], 6)), views))
    bar.close()
    classes = [SemanticClass(c["id"], c["name"], c["road"], c["movable"], c["sky"]) for c in CLASSES]
    return Sequence(f"synth-{p.preset}-seed{p.seed}", classes, cams, frames, GEO_ORIGINS[p.preset], root)


def _save_png(path: Path, a: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    im = Image.fromarray(a)  # uint16 becomes mode I;16
    im.save(path, compress_level=PNG_LEVEL)


def lidar_rings(K: np.ndarray, R_veh_cam: np.ndarray, H: int, W: int, beams: int = 32) -> tuple[np.ndarray, np.ndarray]:
    """Pixels on 32 LiDAR beam rings (−30.7°…+10.7° elevation in the vehicle frame) and ray lengths.

    Constant per camera mount, so computed once: ((H, W) bool, (H, W) float32 |K⁻¹[u, v, 1]|).
    """
    T_veh_cam = np.eye(4)
    T_veh_cam[:3, :3] = R_veh_cam
    _, d = pixel_rays(K, T_veh_cam, pixel_grid(W, H, dtype=torch.float64))
    rays = d.numpy().reshape(H, W, 3)
    elev = np.degrees(np.arctan2(rays[..., 2], np.hypot(rays[..., 0], rays[..., 1])))
    ring = np.linspace(-30.67, 10.67, beams)
    k = np.clip(np.round((elev - ring[0]) / (ring[1] - ring[0])), 0, beams - 1).astype(int)
    on_ring = np.abs(elev - ring[k]) < 0.5 * np.degrees(1.0 / K[1, 1])
    return on_ring, np.linalg.norm(rays, axis=-1).astype(np.float32)


def lidar_mask(depth: np.ndarray, rings: tuple[np.ndarray, np.ndarray], seed: int, frame: int, cam: int,
               max_range: float = 70.0) -> np.ndarray:
    """LiDAR-like sparse depth (~3–5 % of pixels): (H, W) float32 metres in, 0 where no return."""
    on_ring, ray_len = rings
    H, W = depth.shape
    rng = np.random.default_rng([seed, frame, cam, 7])
    keep = on_ring & (depth > 0) & (depth * ray_len < max_range)
    # one ring is one pixel row whatever the resolution, so small images get a larger share:
    # thin out to ~4 % (and drop 10 % of returns anyway, like a real scanner)
    frac = max(float(keep.mean()), 1e-9)
    keep &= rng.random((H, W)) < 0.9 * min(1.0, 0.04 / frac)
    return np.where(keep, depth, 0.0).astype(np.float32)


# ---------------------------------------------------------------------------- truth


def defect_polygon(d: dict):
    """Shapely polygon of a defect dict (crack: polyline buffered by its band; blob: its boundary)."""
    from shapely.geometry import LineString, Polygon

    if d["kind"] == "line":
        return LineString(np.asarray(d["line"])).buffer(d["band_m"], quad_segs=4)
    return Polygon(blob_polygon(d))


def _write_truth(world: World, root: Path) -> None:
    truth = root / "truth"
    truth.mkdir(parents=True, exist_ok=True)
    polys, props_all = [], []
    for d in world.defects:
        poly = defect_polygon(d)
        code = DEFECT_CODES[d["cls"]]
        # the defect schema of every pavemap GeoJSON (pavemap.export.geojson.PROPERTY_SCHEMA)
        props = {"id": d["id"], "cls": d["cls"], "code": code, "name": DEFECT_NAMES[code],
                 "area_m2": round(float(poly.area), 4), "length_m": round(float(d["length_m"]), 4),
                 "x_m": round(float(d["centre"][0]), 4), "y_m": round(float(d["centre"][1]), 4)}
        if d["kind"] == "line":
            props["width_m"] = round(float(d["width_m"]), 4)
            props["band_m"] = d["band_m"]
        if d["cls"] == 3:
            props["depth_m"] = round(float(d["depth_m"]), 4)
            props.update(pothole_truth(world, d))
        if d.get("grown"):
            props["grown_in_survey"] = int(world.params.survey)
        if d.get("new_in_survey"):
            props["new_in_survey"] = int(d["new_in_survey"])
        polys.append(poly)
        props_all.append(props)
    from pavemap.export.geojson import features_to_geojson

    # local world metres (stated in the file): the truth is compared in the world frame
    atomic_write_json(truth / "defects.geojson", features_to_geojson(polys, props_all), indent=None)
    write_truth_height(root, world.height, world.height_grid, extra={
        "sample_at": "height[j, i] is the surface at (x0 + i*res, y0 + j*res)", "interpolation": "bilinear"})
    atomic_write_json(truth / "world.json", world.to_json())


def pothole_truth(world: World, d: dict) -> dict:
    """Depth and volume of a pothole as carved into the exact surface (the 0.05 m height raster).

    Integrates :func:`pavemap.synth.world.pothole_dent` on the raster's own samples, so the volume is
    the integral of ``truth/height.npy``'s dent: ``depth_max_m`` the deepest sample (rough bottom
    included, so up to 6 mm beyond the nominal ``depth_m``), ``depth_mean_m`` the mean over the
    samples inside the outline, ``volume_l`` litres (sample dent x cell area).
    """
    g = world.height_grid
    rows, cols = pothole_window(d, g)
    X, Y = np.meshgrid(g.xs()[cols], g.ys()[rows])
    dent = pothole_dent(d, X, Y).astype(np.float32).astype(np.float64)  # as carved (float32 raster)
    inside = blob_q_np(d, X, Y) < 1
    if not inside.any():
        return {"depth_max_m": 0.0, "depth_mean_m": 0.0, "volume_l": 0.0}
    return {"depth_max_m": round(float(dent.max()), 5), "depth_mean_m": round(float(dent[inside].mean()), 5),
            "volume_l": round(float(dent.sum() * g.res * g.res * 1000.0), 4)}


def load_truth_defects(seq_root: str | os.PathLike) -> list[TruthDefect]:
    """Read ``truth/defects.geojson`` of a synthetic sequence as shapely polygons with id and cls."""
    from pavemap.export.geojson import read_geojson
    from pavemap.io.sequence import SequenceError

    path = Path(seq_root) / "truth" / "defects.geojson"
    if not path.is_file():
        raise SequenceError(path, "not found; ground truth exists only for synthetic sequences (pavemap synth)")
    try:
        layer = read_geojson(path)
        out = []
        for i, (geom, pr) in enumerate(zip(layer.geometries, layer.properties, strict=True)):
            cls = int(pr["cls"])
            if not 0 <= cls < len(DEFECT_CODES):
                raise ValueError(f"feature {i}: cls {cls} outside 0..3")
            out.append(TruthDefect(int(pr["id"]), cls, geom, dict(pr)))
    except (PavemapError, KeyError, TypeError, ValueError) as e:
        raise SequenceError(path, f"not a defects FeatureCollection ({e})") from None
    return out


def load_truth_height(seq_root: str | os.PathLike) -> tuple[np.ndarray, GridSpec]:
    """(ny, nx) float32 true surface and its grid, from ``truth/height.npy`` / ``height.json``."""
    return read_truth_grid(seq_root)


def load_world(seq_root: str | os.PathLike) -> World:
    """Rebuild the World of a synthetic sequence from ``truth/world.json`` (deterministic)."""
    from pavemap.io.sequence import SequenceError

    path = Path(seq_root) / "truth" / "world.json"
    try:
        params = json.loads(path.read_text(encoding="utf-8"))["params"]
    except (OSError, ValueError, KeyError) as e:
        raise SequenceError(path, f"cannot read world parameters ({e})") from None
    preset = params.pop("preset")
    seed = params.pop("seed")
    return make_world(preset, seed, **params)


__all__ = [
    "TruthDefect",
    "defect_polygon",
    "lidar_mask",
    "lidar_rings",
    "load_truth_defects",
    "load_truth_height",
    "load_world",
    "pothole_truth",
    "synthesize",
]
