"""GPS tracks in: GPX, NMEA (RMC / GGA), CSV columns, EXIF GPS of JPEGs, KITTI raw OXTS.

Every reader returns a :class:`GpsTrack`: fixes with WGS84 latitude / longitude, altitude and
heading where the source has them (NaN elsewhere) and a time in seconds — absolute (Unix epoch,
UTC) when the source has a date, else relative — or, for sources that come per image (poses.csv
columns, EXIF, OXTS), the frame each fix belongs to. Matching to frames and the fit are in
:mod:`pavemap.geo.georef`. Problems raise :class:`~pavemap.errors.SequenceError` naming the file.

Headings are degrees clockwise from north (RMC course, EXIF GPSImgDirection, OXTS yaw converted);
altitudes are metres as the source gives them (GPX ``ele``, GGA above mean sea level, OXTS).
"""

from __future__ import annotations

import csv
import datetime as dt
import math
import os
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pavemap.errors import SequenceError

NMEA_SUFFIXES = (".nmea", ".nma", ".log", ".txt")
_LAT = ("lat", "latitude")
_LON = ("lon", "lng", "long", "longitude")
_ALT = ("alt", "altitude", "ele", "elevation", "height")
_HEADING = ("heading", "course", "bearing", "heading_deg", "yaw_deg")
_TIME = ("timestamp", "time", "t", "datetime", "utc")


@dataclass
class GpsTrack:
    """Fixes of one source. Arrays (N,) float64; ``frame`` (N,) int64 for per-image fixes, else None."""

    source: str  # the file (or folder) they came from, for messages
    kind: str  # gpx | nmea | csv | exif | oxts
    t: np.ndarray  # seconds: absolute (Unix epoch, UTC) when ``absolute``, else relative; NaN unknown
    lat: np.ndarray
    lon: np.ndarray
    alt: np.ndarray  # NaN when unknown
    heading: np.ndarray  # degrees clockwise from north, NaN when unknown
    absolute: bool = False
    frame: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.lat)


def make_track(source: str | os.PathLike, kind: str, rows: list[tuple], absolute: bool,
               frames: list[int] | None = None) -> GpsTrack:
    """A track from rows ``(t, lat, lon, alt, heading)`` (None → NaN); fixes out of range raise."""
    a = np.array([[np.nan if v is None else float(v) for v in r] for r in rows], dtype=np.float64).reshape(-1, 5)
    bad = ~((np.abs(a[:, 1]) <= 90) & (np.abs(a[:, 2]) <= 180))
    if bad.any():
        k = int(np.argmax(bad))
        raise SequenceError(source, f"fix {k + 1}: latitude/longitude {a[k, 1]}, {a[k, 2]} out of range")
    if len(a) and not np.all(np.isnan(a[:, 0])) and frames is None:
        order = np.argsort(a[:, 0], kind="stable")
        a = a[order]
    fr = None if frames is None else np.asarray(frames, dtype=np.int64)
    return GpsTrack(str(source), kind, a[:, 0], a[:, 1], a[:, 2], a[:, 3], a[:, 4] % 360.0, absolute, fr)


def _epoch(t: dt.datetime) -> float:
    if t.tzinfo is None:
        t = t.replace(tzinfo=dt.UTC)  # GPX and NMEA times are UTC
    return t.timestamp()


# ---------------------------------------------------------------------------- GPX


def read_gpx(path: str | os.PathLike) -> GpsTrack:
    """Track points of every track and segment (else route points, else waypoints) of a GPX file."""
    import gpxpy
    import gpxpy.gpx

    path = Path(path)
    try:
        gpx = gpxpy.parse(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise SequenceError(path, "GPS file not found") from None
    except (gpxpy.gpx.GPXException, UnicodeDecodeError, ValueError) as e:
        raise SequenceError(path, f"not a readable GPX file ({e})") from None
    pts = [p for trk in gpx.tracks for seg in trk.segments for p in seg.points]
    pts = pts or [p for r in gpx.routes for p in r.points] or list(gpx.waypoints)
    if any(p.time is None for p in pts):
        raise SequenceError(path, f"{sum(p.time is None for p in pts)} of {len(pts)} GPX points have no <time>; "
                                  "fixes are matched to frames by time")
    rows = [(_epoch(p.time), p.latitude, p.longitude, p.elevation, getattr(p, "course", None)) for p in pts]
    return make_track(path, "gpx", rows, absolute=True)


# ---------------------------------------------------------------------------- NMEA


def read_nmea(path: str | os.PathLike) -> GpsTrack:
    """RMC and GGA sentences (any talker: GP, GN, GL …); RMC gives date and course, GGA altitude.

    Sentences of the same time are merged; fixes flagged invalid (RMC status V, GGA quality 0) are
    dropped. Without any RMC date the times are seconds of the day (relative).
    """
    import pynmea2

    path = Path(path)
    try:
        lines = path.read_text(encoding="ascii", errors="replace").splitlines()
    except FileNotFoundError:
        raise SequenceError(path, "GPS file not found") from None
    fixes: dict[float, dict] = {}
    date: dt.date | None = None
    parsed = 0
    for line in lines:
        line = line.strip()
        if not line.startswith("$"):
            continue
        try:
            msg = pynmea2.parse(line)
        except (pynmea2.ParseError, ValueError, AttributeError):
            continue
        parsed += 1
        kind = type(msg).__name__
        if kind not in ("RMC", "GGA") or msg.timestamp is None:
            continue
        tod = msg.timestamp.hour * 3600 + msg.timestamp.minute * 60 + msg.timestamp.second \
            + msg.timestamp.microsecond * 1e-6
        if kind == "RMC":
            if msg.status != "A":
                continue
            date = msg.datestamp or date
        elif not msg.gps_qual or not msg.lat:
            continue
        rec = fixes.setdefault(round(tod, 3), {"date": date})
        rec["lat"], rec["lon"] = float(msg.latitude), float(msg.longitude)
        if kind == "GGA" and msg.altitude is not None:
            rec["alt"] = float(msg.altitude)
        if kind == "RMC":
            rec["date"] = msg.datestamp
            if msg.true_course not in (None, ""):
                rec["heading"] = float(msg.true_course)
    if not parsed:
        raise SequenceError(path, "no NMEA sentences found (expected lines such as $GPRMC,… or $GPGGA,…)")
    absolute = date is not None
    rows, day, last = [], 0.0, None
    for tod in fixes:  # file order; a time of day going back means midnight passed
        rec = fixes[tod]
        if last is not None and tod < last - 43200:
            day += 86400.0
        last = tod
        d = rec.get("date") or date
        t = (_epoch(dt.datetime.combine(d, dt.time())) + tod if absolute and d is not None else day + tod)
        rows.append((t, rec["lat"], rec["lon"], rec.get("alt"), rec.get("heading")))
    return make_track(path, "nmea", rows, absolute=absolute)


def looks_like_nmea(path: Path) -> bool:
    try:
        with open(path, "rb") as fh:
            head = fh.read(4096).decode("ascii", "replace")
    except OSError:
        return False
    return bool(re.search(r"^\$[A-Z]{2}(RMC|GGA|GSA|GSV|VTG|GLL),", head, re.M))


# ---------------------------------------------------------------------------- CSV


def _column(cols: dict[str, str], names: tuple[str, ...]) -> str | None:
    for n in names:
        if n in cols:
            return cols[n]
    return None


def csv_has_gps(header: list[str]) -> bool:
    """True when a CSV header carries latitude and longitude columns."""
    cols = {h.strip().lower() for h in header}
    return any(n in cols for n in _LAT) and any(n in cols for n in _LON)


def _time_value(v: str) -> tuple[float, bool]:
    """Seconds and whether absolute: a number (absolute when past 1973) or an ISO 8601 date-time."""
    try:
        f = float(v)
        return f, f > 1e8
    except ValueError:
        t = dt.datetime.fromisoformat(v.strip().replace("Z", "+00:00"))
        return _epoch(t), True


def read_gps_csv(path: str | os.PathLike, per_frame: bool = False) -> GpsTrack:
    """``lat, lon[, alt][, heading]`` with ``timestamp``/``time`` (seconds or ISO 8601) or ``frame``.

    ``per_frame`` (the columns of a poses.csv): one fix per frame index (``frame`` column, else row
    order; rows of other cameras of the same frame are skipped). Rows with an empty lat/lon are skipped.
    """
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise SequenceError(path, "GPS file not found") from None
    reader = csv.DictReader(line for line in text.splitlines() if line.strip() and not line.startswith("#"))
    header = reader.fieldnames or []
    cols = {h.strip().lower(): h for h in header}
    lat_c, lon_c = _column(cols, _LAT), _column(cols, _LON)
    if lat_c is None or lon_c is None:
        raise SequenceError(path, f"needs 'lat' and 'lon' columns (degrees WGS84); got {header}")
    alt_c, head_c, time_c = _column(cols, _ALT), _column(cols, _HEADING), _column(cols, _TIME)
    frame_c = cols.get("frame")
    if not per_frame and time_c is None:
        raise SequenceError(path, "needs a 'timestamp' or 'time' column (seconds or ISO 8601) to match frames")
    rows, frames, absolute, seen = [], [], False, set()
    for i, r in enumerate(reader):
        line = i + 2
        if not (r.get(lat_c) or "").strip() or not (r.get(lon_c) or "").strip():
            continue
        try:
            t = None
            if time_c is not None and (r.get(time_c) or "").strip():
                t, absolute = _time_value(r[time_c])
            fr = int(r[frame_c]) if frame_c and (r.get(frame_c) or "").strip() else i

            def num(c: str | None, r: dict = r) -> float | None:
                return float(r[c]) if c and (r.get(c) or "").strip() else None

            vals = (t, float(r[lat_c]), float(r[lon_c]), num(alt_c), num(head_c))
        except ValueError as e:
            raise SequenceError(path, f"line {line}: bad value ({e})") from None
        if not all(v is None or math.isfinite(v) for v in vals):
            raise SequenceError(path, f"line {line}: non-finite GPS value")
        if per_frame:
            if fr in seen:
                continue
            seen.add(fr)
            frames.append(fr)
        rows.append(vals)
    return make_track(path, "csv", rows, absolute, frames if per_frame else None)


# ---------------------------------------------------------------------------- EXIF


def _dms(v: object) -> float:
    d, m, s = (float(x) for x in v)  # type: ignore[union-attr]
    return d + m / 60.0 + s / 3600.0


def exif_fix(path: str | os.PathLike) -> tuple | None:
    """``(t, lat, lon, alt, heading)`` from a JPEG's EXIF GPS IFD, or None when it has none."""
    from PIL import Image

    try:
        with Image.open(path) as im:
            exif = im.getexif()
            gps = exif.get_ifd(0x8825)
            when = exif.get_ifd(0x8769).get(0x9003) or exif.get(0x0132)  # DateTimeOriginal / DateTime
    except OSError as e:
        raise SequenceError(path, f"unreadable image ({e})") from None
    if not gps or 2 not in gps or 4 not in gps:
        return None
    try:
        lat = _dms(gps[2]) * (-1 if str(gps.get(1, "N")).upper().startswith("S") else 1)
        lon = _dms(gps[4]) * (-1 if str(gps.get(3, "E")).upper().startswith("W") else 1)
        alt = float(gps[6]) * (-1 if gps.get(5) in (1, b"\x01") else 1) if 6 in gps else None
        heading = float(gps[17]) if 17 in gps else None
        t = None
        if 29 in gps and 7 in gps:  # GPSDateStamp + GPSTimeStamp (UTC)
            h, m, s = (float(x) for x in gps[7])
            day = dt.datetime.strptime(str(gps[29]).strip(), "%Y:%m:%d")
            t = _epoch(day) + h * 3600 + m * 60 + s
        elif when:
            t = _epoch(dt.datetime.strptime(str(when).strip(), "%Y:%m:%d %H:%M:%S"))
    except (TypeError, ValueError, ZeroDivisionError) as e:
        raise SequenceError(path, f"malformed EXIF GPS tags ({e})") from None
    return (t, lat, lon, alt, heading)


def read_exif_gps(images: dict[int, Path], source: str | os.PathLike) -> GpsTrack:
    """Per-frame fixes from the EXIF GPS of ``{frame index: image path}`` (images without GPS skipped)."""
    rows, frames = [], []
    for fr in sorted(images):
        fix = exif_fix(images[fr])
        if fix is not None:
            rows.append(fix)
            frames.append(fr)
    if not rows:
        raise SequenceError(source, f"none of the {len(images)} images carries EXIF GPS tags")
    return make_track(source, "exif", rows, absolute=True, frames=frames)


# ---------------------------------------------------------------------------- KITTI raw OXTS


def oxts_folder(path: str | os.PathLike) -> Path:
    """The ``oxts`` folder of a KITTI raw drive given the drive folder, its ``oxts/`` or ``oxts/data``."""
    p = Path(path)
    for cand in (p, p / "oxts", p.parent):
        if (cand / "data").is_dir() and any((cand / "data").glob("*.txt")):
            return cand
    raise SequenceError(p, "not a KITTI raw OXTS folder (expected oxts/data/0000000000.txt …)")


def read_oxts(path: str | os.PathLike, first: int = 0, count: int | None = None) -> GpsTrack:
    """KITTI raw ``oxts/data/*.txt`` (lat, lon, alt, roll, pitch, yaw, …; yaw 0 = east, counter-clockwise).

    Fix ``k`` (file ``first + k``) belongs to frame ``k`` of the imported sequence's numbering.
    """
    folder = oxts_folder(path)
    files = sorted((folder / "data").glob("*.txt"))[first:]
    if count is not None:
        files = files[:count]
    if not files:
        raise SequenceError(folder / "data", f"no OXTS records from index {first}")
    stamps: list[str] = []
    ts_file = folder / "timestamps.txt"
    if ts_file.is_file():
        stamps = ts_file.read_text(encoding="utf-8").splitlines()[first:]
    rows, frames = [], []
    for k, f in enumerate(files):
        try:
            v = [float(x) for x in f.read_text(encoding="utf-8").split()]
        except ValueError:
            raise SequenceError(f, "expected 30 numbers (KITTI OXTS record)") from None
        if len(v) < 6:
            raise SequenceError(f, f"{len(v)} numbers; a KITTI OXTS record has 30")
        t = None
        if k < len(stamps) and stamps[k].strip():
            s = stamps[k].strip()
            base, _, frac = s.partition(".")
            t = _epoch(dt.datetime.strptime(base, "%Y-%m-%d %H:%M:%S")) + float(f"0.{frac or 0}")
        rows.append((t, v[0], v[1], v[2], 90.0 - math.degrees(v[5])))
        frames.append(int(f.stem) - first if f.stem.isdigit() else k)
    return make_track(folder, "oxts", rows, absolute=bool(stamps), frames=frames)


def _calib_rt(path: Path) -> np.ndarray:
    """(4, 4) from a KITTI raw calibration file's ``R:`` (9 numbers) and ``T:`` (3 numbers) lines."""
    vals: dict[str, list[float]] = {}
    for line in path.read_text(encoding="utf-8").splitlines():
        key, _, rest = line.partition(":")
        if key.strip() in ("R", "T"):
            try:
                vals[key.strip()] = [float(x) for x in rest.split()]
            except ValueError:
                raise SequenceError(path, f"line {key.strip()}: expected numbers") from None
    if len(vals.get("R", [])) != 9 or len(vals.get("T", [])) != 3:
        raise SequenceError(path, "expected an 'R:' line of 9 numbers and a 'T:' line of 3 (KITTI raw calibration)")
    T = np.eye(4)
    T[:3, :3] = np.reshape(vals["R"], (3, 3))
    T[:3, 3] = vals["T"]
    return T


#: KITTI camera frame (x right, y down, z forward) → pavemap world (x forward, y left, z up).
A_KITTI_TO_WORLD = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


def oxts_antenna_in_cam0(path: str | os.PathLike) -> np.ndarray | None:
    """(3,) the OXTS unit's position in KITTI cam0 coordinates (x right, y down, z forward; metres), from the
    raw date folder's ``calib_imu_to_velo.txt`` and ``calib_velo_to_cam.txt`` (the folder above the drive);
    None when they are not there. About 1.1 m behind, 0.3 m left of and 0.7 m below the camera in KITTI."""
    date_dir = oxts_folder(path).parent.parent
    imu_velo, velo_cam = date_dir / "calib_imu_to_velo.txt", date_dir / "calib_velo_to_cam.txt"
    if not (imu_velo.is_file() and velo_cam.is_file()):
        return None
    return (_calib_rt(velo_cam) @ _calib_rt(imu_velo))[:3, 3]


# ---------------------------------------------------------------------------- dispatch


def read_gps(path: str | os.PathLike) -> GpsTrack:
    """Any GPS file by suffix or content: ``.gpx``, NMEA (``.nmea``/``.log``/``.txt``), ``.csv``."""
    p = Path(path)
    if not p.is_file():
        raise SequenceError(p, "GPS file not found")
    suffix = p.suffix.lower()
    if suffix == ".gpx":
        return read_gpx(p)
    if suffix == ".csv":
        return read_gps_csv(p)
    if suffix in NMEA_SUFFIXES or looks_like_nmea(p):
        return read_nmea(p)
    raise SequenceError(p, "unknown GPS format; give a .gpx, an NMEA log (.nmea) or a .csv with lat, lon, time")


__all__ = ["GpsTrack", "csv_has_gps", "exif_fix", "make_track", "oxts_antenna_in_cam0", "oxts_folder",
           "read_exif_gps", "read_gps", "read_gps_csv", "read_gpx", "read_nmea", "read_oxts"]
