"""Reading back a GeoPackage's QGIS styles (``layer_styles``) and checking each QML against the palette."""

from __future__ import annotations

import shutil
import sqlite3
import subprocess
import xml.etree.ElementTree as ET
from pathlib import Path

from pavemap.export.qgis_style import COLUMNS
from pavemap.palette import CONDITION_BANDS, DEFECT_HEX, NOT_ASSESSED_HEX, PRIORITY_HEX, STATUS_HEX, TRAJECTORY_HEX

OGRINFO = shutil.which("ogrinfo")
#: layer -> (renderer, attribute, {class value or label: colour}, label field) of what each file must carry
SURVEY = {"defects": ("categorizedSymbol", "priority", PRIORITY_HEX, "code"),
          "defect_points": ("categorizedSymbol", "priority", PRIORITY_HEX, "code"),
          "baseline_defects": ("categorizedSymbol", "code", DEFECT_HEX, "code"),
          "trajectory": ("singleSymbol", None, {"0": TRAJECTORY_HEX}, None),
          "survey": ("singleSymbol", None, {"0": TRAJECTORY_HEX}, None),
          "segments": ("graduatedSymbol", 'coalesce("pci", -1)', None, None)}
REGISTER = {"defects": ("categorizedSymbol", "status", STATUS_HEX, "code"),
            "observations": ("categorizedSymbol", "priority", PRIORITY_HEX, "code"),
            "drives": ("singleSymbol", None, {"0": TRAJECTORY_HEX}, None),
            "segments": ("graduatedSymbol", 'coalesce("pci", -1)', None, None)}


def _rgb(hex_colour: str) -> str:
    h = hex_colour.lstrip("#")
    return ",".join(str(int(h[k:k + 2], 16)) for k in (0, 2, 4))


def _colour(symbol: ET.Element) -> str:
    """A symbol's colour as ``r,g,b`` (the fill / marker ``color``, a line's ``line_color``)."""
    opts = {o.get("name"): o.get("value") for o in symbol.find("layer").find("Option")}
    return ",".join((opts.get("color") or opts["line_color"]).split(",")[:3])


def read_styles(gpkg: Path) -> dict[str, dict]:
    """layer -> its layer_styles row (column -> value), checking the table's columns are QGIS'."""
    con = sqlite3.connect(gpkg)
    try:
        cols = [r[1] for r in con.execute('PRAGMA table_info("layer_styles")')]
        assert cols == ["id", *COLUMNS], cols
        assert con.execute("SELECT data_type FROM gpkg_contents WHERE table_name='layer_styles'").fetchone() == \
            ("attributes",)
        rows = [dict(zip(cols, r, strict=True)) for r in con.execute('SELECT * FROM "layer_styles"')]
        geom = dict(con.execute("SELECT table_name, column_name FROM gpkg_geometry_columns").fetchall())
    finally:
        con.close()
    out = {}
    for r in rows:
        assert r["useAsDefault"] == 1 and r["f_table_catalog"] == "" and r["f_table_schema"] == ""
        assert r["f_geometry_column"] == geom[r["f_table_name"]] and r["styleName"] and r["update_time"]
        out[r["f_table_name"]] = r
    return out


def check_styles(gpkg: Path, expected: dict[str, tuple]) -> dict[str, ET.Element]:
    """Every user-facing layer the file has carries one default style whose QML has the expected renderer,
    attribute, class colours (the palette's) and label field; ``ogrinfo`` lists ``layer_styles``."""
    if OGRINFO:
        listing = subprocess.run([OGRINFO, "-ro", "-q", str(gpkg)], capture_output=True, text=True, timeout=60)
        assert "layer_styles (None)" in listing.stdout, listing.stdout
    styles = read_styles(gpkg)
    con = sqlite3.connect(gpkg)
    layers = {r[0] for r in con.execute("SELECT table_name FROM gpkg_geometry_columns")}
    con.close()
    assert set(styles) == layers & set(expected), (set(styles), layers)
    roots = {}
    for layer, row in styles.items():
        kind, attr, colours, label = expected[layer]
        assert row["styleQML"].startswith("<!DOCTYPE qgis"), row["styleQML"][:80]
        root = ET.fromstring(row["styleQML"].split("\n", 1)[1])
        assert root.tag == "qgis" and root.get("version", "").startswith("3.")
        r = root.find("renderer-v2")
        assert r.get("type") == kind and r.get("attr") == attr, (layer, r.attrib)
        symbols = {s.get("name"): s for s in r.find("symbols")}
        if kind == "categorizedSymbol":
            got = {c.get("value"): _colour(symbols[c.get("symbol")]) for c in r.find("categories")}
            assert {k: v for k, v in got.items() if k} == {k: _rgb(v) for k, v in colours.items()}, layer
        elif kind == "graduatedSymbol":
            ranges = [(float(x.get("lower")), float(x.get("upper")), _colour(symbols[x.get("symbol")]))
                      for x in r.find("ranges")]
            assert ranges[0][:2] == (-1.0, -0.5) and ranges[0][2] == _rgb(NOT_ASSESSED_HEX)  # not assessed: grey
            assert [c for *_, c in ranges[1:]] == [_rgb(c) for _, c in CONDITION_BANDS]
            assert ranges[1][0] == 0 and ranges[-1][1] == 100
            assert all(a[1] == b[0] for a, b in zip(ranges[1:], ranges[2:], strict=False))  # no gap, no overlap
        else:
            assert _colour(symbols["0"]) == _rgb(colours["0"])
        lab = root.find("labeling/settings/text-style")
        assert (lab.get("fieldName") if lab is not None else None) == label, layer
        assert root.get("labelsEnabled") == ("1" if label else "0")
        roots[layer] = root
    return roots
