"""Own drive → sequence folder: a folder of images or a video, a cameras.json and poses.

``cameras.json`` (one entry per camera; ``K`` or ``fx, fy, cx, cy``)::

    {"cameras": {"front": {"width": 1920, "height": 1080,
                           "K": [[1400, 0, 959.5], [0, 1400, 539.5], [0, 0, 1]]}}}

(the top-level ``"cameras"`` wrapper is optional). ``poses.csv`` holds one row per image, camera-to-world
``T_world_cam`` with OpenCV camera axes (x right, y down, z forward) in a metric world with z up; columns:

- ``frame`` (int, optional: default row order), ``camera`` (optional when there is one camera), ``timestamp``
  (seconds, optional), ``image`` (relative to the images folder, optional: the k-th image of that camera by name);
- the pose, either ``tx, ty, tz, qw, qx, qy, qz`` (unit quaternion, scalar first) or ``m00 … m23`` (the top
  three rows of the 4×4, row-major) or ``m00 … m33``.

Images: ``IMAGES_DIR/*.png|jpg`` for one camera, or ``IMAGES_DIR/<camera>/*`` per camera. ``poses sfm`` instead
of a CSV estimates poses from the images with pycolmap (:mod:`pavemap.sfm.pipeline`), metric by the known camera
height above the road, and leaves what it measured in ``sfm.json``.
"""

from __future__ import annotations

import csv
import os
import shutil
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from PIL import Image

from pavemap.errors import PavemapError
from pavemap.geo.attach import GeoInput, attach_geo  # upward (io -> geo), allowed: moves to commands with issue 42
from pavemap.io.atomic import atomic_path
from pavemap.io.egomask import resolve_ego_mask, store_ego_masks
from pavemap.io.sequence import SequenceError, check_intrinsics, check_pose, write_sequence
from pavemap.palette import PAVEMAP_CLASSES
from pavemap.sfm.pipeline import (  # pycolmap is imported when SfM runs
    frames_by_motion,
    report_result,
    sfm_poses_or_report,
)
from pavemap.types import Camera, Frame, SemanticClass, Sequence, View

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")

#: Label table of a sequence without semantics (same ids as the synthetic world, so a
#: segmenter or label folder mapped with the "pavemap" preset fits it).
DEFAULT_CLASSES: list[SemanticClass] = PAVEMAP_CLASSES


# ----------------------------------------------------------------------------- shared helpers


def image_size(path: str | os.PathLike) -> tuple[int, int]:
    """(width, height) of an image file; unreadable → SequenceError naming the file."""
    try:
        with Image.open(path) as im:
            return im.size
    except FileNotFoundError:
        raise SequenceError(path, "image not found") from None
    except OSError as e:
        raise SequenceError(path, f"unreadable image ({e})") from None


def copy_image(src: str | os.PathLike, dst: str | os.PathLike, to_rgb: bool = False) -> Path:
    """Copy an image into a sequence (atomically). ``to_rgb`` re-encodes grey/other modes as RGB PNG."""
    src, dst = Path(src), Path(dst)
    dst.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(dst) as tmp:
        if to_rgb or src.suffix.lower() not in IMAGE_SUFFIXES:
            try:
                with Image.open(src) as im:
                    im.convert("RGB").save(tmp, format="PNG" if dst.suffix.lower() == ".png" else "JPEG")
            except OSError as e:
                raise SequenceError(src, f"unreadable image ({e})") from None
        else:
            shutil.copyfile(src, tmp)
    return dst


def list_images(folder: Path) -> list[Path]:
    return sorted(p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES)


def make_pose(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """(4, 4) float64 from (3, 3) rotation and (3,) translation."""
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return T


def quat_to_rot(q: np.ndarray) -> np.ndarray:
    """(N, 4) quaternions w, x, y, z (normalised here) → (N, 3, 3) rotation matrices (scipy's ``Rotation``)."""
    from scipy.spatial.transform import Rotation

    q = np.asarray(q, dtype=np.float64).reshape(-1, 4)
    return Rotation.from_quat(q, scalar_first=True).as_matrix().reshape(-1, 3, 3)


#: How far a quaternion's norm may be from 1: rounding to ~5 digits in a file, not a quaternion that is not one.
QUAT_NORM_TOL = 1e-4


def _quat_pose(v: np.ndarray, path: Path, line: int) -> np.ndarray:
    """(4, 4) pose from ``tx ty tz qw qx qy qz`` (7,); a quaternion of norm other than 1 raises SequenceError."""
    if not np.isfinite(v).all():
        raise SequenceError(path, f"line {line}: the pose holds NaN or infinity ({', '.join(_QUAT)} = "
                                  f"{', '.join(f'{x:g}' for x in v)})")
    norm = float(np.linalg.norm(v[3:]))
    if abs(norm - 1.0) > QUAT_NORM_TOL:
        raise SequenceError(path, f"line {line}: quaternion qw, qx, qy, qz has norm {norm:.6g}, expected 1 (within "
                                  f"{QUAT_NORM_TOL:g}): not a rotation; write unit quaternions")
    return make_pose(quat_to_rot(v[3:])[0], v[:3])


# ----------------------------------------------------------------------------- cameras.json


def read_cameras_json(path: str | os.PathLike) -> dict[str, Camera]:
    """Parse ``cameras.json`` → {name: Camera}; problems raise SequenceError naming the file."""
    from pavemap.io.schema import load_json  # the one JSON reader of user files: duplicate keys refused

    path = Path(path)
    if not path.is_file():
        raise SequenceError(path, "cameras file not found")
    d = load_json(path)
    if isinstance(d, dict) and isinstance(d.get("cameras"), dict):
        d = d["cameras"]
    if not isinstance(d, dict) or not d:
        raise SequenceError(path, "expected {camera name: {width, height, K | fx, fy, cx, cy}}")
    cams: dict[str, Camera] = {}
    for name, c in d.items():
        try:
            w, h = int(c["width"]), int(c["height"])
            if "K" in c:
                K = np.asarray(c["K"], dtype=np.float64)
            else:
                K = np.array([[c["fx"], 0, c["cx"]], [0, c.get("fy", c["fx"]), c["cy"]], [0, 0, 1]], float)
        except (KeyError, TypeError, ValueError) as e:
            raise SequenceError(path, f"camera {name!r} needs width, height and K or fx, fy, cx, cy ({e})") from None
        why = check_intrinsics(K)
        if why:
            raise SequenceError(path, f"camera {name!r}: {why}")
        cams[str(name)] = Camera(str(name), w, h, K)
    return cams


# ----------------------------------------------------------------------------- poses.csv


@dataclass
class PoseRow:
    frame: int
    camera: str | None
    timestamp: float | None
    image: str | None
    T: np.ndarray  # (4, 4) float64 camera-to-world


_QUAT = ("tx", "ty", "tz", "qw", "qx", "qy", "qz")
_M12 = tuple(f"m{r}{c}" for r in range(3) for c in range(4))
_M16 = tuple(f"m{r}{c}" for r in range(4) for c in range(4))


def read_poses_csv(path: str | os.PathLike) -> list[PoseRow]:
    """Parse ``poses.csv`` (schema in the module docstring); bad rows raise naming file and line."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise SequenceError(path, "poses file not found") from None
    rows = list(csv.DictReader(line for line in text.splitlines() if line.strip() and not line.startswith("#")))
    if not rows:
        raise SequenceError(path, "no pose rows (expected a header line and one row per image)")
    cols = {c.strip() for c in rows[0]}
    if set(_QUAT) <= cols:
        kind = "quat"
    elif set(_M12) <= cols:
        kind = "m16" if set(_M16) <= cols else "m12"
    else:
        raise SequenceError(
            path, f"needs pose columns {', '.join(_QUAT)} or m00..m23 (row-major 3x4/4x4); got {sorted(cols)}"
        )
    out: list[PoseRow] = []
    for i, r in enumerate(rows):
        r = {k.strip(): (v.strip() if isinstance(v, str) else v) for k, v in r.items() if k is not None}
        line = i + 2
        try:
            if kind == "quat":
                T = _quat_pose(np.array([float(r[c]) for c in _QUAT]), path, line)
            else:
                names = _M16 if kind == "m16" else _M12
                m = np.array([float(r[c]) for c in names]).reshape(-1, 4)
                T = np.eye(4)
                T[: m.shape[0]] = m
            frame = int(r["frame"]) if r.get("frame") not in (None, "") else i
            ts = float(r["timestamp"]) if r.get("timestamp") not in (None, "") else None
        except SequenceError:
            raise
        except (KeyError, ValueError) as e:
            raise SequenceError(path, f"line {line}: bad value ({e})") from None
        why = check_pose(T, tol=QUAT_NORM_TOL)
        if why:
            raise SequenceError(path, f"line {line}: {why}")
        # re-orthonormalise rounding (within the tolerance) so the stored pose is a rotation to float precision
        U, _, Vt = np.linalg.svd(T[:3, :3])
        T[:3, :3] = U @ Vt
        out.append(PoseRow(frame, r.get("camera") or None, ts, r.get("image") or None, T))
    return out


# ----------------------------------------------------------------------------- folder import


def _camera_images(images_dir: Path, cameras: dict[str, Camera]) -> dict[str, list[Path]]:
    if not images_dir.is_dir():
        raise SequenceError(images_dir, "images folder not found")
    if len(cameras) == 1 and list_images(images_dir):
        return {next(iter(cameras)): list_images(images_dir)}
    found: dict[str, list[Path]] = {}
    for name in cameras:
        sub = images_dir / name
        if not sub.is_dir():
            raise SequenceError(
                images_dir, f"no images for camera {name!r}: expected image files here or a subfolder {name}/"
            )
        found[name] = list_images(sub)
        if not found[name]:
            raise SequenceError(sub, f"no .png/.jpg images for camera {name!r}")
    return found


def import_folder(
    images_dir: str | os.PathLike, cameras_json: str | os.PathLike, poses: str | os.PathLike,
    out: str | os.PathLike, name: str | None = None, camera_height: float = 1.5,
    classes: list[SemanticClass] | None = None, geo: GeoInput | None = None,
    ego_mask: str | os.PathLike | None = None, refine_intrinsics: bool = False, fps: float | None = None,
) -> Sequence:
    """Import an own drive: images + cameras.json + poses.csv (or ``poses="sfm"``) → sequence folder.

    ``ego_mask``: "auto" (found in the images; the default with ``poses="sfm"``), "none", or a mask image
    (white = ego vehicle); stored as ``masks/<camera>.png``. ``refine_intrinsics``: SfM refines the
    nominal focal length and principal point (written to the sequence's camera). ``geo``: GPS or a
    hand-given origin (:mod:`pavemap.geo.attach`); lat/lon columns of poses.csv are GPS too. ``fps``: the
    images are frames this many per second apart (frame times where poses.csv gives none; with SfM the
    path's speed changes are checked against a car's)."""
    from tqdm import tqdm

    images_dir, out = Path(images_dir), Path(out)
    cameras = read_cameras_json(cameras_json)
    per_cam = _camera_images(images_dir, cameras)
    if fps is not None and not 0 < fps < float("inf"):
        raise PavemapError(f"--fps must be a positive, finite number of frames per second, got {fps}")

    sfm_res = None
    if str(poses).lower() == "sfm":
        if len(cameras) != 1:
            raise PavemapError("--poses sfm supports one camera; give a poses.csv for a multi-camera rig")
        cam = next(iter(cameras.values()))
        ego, _ = resolve_ego_mask(ego_mask, per_cam[cam.name], cam.width, cam.height, default_auto=True)
        res = sfm_res = sfm_poses_or_report(out, per_cam[cam.name], cam, camera_height=camera_height, ego_mask=ego,
                                          refine_intrinsics=refine_intrinsics,
                                          times=None if fps is None else np.arange(len(per_cam[cam.name])) / fps)
        if refine_intrinsics and res.K is not None:
            cam.K = res.K
        egos = {cam.name: ego}
        # frames SfM could not register are left out (logged by sfm_poses); image names kept explicit
        rows = [
            PoseRow(i, cam.name, None, str(per_cam[cam.name][i].relative_to(images_dir)), res.T_world_cam[i])
            for i in np.nonzero(res.registered)[0]
        ]
    else:
        rows = read_poses_csv(poses)
        egos = {c.name: resolve_ego_mask(ego_mask, per_cam[c.name], c.width, c.height, default_auto=False)[0]
                for c in cameras.values()} if ego_mask is not None else {}

    poses_file = Path(str(poses))
    by_cam: dict[str, list[PoseRow]] = {c: [] for c in cameras}
    for r in rows:
        cam = r.camera or (next(iter(cameras)) if len(cameras) == 1 else None)
        if cam is None:
            raise SequenceError(poses_file, "several cameras: every row needs a 'camera' column value")
        if cam not in cameras:
            raise SequenceError(poses_file, f"unknown camera {cam!r}; cameras.json has {sorted(cameras)}")
        by_cam[cam].append(r)

    frames: dict[int, Frame] = {}
    jobs: list[tuple[Path, Path]] = []
    for cam, cam_rows in by_cam.items():
        imgs = per_cam[cam]
        if cam_rows and all(r.image is None for r in cam_rows) and len(cam_rows) != len(imgs):
            raise SequenceError(
                poses_file,
                f"camera {cam!r}: {len(cam_rows)} poses but {len(imgs)} images in "
                f"{imgs[0].parent if imgs else images_dir}; counts must match (or add an 'image' column)",
            )
        for k, r in enumerate(cam_rows):
            src = (images_dir / r.image) if r.image else imgs[k]
            if r.image and not src.is_file() and (images_dir / cam / r.image).is_file():
                src = images_dir / cam / r.image
            w, h = image_size(src)
            c = cameras[cam]
            if (w, h) != (c.width, c.height):
                raise SequenceError(src, f"image is {w}x{h}, cameras.json says {cam} is {c.width}x{c.height}")
            rel = f"images/{cam}/{r.frame:06d}{src.suffix.lower()}"
            ts = r.timestamp if r.timestamp is not None else (r.frame / fps if fps else float(r.frame))
            f = frames.setdefault(r.frame, Frame(r.frame, ts, {}))
            if cam in f.views:
                raise SequenceError(poses_file, f"frame {r.frame} camera {cam!r} appears twice")
            f.views[cam] = View(cam, rel, r.T)
            jobs.append((src, out / rel))
    seq = Sequence(
        name or images_dir.resolve().name, list(classes or DEFAULT_CLASSES), cameras,
        [frames[i] for i in sorted(frames)],
    )
    src_of = {dst: src for src, dst in jobs}  # georeference before copying: a GPS that does not fit copies nothing
    attach_geo(seq, geo, poses=poses, images={f.index: src_of[out / next(iter(f.views.values())).image]
                                              for f in seq.frames})  # GPS (--gps, poses.csv lat/lon, EXIF) or by hand
    for src, dst in tqdm(jobs, desc="copy images", unit="img", disable=None):
        copy_image(src, dst)
    store_ego_masks(cameras, egos, out)
    report_result(sfm_res, out)
    write_sequence(seq, out)
    return seq


# ----------------------------------------------------------------------------- video import


def extract_video_frames(
    video: str | os.PathLike, out_dir: str | os.PathLike, fps: float | None = 2.0,
    start: float = 0.0, stop: float | None = None, max_frames: int | None = None,
) -> tuple[list[Path], list[float]]:
    """Split a video into JPEG frames at ``fps`` (None = every frame) with OpenCV.

    Returns the written paths and their timestamps (seconds from the video start).
    """
    import cv2

    video = Path(video)
    if not video.is_file():
        raise SequenceError(video, "video file not found")
    cap = cv2.VideoCapture(str(video))
    if not cap.isOpened():
        raise SequenceError(video, "cannot open video (format or codec not supported by OpenCV)")
    native = cap.get(cv2.CAP_PROP_FPS) or 30.0
    n_total = int(cap.get(cv2.CAP_PROP_FRAME_COUNT) or 0)
    step = 1.0 if not fps or fps >= native else native / fps
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    paths: list[Path] = []
    stamps: list[float] = []
    next_pick = start * native
    i = 0
    from tqdm import tqdm

    with tqdm(total=n_total or None, desc="read video", unit="frame", disable=None) as bar:
        while True:
            ok = cap.grab()
            if not ok:
                break
            t = i / native
            if stop is not None and t > stop:
                break
            if i + 1e-6 >= next_pick:
                ok, img = cap.retrieve()
                if not ok:
                    raise SequenceError(video, f"cannot decode frame {i}")
                p = out_dir / f"{len(paths):06d}.jpg"
                with atomic_path(p) as tmp:  # the temporary name keeps the .jpg suffix OpenCV needs
                    if not cv2.imwrite(str(tmp), img, [cv2.IMWRITE_JPEG_QUALITY, 95]):
                        raise SequenceError(p, "cannot write frame")
                paths.append(p)
                stamps.append(t)
                next_pick += step
                if max_frames is not None and len(paths) >= max_frames:
                    break
            i += 1
            bar.update(1)
    cap.release()
    if not paths:
        raise SequenceError(video, "no frames decoded in the requested range")
    return paths, stamps


#: ``--fps auto``: frames are read at up to this rate, then kept by the motion between them
AUTO_FPS_CEILING = 10.0
#: ... a frame is kept once the scene has moved this share of the image width since the last one kept (the
#: median flow of tracked corners; 2 Hz keyframes of a car at 30 km/h move ~3 %, which SfM and the road's steps
#: handle; more than ~8 % and the road ahead no longer overlaps well)
AUTO_PARALLAX = 0.03


def _frames_by_motion(paths: list[Path], stamps: list[float], cam: Camera,
                      max_frames: int | None) -> tuple[list[Path], list[float]]:
    """The extracted frames ``paths`` kept where the camera moved enough since the last one kept (a frame rate
    from the motion: a stop keeps one frame, a fast stretch keeps more per second); the others, written by this
    import, are removed. ``max_frames`` caps what is kept."""
    ego, _ = resolve_ego_mask(None, paths, cam.width, cam.height, default_auto=True)
    keep = frames_by_motion(paths, AUTO_PARALLAX, ego)
    idx = np.flatnonzero(keep)[: max_frames or None]
    for i in sorted(set(range(len(paths))) - set(idx.tolist())):
        paths[i].unlink(missing_ok=True)
    return [paths[i] for i in idx], [stamps[i] for i in idx]


def interpolate_poses(rows: list[PoseRow], times: np.ndarray) -> np.ndarray:
    """Camera-to-world poses at ``times`` (N,) from timestamped rows: linear position, slerp rotation → (N, 4, 4)."""
    from scipy.spatial.transform import Rotation, Slerp

    t = np.array([r.timestamp for r in rows], dtype=np.float64)
    order = np.argsort(t)
    t = t[order]
    Ts = np.stack([rows[i].T for i in order])
    tq = np.clip(times, t[0], t[-1])
    slerp = Slerp(t, Rotation.from_matrix(Ts[:, :3, :3]))
    out = np.tile(np.eye(4), (len(times), 1, 1))
    out[:, :3, :3] = slerp(tq).as_matrix()
    for k in range(3):
        out[:, k, 3] = np.interp(tq, t, Ts[:, k, 3])
    return out


def import_video(
    video: str | os.PathLike,
    cameras_json: str | os.PathLike,
    poses: str | os.PathLike,
    out: str | os.PathLike,
    fps: float | str | None = 2.0,
    start: float = 0.0,
    stop: float | None = None,
    max_frames: int | None = None,
    camera_height: float = 1.5,
    name: str | None = None, geo: GeoInput | None = None,
) -> Sequence:
    """Import a video of one camera: frames at ``fps`` (``"auto"``: chosen by the motion, :func:`_frames_by_motion`);
    poses from a CSV (timestamped rows are interpolated to the frame times, else one row per extracted frame) or
    ``"sfm"``."""
    video, out = Path(video), Path(out)
    cameras = read_cameras_json(cameras_json)
    if len(cameras) != 1:
        raise SequenceError(cameras_json, f"a video has one camera; cameras.json lists {sorted(cameras)}")
    cam = next(iter(cameras.values()))
    auto = isinstance(fps, str)
    if auto and fps != "auto":
        raise PavemapError(f"--fps must be a number of frames per second or 'auto', got {fps!r}")
    paths, stamps = extract_video_frames(video, out / "images" / cam.name, AUTO_FPS_CEILING if auto else fps,
                                         start, stop, None if auto else max_frames)
    if auto:
        paths, stamps = _frames_by_motion(paths, stamps, cam, max_frames)
    w, h = image_size(paths[0])
    if (w, h) != (cam.width, cam.height):
        raise SequenceError(video, f"frames are {w}x{h}, cameras.json says {cam.name} is {cam.width}x{cam.height}")
    times = np.asarray(stamps)
    ego = None
    if str(poses).lower() == "sfm":
        ego, _ = resolve_ego_mask(None, paths, cam.width, cam.height, default_auto=True)  # bonnet: kept out of SfM
        res = sfm_poses_or_report(out, paths, cam, camera_height=camera_height, ego_mask=ego, times=times)
        Ts = res.T_world_cam
        for i in np.nonzero(~res.registered)[0]:  # frames SfM could not register are dropped
            paths[i].unlink(missing_ok=True)
    else:
        rows = read_poses_csv(poses)
        if all(r.timestamp is not None for r in rows) and len(rows) >= 2:
            Ts = interpolate_poses(rows, times)
        elif len(rows) == len(paths):
            Ts = np.stack([r.T for r in rows])
        else:
            raise SequenceError(
                poses, f"{len(rows)} poses for {len(paths)} extracted frames; give timestamps "
                "(seconds from the video start) or one row per extracted frame"
            )
    frames = [
        Frame(i, float(times[i]), {cam.name: View(cam.name, f"images/{cam.name}/{p.name}", Ts[i])})
        for i, p in enumerate(paths)
        if np.isfinite(Ts[i]).all()
    ]
    seq = Sequence(name or video.stem, list(DEFAULT_CLASSES), {cam.name: cam}, frames)
    attach_geo(seq, geo, poses=poses, per_frame=False)
    store_ego_masks({cam.name: cam}, {cam.name: ego}, out)  # the bonnet found for SfM: masks/<camera>.png
    report_result(res if str(poses).lower() == "sfm" else None, out)
    write_sequence(seq, out)
    return seq
