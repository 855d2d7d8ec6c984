"""Import a KITTI odometry sequence (images, calibration, poses, optional velodyne depth) into a sequence folder."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from pavemap.errors import PavemapError
from pavemap.geo.attach import GeoInput, attach_geo
from pavemap.io.atomic import atomic_path
from pavemap.io.folder import DEFAULT_CLASSES, copy_image, image_size, list_images
from pavemap.io.kitti import KITTI_RAW, kitti_to_world, lidar_depth, read_calib, read_poses, read_velodyne
from pavemap.io.sequence import SequenceError, save_depth, write_sequence
from pavemap.types import Camera, Frame, SemanticClass, Sequence, View

#: the KITTI cameras' height over the road (Geiger et al., IJRR 2013: the rig's figure)
KITTI_MOUNT_HEIGHT_M = 1.65


def _find_poses(root: Path, seq_dir: Path, sequence: str) -> Path:
    for p in (root / "poses" / f"{sequence}.txt", seq_dir / "poses.txt", root / "poses.txt"):
        if p.is_file():
            return p
    raise SequenceError(
        root / "poses" / f"{sequence}.txt",
        f"poses not found (also looked for {seq_dir / 'poses.txt'}); KITTI publishes poses for sequences 00-10",
    )


def _sequence_dir(root: Path, sequence: str, camera: int, stride: int) -> Path:
    """``root/sequences/<sequence>``, or a one-line error for a wrong camera, stride or sequence."""
    if camera not in (0, 1, 2, 3):
        raise PavemapError(f"--camera must be 0, 1 (grey) or 2, 3 (colour), got {camera}")
    if stride < 1:
        raise PavemapError(f"--stride must be >= 1, got {stride}")
    seq_root = root / "sequences"
    seq_dir = seq_root / sequence
    if not seq_dir.is_dir():
        have = sorted(p.name for p in seq_root.iterdir() if p.is_dir()) if seq_root.is_dir() else []
        raise SequenceError(seq_dir, f"sequence {sequence!r} not found; available: {have or 'none (wrong ROOT?)'}")
    return seq_dir


def import_kitti(
    root: str | os.PathLike,
    sequence: str,
    out: str | os.PathLike,
    camera: int = 2,
    start: int = 0,
    stop: int | None = None,
    stride: int = 1,
    lidar: bool = True,
    classes: list[SemanticClass] | None = None,
    geo: GeoInput | None = None,
) -> Sequence:
    """KITTI odometry sequence → sequence folder at ``out`` (frames ``start:stop:stride``).

    ``geo``: ``gps`` a raw drive's OXTS folder (``oxts_first`` defaults to :data:`KITTI_RAW`'s offset)
    or a GPS file, or a hand-given origin (:mod:`pavemap.geo.attach`)."""
    from tqdm import tqdm

    root, out = Path(root), Path(out)
    seq_dir = _sequence_dir(root, sequence, camera, stride)
    calib = read_calib(seq_dir / "calib.txt")
    if camera not in calib.P:
        raise SequenceError(seq_dir / "calib.txt", f"no P{camera} for --camera {camera}; has {sorted(calib.P)}")
    img_dir = seq_dir / f"image_{camera}"
    if not img_dir.is_dir():
        raise SequenceError(img_dir, f"image folder for --camera {camera} not found")
    images = list_images(img_dir)
    T_all = read_poses(poses_file := _find_poses(root, seq_dir, sequence))
    if len(images) != len(T_all):
        raise SequenceError(poses_file, f"{len(T_all)} poses but {len(images)} images in {img_dir}")
    times_file = seq_dir / "times.txt"
    times = (
        np.loadtxt(times_file, dtype=np.float64, ndmin=1) if times_file.is_file() else np.arange(len(images)) * 0.1
    )
    if len(times) != len(images):
        raise SequenceError(times_file, f"{len(times)} timestamps but {len(images)} images")

    idx = np.arange(len(images))[start:stop:stride]
    if idx.size == 0:
        raise PavemapError(f"no frames in --start {start} --stop {stop} (sequence has {len(images)})")
    t_cam = calib.t_cam0_to_cam(camera)
    K = calib.intrinsics(camera)
    w, h = image_size(images[0])
    name = f"cam{camera}"
    cam = Camera(name, w, h, K, height_m=KITTI_MOUNT_HEIGHT_M)
    T_world = kitti_to_world(T_all[idx], t_cam)
    velo_dir = seq_dir / "velodyne"
    use_lidar = lidar and velo_dir.is_dir()
    if use_lidar and calib.Tr is None:
        raise SequenceError(seq_dir / "calib.txt", "velodyne/ present but calib has no Tr (velodyne -> cam0)")
    grey = camera in (0, 1)

    frames = []
    for k, i in enumerate(tqdm(idx, desc=f"kitti {sequence}", unit="frame", disable=None)):
        src = images[i]
        size = image_size(src)
        if size != (w, h):
            raise SequenceError(src, f"image is {size[0]}x{size[1]}, the sequence's first image is {w}x{h}")
        rel = f"images/{name}/{i:06d}.png"
        copy_image(src, out / rel, to_rgb=grey)  # grey becomes 3 channels
        depth_rel = None
        if use_lidar:
            bin_file = velo_dir / f"{src.stem}.bin"
            if bin_file.is_file():
                d = lidar_depth(read_velodyne(bin_file), calib.Tr, t_cam, K, w, h)
                depth_rel = f"depth/{name}/{i:06d}.png"
                with atomic_path(out / depth_rel) as tmp:
                    save_depth(tmp, d)
        frames.append(Frame(int(i), float(times[i]), {name: View(name, rel, T_world[k], None, depth_rel)}))
    seq = Sequence(f"kitti-{sequence}", list(classes or DEFAULT_CLASSES), {name: cam}, frames)
    if geo is not None and geo.gps is not None and Path(geo.gps).is_dir() and geo.oxts_first is None \
            and sequence in KITTI_RAW:
        drive, first, last = KITTI_RAW[sequence]
        if last - first + 1 != len(T_all):  # another sequence under a devkit number: the offset would be wrong
            raise SequenceError(poses_file, f"{len(T_all)} poses, but odometry {sequence} ({drive}) has "
                                f"{last - first + 1}: give --oxts-first for the OXTS record of frame 0")
        geo.oxts_first = first
    attach_geo(seq, geo)
    write_sequence(seq, out)
    return seq
