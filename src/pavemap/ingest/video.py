"""Import a video of one camera: frames at a fixed rate or chosen by the motion, poses from a CSV or SfM."""

from __future__ import annotations

import os
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path

import numpy as np

from pavemap.errors import PavemapError
from pavemap.geo.attach import GeoInput, attach_geo
from pavemap.ingest.folder import SfmImport, sfm_import
from pavemap.ingest.parts import import_other_parts
from pavemap.io.atomic import atomic_path
from pavemap.io.egomask import resolve_ego_mask, store_ego_masks
from pavemap.io.folder import DEFAULT_CLASSES, PoseRow, image_size, read_cameras_json, read_poses_csv
from pavemap.io.sequence import SequenceError, write_sequence
from pavemap.sfm.pipeline import frames_by_motion, report_result, sfm_poses_or_report
from pavemap.types import Camera, Frame, Sequence, View


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
    movers: Callable[[Path], np.ndarray | None] | None = None,
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
        cam.height_m = camera_height  # the path is scaled to it: stage 1's prior (Camera.height_m)
        ego, _ = resolve_ego_mask(None, paths, cam.width, cam.height, default_auto=True)  # bonnet: kept out of SfM
        res = sfm_poses_or_report(out, paths, cam, camera_height=camera_height, ego_mask=ego, times=times,
                                  movers=movers)
        Ts = res.T_world_cam
        kept = np.flatnonzero(res.registered)
        spec = SfmImport(paths[0].parent, {cam.name: cam}, name or video.stem, list(DEFAULT_CLASSES), geo, None,
                         camera_height, False, movers, ego, times, nominal_times=False)
        res.info["other_parts"] = import_other_parts(  # before the frames they use are dropped here
            paths, (int(kept[0]), int(kept[-1])), out,
            lambda imgs, dest, a: sfm_import(replace(spec, name=f"{spec.name}-frames-{a}"), imgs, dest, a, False))
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
