"""Export layer: geo conversion, GeoJSON, GeoTIFF, CSV, figures, report, write_outputs."""

from __future__ import annotations

import csv
import json
import re

import numpy as np
import pytest
import rasterio
from pyproj import CRS, Geod, Transformer
from shapely.geometry import Polygon, box, shape

from pavemap.errors import PavemapError
from pavemap.export import read_geojson, to_dataframe, write_outputs
from pavemap.export.geojson import instances_to_geojson, write_geojson
from pavemap.export.geotiff import BAND_DESCRIPTIONS, write_geotiff
from pavemap.export.report import build_report_html
from pavemap.export.sample import sample_inputs
from pavemap.export.tables import columns, write_csv
from pavemap.geo.tangent import local_tangent
from pavemap.geometry.grid import GridSpec
from pavemap.types import DefectInstance, GeoOrigin

GEOD = Geod(ellps="WGS84")
ORIGIN = GeoOrigin(lat=48.1374, lon=11.5755, alt=520.0, heading_deg=90.0)


def inst(i: int, poly, cls: int = 0, prio: str = "schedule") -> DefectInstance:
    return DefectInstance(id=i, cls=cls, polygon=poly, severity_mean=0.2 + 0.1 * cls, severity_max=0.5,
                          confidence=0.6, observations=3, probability=0.55, area_m2=float(poly.area),
                          length_m=1.0, centroid=(0.0, 0.0) if poly.is_empty else (poly.centroid.x, poly.centroid.y),
                          priority=prio)


# ------------------------------------------------------------------ geo
@pytest.mark.parametrize("heading, azimuth", [(90.0, 90.0), (0.0, 0.0), (30.0, 30.0), (200.0, -160.0)])
def test_world_x_follows_heading(heading, azimuth):
    lt = local_tangent(GeoOrigin(ORIGIN.lat, ORIGIN.lon, heading_deg=heading))
    lon, lat = lt.to_lonlat(np.array([100.0]), np.array([0.0]))
    az, _, dist = GEOD.inv(ORIGIN.lon, ORIGIN.lat, lon[0], lat[0])
    assert dist == pytest.approx(100.0, abs=1e-3)
    assert az == pytest.approx(azimuth, abs=1e-3)


def test_world_y_is_left_of_x():
    # heading 90 (x east): +y must point north (right-handed, z up)
    lt = local_tangent(ORIGIN)
    lon, lat = lt.to_lonlat(np.array([0.0]), np.array([50.0]))
    az, _, dist = GEOD.inv(ORIGIN.lon, ORIGIN.lat, lon[0], lat[0])
    assert dist == pytest.approx(50.0, abs=1e-3) and az == pytest.approx(0.0, abs=1e-3)


def test_roundtrip_below_a_millimetre():
    lt = local_tangent(GeoOrigin(-33.86, 151.2, heading_deg=123.4))
    rng = np.random.default_rng(1)
    x, y = rng.uniform(-800, 800, 500), rng.uniform(-800, 800, 500)
    lon, lat = lt.to_lonlat(x, y)
    x2, y2 = lt.from_lonlat(lon, lat)
    assert np.max(np.hypot(x2 - x, y2 - y)) < 1e-3


def test_bad_origin_is_a_clear_error():
    with pytest.raises(PavemapError, match="lat"):
        local_tangent(GeoOrigin(lat=123.0, lon=0.0))


# ------------------------------------------------------------------ geojson
def test_geojson_local_metres():
    # a clockwise square with a hole: the writer must re-orient it
    sq = Polygon([(0, 0), (0, 2), (2, 2), (2, 0)], holes=[[(0.5, 0.5), (1.5, 0.5), (1.5, 1.5), (0.5, 1.5)]])
    fc = instances_to_geojson([inst(7, sq, cls=3, prio="repair now")])
    assert fc["type"] == "FeatureCollection" and "crs" not in fc
    assert fc["pavemap"]["coordinates"] == "local" and fc["pavemap"]["geo_origin"] is None
    f = fc["features"][0]
    assert f["properties"]["code"] == "D40" and f["properties"]["name"] == "pothole"
    for key in ("id", "cls", "code", "name", "paper_severity", "paper_severity_max", "confidence", "observations",
                "probability", "area_m2", "length_m", "priority"):
        assert key in f["properties"]
    ext, hole = (np.array(r) for r in f["geometry"]["coordinates"])
    signed = [0.5 * np.sum(r[:-1, 0] * r[1:, 1] - r[1:, 0] * r[:-1, 1]) for r in (ext, hole)]
    assert signed[0] > 0 and signed[1] < 0  # RFC 7946 right-hand rule
    assert shape(f["geometry"]).area == pytest.approx(3.0)
    assert fc["bbox"] == [0.0, 0.0, 2.0, 2.0]


@pytest.mark.parametrize("heading", [90.0, 37.0])
def test_geojson_lonlat_lands_at_the_right_place(tmp_path, heading):
    origin = GeoOrigin(ORIGIN.lat, ORIGIN.lon, heading_deg=heading)
    poly = box(99.0, -1.0, 101.0, 1.0)  # 2 m square centred 100 m along world x
    p = write_geojson(tmp_path / "d.geojson", [inst(1, poly)], origin)
    fc = json.loads(p.read_text())
    assert fc["pavemap"]["coordinates"] == "lonlat"
    g = shape(fc["features"][0]["geometry"])
    c = g.centroid
    az, _, dist = GEOD.inv(origin.lon, origin.lat, c.x, c.y)
    assert dist == pytest.approx(100.0, abs=0.02) and az == pytest.approx(heading, abs=0.02)
    ring = np.array(fc["features"][0]["geometry"]["coordinates"][0])
    assert 0.5 * np.sum(ring[:-1, 0] * ring[1:, 1] - ring[1:, 0] * ring[:-1, 1]) > 0
    props = fc["features"][0]["properties"]
    assert props["lon"] == pytest.approx(c.x, abs=1e-6) and props["lat"] == pytest.approx(c.y, abs=1e-6)
    # read back into world metres
    layer = read_geojson(p)
    assert layer.geo_origin == origin
    assert layer.geometries[0].hausdorff_distance(poly) < 0.003


def test_geojson_multipolygon_and_empty():
    mp = box(0, 0, 1, 1).union(box(3, 0, 4, 1))
    fc = instances_to_geojson([inst(1, mp), inst(2, Polygon())])
    assert fc["features"][0]["geometry"]["type"] == "MultiPolygon"
    assert fc["features"][1]["geometry"] is None


def test_read_geojson_errors(tmp_path):
    bad = tmp_path / "bad.geojson"
    bad.write_text("{not json")
    with pytest.raises(PavemapError, match="bad.geojson"):
        read_geojson(bad)
    bad.write_text(json.dumps({"type": "Feature"}))
    with pytest.raises(PavemapError, match="FeatureCollection"):
        read_geojson(bad)


# ------------------------------------------------------------------ geotiff
def _maps(H=40, W=60, peak=(10, 45)):
    prob = np.zeros((H, W), np.float32)
    prob[peak] = 0.9
    cls = np.zeros((4, H, W), np.float32)
    cls[2][peak] = 0.7
    return prob, cls


def test_geotiff_local_north_up(tmp_path):
    prob, cls = _maps()
    grid = GridSpec(-3.0, 5.0, 0.2, nx=60, ny=40)
    p = write_geotiff(tmp_path / "m.tif", prob, cls, grid)
    with rasterio.open(p) as ds:
        # a local engineering CRS, never read as longitude/latitude (issue 15)
        assert ds.count == 5 and not ds.crs.is_geographic and "pavemap local world frame" in ds.crs.to_wkt()
        assert ds.descriptions == BAND_DESCRIPTIONS
        assert ds.tags(ns="IMAGE_STRUCTURE").get("LAYOUT", "COG") == "COG"
        a = ds.read()
        assert ds.transform.e < 0  # north-up
        r, c = np.unravel_index(np.argmax(a[0]), a[0].shape)
        assert a[0, r, c] == pytest.approx(0.9) and a[3, r, c] == pytest.approx(0.7)
        x, y = ds.xy(r, c)  # cell centre
    assert x == pytest.approx(-3.0 + 45 * 0.2) and y == pytest.approx(5.0 + 10 * 0.2)
    # the top row of the raster is the largest y (our last row)
    assert r == 40 - 1 - 10


@pytest.mark.parametrize("heading", [90.0, 30.0])
def test_geotiff_georeferenced(tmp_path, heading):
    prob, cls = _maps(peak=(20, 30))
    grid = GridSpec(10.0, -4.0, 0.25, nx=60, ny=40)
    origin = GeoOrigin(ORIGIN.lat, ORIGIN.lon, heading_deg=heading)
    p = write_geotiff(tmp_path / "g.tif", prob, cls, grid, origin)
    wx, wy = 10.0 + 30 * 0.25, -4.0 + 20 * 0.25
    lon_t, lat_t = local_tangent(origin).to_lonlat(np.array([wx]), np.array([wy]))
    with rasterio.open(p) as ds:
        assert ds.crs.to_epsg() == 32632  # the drive's UTM zone (Munich: 32N)
        a = ds.read(1)
        r, c = np.unravel_index(np.argmax(a), a.shape)
        e, n = ds.xy(r, c)
        tr = Transformer.from_crs(CRS.from_wkt(ds.crs.to_wkt()), "EPSG:4326", always_xy=True)
        lon, lat = tr.transform(e, n)
    _, _, dist = GEOD.inv(lon, lat, lon_t[0], lat_t[0])
    assert a[r, c] > 0.2 and dist < 0.25 * 0.75  # resampled (bilinear) onto the north-up UTM grid: within a cell


def test_geotiff_shape_mismatch(tmp_path):
    prob, cls = _maps()
    with pytest.raises(PavemapError, match="grid"):
        write_geotiff(tmp_path / "x.tif", prob, cls, GridSpec(0, 0, 0.1, 10, 10))
    # a grid read back from a file (GridSpec.to_dict, or an older file's keys) is checked the same way
    with pytest.raises(PavemapError, match="BEV map grid"):
        write_geotiff(tmp_path / "x.tif", prob, cls, {"x0": 0, "y0": 0, "res": 0.1, "shape": [10, 10]})
    with pytest.raises(PavemapError, match="res > 0"):
        write_geotiff(tmp_path / "x.tif", prob, cls, {"x0": 0, "y0": 0, "res": 0.0, "nx": 60, "ny": 40})
    assert not list(tmp_path.iterdir())


# ------------------------------------------------------------------ tables
def test_csv_and_dataframe(tmp_path):
    items = [inst(2, box(0, 0, 1, 1), 1), inst(1, box(5, 5, 6, 7), 3, "repair now")]
    p = write_csv(tmp_path / "d.csv", items, ORIGIN)
    rows = list(csv.DictReader(p.open()))
    assert [r["id"] for r in rows] == ["1", "2"]
    assert list(rows[0]) == list(columns(geo=True))
    assert list(rows[0])[:3] == ["id", "priority", "priority_rank"] and {"lat", "lon"} <= set(rows[0])
    assert float(rows[0]["area_m2"]) == pytest.approx(2.0) and rows[0]["code"] == "D40"
    assert float(rows[0]["x_m"]) == pytest.approx(5.5)
    df = to_dataframe(items)
    recs = df.to_dict("records") if hasattr(df, "to_dict") else df
    assert len(recs) == 2 and "lon" not in recs[0]
    empty = write_csv(tmp_path / "e.csv", [])
    assert empty.read_text().strip().split(",")[0] == "id" and len(empty.read_text().splitlines()) == 1


# ------------------------------------------------------------------ report + write_outputs
def test_report_is_self_contained_and_escaped():
    kw = sample_inputs(5, seed=3)
    kw["config"]["note"] = "</script><b>x</b>"
    html = build_report_html(kw["instances"], bev_rgb=kw["bev_rgb"], bev_semantic=kw["bev_semantic"],
                             mesh_grid=kw["mesh_grid"], prob_map=kw["prob_map"], grid=kw["grid"],
                             metrics=kw["metrics"], config=kw["config"], detections=kw["detections"])
    assert not re.search(r"""(src|href)\s*=\s*["']?(https?:)?//""", html)
    assert "@import" not in html and "url(http" not in html
    assert html.count("</script>") == 2  # the config text did not close a script early
    assert 'id="defect-count">5<' in html
    assert html.count('class="d"') == 5 and html.count("<tr data-id=") == 5
    assert "data:image/jpeg;base64," in html


def test_report_without_defects_says_so():
    dets = [{"frame": 0, "camera": "C", "box": [0, 0, 5, 5], "cls": 0, "conf": 0.3, "kept": False,
             "reason": "off road"}]
    html = build_report_html([], detections=dets)
    assert 'id="no-defects"' in html and "All 1 detections were filtered out (1 off road)" in html
    assert 'id="defect-count">0<' in html
    assert "no detections at all" in build_report_html([], detections=[])


@pytest.mark.parametrize("geo", [False, True])
def test_write_outputs_all_files(tmp_path, geo):
    kw = sample_inputs(6, seed=1, geo=geo, heading_deg=60.0)
    traj = kw.pop("trajectory")
    mesh = tmp_path / "stage1" / "road_mesh.ply"
    mesh.parent.mkdir()
    mesh.write_text("ply\nformat ascii 1.0\nend_header\n")
    img = np.full((90, 160, 3), 120, np.uint8)
    out = tmp_path / "run"
    paths = write_outputs(out, figures_extra={"sweep": [{"tau_conf": t, "msr": 1 - t} for t in (0.05, 0.1, 0.3)],
                                              "frames": [{"frame": 0, "camera": "CAM_FRONT", "image": img}]},
                          mesh_path=mesh, trajectory=traj, progress=False, **kw)
    for name in ("survey.gpkg", "defects.csv", "defect_map.tif", "bev_rgb.png", "bev_semantic.png",
                 "metrics.json", "road_mesh.ply", "report.html", "figures/bev_overview.png",
                 "figures/threshold_sweep.png", "figures/frame_000000_CAM_FRONT.png"):
        assert (out / name).is_file() and (out / name).stat().st_size > 0, name
    assert paths["report.html"] == out / "report.html"
    assert not [p for p in out.rglob("*") if ".partial-" in p.name]
    # GeoJSON only in WGS84 (RFC 7946): none without a geo origin (issue 15)
    assert (out / "defects.geojson").is_file() == geo
    if geo:
        fc = json.loads((out / "defects.geojson").read_text())
        assert len(fc["features"]) == 6 and fc["pavemap"]["coordinates"] == "lonlat"
    html = (out / "report.html").read_text()
    assert html.count("data:image/png;base64,") >= 4  # figures inline
    with rasterio.open(out / "defect_map.tif") as ds:
        assert ds.crs.is_projected == geo and not ds.crs.is_geographic


def test_write_outputs_bad_input(tmp_path):
    kw = sample_inputs(2, seed=1)
    kw.pop("trajectory")
    kw["bev_rgb"] = kw["bev_rgb"][:, :, 0]
    with pytest.raises(PavemapError, match="bev_rgb"):
        write_outputs(tmp_path / "o", progress=False, **kw)
    assert not (tmp_path / "o" / "report.html").exists()


def test_write_outputs_no_defects_no_bev(tmp_path):
    """A run where everything was filtered: every file is still written and the report says so."""
    grid = GridSpec(0.0, 0.0, 0.1, nx=50, ny=30)
    dets = [{"frame": 3, "camera": "CAM_FRONT", "box": [10, 10, 40, 30], "cls": 3, "conf": 0.4, "kept": False,
             "reason": "off road", "r_road": 0.1, "mapped": False}]
    paths = write_outputs(tmp_path, [], np.zeros((30, 50), np.float32), np.zeros((4, 30, 50), np.float32), grid,
                          None, None, None, None, {"paper": {"filter_rate": 1.0}}, {"preset": "kitti"}, dets,
                          progress=False)
    assert "defects.geojson" not in paths and paths["survey.gpkg"].is_file()
    html = paths["report.html"].read_text()
    assert "All 1 detections were filtered out" in html
    assert (tmp_path / "figures" / "bev_overview.png").is_file()
    with rasterio.open(paths["defect_map.tif"]) as ds:
        assert ds.read().max() == 0.0 and ds.width == 50 and ds.height == 30


def test_select_overlay_frames_prefers_mixed_views():
    from pavemap.export.figures import select_overlay_frames

    d = [{"frame": 0, "camera": "A", "kept": True}] * 5 + [
        {"frame": 1, "camera": "B", "kept": True}, {"frame": 1, "camera": "B", "kept": False},
        {"frame": 2, "camera": "A", "kept": False}]
    assert select_overlay_frames(d, k=2) == [(1, "B"), (0, "A")]


def test_sweep_from_records_and_semantic_colours():
    from pavemap.export.figures import colour_semantics, sweep_from_records
    from pavemap.types import SemanticClass

    recs = [{"conf": 0.02, "kept": False, "reason": "low_conf"},
            {"conf": 0.1, "kept": True, "reason": "kept", "mapped": True},
            {"conf": 0.2, "kept": False, "reason": "off_road"},
            {"conf": 0.4, "kept": True, "reason": "kept", "mapped": False},
            {"conf": None, "kept": False, "reason": "bad_box"}]
    rows = sweep_from_records(recs, [0.01, 0.05, 0.3])
    assert [r["tau_conf"] for r in rows] == [0.05, 0.3]  # 0.01 would need the low_conf detection
    assert rows[0]["detections"] == 3 and rows[0]["filter_rate"] == pytest.approx(1 / 3)
    assert rows[0]["msr"] == pytest.approx(0.5)
    assert rows[1] == {"tau_conf": 0.3, "detections": 1, "kept": 1, "filter_rate": 0.0, "orp": 1.0, "msr": 0.0}
    classes = [SemanticClass(0, "road", road=True), SemanticClass(3, "asphalt patch", road=True),
               SemanticClass(5, "car", movable=True)]
    img = colour_semantics(np.array([[0, 3, 5, -1]]), classes)
    assert img.dtype == np.uint8 and img.shape == (1, 4, 3)
    assert img[0, 0].tolist() == [128, 64, 128] and img[0, 1].tolist() == [128, 64, 128]
    assert img[0, 3].tolist() == [0, 0, 0] and img[0, 2].tolist() == [0, 0, 142]


def test_write_outputs_with_sequence_and_output_settings(tmp_path):
    """The pipeline passes its Sequence and output settings: overlays and the sweep are made from them."""
    from PIL import Image

    from pavemap.types import Camera, Frame, SemanticClass, Sequence, View

    root = tmp_path / "seq"
    (root / "images").mkdir(parents=True)
    frames = []
    for f in range(2):
        Image.fromarray(np.full((60, 100, 3), 40 * (f + 1), np.uint8)).save(root / "images" / f"{f:06d}.png")
        T = np.eye(4)
        T[0, 3] = 3.0 * f
        frames.append(Frame(f, 0.1 * f, {"CAM": View("CAM", f"images/{f:06d}.png", T)}))
    seq = Sequence("scene-x", [SemanticClass(0, "road", road=True)],
                   {"CAM": Camera("CAM", 100, 60, np.eye(3))}, frames, None, root)
    kw = sample_inputs(3, seed=2)
    kw.pop("trajectory")
    kw["detections"] = [
        {"frame": 1, "camera": "CAM", "box": [10, 10, 30, 30], "cls": 0, "conf": 0.5, "kept": True, "reason": "kept",
         "mapped": True},
        {"frame": 1, "camera": "CAM", "box": [50, 20, 70, 40], "cls": 3, "conf": 0.3, "kept": False,
         "reason": "off_road"},
        {"frame": 0, "camera": "CAM", "box": [None, 1, 2, 3], "cls": 1, "conf": 0.2, "kept": False,
         "reason": "bad_box"},
        {"frame": 7, "camera": "CAM", "box": [1, 1, 2, 2], "cls": 1, "conf": 0.2, "kept": False,
         "reason": "unknown_frame"}]
    out = tmp_path / "run"
    paths = write_outputs(out, seq=seq, output={"overlay_frames": 5, "sweep_tau_conf": (0.1, 0.4)},
                          progress=False, **kw)
    assert (out / "figures" / "frame_000001_CAM.png").is_file()
    assert (out / "figures" / "frame_000000_CAM.png").is_file()  # drawn without its invalid box
    assert not (out / "figures" / "frame_000007_CAM.png").exists()
    assert (out / "figures" / "threshold_sweep.png").is_file()
    assert "scene-x" in paths["report.html"].read_text()
    paths = write_outputs(tmp_path / "bare", seq=seq, output={"figures": False, "report": False}, progress=False,
                          **kw)
    assert "report.html" not in paths and not list((tmp_path / "bare" / "figures").iterdir())


@pytest.mark.parametrize("georef", [False, True])
def test_geotiff_strips_join_without_seams(tmp_path, monkeypatch, georef):
    """The map is written a strip of rows at a time (a long drive's map never sits in memory twice): strips of
    16 rows give the raster one strip over the whole map gives, NaN and nodata handling included."""
    import pavemap.export.geotiff as gt

    rng = np.random.default_rng(4)
    H, W = 150, 45
    prob = rng.uniform(0, 1, (H, W)).astype(np.float32)
    prob[5, 7] = np.nan
    cls = rng.uniform(0, 1, (4, H, W)).astype(np.float32)
    valid = rng.uniform(0, 1, (H, W)) > 0.1
    grid = GridSpec(2.0, -3.0, 0.2, nx=W, ny=H)
    origin = GeoOrigin(ORIGIN.lat, ORIGIN.lon, heading_deg=84.0) if georef else None  # a strip: a band of rows
    got = {}
    for rows in (16, 10_000):
        monkeypatch.setattr(gt, "ROWS", rows)
        p = write_geotiff(tmp_path / f"m{rows}.tif", prob, cls, grid, origin, valid=valid)
        with rasterio.open(p) as ds:
            got[rows] = ds.read()
            assert ds.tags(ns="IMAGE_STRUCTURE").get("LAYOUT", "COG") == "COG"
    assert np.array_equal(got[16], got[10_000])
    assert sorted(x.name for x in tmp_path.iterdir()) == ["m10000.tif", "m16.tif"]  # no strip file left behind
    if not georef:  # the local raster is the map itself, north-up, nodata outside the surveyed cells
        want = np.where(valid, np.nan_to_num(np.concatenate([prob[None], cls])), gt.NODATA)[:, ::-1]
        assert np.array_equal(got[16], want.astype(np.float32))


def test_report_heat_layer_is_thinned_before_colouring():
    """The report's probability layer is strided to the page's image size before it is coloured (float RGBA of a
    long drive's whole map would be 32 bytes a cell), and equals colouring the whole map then striding."""
    from matplotlib import colormaps

    from pavemap.export.report import MAX_IMAGE_SIDE, _prob_rgba

    rng = np.random.default_rng(1)
    prob = rng.uniform(0, 1, (MAX_IMAGE_SIDE + 501, 300)).astype(np.float32)
    got = _prob_rgba(prob)
    assert max(got.shape[:2]) <= MAX_IMAGE_SIDE and got.shape[2] == 4
    full = colormaps["inferno"](0.25 + 0.75 * prob)
    full[..., 3] = np.where(prob < 0.02, 0.0, np.clip(0.25 + prob, 0.0, 0.9))
    assert np.array_equal(got, (full[::-1][::2, ::2] * 255).astype(np.uint8))
