"""QGIS layer styles in a GeoPackage: the table QGIS writes, one default QML per layer, the palette's colours."""

from __future__ import annotations

import sqlite3

import pyogrio
from pyproj import CRS
from shapely.geometry import LineString, MultiPolygon, box

from pavemap.export.gis import _GPKG_OPTIONS, _write_layer
from pavemap.export.qgis_style import register_styles, survey_styles, write_layer_styles
from pavemap.palette import PRIORITY_HEX
from qgis_support import REGISTER, SURVEY, check_styles


def _gpkg(path, layers: dict[str, str]):
    crs = CRS.from_epsg(32633)
    for k, (name, gtype) in enumerate(layers.items()):
        geom = LineString([(0, 0), (5, 5)]) if "LineString" in gtype else MultiPolygon([box(0, 0, 1, 1)])
        _write_layer(path, "GPKG", name, [geom], [{"code": "D40", "priority": "repair now", "pci": 50.0}], crs,
                     gtype, [("code", "str"), ("priority", "str"), ("pci", "float")],
                     **({"dataset_options": _GPKG_OPTIONS} if k == 0 else {}))
    return path


def test_survey_styles_round_trip(tmp_path):
    gpkg = _gpkg(tmp_path / "survey.gpkg", {"defects": "MultiPolygon", "defect_points": "MultiPolygon",
                                            "trajectory": "LineString", "segments": "MultiPolygon"})
    assert write_layer_styles(gpkg, survey_styles()) == 4  # only the layers the file has
    roots = check_styles(gpkg, SURVEY)
    assert set(roots) == {"defects", "defect_points", "trajectory", "segments"}
    # GDAL still reads every layer, and sees the styles as an attributes table
    assert dict(pyogrio.list_layers(gpkg))["layer_styles"] is None
    assert len(pyogrio.read_dataframe(gpkg, layer="defects")) == 1


def test_register_styles_round_trip(tmp_path):
    gpkg = _gpkg(tmp_path / "register.gpkg", {"defects": "MultiPolygon", "observations": "MultiPolygon",
                                              "drives": "LineString"})
    write_layer_styles(gpkg, register_styles())
    assert set(check_styles(gpkg, REGISTER)) == {"defects", "observations", "drives"}


def test_the_check_fails_on_a_colour_not_from_the_palette(tmp_path):
    """The checker is not vacuous: a style whose urgency colour drifted from the report's is caught."""
    gpkg = _gpkg(tmp_path / "s.gpkg", {"defects": "MultiPolygon"})
    write_layer_styles(gpkg, survey_styles())
    con = sqlite3.connect(gpkg)
    red = PRIORITY_HEX["repair now"].lstrip("#")
    rgb = ",".join(str(int(red[k:k + 2], 16)) for k in (0, 2, 4))
    con.execute("UPDATE layer_styles SET styleQML = replace(styleQML, ?, '1,2,3')", (rgb,))
    con.commit()
    con.close()
    try:
        check_styles(gpkg, SURVEY)
    except AssertionError:
        return
    raise AssertionError("a changed colour passed the style check")
