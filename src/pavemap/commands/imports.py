"""``pavemap import kitti|nuscenes|folder|video``: real drives → sequence folders (SPEC §6).

Every importer can add per-frame semantics: ``--labels DIR`` (label PNGs) with
``--class-map`` (preset or YAML), or ``--segmenter W.pt`` (ultralytics semantic model).
With neither, the warned trajectory-corridor fallback writes road masks
(``--no-semantics`` skips masks altogether).
"""

from __future__ import annotations

from pathlib import Path

import typer

from pavemap.commands.options import DEVICE_HELP
from pavemap.types import Sequence

imports_app = typer.Typer(name="import", help="Import real data (KITTI, nuScenes, own images or video).",
                          no_args_is_help=True)

_LABELS = typer.Option(None, "--labels", help="Folder of label PNGs (<camera>/<frame>.png or <image stem>.png).")
_CLASS_MAP = typer.Option(
    None, "--class-map", help="Label set: preset (rome-nuscenes, rome-kitti, mapillary-vistas, pavemap) or YAML."
)
_SEGMENTER = typer.Option(None, "--segmenter", help="ultralytics semantic-segmentation weights (.pt).")
_NO_SEM = typer.Option(False, "--no-semantics", help="Write no semantic masks (no fallback either).")
_DEVICE = typer.Option("auto", help=f"Segmenter device: {DEVICE_HELP}.")


def add_semantics(seq: Sequence, labels: Path | None, class_map: str | None, segmenter: Path | None,
                  no_semantics: bool, camera_height: float | None, device: str = "auto") -> str:
    """Attach semantics to an imported sequence; returns a one-word description of what was done."""
    from pavemap.segment import attach_label_folder, corridor_semantics, segment_sequence

    if labels is not None and segmenter is not None:
        raise typer.BadParameter("give --labels or --segmenter, not both")
    if labels is not None:
        attach_label_folder(seq, labels, class_map or "pavemap")
        return "labels"
    if segmenter is not None:
        from pavemap.segment.yolo_seg import UltralyticsSegmenter

        segment_sequence(seq, UltralyticsSegmenter(segmenter, class_map or "mapillary-vistas", device=device))
        return "segmenter"
    if no_semantics:
        return "none"
    typer.secho("warning: no --labels or --segmenter: road masks from the trajectory corridor (fallback)",
                fg=typer.colors.YELLOW, err=True)
    corridor_semantics(seq, camera_height=camera_height)
    return "corridor fallback"


def _done(seq: Sequence, out: Path, sem: str) -> None:
    views = sum(len(f.views) for f in seq.frames)
    typer.echo(f"{seq.name}: {len(seq.frames)} frames, {views} views, semantics: {sem} -> {out}")


@imports_app.command("kitti")
def kitti_cmd(
    root: Path = typer.Argument(..., help="KITTI odometry root (holds sequences/ and poses/)."),
    out: Path = typer.Option(..., "--out", help="Output sequence folder."),
    sequence: str = typer.Option("00", help="Sequence number, e.g. 00."),
    camera: int = typer.Option(2, help="2 = left colour (image_2), 0 = left grey (image_0)."),
    start: int = typer.Option(0, help="First frame."),
    stop: int | None = typer.Option(None, help="Stop before this frame."),
    stride: int = typer.Option(1, help="Take every n-th frame."),
    lidar: bool = typer.Option(True, help="Write sparse depth from velodyne/*.bin when present."),
    labels: Path | None = _LABELS, class_map: str | None = _CLASS_MAP, segmenter: Path | None = _SEGMENTER,
    no_semantics: bool = _NO_SEM, device: str = _DEVICE,
) -> None:
    """KITTI odometry sequence → sequence folder."""
    from pavemap.io.kitti import import_kitti

    seq = import_kitti(root, sequence, out, camera=camera, start=start, stop=stop, stride=stride, lidar=lidar)
    _done(seq, out, add_semantics(seq, labels, class_map, segmenter, no_semantics, 1.65, device))


@imports_app.command("nuscenes")
def nuscenes_cmd(
    dataroot: Path = typer.Argument(..., help="nuScenes dataroot (holds v1.0-mini/, samples/, sweeps/)."),
    out: Path = typer.Option(..., "--out", help="Output sequence folder."),
    scene: str = typer.Option(..., help="Scene name, e.g. scene-0064."),
    version: str = typer.Option("v1.0-mini", help="Release folder name."),
    sweeps: bool = typer.Option(False, "--sweeps", help="All camera images (12 Hz), not only keyframes."),
    cameras: str | None = typer.Option(None, help="Comma-separated channels (default: the six CAM_*)."),
    max_frames: int | None = typer.Option(None, help="Keep at most this many frames."),
    labels: Path | None = _LABELS, class_map: str | None = _CLASS_MAP, segmenter: Path | None = _SEGMENTER,
    no_semantics: bool = _NO_SEM, device: str = _DEVICE,
) -> None:
    """One nuScenes scene (6 cameras, keyframes or sweeps) → sequence folder."""
    import numpy as np

    from pavemap.io.nuscenes import import_nuscenes

    cams = [c.strip() for c in cameras.split(",") if c.strip()] if cameras else None
    seq = import_nuscenes(dataroot, scene, out, version=version, cameras=cams, sweeps=sweeps, max_frames=max_frames)
    # the world origin is the first ego position, on the ground: camera z is its mounting height
    h = float(np.mean([v.T_world_cam[2, 3] for v in seq.frames[0].views.values()]))
    _done(seq, out, add_semantics(seq, labels, class_map, segmenter, no_semantics, h, device))


@imports_app.command("folder")
def folder_cmd(
    images: Path = typer.Argument(..., help="Images folder (files, or one subfolder per camera)."),
    out: Path = typer.Option(..., "--out", help="Output sequence folder."),
    cameras: Path = typer.Option(..., "--cameras", help="cameras.json (see README: own drive)."),
    poses: str = typer.Option(..., "--poses", help="poses.csv, or 'sfm' to estimate them with pycolmap."),
    camera_height: float = typer.Option(1.5, help="Camera height above the road, metres (SfM scale, fallback)."),
    name: str | None = typer.Option(None, help="Sequence name (default: the folder name)."),
    labels: Path | None = _LABELS, class_map: str | None = _CLASS_MAP, segmenter: Path | None = _SEGMENTER,
    no_semantics: bool = _NO_SEM, device: str = _DEVICE,
) -> None:
    """Own drive: images + cameras.json + poses.csv (or --poses sfm) → sequence folder."""
    from pavemap.io.folder import import_folder

    seq = import_folder(images, cameras, poses, out, name=name, camera_height=camera_height)
    _done(seq, out, add_semantics(seq, labels, class_map, segmenter, no_semantics, camera_height, device))


@imports_app.command("video")
def video_cmd(
    video: Path = typer.Argument(..., help="Video file (any format OpenCV reads)."),
    out: Path = typer.Option(..., "--out", help="Output sequence folder."),
    cameras: Path = typer.Option(..., "--cameras", help="cameras.json with the video's one camera."),
    poses: str = typer.Option(..., "--poses", help="poses.csv (timestamps in s, interpolated) or 'sfm'."),
    fps: float = typer.Option(2.0, help="Frames per second to keep (0 = every frame)."),
    start: float = typer.Option(0.0, help="Start time, seconds."),
    stop: float | None = typer.Option(None, help="Stop time, seconds."),
    max_frames: int | None = typer.Option(None, help="Keep at most this many frames."),
    camera_height: float = typer.Option(1.5, help="Camera height above the road, metres (SfM scale, fallback)."),
    labels: Path | None = _LABELS, class_map: str | None = _CLASS_MAP, segmenter: Path | None = _SEGMENTER,
    no_semantics: bool = _NO_SEM, device: str = _DEVICE,
) -> None:
    """A video of one camera → frames at --fps with poses from a CSV or SfM → sequence folder."""
    from pavemap.io.folder import import_video

    seq = import_video(video, cameras, poses, out, fps=fps or None, start=start, stop=stop, max_frames=max_frames,
                       camera_height=camera_height)
    _done(seq, out, add_semantics(seq, labels, class_map, segmenter, no_semantics, camera_height, device))


def register(app: typer.Typer) -> None:
    app.add_typer(imports_app, name="import")
