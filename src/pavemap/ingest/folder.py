"""Import an own drive: a folder of images + cameras.json + poses.csv, or ``--poses sfm`` (poses from the images)."""

from __future__ import annotations

import os
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from pavemap.errors import PavemapError
from pavemap.geo.attach import GeoInput, attach_geo
from pavemap.ingest.parts import import_other_parts
from pavemap.io.egomask import resolve_ego_mask, store_ego_masks
from pavemap.io.folder import (
    DEFAULT_CLASSES,
    PoseRow,
    copy_image,
    image_size,
    list_images,
    read_cameras_json,
    read_poses_csv,
)
from pavemap.io.sequence import SequenceError, write_sequence
from pavemap.sfm.checks import SfmChecks
from pavemap.sfm.pipeline import report_result, sfm_poses_or_report  # pycolmap is imported when SfM runs
from pavemap.sfm.result import SfmResult
from pavemap.types import Camera, Frame, SemanticClass, Sequence, View


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
    movers: Callable[[Path], np.ndarray | None] | None = None,
) -> Sequence:
    """Import an own drive: images + cameras.json + poses.csv (or ``poses="sfm"``) → sequence folder.

    ``ego_mask``: "auto" (found in the images; the default with ``poses="sfm"``), "none", or a mask image
    (white = ego vehicle); stored as ``masks/<camera>.png``. ``refine_intrinsics``: SfM refines the
    nominal focal length and principal point (written to the sequence's camera). ``geo``: GPS or a
    hand-given origin (:mod:`pavemap.geo.attach`); lat/lon columns of poses.csv are GPS too. ``fps``: the
    images are frames this many per second apart (frame times where poses.csv gives none; with SfM the
    path's speed changes are checked against a car's). ``movers``: image -> (H, W) bool on what may move, kept
    out of SfM (:func:`pavemap.segment.movers.movable_masks`; the commands build it). With SfM, the stretches
    of the clip outside the part it kept are imported as sequences of their own (:mod:`pavemap.ingest.parts`,
    listed in ``sfm.json``'s ``other_parts``)."""
    images_dir, out = Path(images_dir), Path(out)
    cameras = read_cameras_json(cameras_json)
    per_cam = _camera_images(images_dir, cameras)
    if fps is not None and not 0 < fps < float("inf"):
        raise PavemapError(f"--fps must be a positive, finite number of frames per second, got {fps}")
    spec = SfmImport(images_dir, cameras, name or images_dir.resolve().name, list(classes or DEFAULT_CLASSES), geo,
                     fps, camera_height, refine_intrinsics, movers)
    if str(poses).lower() != "sfm":
        rows = read_poses_csv(poses)
        egos = {c.name: resolve_ego_mask(ego_mask, per_cam[c.name], c.width, c.height, default_auto=False)[0]
                for c in cameras.values()} if ego_mask is not None else {}
        return _write(spec, rows, per_cam, Path(str(poses)), egos, out, None)
    if len(cameras) != 1:
        raise PavemapError("--poses sfm supports one camera; give a poses.csv for a multi-camera rig")
    cam = next(iter(cameras.values()))
    cam.height_m = camera_height  # the path is scaled to it: stage 1's prior (Camera.height_m)
    images = per_cam[cam.name]
    spec.ego, _ = resolve_ego_mask(ego_mask, images, cam.width, cam.height, default_auto=True)
    if fps is not None:  # a claim about the images, not a measurement: SfmChecks.nominal_times
        spec.times = np.arange(len(images)) / fps
    return sfm_import(spec, images, out, 0, whole_clip=True)


@dataclass
class SfmImport:
    """What every part of one SfM import shares. ``times`` (N,) s of the whole clip's frames or None;
    ``nominal_times``: they are a claim (an image folder's ``--fps``), not measured (a video's)."""

    images_dir: Path
    cameras: dict[str, Camera]
    name: str
    classes: list[SemanticClass]
    geo: GeoInput | None
    fps: float | None
    camera_height: float
    refine_intrinsics: bool
    movers: Callable[[Path], np.ndarray | None] | None
    ego: np.ndarray | None = None
    times: np.ndarray | None = None
    nominal_times: bool = True


def sfm_import(spec: SfmImport, images: list[Path], out: Path, first: int, whole_clip: bool) -> Sequence:
    """SfM poses for ``images`` (frames ``first``, ``first + 1``, ... of the clip) of the one camera -> the
    sequence in ``out``; for the whole clip, its other stretches too (:func:`import_other_parts`)."""
    cam = next(iter(spec.cameras.values()))
    times = None if spec.times is None else spec.times[first:first + len(images)]
    res = sfm_poses_or_report(out, images, cam, camera_height=spec.camera_height, ego_mask=spec.ego,
                              refine_intrinsics=spec.refine_intrinsics, movers=spec.movers, times=times,
                              checks=SfmChecks(nominal_times=spec.nominal_times))
    if spec.refine_intrinsics and res.K is not None:
        cam.K = res.K
    # frames SfM could not register are left out (named in sfm.json); image names kept explicit
    rows = [PoseRow(first + i, cam.name, None if times is None else float(times[i]),
                    str(images[i].relative_to(spec.images_dir)), res.T_world_cam[i])
            for i in np.nonzero(res.registered)[0]]
    if whole_clip:
        kept = np.flatnonzero(res.registered)
        name = spec.name
        res.info["other_parts"] = import_other_parts(
            images, (int(kept[0]), int(kept[-1])), out,
            lambda imgs, dest, a: sfm_import(replace(spec, name=f"{name}-frames-{a}"), imgs, dest, a, False))
    return _write(spec, rows, {cam.name: images}, Path("sfm"), {cam.name: spec.ego}, out, res)


def _write(spec: SfmImport, rows: list[PoseRow], per_cam: dict[str, list[Path]], poses_file: Path,
           egos: dict[str, np.ndarray | None], out: Path, sfm_res: SfmResult | None) -> Sequence:
    """The sequence of ``rows`` in ``out``: georeferenced, its images copied, ego masks and SfM's report."""
    from tqdm import tqdm

    frames, jobs = _frames(rows, spec.cameras, per_cam, spec.images_dir, poses_file, out, spec.fps)
    seq = Sequence(spec.name, list(spec.classes), spec.cameras, [frames[i] for i in sorted(frames)])
    src_of = {dst: src for src, dst in jobs}  # georeference before copying: a GPS that does not fit copies nothing
    attach_geo(seq, spec.geo, poses=poses_file,
               images={f.index: src_of[out / next(iter(f.views.values())).image] for f in seq.frames})
    for src, dst in tqdm(jobs, desc="copy images", unit="img", disable=None):
        copy_image(src, dst)
    store_ego_masks(spec.cameras, egos, out)
    report_result(sfm_res, out)
    write_sequence(seq, out)
    return seq


def _frames(rows: list[PoseRow], cameras: dict[str, Camera], per_cam: dict[str, list[Path]], images_dir: Path,
            poses_file: Path, out: Path, fps: float | None) -> tuple[dict[int, Frame], list[tuple[Path, Path]]]:
    """The sequence's frames from the pose rows (each view's image checked against its camera's size) and the
    copy jobs (source image, destination in ``out``)."""
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
    return frames, jobs
