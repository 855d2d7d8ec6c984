"""QGIS layer styles stored in a GeoPackage: the ``layer_styles`` table QGIS itself writes and reads.

QGIS keeps a layer's style in the GeoPackage it comes from, in a table ``layer_styles`` (the QGIS
GeoPackage styling extension) whose columns and DDL are copied here from what QGIS creates
(:data:`LAYER_STYLES_DDL`); a row with ``useAsDefault = 1`` for a layer's table and geometry column is
applied when the layer is opened. Each row carries a QML document (QGIS 3 style XML) built here:

- defects (polygons and points): a ``categorizedSymbol`` renderer on ``priority`` (urgency) in the
  colours of the HTML report's map (:data:`pavemap.palette.PRIORITY_HEX`), labelled with ``code``;
- the network register's defects: categorized on ``status`` (:data:`pavemap.palette.STATUS_HEX`), labelled
  with ``code``; the baseline: categorized on ``code`` (:data:`pavemap.palette.DEFECT_HEX`);
- segments: a ``graduatedSymbol`` renderer on ``coalesce("pci", -1)``: the PCI bands of
  :data:`pavemap.palette.CONDITION_BANDS`, and one class [-1, -0.5] for the segments without an index
  (not assessed) in :data:`pavemap.palette.NOT_ASSESSED_HEX` (a graduated renderer draws no NULL);
- trajectory / drives: a ``singleSymbol`` line; the surveyed area: an outline.

The XML follows what QGIS 3.28 writes (``renderer-v2`` with ``categories`` / ``ranges`` and ``symbols``,
symbol layers as ``Option`` maps, ``labeling type="simple"``). :func:`write_layer_styles` adds the
table to a GeoPackage that GDAL has written and closed; the callers do it on the temporary file
before the rename, so the styled file appears at once (:func:`pavemap.io.atomic.atomic_path`).
"""

from __future__ import annotations

import datetime as dt
import os
import sqlite3
import xml.etree.ElementTree as ET
from dataclasses import dataclass

from pavemap.palette import CONDITION_BANDS, DEFECT_HEX, NOT_ASSESSED_HEX, PRIORITY_HEX, STATUS_HEX, TRAJECTORY_HEX

QGIS_VERSION = "3.28.0-Firenze"
STYLE_NAME = "pavemap"
#: the table as QGIS creates it in a GeoPackage (QgsOgrProviderUtils / the QGIS styling extension)
LAYER_STYLES_DDL = (
    'CREATE TABLE "layer_styles" ( "id" INTEGER PRIMARY KEY AUTOINCREMENT NOT NULL, "f_table_catalog" TEXT(256), '
    '"f_table_schema" TEXT(256), "f_table_name" TEXT(256), "f_geometry_column" TEXT(256), "styleName" TEXT(30), '
    '"styleQML" TEXT, "styleSLD" TEXT, "useAsDefault" BOOLEAN, "description" TEXT, "owner" TEXT(30), '
    '"ui" TEXT(30), "update_time" DATETIME DEFAULT (strftime(\'%Y-%m-%dT%H:%M:%fZ\',\'now\')))'
)
COLUMNS = ("f_table_catalog", "f_table_schema", "f_table_name", "f_geometry_column", "styleName", "styleQML",
           "styleSLD", "useAsDefault", "description", "owner", "ui", "update_time")
NOT_ASSESSED_VALUE = -1.0  # what coalesce() gives a segment without an index


@dataclass(frozen=True)
class Style:
    """One layer's style: its QML and a line for the ``description`` column."""

    qml: str
    description: str


def rgba(hex_colour: str, alpha: int = 255) -> str:
    """``#rrggbb`` -> QGIS' ``r,g,b,a``."""
    h = hex_colour.lstrip("#")
    return ",".join(str(int(h[k:k + 2], 16)) for k in (0, 2, 4)) + f",{alpha}"


def _options(parent: ET.Element, props: dict[str, str]) -> None:
    m = ET.SubElement(parent, "Option", type="Map")
    for k, v in props.items():
        ET.SubElement(m, "Option", type="QString", name=k, value=v)


def _symbol(parent: ET.Element, name: str, kind: str, hex_colour: str) -> None:
    """One symbol: ``fill`` (polygons, half-transparent with a solid outline), ``marker`` or ``line``."""
    sym = ET.SubElement(parent, "symbol", type=kind, name=name, alpha="1", clip_to_extent="1", force_rhr="0")
    if kind == "fill":
        cls, props = "SimpleFill", {"color": rgba(hex_colour, 150), "style": "solid", "outline_color":
                                    rgba(hex_colour), "outline_style": "solid", "outline_width": "0.5",
                                    "outline_width_unit": "MM", "joinstyle": "bevel"}
    elif kind == "marker":
        cls, props = "SimpleMarker", {"color": rgba(hex_colour), "name": "circle", "size": "3", "size_unit": "MM",
                                      "outline_color": "35,35,35,255", "outline_style": "solid",
                                      "outline_width": "0.2", "outline_width_unit": "MM"}
    else:
        cls, props = "SimpleLine", {"line_color": rgba(hex_colour), "line_style": "solid", "line_width": "0.8",
                                    "line_width_unit": "MM", "capstyle": "round", "joinstyle": "round"}
    layer = ET.SubElement(sym, "layer", {"class": cls, "enabled": "1", "locked": "0", "pass": "0"})
    _options(layer, props)


def _root(label_field: str | None) -> ET.Element:
    return ET.Element("qgis", version=QGIS_VERSION, styleCategories="Symbology|Labels",
                      labelsEnabled="1" if label_field else "0")


def _renderer(root: ET.Element, kind: str, **attrs: str) -> ET.Element:
    return ET.SubElement(root, "renderer-v2", {"type": kind, "forceraster": "0", "symbollevels": "0",
                                               "enableorderby": "0", "referencescale": "-1", **attrs})


def _labeling(root: ET.Element, field: str, kind: str) -> None:
    """Labels with ``field`` (bold, white halo): over the polygon's centre, beside a point."""
    settings = ET.SubElement(ET.SubElement(root, "labeling", type="simple"), "settings", calloutType="simple")
    style = ET.SubElement(settings, "text-style", fieldName=field, isExpression="0", fontSize="8",
                          fontSizeUnit="Point", fontWeight="75", textColor="20,20,20,255", textOpacity="1")
    ET.SubElement(style, "text-buffer", bufferDraw="1", bufferSize="0.7", bufferSizeUnits="MM",
                  bufferColor="255,255,255,255", bufferOpacity="0.85")
    ET.SubElement(settings, "placement", placement="1" if kind == "fill" else "0", dist="1", distUnits="MM")
    ET.SubElement(settings, "rendering", obstacle="1", displayAll="0", drawLabels="1", limitNumLabels="0")


def _qml(root: ET.Element) -> str:
    ET.indent(root)
    return "<!DOCTYPE qgis PUBLIC 'http://mrcc.com/qgis.dtd' 'SYSTEM'>\n" + ET.tostring(root, encoding="unicode")


def categorized_qml(attr: str, classes: dict[str, str], kind: str, label_field: str | None = None,
                    other: str | None = "#999999") -> str:
    """A ``categorizedSymbol`` style: one category per {value: colour}; ``other`` colours every other value
    (QGIS' empty-value category). ``kind``: fill / marker / line."""
    root = _root(label_field)
    r = _renderer(root, "categorizedSymbol", attr=attr)
    cats, syms = ET.SubElement(r, "categories"), ET.SubElement(r, "symbols")
    items = list(classes.items()) + ([("", other)] if other else [])
    for k, (value, colour) in enumerate(items):
        ET.SubElement(cats, "category", type="string", render="true", value=value, symbol=str(k),
                      label=value or "other")
        _symbol(syms, str(k), kind, colour)
    if label_field:
        _labeling(root, label_field, kind)
    return _qml(root)


def graduated_qml(field: str, kind: str = "fill") -> str:
    """A ``graduatedSymbol`` style on ``coalesce(field, -1)``: the condition bands, and not assessed (null)."""
    root = _root(None)
    r = _renderer(root, "graduatedSymbol", attr=f'coalesce("{field}", {NOT_ASSESSED_VALUE:g})',
                  graduatedMethod="GraduatedColor")
    ranges, syms = ET.SubElement(r, "ranges"), ET.SubElement(r, "symbols")
    bounds = [(NOT_ASSESSED_VALUE, -0.5, "not assessed", NOT_ASSESSED_HEX)]
    lo = 0.0
    for hi, colour in CONDITION_BANDS:
        top = min(hi, 100.0)
        bounds.append((lo, top, f"{lo:g} - {top:g}", colour))
        lo = top
    for k, (a, b, label, colour) in enumerate(bounds):
        ET.SubElement(ranges, "range", lower=f"{a:.15f}", upper=f"{b:.15f}", symbol=str(k), label=label,
                      render="true")
        _symbol(syms, str(k), kind, colour)
    ET.SubElement(r, "mode", name="manual")
    return _qml(root)


def single_qml(kind: str, colour: str) -> str:
    """A ``singleSymbol`` style: every feature the same (a line, or an outline for ``fill``)."""
    root = _root(None)
    r = _renderer(root, "singleSymbol")
    _symbol(ET.SubElement(r, "symbols"), "0", kind, colour)
    if kind == "fill":  # the surveyed area: an outline only, the defects stay visible through it
        layer = r.find("symbols/symbol/layer/Option")
        for o in layer.findall("Option"):
            if o.get("name") == "style":
                o.set("value", "no")
    return _qml(root)


def survey_styles() -> dict[str, Style]:
    """The styles of ``survey.gpkg``'s layers, by layer name."""
    return {
        "defects": Style(categorized_qml("priority", PRIORITY_HEX, "fill", "code"),
                         "defects by urgency (priority), labelled with the class code"),
        "defect_points": Style(categorized_qml("priority", PRIORITY_HEX, "marker", "code"),
                               "defect centres by urgency (priority), labelled with the class code"),
        "trajectory": Style(single_qml("line", TRAJECTORY_HEX), "the drive"),
        "survey": Style(single_qml("fill", TRAJECTORY_HEX), "the surveyed area (outline)"),
        "baseline_defects": Style(categorized_qml("code", DEFECT_HEX, "fill", "code"),
                                  "single-frame baseline by class code"),
        "segments": Style(graduated_qml("pci"), "segments by PCI-like condition index; grey: not assessed"),
    }


def register_styles() -> dict[str, Style]:
    """The styles of ``register.gpkg``'s layers, by layer name."""
    return {
        "defects": Style(categorized_qml("status", STATUS_HEX, "fill", "code"),
                         "physical defects by status since the last survey, labelled with the class code"),
        "observations": Style(categorized_qml("priority", PRIORITY_HEX, "fill", "code"),
                              "every drive's defects by urgency (priority), labelled with the class code"),
        "drives": Style(single_qml("line", TRAJECTORY_HEX), "the drives"),
        "segments": Style(graduated_qml("pci"), "segments by PCI-like condition index; grey: not assessed"),
    }


def write_layer_styles(gpkg: str | os.PathLike, styles: dict[str, Style]) -> int:
    """Add ``layer_styles`` (one default style per layer of ``styles`` the file has) to a closed GeoPackage;
    registered in ``gpkg_contents`` as an attributes table, as QGIS does. Returns the rows written."""
    now = dt.datetime.now(dt.UTC).strftime("%Y-%m-%dT%H:%M:%S.%f")[:-3] + "Z"
    con = sqlite3.connect(os.fspath(gpkg))
    try:
        geom_cols = dict(con.execute("SELECT table_name, column_name FROM gpkg_geometry_columns").fetchall())
        rows = [("", "", layer, geom_cols[layer], STYLE_NAME, s.qml, "", 1, s.description, "", None, now)
                for layer, s in styles.items() if layer in geom_cols]
        con.execute(LAYER_STYLES_DDL)
        names = ", ".join(f'"{c}"' for c in COLUMNS)
        con.executemany(f'INSERT INTO "layer_styles" ({names}) VALUES ({", ".join("?" * len(COLUMNS))})', rows)
        con.execute("INSERT INTO gpkg_contents (table_name, data_type, identifier, description, last_change) "
                    "VALUES ('layer_styles', 'attributes', 'layer_styles', '', ?)", (now,))
        if con.execute("SELECT 1 FROM sqlite_master WHERE name = 'gpkg_ogr_contents'").fetchone():
            con.execute("INSERT INTO gpkg_ogr_contents (table_name, feature_count) VALUES ('layer_styles', ?)",
                        (len(rows),))
        con.commit()
    finally:
        con.close()
    return len(rows)


__all__ = ["COLUMNS", "LAYER_STYLES_DDL", "Style", "categorized_qml", "graduated_qml", "register_styles", "rgba",
           "single_qml", "survey_styles", "write_layer_styles"]
