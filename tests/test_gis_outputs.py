"""GIS outputs (issue 15), opened with real GDAL: `ogrinfo` / `gdalinfo` (Debian's gdal-bin) where
installed, and always through pyogrio / rasterio (GDAL in their wheels).

A georeferenced run: survey.gpkg (defects MultiPolygon only, defect_points, trajectory LineString ZM
with frame times, survey), defects.fgb, KML/KMZ, a COG GeoTIFF in the UTM zone with nodata. A run
without a geo origin: no layer that GDAL reads as EPSG:4326.
"""

from __future__ import annotations

import json
import shutil
import struct
import subprocess
import sys
from pathlib import Path

import numpy as np
import pyogrio
import pytest
import rasterio
import shapely
from pyproj import CRS
from typer.testing import CliRunner

from pavemap.cli import app
from pavemap.errors import PavemapError
from pavemap.export.geojson import PROPERTY_SCHEMA
from pavemap.export.geotiff import NODATA
from pavemap.export.report import build_report_html
from pavemap.export.sample import sample_inputs
from pavemap.geo.crs import utm_epsg
from pavemap.pipeline import RunResult
from qgis_support import SURVEY, check_styles

OGRINFO = shutil.which("ogrinfo")
GDALINFO = shutil.which("gdalinfo")


def _fuse(seq, out, *args):
    r = CliRunner().invoke(app, ["fuse", str(seq), "--surface", "truth", "-o", str(out), *args])
    assert r.exit_code == 0, r.output
    return out


def _ogrinfo(path, *layer) -> str:
    if OGRINFO is None:
        return ""
    args = [str(path), *layer] if layer else ["-al", str(path)]  # one layer's summary, or all layers'
    r = subprocess.run([OGRINFO, "-ro", "-so", *args], capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    assert "partially supported" not in r.stderr  # GeoPackage version GDAL 3.6 reads fully
    return r.stdout


def _gpkg_wkb(path, table: str) -> bytes:
    """The WKB of a GeoPackage table's first geometry (GeoPackage binary: GP header, envelope, WKB)."""
    import sqlite3

    with sqlite3.connect(path) as db:
        (blob,) = db.execute(f"SELECT geom FROM {table}").fetchone()
    assert blob[:2] == b"GP"
    envelope = {0: 0, 1: 32, 2: 48, 3: 48, 4: 64}[(blob[3] >> 1) & 7]
    return bytes(blob[8 + envelope:])


def _crs(path, layer=None) -> CRS | None:
    info = pyogrio.read_info(path, layer=layer)
    return CRS.from_user_input(info["crs"]) if info["crs"] else None


@pytest.fixture(scope="module")
def geo_run(tiny_seq, tmp_path_factory):
    out = tmp_path_factory.mktemp("gis") / "run"
    return _fuse(tiny_seq.root, out, "--set", "output.extra_formats=fgb,kml,kmz", "--set", "output.vehicle=VAN-7")


@pytest.fixture(scope="module")
def local_run(tiny_seq, tmp_path_factory):
    base = tmp_path_factory.mktemp("gis_local")
    seq = base / "seq"
    shutil.copytree(tiny_seq.root, seq)
    d = json.loads((seq / "sequence.json").read_text())
    d["geo_origin"] = None
    (seq / "sequence.json").write_text(json.dumps(d))
    return seq, _fuse(seq, base / "run", "--set", "output.extra_formats=fgb,kml")


@pytest.mark.filterwarnings("ignore:Measured \\(M\\) geometry types")
def test_georeferenced_gpkg_layers(geo_run, tiny_seq):
    gpkg = geo_run / "survey.gpkg"
    layers = {name: kind for name, kind in pyogrio.list_layers(gpkg)}
    assert layers["defects"] == "MultiPolygon" and layers["defect_points"] == "Point"
    assert layers["baseline_defects"] == "MultiPolygon" and "trajectory" in layers and "survey" in layers
    assert layers["segments"] == "MultiPolygon" and {"segment", "pci", "grade"} <= set(
        pyogrio.read_info(gpkg, layer="segments")["fields"])
    o = tiny_seq.geo_origin
    epsg = utm_epsg(o.lon, o.lat)
    assert layers.pop("layer_styles") is None  # the QGIS styles: a table without geometry or CRS
    check_styles(gpkg, SURVEY)  # one default style per user-facing layer, in the report's colours
    for layer in layers:
        assert _crs(gpkg, layer).to_epsg() == epsg, layer
    _, _, geoms, _ = pyogrio.raw.read(gpkg, layer="defects")
    assert len(geoms) > 0 and {shapely.from_wkb(g).geom_type for g in geoms} == {"MultiPolygon"}
    info = pyogrio.read_info(gpkg, layer="defects")
    assert {"id", "code", "priority", "priority_rank", "severity_level", "paper_severity", "area_m2", "lon", "lat",
            "x_m", "y_m"} <= set(info["fields"])
    # the trajectory: one LineString ZM whose M values are the frame timestamps
    wkb = _gpkg_wkb(gpkg, "trajectory")  # pyogrio drops M on reading: the GeoPackage blob itself
    kind, n = struct.unpack_from("<II", wkb, 1)
    pts = np.frombuffer(wkb, "<f8", offset=9, count=4 * n).reshape(n, 4)
    assert kind == 3002 and n == len(tiny_seq.frames)
    np.testing.assert_allclose(pts[:, 3], [f.timestamp for f in tiny_seq.frames])
    assert abs(pts[0, 2] - (o.alt + tiny_seq.trajectory()[0, 2])) < 1e-6
    meta, _, (area,), values = pyogrio.raw.read(gpkg, layer="survey")
    rec = {k: v[0] for k, v in zip(meta["fields"], values, strict=True)}
    assert rec["vehicle"] == "VAN-7" and rec["software"].startswith("pavemap ") and rec["georeferenced"] == 1
    assert rec["crs"].startswith(f"EPSG:{epsg}") and rec["origin_lat"] == pytest.approx(o.lat)
    assert shapely.from_wkb(area).area > 100.0  # the surveyed area, m²
    text = _ogrinfo(gpkg)
    if OGRINFO:
        assert "defects (Multi Polygon)" in text or "Geometry: Multi Polygon" in text
        assert "3D Measured Line String" in text and f'ID["EPSG",{epsg}]' in text


def test_every_defect_layer_has_the_one_schema(geo_run, local_run):
    """defects, defect_points, baseline_defects, defects.fgb and defects.csv: exactly the fields of
    PROPERTY_SCHEMA (lon/lat only with a geo origin), layers in its order; `pavemap run` writes the same
    (tests/test_run_outputs.py), the register's observations too (tests/test_network.py)."""
    for run, geo in ((geo_run, True), (local_run[1], False)):
        want = [n for n, *_ in PROPERTY_SCHEMA if geo or n not in ("lon", "lat")]
        layers = [(run / "survey.gpkg", n) for n in ("defects", "defect_points", "baseline_defects")]
        for path, layer in [*layers, (run / "defects.fgb", None)]:
            assert list(pyogrio.read_info(path, layer=layer)["fields"]) == want, (path, layer)
        assert sorted((run / "defects.csv").read_text().splitlines()[0].split(",")) == sorted(want)


def test_georeferenced_raster_is_a_utm_cog_with_nodata(geo_run, tiny_seq):
    tif = geo_run / "defect_map.tif"
    o = tiny_seq.geo_origin
    with rasterio.open(tif) as ds:
        assert ds.crs.to_epsg() == utm_epsg(o.lon, o.lat) and ds.nodata == NODATA
        a = ds.read(1)
        assert (a == NODATA).mean() > 0.2 and (a != NODATA).any()  # outside the surveyed area: nodata
        assert ((a[a != NODATA] >= 0) & (a[a != NODATA] <= 1)).all()
        assert ds.overviews(1) or min(ds.width, ds.height) < 512
    cogeo = pytest.importorskip("rio_cogeo.cogeo")
    valid, errors, _ = cogeo.cog_validate(str(tif))
    assert valid, errors
    rio = shutil.which("rio", path=str(Path(sys.executable).parent)) or shutil.which("rio")
    if rio:  # the command line a GIS person runs
        r = subprocess.run([rio, "cogeo", "validate", str(tif)], capture_output=True, text=True, timeout=60)
        assert r.returncode == 0 and "is a valid cloud optimized GeoTIFF" in r.stdout, r.stdout + r.stderr
    if GDALINFO:
        out = subprocess.run([GDALINFO, str(tif)], capture_output=True, text=True, timeout=60).stdout
        assert "LAYOUT=COG" in out and "NoData Value=-9999" in out and "UTM zone" in out


def test_georeferenced_geojson_fgb_kml(geo_run):
    assert _crs(geo_run / "defects.geojson").to_epsg() == 4326  # RFC 7946: lon/lat, correctly
    fc = json.loads((geo_run / "defects.geojson").read_text())
    lon, lat = fc["features"][0]["properties"]["lon"], fc["features"][0]["properties"]["lat"]
    assert 8.0 < lon < 9.0 and 48.5 < lat < 49.5  # the kitti-like world is in Karlsruhe
    assert _crs(geo_run / "defects.fgb").is_projected
    assert pyogrio.read_info(geo_run / "defects.fgb")["geometry_type"] == "MultiPolygon"
    for kml in ("survey.kml", "survey.kmz"):
        names = [n for n, _ in pyogrio.list_layers(geo_run / kml)]
        assert names == ["defects", "trajectory"], names
        assert _crs(geo_run / kml, "defects").to_epsg() == 4326
        assert pyogrio.read_info(geo_run / kml, layer="defects")["features"] == len(fc["features"])
    header = (geo_run / "defects.csv").read_text().splitlines()[0].split(",")
    assert "lon" in header and "lat" in header


def assert_no_wgs84_layer(folder) -> list[str]:
    """Every layer file under ``folder`` (GeoPackage, FlatGeobuf, GeoTIFF: each layer) is in the local engineering
    CRS, read back by GDAL (pyogrio / rasterio, and ogrinfo / gdalinfo where installed); no GeoJSON or KML
    (WGS84 by definition) exists. Returns the files checked."""
    assert not list(folder.rglob("*.geojson")) and not list(folder.rglob("*.km[lz]"))
    checked = []
    for path in sorted([*folder.rglob("*.gpkg"), *folder.rglob("*.fgb")]):
        for layer in [n for n, k in pyogrio.list_layers(path) if k is not None] if path.suffix == ".gpkg" else [None]:
            crs = _crs(path, layer)
            assert crs is not None and not crs.is_geographic and crs.to_epsg() != 4326, (path, layer)
            assert "pavemap local world frame" in crs.to_wkt(), (path, layer)
            text = _ogrinfo(path, *([layer] if layer else []))
            assert 'ID["EPSG",4326]' not in text and "WGS 84" not in text, (path, layer)
            assert not OGRINFO or 'ENGCRS["pavemap local world frame' in text, text  # ogrinfo printed its CRS
        checked.append(path.name)
    for path in sorted(folder.rglob("*.tif")):
        with rasterio.open(path) as ds:
            assert not ds.crs.is_geographic and "pavemap local world frame" in ds.crs.to_wkt(), path
        if GDALINFO:
            text = subprocess.run([GDALINFO, str(path)], capture_output=True, text=True, timeout=60).stdout
            assert "pavemap local world frame" in text and "WGS 84" not in text, path
        checked.append(path.name)
    return checked


@pytest.mark.filterwarnings("ignore:Measured \\(M\\) geometry types")
def test_run_without_geo_origin_has_no_wgs84_layer(local_run, tmp_path):
    seq, run = local_run
    assert {"survey.gpkg", "defects.fgb", "defect_map.tif"} <= set(assert_no_wgs84_layer(run))
    # eval and compare still read the run (from survey.gpkg)
    r = CliRunner().invoke(app, ["eval", str(run), "--truth", str(seq)])
    assert r.exit_code == 0, r.output
    assert json.loads((run / "eval.json").read_text())["precision"] > 0.5
    r = CliRunner().invoke(app, ["compare", str(run), str(run), "-o", str(tmp_path / "cmp")])
    assert r.exit_code == 0, r.output
    assert json.loads((tmp_path / "cmp" / "changes.json").read_text())["counts"]["unchanged"] > 0
    assert assert_no_wgs84_layer(tmp_path / "cmp") == ["changes.gpkg"]  # compare's layer: local too


def test_crs_option(tiny_seq, local_run, tmp_path):
    out = _fuse(tiny_seq.root, tmp_path / "etrs", "--crs", "EPSG:25832")
    with rasterio.open(out / "defect_map.tif") as ds:
        assert ds.crs.to_epsg() == 25832
    assert _crs(out / "survey.gpkg", "defects").to_epsg() == 25832


@pytest.mark.parametrize("command", ["fuse", "run"])
@pytest.mark.parametrize("code", ["EPSG:999999", "EPSG:4326"])
def test_a_crs_that_does_not_exist_or_is_not_projected_stops_before_anything_is_written(tiny_seq, tmp_path, command,
                                                                                         code):
    from fuzz_support import check, invoke

    args = ["--surface", "truth"] if command == "fuse" else ["--epochs", "1"]
    r = invoke(command, tiny_seq.root, *args, "-o", tmp_path / "x", "--crs", code)
    check(r, 2, code, "is not a projected CRS" if code == "EPSG:4326" else "not a coordinate reference system")
    assert [x for x in r.output.splitlines() if x.startswith("error:")] == [r.output.splitlines()[-1]]
    assert not (tmp_path / "x").exists()  # no folder, no layer, nothing claims a position


@pytest.mark.parametrize("command", ["fuse", "run"])
def test_a_projected_crs_without_a_geo_origin_stops_before_anything_is_written(local_run, tmp_path, command):
    from fuzz_support import check, invoke

    args = ["--surface", "truth"] if command == "fuse" else ["--epochs", "1"]
    check(invoke(command, local_run[0], *args, "-o", tmp_path / "y", "--crs", "EPSG:25832"), 2,
          "--crs EPSG:25832", "no geo origin")
    assert not (tmp_path / "y").exists()


def test_run_result_geojson_and_dataframe():
    kw = sample_inputs(4, seed=2, geo=True)
    res = RunResult(out_dir=None, defects=kw["instances"], prob_map=kw["prob_map"], class_maps=kw["class_maps"],
                    grid=kw["grid"], metrics={}, geo_origin=kw["geo_origin"])
    fc = res.to_geojson()
    assert fc["pavemap"]["coordinates"] == "lonlat" and len(fc["features"]) == 4
    gpd = pytest.importorskip("geopandas")
    df = res.to_dataframe()
    assert isinstance(df, gpd.GeoDataFrame) and df.crs.to_epsg() == 4326 and len(df) == 4
    assert df.geometry.iloc[0].geom_type == "MultiPolygon" and {"lon", "lat"} <= set(df.columns)
    utm = res.to_dataframe(crs="auto")
    assert utm.crs.is_projected and utm.geometry.area.sum() == pytest.approx(
        sum(d.polygon.area for d in res.defects), rel=0.01)
    res.geo_origin = None
    with pytest.raises(PavemapError, match="no geo origin: GeoJSON is WGS84"):
        res.to_geojson()
    assert "pavemap local world frame" in res.to_dataframe().crs.to_wkt()


def test_report_shows_lat_lon_next_to_the_class():
    kw = sample_inputs(3, seed=1, geo=True)
    html = build_report_html(kw["instances"], geo_origin=kw["geo_origin"])
    worklist, _, rest = html.partition('<table id="worklist-table">')[2].partition("</table>")

    def keys(table: str) -> list[str]:
        return [h.split('"', 1)[0] for h in table.split('<th data-key="')[1:]]

    # the work list (first screen): lat, lon within the first columns, before the photo
    wl = keys(worklist)
    assert "latlon" in wl and wl.index("latlon") < wl.index("photo") and wl.index("latlon") <= 7, wl
    # the full table: lat / lon right after class and urgency (chainage, when known, between)
    full = [k for k in keys(rest) if k != "chainage_m"]
    assert full[:5] == ["id", "code", "priority", "lat", "lon"], full


def test_survey_record_of_a_georeferenced_drive_with_absolute_times():
    """The survey layer's record: date (from absolute frame times), vehicle, cameras, software, CRS and the
    georeferencing residual; the trajectory's start and end as UTC times."""
    import datetime as dt

    from pavemap import __version__
    from pavemap.export.gis import _Projector, survey_record, trajectory_layer
    from pavemap.types import GeoOrigin
    from test_georef import _seq

    seq = _seq(length_m=50.0)
    t0 = dt.datetime(2025, 3, 4, 23, 59, 58, tzinfo=dt.UTC).timestamp()
    for f in seq.frames:
        f.timestamp += t0
    origin = GeoOrigin(48.1, 11.5, 520.0, 30.0, georef={"source": "/x/drive.nmea", "fixes": 9, "inliers": 8,
                                                        "rms_m": 2.345, "scale_applied": 1.0, "warnings": ["w"]})
    crs = CRS.from_epsg(utm_epsg(origin.lon, origin.lat))
    rec = survey_record(seq, origin, crs, 4, vehicle="VAN-7")
    assert rec["date"] == "2025-03-04" and rec["vehicle"] == "VAN-7" and rec["cameras"] == "front 64x48"
    assert rec["software"] == f"pavemap {__version__}" and rec["crs"].startswith("EPSG:32632")
    assert rec["georef_rms_m"] == 2.345 and (rec["georef_fixes"], rec["georef_inliers"]) == (9, 8)
    assert rec["georef_source"] == "/x/drive.nmea" and rec["georef_warnings"] == "w" and rec["defects"] == 4
    _, fields = trajectory_layer(seq, _Projector(origin, crs), origin)
    assert fields["start_time"].startswith("2025-03-04T23:59:58") and fields["end_time"].startswith("2025-03-05")
    assert "Unix time" in fields["m_values"] and fields["length_m"] == pytest.approx(50.0, rel=0.02)
    plain = survey_record(seq, None, crs, 0)
    assert plain["georeferenced"] is False and np.isnan(plain["origin_lat"]) and np.isnan(plain["georef_rms_m"])
