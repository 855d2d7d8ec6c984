"""What the importers call: a geo origin for a new sequence from GPS or by hand.

Sources, first match wins: ``--geo-origin LAT,LON[,ALT[,HEADING]]`` (by hand); ``--gps FILE``
(GPX, NMEA, CSV; ``exif`` for the EXIF GPS of the images; a KITTI raw ``oxts`` folder); the
``lat``/``lon`` columns of the importer's poses.csv. Giving a hand origin and GPS together is an
error (which one would be right?).
"""

from __future__ import annotations

import csv
import logging
import math
import os
from dataclasses import dataclass
from pathlib import Path

from pavemap.errors import PavemapError
from pavemap.geo.georef import Georef, georeference, scale_poses
from pavemap.geo.tangent import check_origin
from pavemap.io.gps import GpsTrack, csv_has_gps, read_exif_gps, read_gps, read_gps_csv, read_oxts
from pavemap.types import GeoOrigin, Sequence

log = logging.getLogger("pavemap")


@dataclass
class GeoInput:
    """The importer options: ``gps`` (a file, ``exif``, or a KITTI raw oxts folder), its clock offset
    (GPS time minus frame time, seconds), a hand-given origin, the OXTS record of the first frame, and the
    antenna's lever arm (metres, x forward, y left, z up from the camera; KITTI: from the raw calibration)."""

    gps: str | None = None
    offset: float | None = None
    origin: str | None = None
    oxts_first: int | None = None
    lever_arm: tuple[float, float, float] | None = None

    @property
    def given(self) -> bool:
        return self.gps is not None or self.origin is not None


def parse_geo_origin(text: str) -> GeoOrigin:
    """``LAT,LON[,ALT[,HEADING]]`` (degrees, metres, degrees clockwise from north of world +x)."""
    parts = [p.strip() for p in str(text).split(",")]
    try:
        vals = [float(p) for p in parts]
    except ValueError:
        vals = []
    if not 2 <= len(vals) <= 4 or not all(math.isfinite(v) for v in vals):
        raise PavemapError(f"--geo-origin {text!r}: expected LAT,LON[,ALT[,HEADING]] as numbers, e.g. "
                           "49.0111,8.4167,115,90")
    lat, lon, alt, heading = (vals + [0.0, 90.0][len(vals) - 2:])[:4]
    origin = GeoOrigin(lat, lon, alt, heading % 360.0, georef={"source": "--geo-origin (given by hand)"})
    try:
        check_origin(origin)
    except PavemapError as e:
        raise PavemapError(f"--geo-origin {text!r}: {str(e).removeprefix('geo_origin: ')}") from None
    return origin


def parse_lever_arm(text: str | None) -> tuple[float, float, float] | None:
    """``X,Y,Z`` metres (x forward, y left, z up; the antenna minus the camera) -> a tuple; None for None."""
    if text is None:
        return None
    try:
        vals = tuple(float(p) for p in str(text).split(","))
    except ValueError:
        vals = ()
    if len(vals) != 3 or not all(math.isfinite(v) and abs(v) < 50.0 for v in vals):
        raise PavemapError(f"--gps-lever-arm {text!r}: expected X,Y,Z in metres (x forward, y left, z up from the "
                           "camera to the GPS antenna, each under 50 m), e.g. -1.1,0.3,0.8")
    return vals  # type: ignore[return-value]


def _csv_track(poses: Path | None, per_frame: bool) -> GpsTrack | None:
    if poses is None or poses.suffix.lower() != ".csv" or not poses.is_file():
        return None
    with open(poses, encoding="utf-8", newline="") as fh:
        header = next(csv.reader(line for line in fh if line.strip() and not line.startswith("#")), [])
    return read_gps_csv(poses, per_frame=per_frame) if csv_has_gps(header) else None


def _track(geo: GeoInput, poses: Path | None, images: dict[int, Path] | None, per_frame: bool) -> GpsTrack | None:
    if geo.gps is None:
        return _csv_track(poses, per_frame)
    if str(geo.gps).lower() == "exif":
        if not images:
            raise PavemapError("--gps exif reads the EXIF GPS of the imported images; this importer has none")
        return read_exif_gps(images, next(iter(images.values())).parent)
    p = Path(geo.gps)
    if p.is_dir():
        return read_oxts(p, first=geo.oxts_first or 0)
    return read_gps(p)


def attach_geo(seq: Sequence, geo: GeoInput | None, *, poses: str | os.PathLike | None = None,
               root: Path | None = None, scale_free: bool | None = None, per_frame: bool = True,
               images: dict[int, Path] | None = None) -> Georef | None:
    """Set ``seq.geo_origin`` (and, for scale-free poses, rescale them to the GPS) before it is written.

    ``poses``: the importer's poses.csv (its lat/lon columns are GPS when no ``--gps`` is given) or
    ``"sfm"`` (scale-free fit unless ``scale_free`` says otherwise); ``images`` {frame index: image path}
    (``--gps exif`` reads them; the originals, so a failed fit happens before anything is copied) or ``root``,
    the folder they were copied to (JPEGs are copied byte for byte); ``per_frame``: the
    CSV columns are one fix per frame (else matched by their timestamps). Returns the fit (None by hand
    or without GPS).
    """
    geo = geo or GeoInput()
    sfm = str(poses).lower() == "sfm"
    scale_free = sfm if scale_free is None else scale_free
    poses = None if (poses is None or sfm) else Path(poses)
    if images is None and root is not None:
        images = {f.index: root / next(iter(f.views.values())).image for f in seq.frames}
    if geo.origin is not None:
        if geo.gps is not None or _csv_track(poses, per_frame) is not None:
            raise PavemapError("give either --geo-origin or GPS (--gps, or lat/lon columns in the poses), not both")
        seq.geo_origin = parse_geo_origin(geo.origin)
        return None
    track = _track(geo, poses, images, per_frame)
    if track is None:
        return None
    lever = geo.lever_arm
    if lever is None and track.kind == "oxts":
        from pavemap.io.gps import A_KITTI_TO_WORLD, oxts_antenna_in_cam0

        p = oxts_antenna_in_cam0(geo.gps)  # type: ignore[arg-type]
        lever = None if p is None else tuple(float(v) for v in A_KITTI_TO_WORLD @ p)
        log.info("OXTS lever arm %s", "from the raw calibration: " + ", ".join(f"{v:+.2f}" for v in lever)
                 if lever else "unknown (no calib_imu_to_velo.txt / calib_velo_to_cam.txt): about 1 m error")
    g = georeference(seq, track, scale_free=scale_free, offset=geo.offset, lever_arm=lever)
    scale_poses(seq, g.scale)
    seq.geo_origin = g.origin
    r = g.origin.georef or {}
    log.info("georeferenced from %s: %d of %d fixes, RMS %.2f m, heading %.2f deg", track.source, r.get("inliers", 0),
             r.get("fixes", 0), r.get("rms_m", float("nan")), g.origin.heading_deg)
    return g


def describe(seq: Sequence) -> str:
    """One line about the sequence's geo origin, for the importers' console output."""
    o = seq.geo_origin
    if o is None:
        return "no geo origin (outputs in local metres)"
    r = o.georef or {}
    where = f"geo origin {o.lat:.7f}, {o.lon:.7f}, heading {o.heading_deg:.2f}°"
    if "rms_m" in r:
        where += (f" from {Path(str(r['source'])).name}: {r['inliers']}/{r['fixes']} fixes, RMS {r['rms_m']:.2f} m"
                  + (f", scale x{r['scale_applied']:.4f}" if r.get("scale_applied", 1.0) != 1.0 else ""))
    for w in r.get("warnings", []):
        where += f"\nwarning: {w}"
    return where


__all__ = ["GeoInput", "attach_geo", "describe", "parse_geo_origin", "parse_lever_arm"]
