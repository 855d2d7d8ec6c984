"""Change between surveys: two hand-made surveys of one road where defects were added and enlarged."""

from __future__ import annotations

import json

import numpy as np
import pytest
import typer
from shapely import affinity
from shapely.geometry import Point, box, shape
from typer.testing import CliRunner

from pavemap.commands.compare import register
from pavemap.compare import compare_runs
from pavemap.errors import PavemapError
from pavemap.export.geojson import write_geojson
from pavemap.geo.tangent import local_tangent
from pavemap.types import DefectInstance, GeoOrigin


def inst(i, poly, cls=0, sev=0.3):
    return DefectInstance(id=i, cls=cls, polygon=poly, severity_mean=sev, severity_max=sev, confidence=0.5,
                          observations=3, probability=0.5, area_m2=float(poly.area), length_m=1.0,
                          centroid=(poly.centroid.x, poly.centroid.y), priority="schedule")


def survey_a():
    return [
        inst(1, box(0, 0, 2, 0.15), 0),  # crack, unchanged
        inst(2, Point(10, 2).buffer(0.3), 3, 0.6),  # pothole, will be enlarged
        inst(3, box(20, -1, 20.15, 1), 1, 0.2),  # transverse crack, severity rises
        inst(4, box(30, 0, 31, 1), 2, 0.5),  # alligator patch, repaired (gone)
        inst(5, box(40, 3, 41.5, 3.12), 0),  # crack that becomes alligator cracking
    ]


def survey_b():
    return [
        inst(11, affinity.translate(box(0, 0, 2, 0.15), 0.12, -0.05), 0),  # jitter only
        inst(12, Point(10.1, 2.0).buffer(0.45), 3, 0.62),  # area x2.25
        inst(13, box(20, -1, 20.15, 1), 1, 0.35),  # severity x1.75
        inst(15, box(40, 2.8, 41.6, 3.6), 2, 0.5),  # grew into alligator cracking
        inst(16, Point(50, -2).buffer(0.25), 3, 0.9),  # new pothole
        inst(17, box(5, 4, 7, 4.15), 0),  # new crack
    ]


def _by_change(out):
    """Features of the changes layer, from changes.geojson (lon/lat) or changes.gpkg (local CRS)."""
    if (out / "changes.geojson").is_file():
        fc = json.loads((out / "changes.geojson").read_text())
    else:
        import pyogrio.raw
        import shapely

        meta, _, geoms, fields = pyogrio.raw.read(out / "changes.gpkg", layer="changes")
        feats = []
        for k, g in enumerate(geoms):
            vals = (f[k] for f in fields)
            p = {n: (v.item() if hasattr(v, "item") else v) for n, v in zip(meta["fields"], vals, strict=True)}
            p.update({n: None for n in ("id_a", "id_b") if p[n] is None or p[n] == -1 or p[n] != p[n]})  # NULL
            p["reasons"] = [r for r in p["reasons"].split("; ") if r]
            feats.append({"properties": p, "geometry": shapely.geometry.mapping(shapely.from_wkb(g))})
        fc = {"features": feats, "crs_wkt": meta["crs"]}
    res = {}
    for f in fc["features"]:
        p = f["properties"]
        res.setdefault(p["change"], []).append(p["id_b"] if p["id_b"] is not None else p["id_a"])
    return fc, {k: sorted(v) for k, v in res.items()}


def test_new_grown_unchanged_gone(tmp_path):
    write_geojson(tmp_path / "a" / "defects.geojson", survey_a())
    write_geojson(tmp_path / "b" / "defects.geojson", survey_b())
    s = compare_runs(tmp_path / "a", tmp_path / "b", tmp_path / "out")
    assert s["counts"] == {"new": 2, "grown": 3, "unchanged": 1, "gone": 1}
    fc, by = _by_change(tmp_path / "out")
    assert by == {"new": [16, 17], "grown": [12, 13, 15], "unchanged": [11], "gone": [4]}
    reasons = {f["properties"]["id_b"]: f["properties"]["reasons"] for f in fc["features"]
               if f["properties"]["change"] == "grown"}
    assert reasons[12] == ["area"] and reasons[13] == ["severity"] and "class" in reasons[15]
    # without geo origins the layer is never GeoJSON (it would read as lon/lat) but a local engineering CRS
    assert not (tmp_path / "out" / "changes.geojson").exists()
    assert "ENGCRS" in fc["crs_wkt"] or "pavemap local" in fc["crs_wkt"]
    gone = next(f for f in fc["features"] if f["properties"]["change"] == "gone")
    assert shape(gone["geometry"]).equals(box(30, 0, 31, 1))
    assert (tmp_path / "out" / "changes.png").stat().st_size > 10_000
    saved = json.loads((tmp_path / "out" / "changes.json").read_text())
    assert saved["counts"] == s["counts"] and saved["defects_a"] == 5 and saved["defects_b"] == 6


def test_stricter_thresholds_change_the_answer(tmp_path):
    write_geojson(tmp_path / "a.geojson", survey_a())
    write_geojson(tmp_path / "b.geojson", survey_b())
    s = compare_runs(tmp_path / "a.geojson", tmp_path / "b.geojson", tmp_path / "o", grow_ratio=2.0)
    assert s["counts"]["grown"] == 2  # 12 (area x2.25) and 15 (class); 13's severity x1.75 is not enough
    s = compare_runs(tmp_path / "a.geojson", tmp_path / "b.geojson", tmp_path / "o2", match_m=0.05)
    # the jittered crack still matches because the polygons overlap
    assert s["counts"]["unchanged"] == 1


def test_geo_runs_with_different_origins(tmp_path):
    """Survey B was driven from another start point: its world frame is shifted and rotated."""
    oa = GeoOrigin(lat=45.0, lon=7.0, heading_deg=90.0)
    ob = GeoOrigin(lat=45.0002, lon=7.0003, heading_deg=75.0)
    lta, ltb = local_tangent(oa), local_tangent(ob)

    def move(poly):  # A world -> lon/lat -> B world
        return ltb.geometry_from_lonlat(lta.geometry_to_lonlat(poly))

    b_items = [inst(d.id, move(d.polygon), d.cls, d.severity_mean) for d in survey_b()]
    # a B-world bbox far from A-world: without the geo conversion nothing would match
    assert np.hypot(*np.subtract(b_items[0].centroid, survey_b()[0].centroid)) > 10
    write_geojson(tmp_path / "a" / "defects.geojson", survey_a(), oa)
    write_geojson(tmp_path / "b" / "defects.geojson", b_items, ob)
    s = compare_runs(tmp_path / "a", tmp_path / "b", tmp_path / "out")
    assert s["coordinates"] == "lonlat"
    assert s["counts"] == {"new": 2, "grown": 3, "unchanged": 1, "gone": 1}
    fc = json.loads((tmp_path / "out" / "changes.geojson").read_text())
    lon, lat = shape(fc["features"][0]["geometry"]).centroid.coords[0]
    assert 6.99 < lon < 7.01 and 44.99 < lat < 45.01


def test_errors_and_cli(tmp_path):
    with pytest.raises(PavemapError, match="no defects.geojson"):
        (tmp_path / "empty").mkdir()
        compare_runs(tmp_path / "empty", tmp_path / "empty", tmp_path / "o")
    write_geojson(tmp_path / "a" / "defects.geojson", survey_a())
    write_geojson(tmp_path / "b" / "defects.geojson", [])
    app = typer.Typer()

    @app.callback()
    def _root() -> None:
        """test app"""

    register(app)
    r = CliRunner().invoke(app, ["compare", str(tmp_path / "a"), str(tmp_path / "b"), "--out", str(tmp_path / "c")])
    assert r.exit_code == 0, r.output
    assert "new 0  grown 0  unchanged 0  gone 5" in r.output
    assert json.loads((tmp_path / "c" / "changes.json").read_text())["counts"]["gone"] == 5


def test_files_from_before_issue_16_carry_severity(tmp_path):
    """Older defects files name the paper's EMA severity ``severity``; newer ones ``paper_severity``."""
    write_geojson(tmp_path / "a.geojson", survey_a())
    write_geojson(tmp_path / "b.geojson", survey_b())
    old = json.loads((tmp_path / "a.geojson").read_text())
    for f in old["features"]:
        f["properties"]["severity"] = f["properties"].pop("paper_severity")
    (tmp_path / "a.geojson").write_text(json.dumps(old))
    s = compare_runs(tmp_path / "a.geojson", tmp_path / "b.geojson", tmp_path / "o")
    assert s["counts"] == {"new": 2, "grown": 3, "unchanged": 1, "gone": 1}  # 13 grew by its severity
