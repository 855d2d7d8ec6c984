"""``report.html``: one self-contained page a maintenance engineer reads offline.

Everything is inline (images as base64 data URIs, CSS and JS in the page, system fonts), so the
file can be mailed or archived alone. Contents: summary cards and metrics, a zoomable/pannable
BEV map (SVG over the BEV RGB image) with the defect polygons (hover shows properties, click
selects and highlights the table row), the defects table (sortable; priority first), the
figures, and the run settings.
"""

from __future__ import annotations

import base64
import datetime as _dt
import html
import io
import json
import os
from collections import Counter
from pathlib import Path

import numpy as np

from pavemap.export.figures import CLASS_COLOURS, flatten_metrics, format_value, grid_extent, headline_metrics
from pavemap.export.geojson import _polygons, instance_properties
from pavemap.export.report_assets import CSS, JS
from pavemap.export.report_worklist import (
    FIELD_CSS,
    PRINT_CSS,
    PRIORITY_FILL,
    PRIORITY_ORDER,
    detector_banner,
    not_assessed_notice,
    order_records,
    segment_strip,
    slug,
    worklist_table,
)
from pavemap.geometry.grid import GridSpec
from pavemap.io.atomic import atomic_write_text
from pavemap.types import DEFECT_CODES, DEFECT_NAMES, DefectInstance, GeoOrigin
from pavemap.version import __version__

MAX_IMAGE_SIDE = 2400  # larger BEV images are downsampled for the page (the PNG files keep full size)


def _esc(v: object) -> str:
    return html.escape(str(v), quote=True)


def _data_uri(img: np.ndarray, fmt: str = "PNG", quality: int = 88) -> str:
    """(H, W, 3|4) uint8 -> a data URI; large images are downsampled by an integer stride."""
    from PIL import Image

    im = Image.fromarray(np.ascontiguousarray(_thin(np.asarray(img))))
    buf = io.BytesIO()
    if fmt == "JPEG":
        im.convert("RGB").save(buf, format="JPEG", quality=quality)
        mime = "image/jpeg"
    else:
        im.save(buf, format="PNG", compress_level=4)
        mime = "image/png"
    return f"data:{mime};base64,{base64.b64encode(buf.getvalue()).decode('ascii')}"


def _thin(a: np.ndarray) -> np.ndarray:
    """A view of (H, W, ...) ``a`` strided down to at most ``MAX_IMAGE_SIDE`` a side (no copy)."""
    step = int(np.ceil(max(a.shape[0], a.shape[1]) / MAX_IMAGE_SIDE))
    return a[::step, ::step] if step > 1 else a


def _file_uri(path: Path) -> str:
    return f"data:image/png;base64,{base64.b64encode(Path(path).read_bytes()).decode('ascii')}"


def _prob_rgba(prob_map: np.ndarray) -> np.ndarray:
    """(H, W) probability -> (h, w, 4) uint8 heat layer, transparent where ~0, rows flipped north-up, strided
    to the report's image size first (a long drive's map in float RGBA would be 32 bytes a cell)."""
    from matplotlib import colormaps

    p = np.clip(np.nan_to_num(np.asarray(_thin(np.asarray(prob_map)[::-1]), dtype=np.float32)), 0.0, 1.0)
    rgba = colormaps["inferno"](0.25 + 0.75 * p)  # (h, w, 4) float
    rgba[..., 3] = np.where(p < 0.02, 0.0, np.clip(0.25 + p, 0.0, 0.9))
    return (rgba * 255).astype(np.uint8)


def _svg_path(geom: object) -> str:
    """SVG path data of a (Multi)Polygon in map coordinates (x, -y), holes with evenodd fill."""
    parts = []
    for p in _polygons(geom):
        for ring in (p.exterior, *p.interiors):
            c = np.asarray(ring.coords, dtype=np.float64)[:, :2]
            if len(c) < 3:
                continue
            pts = " ".join(f"{x:.3f} {-y:.3f}" for x, y in c[:-1])
            parts.append(f"M{pts}Z")
    return "".join(parts)


def _image_el(el_id: str, uri: str, grid: GridSpec, hidden: bool = False) -> str:
    x0, x1, y0, y1 = grid_extent(grid)
    cls = ' class="hidden"' if hidden else ""
    return (f'<image id="{el_id}"{cls} href="{uri}" x="{x0:.4f}" y="{-y1:.4f}" width="{x1 - x0:.4f}" '
            f'height="{y1 - y0:.4f}" preserveAspectRatio="none"/>')


def _detection_summary(detections: list[dict] | None) -> dict:
    if detections is None:
        return {}
    kept = [d for d in detections if d.get("kept", True)]
    reasons = Counter(str(d.get("reason") or "filtered") for d in detections if not d.get("kept", True))
    return {"total": len(detections), "kept": len(kept), "filtered": len(detections) - len(kept),
            "mapped": sum(bool(d.get("mapped")) for d in kept), "reasons": dict(reasons)}


def _no_defects_message(det: dict) -> str:
    msg = "No defects were mapped in this run."
    if not det:
        return msg
    if det["total"] == 0:
        return msg + " The detector reported no detections at all, so there was nothing to map."
    if det["kept"] == 0:
        why = ", ".join(f"{n} {r}" for r, n in sorted(det["reasons"].items()))
        return msg + f" All {det['total']} detections were filtered out ({why})."
    return msg + (f" {det['kept']} of {det['total']} detections passed the road filter and {det['mapped']} were "
                  "mapped onto the road surface, but no area met the defect thresholds.")


def _kv_table(rows: list[tuple[str, str]], head: tuple[str, str] | None = None) -> str:
    h = f"<tr><th>{_esc(head[0])}</th><th>{_esc(head[1])}</th></tr>" if head else ""
    body = "".join(f'<tr><td>{_esc(k)}</td><td class="num">{_esc(v)}</td></tr>' for k, v in rows)
    return f'<table class="kv">{h}{body}</table>'


TABLE_COLUMNS = (  # key, header, type ("num" | "str"), decimals; "severity" reads paper_severity when present
    ("id", "id", "num", None), ("code", "class", "str", None), ("priority", "urgency", "num", None),
    ("severity", "severity", "num", 3), ("severity_max", "sev. max", "num", 3), ("confidence", "conf.", "num", 2),
    ("observations", "obs.", "num", None), ("probability", "prob.", "num", 2), ("area_m2", "area m²", "num", 3),
    ("length_m", "length m", "num", 2), ("x_m", "x m", "num", 2), ("y_m", "y m", "num", 2),
)


def _table_rows(props: list[dict], geo: bool) -> tuple[str, str]:
    """Header and rows of the full defects table (every measure; sortable in the page)."""
    new = any("paper_severity" in p for p in props)  # issue 16 renamed the EMA severity
    sev, sev_max = ("paper_severity", "paper_severity_max") if new else ("severity", "severity_max")
    # lat/lon and chainage right after the urgency: visible without scrolling the table sideways
    extra = [("chainage_m", "chainage m", "num", 1)] if any(p.get("chainage_m") is not None for p in props) else []
    extra += [("lat", "lat", "num", 7), ("lon", "lon", "num", 7)] if geo else []
    cols = [({"severity": sev, "severity_max": sev_max}.get(k, k), h, t, nd) for k, h, t, nd in TABLE_COLUMNS]
    cols = cols[:3] + extra + cols[3:]
    head = "".join(f'<th data-key="{k}" data-type="{t}">{_esc(h)}<span class="arrow"></span></th>'
                   for k, h, t, _ in cols)
    rows = []
    for n, p in enumerate(order_records(props)):
        cells = []
        for k, _, _t, nd in cols:
            v = p.get(k)
            if k == "priority":  # sorts by the work-list order (priority_rank when assessed)
                cells.append(f'<td data-v="{n}"><span class="pill {_esc(slug(v))}">{_esc(v)}</span></td>')
            elif k == "code":
                cells.append(f'<td data-v="{_esc(v)}"><span class="sw" style="background:{CLASS_COLOURS[v]}">'
                             f'</span>{_esc(v)} <span style="color:#5c6677">{_esc(p["name"])}</span></td>')
            else:
                ok = isinstance(v, (int, float)) and not isinstance(v, bool)
                txt = "–" if v is None else (f"{v:.{nd}f}" if nd is not None and ok else str(v))
                cells.append(f'<td class="num" data-v="{_esc(v if ok else "NaN")}">{_esc(txt)}</td>')
        rows.append(f'<tr data-id="{p["id"]}" data-code-of="{_esc(p["code"])}">{"".join(cells)}</tr>')
    return head, "".join(rows)


def _research(props: list[dict], det: dict, metrics: dict | None) -> str:
    """The research metrics (paper statistics, detections, geometry self-check, evaluation), collapsed."""
    area = sum(p["area_m2"] or 0.0 for p in props)
    length = sum(p["length_m"] or 0.0 for p in props)
    cards = [("", f"{area:.2f} m²", "total defect area"), ("", f"{length:.1f} m", "total crack length")]
    if det:
        cards.append(("", f"{det['kept']}/{det['total']}", "detections kept"))
    flat = flatten_metrics(metrics)
    for key in ("timing.total_s", "total_s", "seconds.total"):
        if key in flat:
            cards.append(("", f"{float(flat[key]):.1f} s", "run time"))
            break
    cards_html = "".join(f'<div class="card {c}"><div class="v">{_esc(v)}</div><div class="k">{_esc(k)}</div></div>'
                         for c, v, k in cards)
    per_class = [(f"{c} {DEFECT_NAMES[c]}", str(sum(p["code"] == c for p in props))) for c in DEFECT_CODES]
    tables = _kv_table(per_class, ("class", "instances"))
    if det:
        det_rows = [("detections", str(det["total"])), ("kept by the road filter", str(det["kept"])),
                    ("filtered", str(det["filtered"])), ("mapped onto the mesh", str(det["mapped"]))]
        tables += _kv_table(det_rows + [(f"filtered: {r}", str(n)) for r, n in sorted(det["reasons"].items())],
                            ("detections", "count"))
    heads = headline_metrics(metrics)
    if not heads and flat:
        heads = [("metrics", [(k, format_value(v)) for k, v in list(flat.items())[:12]])]
    geo = ((metrics or {}).get("mesh") or {}).get("geometry") or (metrics or {}).get("geometry")
    if isinstance(geo, dict):
        heads.append(("geometry self-check", [(k, format_value(v)) for k, v in flatten_metrics(geo).items()
                                              if k != "warnings"][:14]))
    for g, rows_ in heads:
        tables += _kv_table(rows_, (g, "value"))
    all_metrics = ""
    if flat:
        all_metrics = (f'<details class="allm"><summary>all metrics ({len(flat)})</summary><div class="cols">'
                       + _kv_table([(k, format_value(v)) for k, v in flat.items()]) + "</div></details>")
    return (f'<section id="research-section"><details id="research"><summary>Research metrics (paper statistics, '
            f'detections, geometry self-check, evaluation)</summary><div class="cards">{cards_html}</div>'
            f'<div class="kvgrid">{tables}</div>{all_metrics}</details></section>')


def _worklist(props: list[dict], det: dict, geo: bool, segments: list | None = None) -> str:
    """The first screen: urgency counts and the work list (or why there is nothing to do)."""
    prio = Counter(str(p["priority"]) for p in props)
    labels = ["repair now"] + sorted({k for k in prio if k != "repair now"}, key=lambda k: PRIORITY_ORDER.get(k, 9))
    if not props:
        labels += ["schedule", "monitor"]
    cards = [("", len(props), "defects", ' id="defect-count"')]
    cards += [(slug(k), prio.get(k, 0), k, "") for k in labels]
    cards_html = "".join(f'<div class="card {c}"><div class="v"{ident}>{_esc(v)}</div><div class="k">{_esc(k)}</div>'
                         "</div>" for c, v, k, ident in cards)
    body = (f'<div class="notice" id="no-defects">{_esc(_no_defects_message(det))}</div>' if not props else
            f'<div class="tablewrap">{worklist_table(props, geo)}</div>')
    missing = sum(not p.get("evidence") for p in props)
    note = (f'<p class="muted">{missing} of {len(props)} defects have no evidence photo (the row says why).</p>'
            if missing else "")
    return (f'<section id="worklist"><h2>Work list — {len(props)} defects, most urgent first</h2>'
            f'<div class="cards small">{cards_html}</div>{not_assessed_notice(segments)}{body}{note}</section>')


def _map(props: list[dict], instances: list[DefectInstance], bev_rgb: np.ndarray | None,
         bev_semantic: np.ndarray | None, mesh_grid: GridSpec | None, prob_map: np.ndarray | None,
         grid: GridSpec | None, trajectory: np.ndarray | None, geo_origin: GeoOrigin | None,
         metrics: dict | None = None) -> tuple[str, list]:
    """The map section (SVG layers, defects coloured by urgency, toolbars) and its home view box."""
    layers, extents = [], []
    if bev_rgb is not None and mesh_grid is not None:
        layers.append(_image_el("layer-rgb", _data_uri(np.asarray(bev_rgb)[::-1], "JPEG"), mesh_grid))
        extents.append(grid_extent(mesh_grid))
    if bev_semantic is not None and mesh_grid is not None:
        layers.append(_image_el("layer-sem", _data_uri(np.asarray(bev_semantic)[::-1], "PNG"), mesh_grid,
                                hidden=bev_rgb is not None))
        extents.append(grid_extent(mesh_grid))
    if prob_map is not None and grid is not None:
        layers.append(_image_el("layer-prob", _data_uri(_prob_rgba(prob_map), "PNG"), grid, hidden=True))
        extents.append(grid_extent(grid))
    layers.append(_contested_el(metrics))
    traj_el = ""
    if trajectory is not None and len(trajectory) > 1:
        t = np.asarray(trajectory, dtype=np.float64)
        traj_el = ('<polyline id="layer-traj" class="traj" points="'
                   + " ".join(f"{x:.2f},{-y:.2f}" for x, y in t[:, :2]) + '"/>')
    shapes, markers = [], []
    for p, inst in zip(props, instances, strict=True):
        d = _svg_path(inst.polygon)
        attrs = f'data-id="{p["id"]}" data-code-of="{p["code"]}" fill="{PRIORITY_FILL.get(p["priority"], "#999")}"'
        if d:
            shapes.append(f'<path class="d" d="{d}" fill-rule="evenodd" {attrs}><title>#{p["id"]} {p["code"]} '
                          f'{_esc(p["priority"])}</title></path>')
        cx, cy = p["x_m"] or 0.0, p["y_m"] or 0.0
        markers.append(f'<circle class="mk" cx="{cx:.3f}" cy="{-cy:.3f}" r="0.5" {attrs}/>')
        if p["bbox"] is not None:
            extents.append([p["bbox"][0], p["bbox"][2], p["bbox"][1], p["bbox"][3]])
    e = np.array(extents or [[-10.0, 10.0, -10.0, 10.0]], dtype=np.float64)
    xmin, xmax, ymin, ymax = e[:, 0].min(), e[:, 1].max(), e[:, 2].min(), e[:, 3].max()
    pad = 0.02 * max(xmax - xmin, ymax - ymin, 1.0)
    view = [round(float(v), 3) for v in (xmin - pad, -ymax - pad, xmax - xmin + 2 * pad, ymax - ymin + 2 * pad)]
    svg = (f'<svg id="map" viewBox="{" ".join(map(str, view))}" '
           f'preserveAspectRatio="xMidYMid meet">{"".join(layers)}{traj_el}<g id="defect-shapes">{"".join(shapes)}'
           f'</g><g id="defect-markers">{"".join(markers)}</g></svg>')
    compass = ""
    if geo_origin is not None:
        # north in world coordinates is (cos h, sin h); on screen y is flipped
        h = np.radians(float(geo_origin.heading_deg))
        ang = float(np.degrees(np.arctan2(np.cos(h), np.sin(h))))  # screen angle from up, clockwise
        compass = (f'<div id="compass" title="north"><div style="transform:rotate({ang:.1f}deg)">▲<br>N</div></div>')
    boxes = []
    for el_id, label, on in (("layer-rgb", "BEV RGB", bev_rgb is not None),
                             ("layer-sem", "semantics", bev_rgb is None and bev_semantic is not None),
                             ("layer-prob", "probability", False), ("layer-traj", "trajectory", True),
                             ("layer-contested", "texture may hold vehicles", True),
                             ("defect-shapes", "polygons", True), ("defect-markers", "markers", True)):
        if el_id in svg:
            boxes.append(f'<label><input type="checkbox" data-layer="{el_id}"{" checked" if on else ""}> {label}'
                         "</label>")
    classes = "".join(f'<label><input type="checkbox" data-code="{c}" checked> <span class="sw" style="background:'
                      f'{CLASS_COLOURS[c]}"></span>{c} {DEFECT_NAMES[c]}</label>' for c in DEFECT_CODES)
    shown = sorted({str(p["priority"]) for p in props} | {"repair now"}, key=lambda k: PRIORITY_ORDER.get(k, 9))
    legend = "".join(f'<span class="plegend"><span class="sw" style="background:{PRIORITY_FILL.get(k, "#999")}">'
                     f"</span>{_esc(k)}</span>" for k in shown)
    return (f'<section id="map-section"><h2>Defect map (coloured by urgency)</h2><div class="toolbar">'
            '<button id="zoom-in" title="zoom in">+</button><button id="zoom-out" title="zoom out">−</button>'
            f'<button id="zoom-home" title="fit the whole map">fit</button>{"".join(boxes)}</div>'
            f'<div class="toolbar">{legend} · show classes: {classes}</div>'
            f'<div id="map-wrap">{svg}<div id="tooltip" hidden></div><div id="scalebar"></div>{compass}'
            '<div id="maphelp">wheel: zoom · drag: pan · click: select</div></div><div id="selected"></div>'
            "</section>"), view


def _files_html(files: dict[str, Path] | None) -> str:
    """The run's files as links; the evidence photos as one line (they are linked from the work list)."""
    items = {k: p for k, p in (files or {}).items() if not str(k).startswith("evidence/")}
    n_ev = sum(str(k).startswith("evidence/") for k in (files or {}))
    lis = "".join(f'<li><a href="{_esc(Path(p).name)}">{_esc(Path(p).name)}</a> — {_esc(k)}</li>'
                  for k, p in items.items())
    if n_ev:
        lis += f'<li><a href="evidence/">evidence/</a> — {n_ev} evidence photos (best view of each defect)</li>'
    return f"<ul>{lis}</ul>" if lis else ""


def build_report_html(instances: list[DefectInstance], *, bev_rgb: np.ndarray | None = None,
                      bev_semantic: np.ndarray | None = None, mesh_grid: GridSpec | None = None,
                      prob_map: np.ndarray | None = None, grid: GridSpec | None = None,
                      geo_origin: GeoOrigin | None = None, metrics: dict | None = None,
                      config: dict | None = None, detections: list[dict] | None = None,
                      figures: dict[str, Path] | None = None, files: dict[str, Path] | None = None,
                      trajectory: np.ndarray | None = None, title: str = "pavemap defect report",
                      subtitle: str = "", segments: list | None = None) -> str:
    """The report page as a string (see ``write_report``)."""
    props = [instance_properties(i, geo_origin) for i in instances]
    for p, inst in zip(props, instances, strict=True):
        g = inst.polygon
        p["bbox"] = [round(float(v), 3) for v in g.bounds] if g is not None and not g.is_empty else None
    det = _detection_summary(detections)
    map_html, view = _map(props, instances, bev_rgb, bev_semantic, mesh_grid, prob_map, grid, trajectory, geo_origin,
                          metrics)
    head, rows = _table_rows(props, geo_origin is not None)
    figs = "".join(f'<figure><img alt="{_esc(name)}" src="{_file_uri(path)}"><figcaption>{_esc(name)}'
                   "</figcaption></figure>" for name, path in (figures or {}).items() if Path(path).is_file())
    cfg_flat = flatten_metrics(config)
    settings = _kv_table([(k, format_value(v)) for k, v in cfg_flat.items()], ("setting", "value")) if cfg_flat \
        else "<p>No settings recorded.</p>"
    cfg_json = _esc(json.dumps(config or {}, indent=2, default=str))
    geo_txt = ("local world metres (no geo origin)" if geo_origin is None else
               f"WGS84 via origin {geo_origin.lat:.7f}, {geo_origin.lon:.7f}, heading {geo_origin.heading_deg:g}°")
    fit = (geo_origin.georef or {}) if geo_origin is not None else {}
    if fit.get("rms_m") is not None:
        geo_txt += (f", fitted to GPS {Path(str(fit.get('source', ''))).name}: residual RMS {fit['rms_m']:.2f} m over "
                    f"{fit.get('inliers')} of {fit.get('fixes')} fixes")
    files_html = _files_html(files)
    data = {"defects": props, "view": view, "geo": geo_origin is not None}
    data_json = json.dumps(data, allow_nan=False, separators=(",", ":")).replace("</", "<\\/")
    now = _dt.datetime.now(_dt.UTC).strftime("%Y-%m-%d %H:%M UTC")
    sub = subtitle or f"{len(props)} defect instances · coordinates: {geo_txt}"
    return f"""<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8">
<meta name="viewport" content="width=device-width, initial-scale=1">
<link rel="icon" href="data:,">
<title>{_esc(title)}</title>
<style>{CSS}{FIELD_CSS}{PRINT_CSS}</style></head>
<body>
<header><h1>{_esc(title)}</h1><div class="sub">{_esc(sub)}</div></header>
<main>
{_geometry_banner(metrics)}{_texture_banner(metrics)}{detector_banner(metrics)}
<div class="first">{_worklist(props, det, geo_origin is not None, segments)}
<div class="side">{map_html}{segment_strip(segments)}</div></div>
<section id="defects-section"><h2>All measures (<span id="shown-count">{len(props)}</span> shown of
{len(props)}; most urgent first — click a header to sort)</h2>
{'<p>No defects to list.</p>' if not props else ''}
<div class="tablewrap"><table id="defects"><thead><tr>{head}</tr></thead><tbody>{rows}</tbody></table></div>
</section>
{_research(props, det, metrics)}
{f'<section id="figures"><h2>Figures</h2><div class="figs">{figs}</div></section>' if figs else ''}
<section id="settings"><h2>Run settings</h2><p>Coordinates: {_esc(geo_txt)}.</p>{settings}
<details><summary>resolved configuration (JSON)</summary><pre>{cfg_json}</pre></details>
{f'<h2 style="margin-top:12px">Files</h2>{files_html}' if files_html else ''}</section>
</main>
<footer>pavemap {_esc(__version__)} · generated {_esc(now)} · self-contained except the evidence/ photos</footer>
<script id="pavemap-data" type="application/json">{data_json}</script>
<script>{JS}</script>
</body></html>
"""


def _stage1(metrics: dict | None, key: str) -> dict:
    """Stage 1's ``key`` section from the run's metrics (``mesh`` → key) or a mesh's own metrics; {} when none."""
    return ((metrics or {}).get("mesh") or {}).get(key) or (metrics or {}).get(key) or {}


def _geometry_banner(metrics: dict | None) -> str:
    """A visible banner with the run's geometry warnings (stage 1's self-check, issue 12); empty when none."""
    geo = _stage1(metrics, "geometry")
    warns = geo.get("warnings") or []
    if not warns:
        return ""
    bad = geo.get("trustworthy") is False
    head = "Road surface not trustworthy" if bad else "Road surface: warnings"
    colour = "#b71c1c" if bad else "#8a6d00"
    items = "".join(f"<li>{_esc(w)}</li>" for w in warns)
    return (f'<div id="geometry-warning" role="alert" style="border:2px solid {colour};background:#fff4f2;'
            f'padding:8px 12px;margin:0 0 12px"><b style="color:{colour}">{head}</b><ul>{items}</ul></div>')


def _contested_el(metrics: dict | None) -> str:
    """The texture check's patches on the map: a dashed circle of each patch's area around its centre (the
    patches, not their outlines, are in metrics.json; bev_contested.npy has the cells); empty when none."""
    patches = _stage1(metrics, "texture_check").get("patches") or []
    circles = "".join(f'<circle cx="{p["x_m"]:.2f}" cy="{-p["y_m"]:.2f}" '
                      f'r="{max(0.5, (p["area_m2"] / np.pi) ** 0.5):.2f}"><title>texture may hold a vehicle: '
                      f'{p["area_m2"]:.1f} m²</title></circle>' for p in patches)
    return (f'<g id="layer-contested" fill="none" stroke="#e6a100" stroke-width="0.25" stroke-dasharray="0.6 0.4">'
            f"{circles}</g>") if circles else ""


def _texture_banner(metrics: dict | None) -> str:
    """Where the BEV texture may hold vehicles (stage 1's texture check, pavemap.mesh.texture_check; issue 13);
    empty when nothing is contested."""
    tc = _stage1(metrics, "texture_check")
    if not tc.get("contested_m2"):
        return ""
    where = "".join(f"<li>{p['area_m2']:.1f} m² at x {p['x_m']:.1f}, y {p['y_m']:.1f} m (local metres)</li>"
                    for p in tc.get("patches", [])[:5])
    more = tc.get("patch_count", 0) - min(5, len(tc.get("patches", [])))
    return ('<div id="texture-warning" role="note" style="border:2px solid #8a6d00;background:#fffbe6;padding:8px 12px;'
            f'margin:0 0 12px"><b style="color:#8a6d00">BEV texture: may hold vehicles</b> over '
            f'{tc["contested_m2"]:.1f} m² in {tc.get("patch_count", 0)} patch(es), where some views disagree with '
            f'it: a vehicle, sun glare on the road, or poses or surface off there (bev_contested.npy; dashed circles '
            f'on the map)<ul>{where}'
            f'{f"<li>… {more} more</li>" if more > 0 else ""}</ul>'
            'Detections come from the frames, not the texture: the map of defects is not affected. A vehicle that '
            'covered the road in every view that saw it cannot be told from the road by this check.</div>')


def write_report(out_dir: str | os.PathLike, instances: list[DefectInstance], **kwargs) -> Path:
    """Write ``out_dir/report.html`` atomically and return its path.

    Keyword arguments as ``build_report_html``: bev_rgb (ny, nx, 3) uint8 and bev_semantic on mesh_grid,
    prob_map (H, W) on grid, geo_origin, metrics, config, detections (records with kept/reason/mapped),
    figures {caption: png path}, files {description: path}, trajectory (F, 2|3), title, subtitle,
    segments (road segments with chainage start/end and a condition index, drawn as the segment strip).
    """
    path = Path(out_dir) / "report.html"
    return atomic_write_text(path, build_report_html(instances, **kwargs))


__all__ = ["build_report_html", "write_report"]
