"""GPS inputs (issue 15): GPX, NMEA RMC/GGA, CSV columns, EXIF GPS, KITTI raw OXTS — written here as
fixtures in the real formats — read, matched to the frames and fitted into a geo origin on import."""

from __future__ import annotations

import datetime as dt
import json
import math
from functools import reduce

import numpy as np
import pytest
from PIL import Image
from scipy.spatial.transform import Rotation
from typer.testing import CliRunner

from pavemap.cli import app
from pavemap.errors import PavemapError, SequenceError
from pavemap.geo.attach import GeoInput, parse_geo_origin
from pavemap.geo.georef import position_error
from pavemap.geo.tangent import local_tangent
from pavemap.ingest.folder import import_folder
from pavemap.ingest.kitti import import_kitti
from pavemap.io.gps import exif_fix, read_gps, read_gpx, read_nmea, read_oxts
from pavemap.io.sequence import read_sequence
from pavemap.types import GeoOrigin

ERR = (PavemapError, SequenceError)
W, H = 48, 32
KMAT = [[40.0, 0, 23.5], [0, 40.0, 15.5], [0, 0, 1]]
TRUE = GeoOrigin(lat=52.52, lon=13.405, alt=34.0, heading_deg=70.0)
T0 = dt.datetime(2024, 5, 17, 9, 30, 0, tzinfo=dt.UTC).timestamp()
N = 30  # frames, 1 s apart, ~5 m apart on a bend: a 150 m drive


def _path(n: int = N) -> tuple[np.ndarray, np.ndarray]:
    """World positions (n, 3) and yaw (n,) of a car on a bend (camera 1.5 m up)."""
    yaw = np.linspace(0.0, 0.9, n)
    step = 5.0 * np.stack([np.cos(yaw), np.sin(yaw)], 1)
    xy = np.vstack([[0.0, 0.0], np.cumsum(step[:-1], 0)])
    return np.column_stack([xy, np.full(n, 1.5)]), yaw


def _lonlat(xyz: np.ndarray, origin: GeoOrigin = TRUE) -> tuple[np.ndarray, np.ndarray]:
    return local_tangent(origin).to_lonlat(xyz[:, 0], xyz[:, 1])


def _drive(tmp_path, n: int = N, gps_columns: bool = False, exif: bool = False, absolute: bool = True):
    """An own-drive folder: images, cameras.json, poses.csv (timestamps absolute or from 0)."""
    xyz, yaw = _path(n)
    lon, lat = _lonlat(xyz)
    imgs = tmp_path / "imgs"
    imgs.mkdir()
    head = "frame,timestamp,tx,ty,tz,qw,qx,qy,qz" + (",lat,lon,alt" if gps_columns else "")
    rows = [head]
    for k in range(n):
        im = Image.fromarray(np.full((H, W, 3), 40 + k, np.uint8))
        ex = Image.Exif()
        if exif:
            ex[0x8825] = _gps_ifd(float(lat[k]), float(lon[k]), TRUE.alt + 1.5, T0 + k)
        im.save(imgs / f"img_{k:03d}.jpg", exif=ex)
        R = Rotation.from_euler("z", yaw[k]).as_matrix() @ np.array([[0, 0, 1], [-1, 0, 0], [0, -1, 0]])
        x, y, z, w = Rotation.from_matrix(R).as_quat()
        t = (T0 if absolute else 0.0) + k
        extra = f",{lat[k]:.9f},{lon[k]:.9f},{TRUE.alt + 1.5}" if gps_columns else ""
        rows.append(f"{k},{t},{xyz[k, 0]},{xyz[k, 1]},{xyz[k, 2]},{w},{x},{y},{z}{extra}")
    (tmp_path / "poses.csv").write_text("\n".join(rows) + "\n")
    (tmp_path / "cameras.json").write_text(json.dumps({"front": {"width": W, "height": H, "K": KMAT}}))
    return imgs, tmp_path / "cameras.json", tmp_path / "poses.csv", xyz


def _dms(v: float) -> tuple:
    d = int(abs(v))
    m = int((abs(v) - d) * 60)
    return (float(d), float(m), round((abs(v) - d - m / 60) * 3600, 6))


def _gps_ifd(lat: float, lon: float, alt: float, t: float) -> dict:
    when = dt.datetime.fromtimestamp(t, dt.UTC)
    return {1: "N" if lat >= 0 else "S", 2: _dms(lat), 3: "E" if lon >= 0 else "W", 4: _dms(lon), 5: 0,
            6: alt, 7: (float(when.hour), float(when.minute), float(when.second)),
            29: when.strftime("%Y:%m:%d"), 16: "T", 17: 123.5}


def _nmea(body: str) -> str:
    return f"${body}*{reduce(lambda a, c: a ^ ord(c), body, 0):02X}"


def _ddm(v: float, lat: bool) -> str:
    d = int(abs(v))
    m = (abs(v) - d) * 60
    hemi = ("N" if v >= 0 else "S") if lat else ("E" if v >= 0 else "W")
    return (f"{d:02d}{m:07.4f}" if lat else f"{d:03d}{m:07.4f}") + "," + hemi


def write_nmea(path, t, lat, lon, alt) -> None:
    lines = ["garbage line", _nmea("GPRMC,092959.00,V,,,,,,,170524,,,N")]  # no fix yet: dropped
    for k in range(len(t)):
        w = dt.datetime.fromtimestamp(t[k], dt.UTC)
        hms = w.strftime("%H%M%S") + f".{w.microsecond // 10000:02d}"
        la, lo = _ddm(lat[k], True), _ddm(lon[k], False)
        lines.append(_nmea(f"GPRMC,{hms},A,{la},{lo},10.0,71.3,{w.strftime('%d%m%y')},,,A"))
        lines.append(_nmea(f"GPGGA,{hms},{la},{lo},1,08,0.9,{alt[k]:.1f},M,46.9,M,,"))
        lines.append(_nmea("GPGSV,1,1,04,01,40,083,46,02,17,308,41,12,07,344,39,14,22,228,45"))
    path.write_text("\r\n".join(lines) + "\r\n")


def write_gpx(path, t, lat, lon, alt) -> None:
    pts = "".join(f'<trkpt lat="{a:.9f}" lon="{b:.9f}"><ele>{e:.2f}</ele>'
                  f"<time>{dt.datetime.fromtimestamp(s, dt.UTC).strftime('%Y-%m-%dT%H:%M:%S.%fZ')}</time></trkpt>"
                  for s, a, b, e in zip(t, lat, lon, alt, strict=True))
    path.write_text('<?xml version="1.0" encoding="UTF-8"?><gpx version="1.1" creator="test" '
                    f'xmlns="http://www.topografix.com/GPX/1/1"><trk><trkseg>{pts}</trkseg></trk></gpx>')


def write_gps_csv(path, t, lat, lon, alt) -> None:
    """A separate GPS file: ``time`` in ISO 8601 (UTC), ``latitude``/``longitude``/``ele`` columns."""
    rows = ["time,latitude,longitude,ele"] + [
        f"{dt.datetime.fromtimestamp(s, dt.UTC).isoformat(timespec='milliseconds')},{a:.9f},{b:.9f},{e:.2f}"
        for s, a, b, e in zip(t, lat, lon, alt, strict=True)]
    path.write_text("\n".join(rows) + "\n")


WRITERS = {"gpx": write_gpx, "nmea": write_nmea, "csv": write_gps_csv}


def _fixes(xyz, hz: float = 1.0, shift: float = 0.3):
    """GPS fix times (absolute, off the frames' clock by ``shift`` s) and noise-free positions."""
    t = np.arange(shift, len(xyz) - 1, 1.0 / hz)
    p = np.stack([np.interp(t, np.arange(len(xyz)), xyz[:, k]) for k in range(3)], 1)
    lon, lat = _lonlat(p)
    return T0 + t, lat, lon, TRUE.alt + p[:, 2]


# ------------------------------------------------------------------ readers


def test_gpx_and_nmea_read_the_same_track(tmp_path):
    xyz, _ = _path()
    t, lat, lon, alt = _fixes(xyz)
    write_gpx(tmp_path / "a.gpx", t, lat, lon, alt)
    write_nmea(tmp_path / "a.nmea", t, lat, lon, alt)
    g, n = read_gpx(tmp_path / "a.gpx"), read_nmea(tmp_path / "a.nmea")
    assert g.absolute and n.absolute and len(g) == len(n) == len(t)
    np.testing.assert_allclose(g.t, t, atol=1e-3)
    np.testing.assert_allclose(n.t, t, atol=0.011)  # NMEA keeps hundredths of a second
    np.testing.assert_allclose(n.lat, lat, atol=2e-6)  # 4 decimals of a minute: ~0.2 m
    np.testing.assert_allclose(n.alt, alt, atol=0.06)
    assert np.allclose(n.heading, 71.3) and np.isnan(g.heading).all()
    assert read_gps(tmp_path / "a.nmea").kind == "nmea"


def test_exif_gps_of_a_jpeg(tmp_path):
    p = tmp_path / "x.jpg"
    ex = Image.Exif()
    ex[0x8825] = _gps_ifd(-33.8568, 151.2153, 12.5, T0)
    Image.new("RGB", (8, 8)).save(p, exif=ex)
    t, lat, lon, alt, heading = exif_fix(p)
    assert lat == pytest.approx(-33.8568, abs=1e-7) and lon == pytest.approx(151.2153, abs=1e-7)
    assert alt == pytest.approx(12.5) and heading == pytest.approx(123.5) and t == pytest.approx(T0)
    Image.new("RGB", (8, 8)).save(tmp_path / "none.jpg")
    assert exif_fix(tmp_path / "none.jpg") is None


def test_kitti_oxts_records(tmp_path):
    d = tmp_path / "2011_09_30_drive_0028_sync" / "oxts"
    (d / "data").mkdir(parents=True)
    stamps = []
    for k in range(5):
        rec = [49.0 + 1e-5 * k, 8.4, 110.0, 0.01, 0.02, math.radians(30.0)] + [0.0] * 24
        (d / "data" / f"{k:010d}.txt").write_text(" ".join(f"{v:.9f}" for v in rec) + "\n")
        stamps.append(f"2011-09-30 12:40:{10 + k:02d}.123456789")
    (d / "timestamps.txt").write_text("\n".join(stamps) + "\n")
    tr = read_oxts(d.parent, first=2)
    assert len(tr) == 3 and list(tr.frame) == [0, 1, 2] and tr.lat[0] == pytest.approx(49.00002)
    assert tr.heading[0] == pytest.approx(60.0)  # yaw 30 deg from east, counter-clockwise = 60 deg from north
    assert tr.absolute and tr.t[1] - tr.t[0] == pytest.approx(1.0)


# ------------------------------------------------------------------ importers


def _check(seq, xyz, tol):
    assert seq.geo_origin is not None and seq.geo_origin.georef["fixes"] >= 3
    err = position_error(TRUE, seq.geo_origin, xyz[:, :2])
    assert err.max() < tol, err.max()


def test_folder_import_with_gps_columns_in_poses_csv(tmp_path):
    imgs, cams, poses, xyz = _drive(tmp_path, gps_columns=True)
    seq = import_folder(imgs, cams, poses, tmp_path / "seq")
    _check(read_sequence(tmp_path / "seq"), xyz, 0.05)
    assert seq.geo_origin.alt == pytest.approx(TRUE.alt, abs=0.01)
    assert seq.geo_origin.heading_deg == pytest.approx(TRUE.heading_deg, abs=0.01)
    on_disk = json.loads((tmp_path / "seq" / "sequence.json").read_text())["geo_origin"]["georef"]
    assert on_disk["kind"] == "csv" and on_disk["rms_m"] < 0.05 and on_disk["inliers"] == N


@pytest.mark.parametrize("fmt", ["gpx", "nmea", "csv"])
def test_folder_import_with_a_gps_file_matched_by_time(tmp_path, fmt):
    imgs, cams, poses, xyz = _drive(tmp_path)
    t, lat, lon, alt = _fixes(xyz)
    gps = tmp_path / f"track.{fmt}"
    WRITERS[fmt](gps, t, lat, lon, alt)
    r = CliRunner().invoke(app, ["import", "folder", str(imgs), "--cameras", str(cams), "--poses", str(poses),
                                 "--gps", str(gps), "--no-semantics", "--out", str(tmp_path / "seq")])
    assert r.exit_code == 0, r.output
    assert "RMS" in r.output
    _check(read_sequence(tmp_path / "seq"), xyz, 0.5)
    rec = json.loads((tmp_path / "seq" / "sequence.json").read_text())["geo_origin"]["georef"]
    assert rec["kind"] == fmt and rec["fixes"] == len(t) and 0 <= rec["rms_m"] < 0.5  # the residual, on disk
    info = CliRunner().invoke(app, ["info", str(tmp_path / "seq")])  # the georeferencing record, not only lat/lon
    assert f"track.{fmt}" in info.output and "fixes, RMS" in info.output, info.output


def test_folder_import_relative_times_and_exif(tmp_path):
    imgs, cams, poses, xyz = _drive(tmp_path, exif=True, absolute=False)
    seq = import_folder(imgs, cams, poses, tmp_path / "seq", geo=GeoInput(gps="exif"))
    _check(seq, xyz, 0.3)  # EXIF keeps seconds of arc to 6 decimals
    # a GPX in absolute time with frames from 0: the first frame is taken at the first fix (warned)
    t, lat, lon, alt = _fixes(xyz, shift=0.0)
    write_gpx(tmp_path / "t.gpx", t, lat, lon, alt)
    seq = import_folder(imgs, cams, poses, tmp_path / "seq2", geo=GeoInput(gps=str(tmp_path / "t.gpx")))
    _check(seq, xyz, 0.5)
    assert "first fix" in " ".join(seq.geo_origin.georef["warnings"])


def _kitti(root, n: int = 12):
    """A KITTI odometry sequence 08 (grey camera 0, bare calib) driving 2 m per frame while turning."""
    s = root / "sequences" / "08"
    (s / "image_0").mkdir(parents=True)
    P = "60 0 47.5 0 0 60 19.5 0 0 0 1 0"
    (s / "calib.txt").write_text(f"{P}\n60 0 47.5 -32.4 0 60 19.5 0 0 0 1 0\n")
    rows = []
    for k in range(n):
        Image.fromarray(np.full((40, 96), 9 * k, np.uint8)).save(s / "image_0" / f"{k:06d}.png")
        a = -0.04 * k
        c, sn = math.cos(a), math.sin(a)
        z, x = 2.0 * sum(math.cos(0.04 * j) for j in range(k)), 2.0 * sum(math.sin(0.04 * j) for j in range(k))
        rows.append(f"{c} 0 {sn} {x} 0 1 0 0 {-sn} 0 {c} {z}")
    (s / "poses.txt").write_text("\n".join(rows) + "\n")
    return s


def test_kitti_import_with_oxts(tmp_path):
    _kitti(tmp_path / "odo")
    seq = import_kitti(tmp_path / "odo", "08", tmp_path / "tmp_seq", camera=0, lidar=False)
    xyz = seq.trajectory()
    lon, lat = _lonlat(xyz)
    oxts = tmp_path / "raw" / "2011_09_30_drive_0028_sync" / "oxts"
    (oxts / "data").mkdir(parents=True)
    for k in range(1100 + len(xyz)):  # odometry 08 starts at raw record 1100 (the devkit's table)
        j = k - 1100
        rec = [lat[j], lon[j], 200.0 + xyz[j, 2], 0, 0, 0] + [0.0] * 24 if j >= 0 else [0.0] * 30
        (oxts / "data" / f"{k:010d}.txt").write_text(" ".join(f"{v:.10f}" for v in rec))
    args = ["import", "kitti", str(tmp_path / "odo"), "--sequence", "08", "--camera", "0", "--no-lidar",
            "--no-semantics", "--oxts", str(oxts.parent), "--out", str(tmp_path / "seq")]
    r = CliRunner().invoke(app, args)  # 08 has 4071 frames in the devkit: this one is another drive
    assert r.exit_code == 2 and "--oxts-first" in r.output and "4071" in r.output
    left = [p.name for p in (tmp_path / "seq").rglob("*") if p.is_file()]
    assert left in ([], [".pavemap-owner.json"]), left  # the images copied before the check are gone again
    r = CliRunner().invoke(app, [*args, "--oxts-first", "1100"])
    assert r.exit_code == 0, r.output
    s = read_sequence(tmp_path / "seq")
    _check(s, xyz, 0.05)
    assert s.geo_origin.alt == pytest.approx(200.0, abs=0.01) and s.geo_origin.georef["kind"] == "oxts"


# ------------------------------------------------------------------ bad input


def test_bad_gps_inputs_name_the_file_and_the_problem(tmp_path):
    imgs, cams, poses, xyz = _drive(tmp_path)
    t, lat, lon, alt = _fixes(xyz)

    def imp(gps: str, out: str, **kw):
        return import_folder(imgs, cams, poses, tmp_path / out, geo=GeoInput(gps=gps, **kw))

    write_gpx(tmp_path / "two.gpx", t[:2], lat[:2], lon[:2], alt[:2])
    with pytest.raises(ERR, match=r"two\.gpx: 2 GPS fix\(es\); .* at least 3"):
        imp(str(tmp_path / "two.gpx"), "s1")
    assert not (tmp_path / "s1").exists() or not any((tmp_path / "s1").rglob("*.*"))  # nothing copied
    write_gpx(tmp_path / "late.gpx", t + 3600, lat, lon, alt)
    with pytest.raises(ERR, match=r"late\.gpx: the GPS fixes .* do not overlap the frames"):
        imp(str(tmp_path / "late.gpx"), "s2")
    # the same shape 30 times larger (km instead of the drive's 150 m)
    big = local_tangent(TRUE)
    bx, by = big.from_lonlat(lon, lat)
    blon, blat = big.to_lonlat(30 * bx, 30 * by)
    write_gpx(tmp_path / "big.gpx", t, blat, blon, alt)
    with pytest.raises(ERR, match=r"big\.gpx: the GPS track spans .* but the drive spans"):
        imp(str(tmp_path / "big.gpx"), "s3")
    with pytest.raises(ERR, match=r"nope\.gpx: GPS file not found"):
        imp(str(tmp_path / "nope.gpx"), "s4")
    (tmp_path / "junk.nmea").write_text("hello\n")
    with pytest.raises(ERR, match=r"junk\.nmea: no NMEA sentences"):
        imp(str(tmp_path / "junk.nmea"), "s5")
    for s in ("s1", "s2", "s3", "s4", "s5"):  # nothing claims a position it does not have
        assert not (tmp_path / s / "sequence.json").exists()


def _standing(poses) -> None:
    """Rewrite a poses.csv so that the vehicle stands at the world origin (tx = ty = 0) in every frame."""
    text = poses.read_text().splitlines()
    cols = text[0].split(",")
    still = [",".join("0.0" if c in ("tx", "ty") else v for c, v in zip(cols, r.split(","), strict=True))
             for r in text[1:]]
    poses.write_text("\n".join([text[0], *still]) + "\n")


def _bad_track(tmp_path, case: str):  # noqa: ANN202
    """A drive and a GPS input that does not fit it: (imgs, cameras, poses, GPS file, words of the message)."""
    imgs, cams, poses, xyz = _drive(tmp_path, gps_columns=case == "standing-columns")
    t, lat, lon, alt = _fixes(xyz)
    gps = tmp_path / f"{case}.gpx"
    if case == "two-fixes":
        t, lat, lon, alt, words = t[:2], lat[:2], lon[:2], alt[:2], ["2 GPS fix(es)", "at least 3"]
    elif case == "no-overlap":  # an hour later than the frames
        t, words = t + 3600, ["do not overlap the frames", "--gps-offset"]
    elif case == "5-km-track":  # the drive's shape, 5 km across instead of its 140 m
        lt = local_tangent(TRUE)
        x, y = lt.from_lonlat(lon, lat)
        k = 5000.0 / math.hypot(np.ptp(x), np.ptp(y))
        lon, lat = lt.to_lonlat(k * x, k * y)
        words = ["the GPS track spans", "but the drive spans", "not this drive's track"]
    else:  # the vehicle stands still while the GPS moves (a file, or the poses.csv's own lat/lon columns)
        _standing(poses)
        words = ["spans only 0.0 m", "standing vehicle", "--geo-origin"]
        if case == "standing-columns":
            return imgs, cams, poses, poses, words
    write_gpx(gps, t, lat, lon, alt)
    return imgs, cams, poses, gps, words


@pytest.mark.parametrize("case", ["two-fixes", "no-overlap", "5-km-track", "standing", "standing-columns"])
def test_bad_gps_on_the_command_line(tmp_path, case):
    """One line naming the GPS file and the problem, exit status 2, no traceback; no image copied and no
    sequence.json (nothing claims a position); `import gps` leaves an existing sequence.json as it was."""
    from fuzz_support import check, invoke
    from pavemap.io.owned import MARKER

    imgs, cams, poses, gps, words = _bad_track(tmp_path, case)
    out = tmp_path / "seq"
    r = invoke("import", "folder", imgs, "--cameras", cams, "--poses", poses, "--no-semantics", "--out", out,
               *(["--gps", gps] if gps != poses else []))
    check(r, 2, f"error: {gps}: ", *words)
    assert len(r.output.strip().splitlines()) == 1, r.output
    assert sorted(p.relative_to(out).as_posix() for p in out.rglob("*") if p.name != MARKER) == []
    if gps == poses:
        return
    import_folder(imgs, cams, poses, tmp_path / "plain")  # without GPS: no geo origin
    before = (tmp_path / "plain" / "sequence.json").read_bytes()
    check(invoke("import", "gps", tmp_path / "plain", "--gps", gps), 2, f"error: {gps}: ", *words)
    assert (tmp_path / "plain" / "sequence.json").read_bytes() == before


def test_standing_vehicle_and_hand_origin(tmp_path):
    imgs, cams, poses, xyz = _drive(tmp_path)
    _standing(poses)
    t, lat, lon, alt = _fixes(xyz)
    write_gpx(tmp_path / "t.gpx", t, lat, lon, alt)
    with pytest.raises(ERR, match=r"t\.gpx: the drive 'imgs' spans only 0\.0 m .* standing vehicle"):
        import_folder(imgs, cams, poses, tmp_path / "s", geo=GeoInput(gps=str(tmp_path / "t.gpx")))
    seq = import_folder(imgs, cams, poses, tmp_path / "s", geo=GeoInput(origin="52.52,13.405,34,70"))
    assert seq.geo_origin.heading_deg == 70.0 and seq.geo_origin.georef["source"].startswith("--geo-origin")
    with pytest.raises(ERR, match=r"--geo-origin '52\.5,200': lon must be in \[-180, 180\]"):
        parse_geo_origin("52.5,200")
    with pytest.raises(ERR, match="LAT,LON"):
        parse_geo_origin("north")
    r = CliRunner().invoke(app, ["import", "gps", str(tmp_path / "s"), "--geo-origin", "1,2,3", "--gps",
                                 str(tmp_path / "t.gpx")])
    assert r.exit_code == 2 and "not both" in r.output


def test_video_import_with_gps(tmp_path):
    from pavemap.ingest.video import import_video
    from test_import_folder import _write_video

    _write_video(tmp_path / "drive.avi", n=60, fps=15.0)  # 4 s
    (tmp_path / "cameras.json").write_text(json.dumps({"front": {"width": W, "height": H, "K": KMAT}}))
    yaw = np.linspace(0, 0.5, 5)
    xyz = np.column_stack([np.cumsum(np.r_[0, 8 * np.cos(yaw[:-1])]), np.cumsum(np.r_[0, 8 * np.sin(yaw[:-1])]),
                           np.full(5, 1.4)])
    rows = ["timestamp,tx,ty,tz,qw,qx,qy,qz"]
    for t in range(5):
        R = Rotation.from_euler("z", yaw[t]).as_matrix() @ np.array([[0, 0, 1], [-1, 0, 0], [0, -1, 0]])
        x, y, z, w = Rotation.from_matrix(R).as_quat()
        rows.append(f"{t},{xyz[t, 0]},{xyz[t, 1]},{xyz[t, 2]},{w},{x},{y},{z}")
    (tmp_path / "poses.csv").write_text("\n".join(rows) + "\n")
    tt = np.arange(0, 4.01, 0.5)  # a 2 Hz receiver, its first fix at the first frame
    p = np.stack([np.interp(tt, np.arange(5), xyz[:, k]) for k in range(3)], 1)
    lon, lat = _lonlat(p)
    write_nmea(tmp_path / "drive.nmea", T0 + tt, lat, lon, TRUE.alt + p[:, 2])
    seq = import_video(tmp_path / "drive.avi", tmp_path / "cameras.json", tmp_path / "poses.csv", tmp_path / "seq",
                       fps=5.0, geo=GeoInput(gps=str(tmp_path / "drive.nmea")))
    _check(seq, xyz, 0.3)
    assert "first fix" in " ".join(seq.geo_origin.georef["warnings"])


def test_oxts_lever_arm_from_the_raw_calibration(tmp_path):
    """KITTI's calibration puts the OXTS unit about 1.08 m behind, 0.32 m left of and 0.72 m below cam0."""
    from pavemap.io.gps import oxts_antenna_in_cam0
    from pavemap.io.kitti import A_KITTI_TO_WORLD

    date = tmp_path / "2011_09_26"
    (date / "2011_09_26_drive_0001_sync" / "oxts" / "data").mkdir(parents=True)
    (date / "2011_09_26_drive_0001_sync" / "oxts" / "data" / "0000000000.txt").write_text("0 " * 30)
    assert oxts_antenna_in_cam0(date / "2011_09_26_drive_0001_sync") is None  # no calibration: unknown
    (date / "calib_imu_to_velo.txt").write_text(
        "calib_time: 25-May-2012 16:47:16\nR: 9.999976e-01 7.553071e-04 -2.035826e-03 -7.854027e-04 9.998898e-01 "
        "-1.482298e-02 2.024406e-03 1.482454e-02 9.998881e-01\nT: -8.086759e-01 3.195559e-01 -7.997231e-01\n")
    (date / "calib_velo_to_cam.txt").write_text(
        "calib_time: 15-Mar-2012 11:37:16\nR: 7.533745e-03 -9.999714e-01 -6.166020e-04 1.480249e-02 7.280733e-04 "
        "-9.998902e-01 9.998621e-01 7.523790e-03 1.480755e-02\nT: -4.069766e-03 -7.631618e-02 -2.717806e-01\n"
        "delta_f: 0 0\ndelta_c: 0 0\n")
    lever = A_KITTI_TO_WORLD @ oxts_antenna_in_cam0(date / "2011_09_26_drive_0001_sync")
    assert lever == pytest.approx([-1.08, 0.32, -0.72], abs=0.02)
    (date / "calib_imu_to_velo.txt").write_text("R: 1 0 0\nT: 0 0 0\n")
    with pytest.raises(SequenceError, match="calib_imu_to_velo.txt"):
        oxts_antenna_in_cam0(date / "2011_09_26_drive_0001_sync")
