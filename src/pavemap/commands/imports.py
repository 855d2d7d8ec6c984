"""``pavemap import kitti|nuscenes|folder|video``: real drives → sequence folders (SPEC §6).

Every importer can add per-frame semantics: ``--labels DIR`` (label PNGs) with
``--class-map`` (preset or YAML), or ``--segmenter`` (ESPNet / ESPNetv2 Cityscapes weights, or an
ultralytics semantic model .pt). With neither, ESPNet labels the images when its weights are found
(else the warned trajectory-corridor fallback, said on the console; ``--no-semantics`` skips masks).
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from pathlib import Path

import typer

from pavemap.commands.options import DEVICE_HELP
from pavemap.errors import PavemapError
from pavemap.types import Sequence

imports_app = typer.Typer(name="import", help="Import real data (KITTI, nuScenes, own images or video).",
                          no_args_is_help=True)

_LABELS = typer.Option(None, "--labels", help="Folder of label PNGs (<camera>/<frame>.png or <image stem>.png).")
_CLASS_MAP = typer.Option(
    None, "--class-map", help="Label set: preset (rome-nuscenes, rome-kitti, mapillary-vistas, pavemap) or YAML."
)
_SEGMENTER = typer.Option(
    None, "--segmenter", help="auto (default: ESPNet when its weights are found and the images are colour, else the "
    "corridor fallback, said on the console), espnet, espnetv2, corridor, none, or an ultralytics semantic "
    "segmentation .pt file. See docs/segmenter.md.")
_SEG_WEIGHTS = typer.Option(None, "--segmenter-weights", help="ESPNet / ESPNetv2 weight file (default: looked up in "
                            "$PAVEMAP_WEIGHTS, ~/.cache/pavemap/weights; see docs/segmenter.md).")
_NO_SEM = typer.Option(False, "--no-semantics", help="Write no semantic masks (no fallback either).")
_DEVICE = typer.Option("auto", help=f"Segmenter device: {DEVICE_HELP}.")
_OVERWRITE = typer.Option(False, "--overwrite", help="Replace a sequence folder pavemap wrote (deletes only the "
                          "files pavemap wrote there; a folder holding anything else is refused).")


def _diagnosis(rel: str) -> bool:
    """What a failed import keeps: SfM's report of what it measured (no sequence: nothing looks imported)."""
    from pavemap.sfm.report import SFM_FIGURE, SFM_REPORT

    return rel in (SFM_REPORT, SFM_FIGURE)


def _owned_output(input_arg: str) -> Callable:
    """An import command writes into ``--out`` only when it is new, empty or a sequence folder pavemap wrote
    (``--overwrite``), never inside its input ``input_arg``; a failed import deletes what it wrote but SfM's diagnosis
    (:func:`pavemap.io.owned.writing`)."""
    def wrap(command: Callable) -> Callable:
        @functools.wraps(command)
        def run(**kw: object) -> object:
            from pavemap.io.owned import writing

            source = kw.get(input_arg)
            with writing(kw["out"], "sequence", bool(kw.get("overwrite")), inputs=(source,),  # type: ignore[arg-type]
                         info={"source": str(source)}, keep_on_failure=_diagnosis):
                return command(**kw)
        return run
    return wrap
_GPS = typer.Option(None, "--gps", help="GPS track: .gpx, NMEA log (RMC/GGA), .csv (lat, lon[, alt][, heading], "
                    "timestamp), or 'exif' (the images' EXIF GPS); fitted to the trajectory -> geo origin.")
_GPS_OFFSET = typer.Option(None, "--gps-offset", help="GPS time minus frame time, seconds (default: 0 when both "
                           "are absolute or both relative, else the first frame is taken at the first fix).")
_LEVER = typer.Option(None, "--gps-lever-arm", help="X,Y,Z metres from the camera to the GPS antenna (x forward, "
                      "y left, z up), e.g. -1.1,0.3,0.8; KITTI raw OXTS: read from the raw calibration.")
_GEO_ORIGIN = typer.Option(None, "--geo-origin", help="LAT,LON[,ALT[,HEADING]] of the world origin by hand "
                           "(HEADING: degrees clockwise from north of world +x).")


def add_semantics(seq: Sequence, labels: Path | None, class_map: str | None, segmenter: str | None,
                  no_semantics: bool, camera_height: float | None, device: str = "auto",
                  segmenter_weights: Path | None = None, shared: object | None = None) -> str:
    """Attach semantics to an imported sequence; returns a short description of what was done. ``shared``: the
    segmenter SfM's vehicle masks used (what it labelled is reused)."""
    from pavemap.segment import attach_label_folder, corridor_semantics, segment_sequence
    from pavemap.segment.auto import GreyImagesError, WeightsMissingError, arch_of, espnet_semantics
    from pavemap.segment.espnet import ARCHS

    spec = segmenter or "auto"
    if labels is not None and segmenter is not None:
        raise typer.BadParameter("give --labels or --segmenter, not both")
    if labels is not None:
        attach_label_folder(seq, labels, class_map or "pavemap")
        return "labels"
    if no_semantics or spec == "none":
        return "none"
    if spec == "corridor":
        corridor_semantics(seq, camera_height=camera_height)
        return "corridor fallback"
    if spec == "auto" or spec in ARCHS:
        try:
            espnet_semantics(seq, arch_of(spec), segmenter_weights, device, segmenter=shared,  # type: ignore[arg-type]
                             camera_height=camera_height)
            return f"{arch_of(spec)} segmenter"
        except (GreyImagesError, WeightsMissingError) as e:
            if spec != "auto":
                raise
            typer.echo(f"segmenter not used: {e}; using the trajectory-corridor fallback")
            corridor_semantics(seq, camera_height=camera_height)
            return "corridor fallback"
    if not Path(spec).is_file():
        what = "no such file" if spec.lower().endswith(".pt") else "not a segmenter name and no such file"
        raise PavemapError(f"--segmenter {spec}: {what}; choose auto, {', '.join(ARCHS)}, corridor, none, or the path "
                           "of an ultralytics semantic-segmentation .pt file (see docs/segmenter.md)")
    from pavemap.segment.yolo_seg import UltralyticsSegmenter

    segment_sequence(seq, UltralyticsSegmenter(spec, class_map or "mapillary-vistas", device=device))
    return "segmenter"


def _done(seq: Sequence, out: Path, sem: str) -> None:
    from pavemap.geo.attach import describe

    views = sum(len(f.views) for f in seq.frames)
    typer.echo(f"{seq.name}: {len(seq.frames)} frames, {views} views, semantics: {sem} -> {out}")
    _say_sfm(out)
    typer.echo(describe(seq))


def _say_sfm(out: Path) -> None:
    """One line on what SfM kept and where its diagnosis is, when the poses came from SfM."""
    import json

    from pavemap.sfm.report import SFM_FIGURE, SFM_REPORT

    rep = Path(out) / SFM_REPORT
    if not rep.is_file():
        return
    r = json.loads(rep.read_text())
    dropped = r.get("dropped") or {}
    typer.echo(f"poses: {r.get('method', 'SfM')}, {r.get('registered')} of {r.get('images')} frames kept"
               + (f", {len(dropped)} dropped (why: {SFM_REPORT})" if dropped else "")
               + f", scale from {r.get('scale_source')}; diagnosis: {rep}, {Path(out) / SFM_FIGURE}")
    for part in _other_parts(out):
        a, b = part["frames"]
        where = Path(out) / part["folder"]
        if part["status"] == "imported":
            lo, hi = part["kept"]
            typer.echo(f"another part of the clip: frames {lo}-{hi} ({part['frames_kept']} kept) imported as a drive "
                       f"of its own (no link to this one across the gap) -> {where}; map it with pavemap run {where}")
        else:
            typer.echo(f"frames {a}-{b}: not imported ({part['reason']}); diagnosis: {where / SFM_REPORT}")


def _geo(gps: str | None, offset: float | None, origin: str | None, oxts_first: int | None = None,  # noqa: ANN202
         lever_arm: str | None = None):
    from pavemap.geo.attach import GeoInput, parse_lever_arm

    return GeoInput(gps, offset, origin, oxts_first, parse_lever_arm(lever_arm))


@imports_app.command("kitti")
@_owned_output("root")
def kitti_cmd(
    root: Path = typer.Argument(..., help="KITTI odometry root (holds sequences/ and poses/)."),
    out: Path = typer.Option(..., "--out", "-o", help="Output sequence folder."),
    sequence: str = typer.Option("00", help="Sequence number, e.g. 00."),
    camera: int = typer.Option(2, help="2 = left colour (image_2), 0 = left grey (image_0)."),
    start: int = typer.Option(0, help="First frame."),
    stop: int | None = typer.Option(None, help="Stop before this frame."),
    stride: int = typer.Option(1, help="Take every n-th frame."),
    lidar: bool = typer.Option(True, help="Write sparse depth from velodyne/*.bin when present."),
    oxts: Path | None = typer.Option(None, "--oxts", help="KITTI raw drive folder (or its oxts/) with the GPS/IMU "
                                     "records of this sequence -> geo origin."),
    oxts_first: int | None = typer.Option(None, help="OXTS record of odometry frame 0 (default: the devkit's "
                                          "offset for sequences 00-10, e.g. 1100 for 08)."),
    geo_origin: str | None = _GEO_ORIGIN, gps_lever_arm: str | None = _LEVER,
    labels: Path | None = _LABELS, class_map: str | None = _CLASS_MAP, segmenter: str | None = _SEGMENTER,
    segmenter_weights: Path | None = _SEG_WEIGHTS,
    no_semantics: bool = _NO_SEM, device: str = _DEVICE, overwrite: bool = _OVERWRITE,
) -> None:
    """KITTI odometry sequence → sequence folder."""
    from pavemap.ingest.kitti import KITTI_MOUNT_HEIGHT_M, import_kitti

    seq = import_kitti(root, sequence, out, camera=camera, start=start, stop=stop, stride=stride, lidar=lidar,
                       geo=_geo(str(oxts) if oxts else None, None, geo_origin, oxts_first, gps_lever_arm))
    _done(seq, out, add_semantics(seq, labels, class_map, segmenter, no_semantics, KITTI_MOUNT_HEIGHT_M, device,
                                  segmenter_weights))


@imports_app.command("nuscenes")
@_owned_output("dataroot")
def nuscenes_cmd(
    dataroot: Path = typer.Argument(..., help="nuScenes dataroot (holds v1.0-mini/, samples/, sweeps/)."),
    out: Path = typer.Option(..., "--out", "-o", help="Output sequence folder."),
    scene: str = typer.Option(..., help="Scene name, e.g. scene-0064."),
    version: str = typer.Option("v1.0-mini", help="Release folder name."),
    sweeps: bool = typer.Option(False, "--sweeps", help="All camera images (12 Hz), not only keyframes."),
    cameras: str | None = typer.Option(None, help="Comma-separated channels (default: the six CAM_*)."),
    max_frames: int | None = typer.Option(None, help="Keep at most this many frames."),
    labels: Path | None = _LABELS, class_map: str | None = _CLASS_MAP, segmenter: str | None = _SEGMENTER,
    segmenter_weights: Path | None = _SEG_WEIGHTS,
    no_semantics: bool = _NO_SEM, device: str = _DEVICE, overwrite: bool = _OVERWRITE,
) -> None:
    """One nuScenes scene (6 cameras, keyframes or sweeps) → sequence folder."""
    import numpy as np

    from pavemap.io.nuscenes import import_nuscenes

    cams = [c.strip() for c in cameras.split(",") if c.strip()] if cameras else None
    seq = import_nuscenes(dataroot, scene, out, version=version, cameras=cams, sweeps=sweeps, max_frames=max_frames)
    # the world origin is the first ego position, on the ground: camera z is its mounting height
    h = float(np.mean([v.T_world_cam[2, 3] for v in seq.frames[0].views.values()]))
    _done(seq, out, add_semantics(seq, labels, class_map, segmenter, no_semantics, h, device, segmenter_weights))


@imports_app.command("folder")
@_owned_output("images")
def folder_cmd(
    images: Path = typer.Argument(..., help="Images folder (files, or one subfolder per camera)."),
    out: Path = typer.Option(..., "--out", "-o", help="Output sequence folder."),
    cameras: Path = typer.Option(..., "--cameras", help="cameras.json (see docs/tutorials/own-video.md)."),
    poses: str = typer.Option(..., "--poses", help="poses.csv, or 'sfm' to estimate them with pycolmap."),
    camera_height: float = typer.Option(1.5, help="Camera height above the road, metres (SfM scale, fallback)."),
    name: str | None = typer.Option(None, help="Sequence name (default: the folder name)."),
    gps: str | None = _GPS, gps_offset: float | None = _GPS_OFFSET, geo_origin: str | None = _GEO_ORIGIN,
    gps_lever_arm: str | None = _LEVER,
    labels: Path | None = _LABELS, class_map: str | None = _CLASS_MAP, segmenter: str | None = _SEGMENTER,
    segmenter_weights: Path | None = _SEG_WEIGHTS,
    no_semantics: bool = _NO_SEM, device: str = _DEVICE, overwrite: bool = _OVERWRITE,
    ego_mask: str | None = typer.Option(
        None, "--ego-mask", help="Ego vehicle (bonnet, dashboard): 'auto' (default with --poses sfm), 'none', "
        "or a mask image (white = ego); kept out of SfM, stored as masks/<camera>.png."),
    refine_intrinsics: bool = typer.Option(
        False, "--refine-intrinsics", help="SfM refines nominal focal length and principal point."),
    fps: float | None = typer.Option(
        None, "--fps", help="Frames per second of the images (e.g. 2 for nuScenes keyframes): frame times; with "
        "SfM a speed change no car makes is warned about (nominal times, so not refused)."),
) -> None:
    """Own drive: images + cameras.json + poses.csv (or --poses sfm) → sequence folder.

    GPS: lat, lon (optional alt, heading) columns in poses.csv, or --gps FILE|exif; or --geo-origin by hand."""
    from pavemap.ingest.folder import import_folder

    movers = _movers(poses, segmenter, segmenter_weights, no_semantics, device)
    seq = import_folder(images, cameras, poses, out, name=name, camera_height=camera_height,
                        geo=_geo(gps, gps_offset, geo_origin, lever_arm=gps_lever_arm), ego_mask=ego_mask,
                        refine_intrinsics=refine_intrinsics, fps=fps, movers=movers)
    _done(seq, out, _semantics_with_parts(seq, out, movers, labels, class_map, segmenter, no_semantics,
                                          camera_height, device, segmenter_weights))


@imports_app.command("video")
@_owned_output("video")
def video_cmd(
    video: Path = typer.Argument(..., help="Video file (any format OpenCV reads)."),
    out: Path = typer.Option(..., "--out", "-o", help="Output sequence folder."),
    cameras: Path = typer.Option(..., "--cameras", help="cameras.json with the video's one camera."),
    poses: str = typer.Option(..., "--poses", help="poses.csv (timestamps in s, interpolated) or 'sfm'."),
    fps: str = typer.Option("2", help="Frames per second to keep (0 = every frame), or 'auto': read at up to "
                            "10 per second and keep a frame whenever the scene moved ~3 % of the image width "
                            "(a frame rate from the motion: see docs/sfm.md)."),
    start: float = typer.Option(0.0, help="Start time, seconds."),
    stop: float | None = typer.Option(None, help="Stop time, seconds."),
    max_frames: int | None = typer.Option(None, help="Keep at most this many frames."),
    camera_height: float = typer.Option(1.5, help="Camera height above the road, metres (SfM scale, fallback)."),
    gps: str | None = _GPS, gps_offset: float | None = _GPS_OFFSET, geo_origin: str | None = _GEO_ORIGIN,
    gps_lever_arm: str | None = _LEVER,
    labels: Path | None = _LABELS, class_map: str | None = _CLASS_MAP, segmenter: str | None = _SEGMENTER,
    segmenter_weights: Path | None = _SEG_WEIGHTS,
    no_semantics: bool = _NO_SEM, device: str = _DEVICE, overwrite: bool = _OVERWRITE,
) -> None:
    """A video of one camera → frames at --fps with poses from a CSV or SfM → sequence folder."""
    from pavemap.ingest.video import import_video

    seq = import_video(video, cameras, poses, out, fps=_fps(fps), start=start, stop=stop, max_frames=max_frames,
                       camera_height=camera_height, geo=_geo(gps, gps_offset, geo_origin, lever_arm=gps_lever_arm),
                       movers=(movers := _movers(poses, segmenter, segmenter_weights, no_semantics, device)))
    _done(seq, out, _semantics_with_parts(seq, out, movers, labels, class_map, segmenter, no_semantics,
                                          camera_height, device, segmenter_weights))


def _semantics_with_parts(seq: Sequence, out: Path, movers: object | None, *args: object) -> str:
    """:func:`add_semantics` (``args`` after ``seq``) on the import and on every other part of the clip SfM imported
    as a sequence of its own (:mod:`pavemap.ingest.parts`), with the segmenter SfM's vehicle masks used."""
    from pavemap.io.sequence import read_sequence

    shared = getattr(movers, "segmenter", None)
    said = add_semantics(seq, *args, shared=shared)  # type: ignore[arg-type]
    for folder in _other_parts(out, imported=True):
        add_semantics(read_sequence(out / folder["folder"]), *args, shared=shared)  # type: ignore[arg-type]
    return said


def _other_parts(out: Path, imported: bool = False) -> list[dict]:
    """``sfm.json``'s ``other_parts`` rows (only the imported ones with ``imported``); none without SfM."""
    import json

    from pavemap.sfm.report import SFM_REPORT

    rep = Path(out) / SFM_REPORT
    rows = json.loads(rep.read_text()).get("other_parts") or [] if rep.is_file() else []
    return [r for r in rows if not imported or r.get("status") == "imported"]


def _movers(poses: str, segmenter: str | None, weights: Path | None, no_semantics: bool, device: str):  # noqa: ANN202
    """With ``--poses sfm``: the segmenter's vehicle and people masks for SfM (said on the console), else None."""
    if str(poses).lower() != "sfm":
        return None
    from pavemap.segment.movers import movable_masks

    masks, said = movable_masks("none" if no_semantics else (segmenter or "auto"), weights, device)
    typer.echo(said)
    return masks


def _fps(text: str) -> float | str | None:
    """--fps: 'auto', or a number of frames per second (0: every frame)."""
    import math

    from pavemap.errors import PavemapError

    if text.strip().lower() == "auto":
        return "auto"
    try:
        v = float(text)
    except ValueError:
        raise PavemapError(f"--fps must be a number of frames per second or 'auto', got {text!r}") from None
    if not math.isfinite(v) or v < 0:
        raise PavemapError(f"--fps must be a positive, finite number of frames per second (0: all), got {text!r}")
    return v or None


@imports_app.command("gps")
def gps_cmd(
    seq: Path = typer.Argument(..., help="An existing sequence folder (its sequence.json is rewritten)."),
    gps: str | None = typer.Option(None, "--gps", help="GPS track (.gpx, NMEA, .csv) or a KITTI raw oxts folder."),
    gps_offset: float | None = _GPS_OFFSET, geo_origin: str | None = _GEO_ORIGIN,
    gps_lever_arm: str | None = _LEVER,
) -> None:
    """Georeference an existing sequence: fit its trajectory to a GPS track (rigid), or set the origin by hand."""
    from pavemap.errors import PavemapError
    from pavemap.geo.attach import attach_geo, describe
    from pavemap.io.sequence import read_sequence, write_sequence

    if gps is None and geo_origin is None:
        raise PavemapError("give --gps FILE or --geo-origin LAT,LON[,ALT[,HEADING]]")
    s = read_sequence(seq)
    attach_geo(s, _geo(gps, gps_offset, geo_origin, lever_arm=gps_lever_arm))
    write_sequence(s, seq)
    typer.echo(f"{s.name}: {describe(s)}")


def register(app: typer.Typer) -> None:
    app.add_typer(imports_app, name="import")
