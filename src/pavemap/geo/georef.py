"""Georeferencing: the geo origin of a drive from its trajectory and a GPS track.

The trajectory (world metres, SPEC §0) is paired with the GPS fixes — per frame when the fixes
come per image (poses.csv columns, EXIF, KITTI OXTS), else by time: the trajectory is
interpolated to each fix's time (not the fixes to the frames', so an outlier fix stays one bad
pair). The fixes are projected into an azimuthal equidistant plane, the robust fit of
:mod:`pavemap.geo.fit` maps the trajectory onto them, and the plane is then re-centred on the
fitted origin and refitted, so that the result is exactly the frame of
:class:`pavemap.geo.tangent.LocalTangent`: world (0, 0) at the origin, world +x at ``heading_deg``.

A GPS antenna is not at the camera: ``lever_arm`` (metres, vehicle frame x forward, y left, z up,
antenna minus the rig's camera centre) moves each trajectory position to where the antenna was,
turned by the direction of travel there (a ground vehicle's yaw; its pitch and roll are ignored).
Where the fixes carry headings (RMC course, EXIF direction, CSV column, OXTS yaw) the heading they
imply is compared with the fitted one; a disagreement above ``HEADING_WARN_DEG`` is a warning.

With poses from SfM the fit is scale free: its scale is the GPS's metres per sequence metre
(the sequence is already scaled by the camera height). The GPS scale is applied when its
standard error is below 1 %; a disagreement above 5 % with the camera-height scale is a warning.
"""

from __future__ import annotations

import datetime as dt
import logging
import math
from dataclasses import dataclass, field

import numpy as np

from pavemap.errors import PavemapError
from pavemap.geo.fit import Fit2D, robust_fit, umeyama_2d
from pavemap.geo.tangent import local_tangent
from pavemap.io.gps import GpsTrack
from pavemap.types import GeoOrigin, Sequence

log = logging.getLogger("pavemap")

MIN_FIXES = 3
MIN_DRIVE_M = 10.0  # below this the heading is not determined by GPS positions
MIN_INLIER_SHARE = 0.5
MAX_RMS_M = 25.0
SCALE_WARN = 0.05  # SfM scale vs GPS scale
SCALE_APPLY_SE = 0.01  # apply the GPS scale when known to 1 %
EXTENT_RATIO = 2.0  # metric poses: GPS track extent vs drive extent beyond this factor is another drive
ABSOLUTE_T = 1e8  # seconds: timestamps above are absolute (Unix epoch, after 1973)
HEADING_WARN_DEG = 5.0  # fitted heading vs the fixes' own headings
MIN_STEP_M = 0.05  # travel below this between frames gives no direction (a standing vehicle)


@dataclass
class Georef:
    """The result: the origin (its ``georef`` record filled) and the scale applied to the poses."""

    origin: GeoOrigin
    scale: float  # applied to the poses (1.0 for metric poses)
    fit: Fit2D
    pairs_xy: np.ndarray  # (N, 2) world x, y (after scaling) of the fixes used
    warnings: list[str] = field(default_factory=list)


def _extent(a: np.ndarray) -> float:
    return float(np.linalg.norm(a.max(0) - a.min(0))) if len(a) else 0.0


def _frame_times(seq: Sequence) -> np.ndarray:
    t = np.array([f.timestamp for f in seq.frames], dtype=np.float64)
    if len(t) > 1 and not np.all(np.diff(t) > 0):
        raise PavemapError(f"{seq.name}: frame timestamps are not increasing; GPS cannot be matched by time")
    return t


def time_offset(track: GpsTrack, frame_t: np.ndarray, offset: float | None) -> tuple[float, str | None]:
    """(GPS time minus frame time, a note when it was guessed)."""
    if offset is not None:
        return float(offset), None
    frames_abs = bool(len(frame_t)) and float(np.nanmin(frame_t)) > ABSOLUTE_T
    if track.absolute == frames_abs:
        return 0.0, None
    off = float(np.nanmin(track.t) - frame_t[0])
    return off, (f"{track.source}: frame times are {'absolute' if frames_abs else 'relative'}, GPS times "
                 f"{'absolute' if track.absolute else 'relative'}: the first frame is taken at the first fix "
                 f"(offset {off:.3f} s); give --gps-offset to set it")


def travel_yaw(traj: np.ndarray) -> np.ndarray:
    """(F, 2|3) positions -> (F,) float64 direction of travel (radians from world +x, counter-clockwise).

    Central differences; frames where the vehicle stands take the direction of the nearest moving frames
    (all zeros when it never moves)."""
    xy = np.asarray(traj, dtype=np.float64)[:, :2]
    if len(xy) < 2:
        return np.zeros(len(xy))
    d = np.gradient(xy, axis=0)
    moving = np.hypot(d[:, 0], d[:, 1]) > MIN_STEP_M / 2
    if not moving.any():
        return np.zeros(len(xy))
    k = np.arange(len(xy))
    # unwrap-free fill: interpolate the unit vector's components, then take the angle
    cx = np.interp(k, k[moving], d[moving, 0] / np.hypot(*d[moving].T))
    cy = np.interp(k, k[moving], d[moving, 1] / np.hypot(*d[moving].T))
    return np.arctan2(cy, cx)


def antenna_positions(traj: np.ndarray, lever_arm: tuple[float, float, float] | None) -> np.ndarray:
    """(F, 3) camera centres -> (F, 3) antenna positions: ``lever_arm`` (x fwd, y left, z up) turned by the yaw."""
    traj = np.asarray(traj, dtype=np.float64)
    if lever_arm is None or not np.any(lever_arm):
        return traj
    lx, ly, lz = (float(v) for v in lever_arm)
    yaw = travel_yaw(traj)
    c, s = np.cos(yaw), np.sin(yaw)
    return traj + np.column_stack([c * lx - s * ly, s * lx + c * ly, np.full(len(traj), lz)])


def pair_fixes(seq: Sequence, track: GpsTrack, offset: float | None = None,
               lever_arm: tuple[float, float, float] | None = None
               ) -> tuple[np.ndarray, np.ndarray, float, list[str]]:
    """World positions (M, 3) of the antenna paired with fix indices (M,): per frame or interpolated by time.

    Returns (xyz, fix index, time offset used, notes).
    """
    if len(track) < MIN_FIXES:
        raise PavemapError(f"{track.source}: {len(track)} GPS fix(es); georeferencing needs at least {MIN_FIXES}")
    traj = antenna_positions(seq.trajectory(), lever_arm)
    if track.frame is not None:
        pos = {f.index: k for k, f in enumerate(seq.frames)}
        idx = np.array([k for k, fr in enumerate(track.frame) if int(fr) in pos], dtype=np.int64)
        if len(idx) < MIN_FIXES:
            raise PavemapError(f"{track.source}: only {len(idx)} of {len(track)} fixes belong to the sequence's "
                               f"{len(seq.frames)} frames; georeferencing needs at least {MIN_FIXES}")
        rows = np.array([pos[int(track.frame[k])] for k in idx])
        return traj[rows], idx, 0.0, []
    ft = _frame_times(seq)
    off, note = time_offset(track, ft, offset)
    gt = track.t - off
    if not np.isfinite(gt).all():
        raise PavemapError(f"{track.source}: GPS fixes without timestamps cannot be matched to the frames by time")
    inside = (gt >= ft[0] - 1e-6) & (gt <= ft[-1] + 1e-6)
    if not inside.any():
        raise PavemapError(
            f"{track.source}: the GPS fixes ({gt.min():.1f} .. {gt.max():.1f} s in frame time, offset {off:.3f} s) "
            f"do not overlap the frames ({ft[0]:.1f} .. {ft[-1]:.1f} s); check the files or --gps-offset")
    idx = np.nonzero(inside)[0]
    if len(idx) < MIN_FIXES:
        raise PavemapError(f"{track.source}: only {len(idx)} GPS fix(es) fall within the frames' time "
                           f"({ft[0]:.1f} .. {ft[-1]:.1f} s); georeferencing needs at least {MIN_FIXES}")
    xyz = np.stack([np.interp(gt[idx], ft, traj[:, k]) for k in range(3)], axis=1)
    return xyz, idx, off, [note] if note else []


def _recentred(lon: np.ndarray, lat: np.ndarray, p: np.ndarray, inl: np.ndarray, start: tuple[float, float]
               ) -> tuple[float, float, float, np.ndarray]:
    """Refit rigidly in the aeqd plane of the current origin until the origin stops moving.

    Returns (lat, lon, theta, residuals)."""
    lat0, lon0 = start
    for _ in range(3):
        lt = local_tangent(GeoOrigin(lat0, lon0, 0.0, 90.0))
        q = np.column_stack(lt.from_lonlat(lon, lat))
        _, theta, t = umeyama_2d(p[inl], q[inl], False)
        lo, la = lt.to_lonlat(np.array([t[0]]), np.array([t[1]]))
        lon0, lat0 = float(lo[0]), float(la[0])
        if math.hypot(*t) < 1e-4:
            break
    c, s = math.cos(theta), math.sin(theta)
    lt = local_tangent(GeoOrigin(lat0, lon0, 0.0, 90.0))
    q = np.column_stack(lt.from_lonlat(lon, lat))
    r = np.linalg.norm(q - p @ np.array([[c, s], [-s, c]]), axis=1)
    return lat0, lon0, theta, r


def _check_shape(track: GpsTrack, p: np.ndarray, q: np.ndarray, scale_free: bool, seq: Sequence) -> None:
    """Refuse a drive too short to give a heading and (metric poses) a track of another size; ``p`` (N, 2) world
    and ``q`` (N, 2) fix positions, metres, of the N paired fixes. The message names the GPS file."""
    drive = _extent(p)
    if drive < MIN_DRIVE_M:
        raise PavemapError(f"{track.source}: the drive {seq.name!r} spans only {drive:.1f} m while these {len(p)} "
                           "GPS fixes were taken (a standing vehicle?): its heading cannot be fitted; give "
                           "--geo-origin LAT,LON,ALT,HEADING")
    ratio = _extent(q) / drive
    if not scale_free and not (1 / EXTENT_RATIO <= ratio <= EXTENT_RATIO):
        raise PavemapError(f"{track.source}: the GPS track spans {_extent(q):.0f} m but the drive spans {drive:.0f} m "
                           f"(x{ratio:.2f}): not this drive's track, or the poses are not in metres")


def heading_check(seq: Sequence, track: GpsTrack, idx: np.ndarray, xyz: np.ndarray, inliers: np.ndarray,
                  heading_deg: float) -> tuple[float | None, str | None]:
    """The origin heading the fixes' own headings imply (circular median over inlier fixes while moving) and a
    warning when it differs from the fitted ``heading_deg`` by more than HEADING_WARN_DEG; (None, None) without."""
    h = track.heading[idx]
    yaw = travel_yaw(xyz)  # the direction of travel at each paired fix (they are in time order)
    step = np.hypot(*np.gradient(xyz[:, :2], axis=0).T) if len(xyz) > 1 else np.zeros(len(xyz))
    ok = np.isfinite(h) & inliers & (step > MIN_STEP_M / 2)
    if ok.sum() < MIN_FIXES:
        return None, None
    # a course h at world yaw psi (counter-clockwise) puts world +x at compass h + psi (compass turns clockwise)
    implied = np.radians(h[ok] + np.degrees(yaw[ok]))
    mean = math.degrees(math.atan2(np.median(np.sin(implied)), np.median(np.cos(implied)))) % 360.0
    diff = (mean - heading_deg + 180.0) % 360.0 - 180.0
    if abs(diff) <= HEADING_WARN_DEG:
        return mean, None
    return mean, (f"{track.source}: the fixes' own headings put world +x at {mean:.1f} deg, the positions at "
                  f"{heading_deg:.1f} deg ({diff:+.1f} deg): a heading that is the vehicle's yaw, not its course, "
                  "or a wrong lever arm / time offset")


def georeference(seq: Sequence, track: GpsTrack, *, scale_free: bool = False, offset: float | None = None,
                 seed: int = 0, lever_arm: tuple[float, float, float] | None = None) -> Georef:
    """Fit the geo origin of ``seq`` to ``track``; PavemapError naming the file for a track that does not fit.

    ``lever_arm``: the GPS antenna minus the camera centre, metres, vehicle frame (x forward, y left, z up)."""
    xyz, idx, off, notes = pair_fixes(seq, track, offset, lever_arm)
    lat, lon = track.lat[idx], track.lon[idx]
    lt0 = local_tangent(GeoOrigin(float(np.median(lat)), float(np.median(lon)), 0.0, 90.0))
    q = np.column_stack(lt0.from_lonlat(lon, lat))
    p = xyz[:, :2]
    _check_shape(track, p, q, scale_free, seq)
    fit = robust_fit(p, q, scale=scale_free, seed=seed)
    warnings = list(notes)
    scale = 1.0
    gps_scale, gps_scale_se = (fit.scale, fit.scale_se) if scale_free else (None, None)
    if scale_free:
        if not (1 / EXTENT_RATIO <= fit.scale <= EXTENT_RATIO):
            raise PavemapError(f"{track.source}: the GPS track is {fit.scale:.2f} times the size of the drive: "
                               "not this drive's track")
        if abs(fit.scale - 1.0) > SCALE_WARN:
            warnings.append(f"the SfM scale (from the camera height) and the GPS disagree by "
                            f"{100 * (fit.scale - 1):+.1f} % (camera height wrong, or poor GPS)")
        if fit.scale_se <= SCALE_APPLY_SE:
            scale = fit.scale
            p = p * scale
            fit = robust_fit(p, q, scale=False, seed=seed)
    share = float(fit.inliers.mean())
    if share < MIN_INLIER_SHARE or fit.rms_m > MAX_RMS_M:
        raise PavemapError(f"{track.source}: the GPS track does not match the trajectory: {int(fit.inliers.sum())} of "
                           f"{len(p)} fixes agree (RMS {fit.rms_m:.1f} m); wrong file or time offset?")
    start = lt0.to_lonlat(np.array([fit.t[0]]), np.array([fit.t[1]]))
    lat0, lon0, theta, r = _recentred(lon, lat, p, fit.inliers, (float(start[1][0]), float(start[0][0])))
    inl = fit.inliers
    alt = track.alt[idx]
    ok = inl & np.isfinite(alt)
    alt0 = float(np.median(alt[ok] - scale * xyz[ok, 2])) if ok.any() else 0.0
    heading = (90.0 - math.degrees(theta)) % 360.0
    gps_heading, heading_note = heading_check(seq, track, idx, xyz * scale, inl, heading)
    if heading_note:
        warnings.append(heading_note)
    record = {
        "source": track.source, "kind": track.kind, "fixes": int(len(p)), "inliers": int(inl.sum()),
        "rms_m": round(float(np.sqrt(np.mean(r[inl] ** 2))), 3), "sigma_m": round(fit.sigma_m, 3),
        "max_inlier_residual_m": round(float(r[inl].max()), 3), "time_offset_s": round(off, 6),
        "scale_free": bool(scale_free), "scale_applied": round(scale, 6),
        "gps_scale": None if gps_scale is None else round(gps_scale, 6),
        "gps_scale_se": None if gps_scale_se is None else round(gps_scale_se, 6),
        "altitude_from_gps": bool(ok.any()),
        "lever_arm_m": None if lever_arm is None else [round(float(v), 4) for v in lever_arm],
        "heading_from_fixes_deg": None if gps_heading is None else round(gps_heading, 3),
        "fitted_utc": dt.datetime.now(dt.UTC).isoformat(timespec="seconds"), "warnings": warnings,
    }
    for w in warnings:
        log.warning("georeference: %s", w)
    origin = GeoOrigin(lat0, lon0, alt0, heading, georef=record)
    fit.residuals = r
    return Georef(origin, scale, fit, p, warnings)


def scale_poses(seq: Sequence, scale: float) -> None:
    """Multiply every camera position by ``scale`` (about the world origin), in place."""
    if scale == 1.0:
        return
    for f in seq.frames:
        for v in f.views.values():
            v.T_world_cam = v.T_world_cam.copy()
            v.T_world_cam[:3, 3] *= scale


def position_error(true: GeoOrigin, fitted: GeoOrigin, xy: np.ndarray) -> np.ndarray:
    """(N,) metres between world points ``xy`` (N, 2) put on the Earth by ``fitted`` and by ``true``."""
    lon, lat = local_tangent(fitted).to_lonlat(xy[:, 0], xy[:, 1])
    x, y = local_tangent(true).from_lonlat(lon, lat)
    return np.hypot(x - xy[:, 0], y - xy[:, 1])


__all__ = ["Georef", "antenna_positions", "georeference", "heading_check", "pair_fixes", "position_error",
           "scale_poses", "time_offset", "travel_yaw"]
