"""nuScenes → sequence folder, through the official nuscenes-devkit (optional extra ``[nuscenes]``).

One scene, its keyframes (2 Hz) or, with ``sweeps``, every camera image (12 Hz).
Per view: ``T_world_cam = T_global_ego(ego_pose) · T_ego_cam(calibrated_sensor)``; nuScenes
camera axes are OpenCV's and its global frame is metric with z up, so no axis change is
needed. The world origin is moved to the first ego position of the scene (keeps
coordinates small for float32 stages); ``geo_origin`` then gives its WGS84 position,
from the devkit's reference coordinates of each map (the south-west corner of the map;
global +x east, +y north, as the devkit's own ``export_poses`` assumes).
"""

from __future__ import annotations

import contextlib
import io
import os
from pathlib import Path

import numpy as np

from pavemap.errors import PavemapError
from pavemap.geometry.valid import check_intrinsics
from pavemap.io.folder import DEFAULT_CLASSES, copy_image, image_size, make_pose, quat_to_rot
from pavemap.io.sequence import SequenceError, write_sequence
from pavemap.types import Camera, Frame, GeoOrigin, SemanticClass, Sequence, View

CAMERAS = ("CAM_FRONT", "CAM_FRONT_RIGHT", "CAM_BACK_RIGHT", "CAM_BACK", "CAM_BACK_LEFT", "CAM_FRONT_LEFT")

#: WGS84 of each map's global origin (nuscenes-devkit, scripts/export_poses.py).
REFERENCE_COORDINATES = {
    "boston-seaport": (42.336849169438615, -71.05785369873047),
    "singapore-onenorth": (1.2882100868743724, 103.78475189208984),
    "singapore-hollandvillage": (1.2993652317780957, 103.78217697143555),
    "singapore-queenstown": (1.2782562240223188, 103.76741409301758),
}


def _pose(record: dict) -> np.ndarray:
    """nuScenes translation + rotation (w, x, y, z) → (4, 4) float64."""
    return make_pose(quat_to_rot(np.asarray(record["rotation"], dtype=np.float64))[0],
                     np.asarray(record["translation"], dtype=np.float64))


def geo_origin_for(location: str, origin_xy: np.ndarray) -> GeoOrigin | None:
    """WGS84 position of global point ``origin_xy`` (metres east, north of the map reference)."""
    ref = REFERENCE_COORDINATES.get(location)
    if ref is None:
        return None
    from pyproj import Geod

    x, y = float(origin_xy[0]), float(origin_xy[1])
    az = float(np.degrees(np.arctan2(x, y)))  # compass bearing of the offset
    lon, lat, _ = Geod(ellps="WGS84").fwd(ref[1], ref[0], az, float(np.hypot(x, y)))
    return GeoOrigin(lat=float(lat), lon=float(lon), alt=0.0, heading_deg=90.0)


def load_nuscenes(dataroot: str | os.PathLike, version: str = "v1.0-mini"):
    """Open a nuScenes release with the devkit; a wrong root or version → clear error with the choices."""
    try:
        from nuscenes.nuscenes import NuScenes
    except ImportError as e:
        raise PavemapError(f"nuScenes import needs the devkit: pip install 'pavemap[nuscenes]' ({e})") from None
    dataroot = Path(dataroot)
    if not dataroot.is_dir():
        raise SequenceError(dataroot, "nuScenes dataroot not found")
    if not (dataroot / version).is_dir():
        have = sorted(p.name for p in dataroot.iterdir() if p.is_dir() and p.name.startswith("v1.0"))
        raise SequenceError(dataroot / version, f"version {version!r} not found; available: {have or 'none'}")
    try:
        with contextlib.redirect_stdout(io.StringIO()):  # the devkit prints table counts
            return NuScenes(version=version, dataroot=str(dataroot), verbose=False)
    except (OSError, KeyError, AssertionError, ValueError) as e:
        raise SequenceError(dataroot / version, f"cannot load nuScenes tables ({type(e).__name__}: {e})") from None


def _camera_chain(nusc, first_sd_token: str, last_sd_token: str) -> list[dict]:
    """All sample_data of one camera from its first to its last keyframe of the scene, sweeps between."""
    out = []
    tok = first_sd_token
    while tok:
        sd = nusc.get("sample_data", tok)
        out.append(sd)
        if tok == last_sd_token:
            break
        tok = sd["next"]
    return out


def _chosen_cameras(first_sample: dict, cameras: list[str] | tuple[str, ...] | None, scene: str) -> list[str]:
    """``cameras`` (default: every camera of the scene, the six of CAMERAS first, in their order); one the
    scene's first sample lacks is refused."""
    available = [c for c in CAMERAS if c in first_sample["data"]] + sorted(
        c for c in first_sample["data"] if c.startswith("CAM") and c not in CAMERAS
    )
    chosen = list(cameras) if cameras else available
    bad = [c for c in chosen if c not in available]
    if bad:
        raise PavemapError(f"camera(s) {bad} not in scene {scene}; available: {', '.join(available)}")
    return chosen


def _camera(nusc, name: str, sd: dict, calib_file: Path) -> Camera:  # noqa: ANN001
    """Camera ``name`` of the sample_data record ``sd`` (size) and its calibrated sensor (K, checked)."""
    cs = nusc.get("calibrated_sensor", sd["calibrated_sensor_token"])
    K = np.asarray(cs["camera_intrinsic"], dtype=np.float64)
    why = check_intrinsics(K)
    if why:
        raise SequenceError(calib_file, f"{name} ({cs['token']}): {why}")
    return Camera(name, int(sd["width"]), int(sd["height"]), K)


def import_nuscenes(
    dataroot: str | os.PathLike,
    scene: str,
    out: str | os.PathLike,
    version: str = "v1.0-mini",
    cameras: list[str] | tuple[str, ...] | None = None,
    sweeps: bool = False,
    max_frames: int | None = None,
    classes: list[SemanticClass] | None = None,
) -> Sequence:
    """Import one nuScenes scene (by name, e.g. ``scene-0064``) into a sequence folder at ``out``."""
    from tqdm import tqdm

    dataroot, out = Path(dataroot), Path(out)
    nusc = load_nuscenes(dataroot, version)
    names = [s["name"] for s in nusc.scene]
    if scene not in names:
        raise PavemapError(f"scene {scene!r} not in {dataroot / version}; valid scenes: {', '.join(sorted(names))}")
    sc = nusc.scene[names.index(scene)]
    location = nusc.get("log", sc["log_token"])["location"]

    samples = []
    tok = sc["first_sample_token"]
    while tok:
        s = nusc.get("sample", tok)
        samples.append(s)
        tok = s["next"]
    chosen = _chosen_cameras(samples[0], cameras, scene)

    # per camera, the ordered list of sample_data records to import
    if sweeps:
        chains = {c: _camera_chain(nusc, samples[0]["data"][c], samples[-1]["data"][c]) for c in chosen}
        n = min(len(v) for v in chains.values())
    else:
        chains = {c: [nusc.get("sample_data", s["data"][c]) for s in samples] for c in chosen}
        n = len(samples)
    if max_frames is not None:
        n = min(n, max_frames)

    cams = {c: _camera(nusc, c, chains[c][0], dataroot / version / "calibrated_sensor.json") for c in chosen}
    first_ego = _pose(nusc.get("ego_pose", chains[chosen[0]][0]["ego_pose_token"]))
    origin = first_ego[:3, 3].copy()
    frames: list[Frame] = []
    with tqdm(total=n * len(chosen), desc=f"nuscenes {scene}", unit="img", disable=None) as bar:
        for k in range(n):
            views: dict[str, View] = {}
            stamps = []
            for c in chosen:
                sd = chains[c][k]
                T = _pose(nusc.get("ego_pose", sd["ego_pose_token"])) @ _pose(
                    nusc.get("calibrated_sensor", sd["calibrated_sensor_token"])
                )
                T[:3, 3] -= origin
                src = dataroot / sd["filename"]
                w, h = image_size(src)
                if (w, h) != (cams[c].width, cams[c].height):
                    raise SequenceError(src, f"image is {w}x{h}, sample_data says {cams[c].width}x{cams[c].height}")
                rel = f"images/{c}/{k:06d}{src.suffix.lower()}"
                copy_image(src, out / rel)
                views[c] = View(c, rel, T)
                stamps.append(sd["timestamp"] * 1e-6)
                bar.update(1)
            frames.append(Frame(k, float(np.mean(stamps)), views))
    t0 = frames[0].timestamp
    for f in frames:
        f.timestamp -= t0
    seq = Sequence(scene, list(classes or DEFAULT_CLASSES), cams, frames,
                   geo_origin=geo_origin_for(location, origin[:2]))
    write_sequence(seq, out)
    return seq
