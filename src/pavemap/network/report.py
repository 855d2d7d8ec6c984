"""``NETWORK/network.html``: one self-contained page for a network survey.

The drives table (status, defects, time, worker, errors, a link to each run's own report), a map
(inline SVG in the register CRS: the drives' trajectories, condition segments coloured by their
index when the runs wrote segments, the physical defects coloured by status) and the register table.
No scripts, no external files: it opens from a file share or an e-mail.
"""

from __future__ import annotations

import html
import os
from pathlib import Path

import numpy as np
import shapely

from pavemap.io.atomic import atomic_write_text
from pavemap.palette import STATUS_HEX

PAGE = "network.html"
STATUS_COLOURS = STATUS_HEX
#: Fields a segments layer may carry its condition in (0-100, higher is better), first found wins.
CONDITION_FIELDS = ("pci", "condition_index", "condition", "index", "score")
#: Colour of a segment without an index (issue 41: not assessed is not perfect).
NOT_ASSESSED = "#b0b0b0"
_W, _H = 900.0, 420.0


def _esc(v: object) -> str:
    if v is None or (isinstance(v, float) and not np.isfinite(v)):
        return ""
    return html.escape(f"{v:.3g}" if isinstance(v, float) else str(v))


def _table(rows: list[dict], cols: list[str]) -> str:
    head = "".join(f"<th>{html.escape(c)}</th>" for c in cols)
    body = "".join("<tr>" + "".join(f"<td>{r.get(c, '') if c == 'report' else _esc(r.get(c))}</td>" for c in cols)
                   + "</tr>" for r in rows)
    return f"<table><thead><tr>{head}</tr></thead><tbody>{body}</tbody></table>"


def _read_layer(gpkg: Path, layer: str) -> tuple[list, list[dict]]:
    import pyogrio

    from pavemap.export.gis import _plain

    try:
        meta, _, geoms, values = pyogrio.raw.read(gpkg, layer=layer)
    except Exception:  # noqa: BLE001 - a missing layer draws nothing
        return [], []
    recs = [{n: _plain(v[k]) for n, v in zip(meta["fields"], values, strict=True)} for k in range(len(geoms))]
    return [None if g is None else shapely.from_wkb(g) for g in geoms], recs


def _assessed(rec: dict, field: str | None) -> bool:
    """Whether a segments-layer record has a condition index (``assessed`` not false and a finite value)."""
    if field is None or rec.get("assessed") in (False, 0):
        return False
    v = rec.get(field)
    return isinstance(v, int | float) and bool(np.isfinite(v))


def _condition_colour(v: float) -> str:
    """0 (failed) red -> 50 yellow -> 100 (good) green."""
    t = float(np.clip(v / 100.0, 0, 1))
    r, g = (1.0, 2 * t) if t < 0.5 else (2 * (1 - t), 1.0)
    return f"#{int(r * 220):02x}{int(g * 190):02x}30"


def _svg(gpkg: Path) -> str:
    drives, _ = _read_layer(gpkg, "drives")
    segs, seg_recs = _read_layer(gpkg, "segments")
    dgeoms, drecs = _read_layer(gpkg, "defects")
    allg = [g for g in drives + segs + dgeoms if g is not None]
    if not allg:
        return "<p>(nothing to draw)</p>"
    x0, y0, x1, y1 = shapely.total_bounds(np.asarray(allg, dtype=object))
    s = min((_W - 20) / max(x1 - x0, 1e-6), (_H - 20) / max(y1 - y0, 1e-6))

    def xy(c: np.ndarray) -> str:
        return " ".join(f"{10 + (x - x0) * s:.1f},{_H - 10 - (y - y0) * s:.1f}" for x, y in c[:, :2])

    def lines(g: object) -> list[np.ndarray]:
        parts = getattr(g, "geoms", [g])
        return [np.asarray(p.exterior.coords if p.geom_type == "Polygon" else p.coords) for p in parts]

    out = [f'<svg xmlns="http://www.w3.org/2000/svg" width="{_W:.0f}" height="{_H:.0f}" class="map">']
    for g in drives:
        out += [f'<polyline points="{xy(c)}" fill="none" stroke="#999" stroke-width="2"/>' for c in lines(g)]
    field = next((f for f in CONDITION_FIELDS if any(isinstance(r.get(f), int | float) for r in seg_recs)), None)
    n_na = 0
    for g, r in zip(segs, seg_recs, strict=True):
        na = not _assessed(r, field)  # a segment without an index is grey, never a condition colour
        n_na += na
        col = NOT_ASSESSED if na else _condition_colour(float(r[field])) if field else "#555"
        out += [f'<polyline points="{xy(c)}" fill="none" stroke="{col}" stroke-width="5" opacity="0.8"/>'
                for c in lines(g)]
    for g, r in zip(dgeoms, drecs, strict=True):
        if g is None:
            continue
        c = g.centroid
        px, py = 10 + (c.x - x0) * s, _H - 10 - (c.y - y0) * s
        out.append(f'<circle cx="{px:.1f}" cy="{py:.1f}" r="4" fill="{STATUS_COLOURS.get(r.get("status"), "#000")}">'
                   f'<title>#{r.get("id")} {_esc(r.get("code"))} {_esc(r.get("status"))}</title></circle>')
    out.append("</svg>")
    legend = " ".join(f'<span style="color:{c}">&#9679; {s}</span>' for s, c in STATUS_COLOURS.items())
    seg_note = (f"; segments coloured by {field} (red 0 - green 100)" + (
        f'; <span style="color:{NOT_ASSESSED}">light grey</span>: {n_na} segments not assessed (not seen well '
        "enough for an index)" if n_na else "") if field else
                "; no condition segments in these runs" if not segs else "; segments without a condition field")
    return "".join(out) + f"<p>{legend} &nbsp; grey: trajectories{seg_note}</p>"


def write_network_page(net: str | os.PathLike) -> Path:
    """Write ``NETWORK/network.html`` from ``network.json`` and ``register.gpkg`` (when built)."""
    from pavemap.network.folder import read_network
    from pavemap.network.register import REGISTER_GPKG

    net = Path(net)
    status = read_network(net)
    rows = []
    for e in status["drives"]:
        r = dict(e)
        rep = net / e["run"] / "report.html"
        r["report"] = f'<a href="{html.escape(e["run"])}/report.html">report</a>' if rep.is_file() else ""
        rows.append(r)
    import json

    from pavemap.network.register import REGISTER_JSON

    reg = status.get("register") or {}
    if (net / REGISTER_JSON).is_file() and not reg.get("error"):  # `pavemap register` rebuilds it later
        reg = json.loads((net / REGISTER_JSON).read_text(encoding="utf-8"))
    parts = [f"<h1>Network survey: {len(rows)} drives</h1>",
             f"<p>manifest {_esc(status.get('manifest'))}; scheduler {_esc(status.get('scheduler'))}; "
             f"updated {_esc(status.get('updated_utc'))}</p>", "<h2>Drives</h2>",
             _table(rows, ["name", "date", "vehicle", "status", "defects", "seconds", "worker", "peak_rss_mb",
                           "report", "error"])]
    gpkg = net / REGISTER_GPKG
    if reg.get("error"):
        parts.append(f"<h2>Register</h2><p class='err'>not built: {_esc(reg['error'])}</p>")
    elif gpkg.is_file():
        _, recs = _read_layer(gpkg, "defects")
        counts = ", ".join(f"{k} {v}" for k, v in (reg.get("status_counts") or {}).items())
        parts += ["<h2>Map</h2>", _svg(gpkg),
                  f"<h2>Register</h2><p>{len(recs)} physical defects from {_esc(reg.get('observations'))} "
                  f"observations ({_esc(counts)}); {_esc(reg.get('crs'))}; register.gpkg</p>",
                  _table(recs, ["id", "code", "status", "reasons", "first_seen", "last_seen", "sightings", "drives",
                                "area_prev_m2", "area_last_m2", "depth_prev_mm", "depth_last_mm", "lon", "lat"])]
    style = ("body{font-family:sans-serif;margin:1.5em}table{border-collapse:collapse;font-size:13px}"
             "td,th{border:1px solid #ccc;padding:2px 6px}th{background:#eee}.err{color:#b00}"
             ".map{border:1px solid #ccc;background:#fafafa}")
    page = (f"<!DOCTYPE html><html><head><meta charset='utf-8'><title>pavemap network</title>"
            f"<style>{style}</style></head><body>{''.join(parts)}</body></html>\n")
    return atomic_write_text(net / PAGE, page)


__all__ = ["PAGE", "write_network_page"]
