"""The field part of ``report.html``: the work list, the segment strip and the print stylesheet.

The work list is what a crew works from: one row per defect, most urgent first (``priority_rank``),
with what to look for (class, severity, size or depth), where (chainage along the route, lat/lon)
and a photo to recognise it (``evidence/<id>.jpg``, linked relatively, next to the report). A column
no record has is left out, so a run without the maintenance measures still gives a sensible list.
"""

from __future__ import annotations

import html

from pavemap.export.figures import CLASS_COLOURS
from pavemap.palette import NOT_ASSESSED_HEX, PRIORITY_HEX, index_colour

# urgency labels, issue 16 (repair now / schedule / monitor) and the earlier ones (inspect / no action)
PRIORITY_ORDER = {"repair now": 0, "schedule": 1, "inspect": 1, "monitor": 2, "no action": 3, "unassessed": 4}
PRIORITY_FILL = PRIORITY_HEX  # one home: pavemap.palette (the QGIS styles use the same)
SEVERITY_ORDER = {"high": 0, "medium": 1, "low": 2}


def _esc(v: object) -> str:
    return html.escape(str(v), quote=True)


def slug(v: object) -> str:
    return str(v).replace(" ", "-")


def paper_severity(p: dict) -> float:
    """The EMA severity of a record (``paper_severity``; ``severity`` before issue 16), 0 when unknown."""
    v = p.get("paper_severity", p.get("severity"))
    return float(v) if isinstance(v, (int, float)) else 0.0


def order_records(props: list[dict]) -> list[dict]:
    """Most urgent first: by ``priority_rank`` when assessed, else by urgency label, then severity, id."""
    def key(p: dict) -> tuple:
        rank = p.get("priority_rank")
        return (rank if isinstance(rank, int) else 1 << 30, PRIORITY_ORDER.get(str(p.get("priority")), 9),
                SEVERITY_ORDER.get(str(p.get("severity_level")), 9), -paper_severity(p), p["id"])
    return sorted(props, key=key)


def _fmt(v: object, nd: int) -> str:
    return "–" if not isinstance(v, (int, float)) or isinstance(v, bool) else f"{v:.{nd}f}"


def size_text(p: dict) -> str:
    """What to measure on site: crack length, area, and a pothole's depth ("not measurable" when so)."""
    code = p.get("code")
    parts = []
    if code in ("D00", "D10"):
        length = p.get("crack_length_m", p.get("length_m"))
        if isinstance(length, (int, float)):
            parts.append(f"{length:.1f} m long")
    if isinstance(p.get("area_m2"), (int, float)) and code not in ("D00", "D10"):
        parts.append(f"{p['area_m2']:.2f} m²")
    if code == "D40" and ("depth_max_mm" in p or "measurable" in p):
        if isinstance(p.get("depth_max_mm"), (int, float)) and p.get("measurable") is not False:
            d = f"depth {p['depth_max_mm']:.0f} mm"
            if isinstance(p.get("depth_sigma_mm"), (int, float)):
                d += f" ± {p['depth_sigma_mm']:.0f}"
            if isinstance(p.get("volume_l"), (int, float)):
                d += f", {p['volume_l']:.1f} l"
            parts.append(d)
        else:
            note = p.get("measure_note")
            parts.append("depth not measurable" + (f" ({note})" if note else ""))
    return " · ".join(parts) or "–"


def _photo_cell(p: dict) -> str:
    ev = p.get("evidence")
    if ev:
        return (f'<td class="photo"><a href="{_esc(ev)}" target="_blank" title="full crop">'
                f'<img class="thumb" src="{_esc(ev)}" alt="defect {p["id"]} evidence photo"></a></td>')
    note = p.get("evidence_note") or "no photo"
    return f'<td class="photo nophoto">{_esc(note)}</td>'


def _columns(props: list[dict], geo: bool) -> list[tuple[str, str]]:
    """(key, header) of the work-list columns some record has a value for."""
    def some(*keys: str) -> bool:
        return any(p.get(k) is not None for p in props for k in keys)

    cols = [("priority_rank", "rank")] if some("priority_rank") else []
    cols += [("id", "defect"), ("code", "class"), ("priority", "urgency")]
    cols += [("severity_level", "severity")] if some("severity_level") else []
    cols += [("size", "size / depth")]
    cols += [("chainage_m", "chainage m")] if some("chainage_m") else []
    cols += [("latlon", "lat, lon")] if geo and some("lat") else []
    cols += [("certainty", "certainty")] if some("certainty") else []
    cols += [("photo", "photo")]
    return cols


def _cell(k: str, p: dict) -> str:
    v = p.get(k)
    if k == "photo":
        return _photo_cell(p)
    if k == "id":
        return f'<td class="num id">#{p["id"]}</td>'
    if k == "code":
        # a defect where the texture may hold a vehicle (pavemap.mesh.texture_check): its detections may be one
        warn = ('<div class="muted vehicle-warning">a vehicle may have been here: check the photo</div>'
                if p.get("texture_contested") else "")
        return (f'<td><span class="sw" style="background:{CLASS_COLOURS.get(str(v), "#999")}"></span>{_esc(v)} '
                f'<span class="muted">{_esc(p.get("name", ""))}</span>{warn}</td>')
    if k == "priority":
        return f'<td><span class="pill {_esc(slug(v))}">{_esc(v)}</span></td>'
    if k == "severity_level":
        return f'<td><span class="lvl {_esc(v)}">{_esc(v if v is not None else "–")}</span></td>'
    if k == "size":
        return f"<td>{_esc(size_text(p))}</td>"
    if k == "chainage_m":
        lane = p.get("lane_position")
        off = p.get("offset_m")
        sub = " · ".join(x for x in (lane if lane else "", f"{off:+.1f} m" if isinstance(off, (int, float))
                                     else "") if x)
        return (f'<td class="num">{_esc(_fmt(v, 1))}' + (f'<div class="muted">{_esc(sub)}</div>' if sub else "")
                + "</td>")
    if k == "latlon":
        lat, lon = p.get("lat"), p.get("lon")
        return f'<td class="num">{_esc(_fmt(lat, 6))}, {_esc(_fmt(lon, 6))}</td>' if lat is not None \
            else "<td>–</td>"
    return f'<td class="num">{_esc("–" if v is None else v)}</td>'


def worklist_table(props: list[dict], geo: bool) -> str:
    """The work-list ``<table id="worklist-table">``, one defect per row, most urgent first."""
    cols = _columns(props, geo)
    head = "".join(f'<th data-key="{k}">{_esc(h)}</th>' for k, h in cols)
    rows = "".join(f'<tr class="wl {_esc(slug(p["priority"]))}" data-id="{p["id"]}" data-code-of="{_esc(p["code"])}">'
                   + "".join(_cell(k, p) for k, _ in cols) + "</tr>" for p in order_records(props))
    return f'<table id="worklist-table"><thead><tr>{head}</tr></thead><tbody>{rows}</tbody></table>'


def _field(seg: object, *names: str) -> object:
    """A segment attribute under any of ``names`` (dataclass attribute or dict key), else None."""
    for n in names:
        v = seg.get(n) if isinstance(seg, dict) else getattr(seg, n, None)
        if v is not None:
            return v
    return None


#: Fill of a segment without an index ("not assessed": the survey could not see it well enough), never green.
NOT_ASSESSED_FILL = NOT_ASSESSED_HEX


def _not_assessed(seg: object) -> bool:
    """A segment that says it was not assessed (``assessed`` False), or one without an index."""
    return _field(seg, "assessed") is False or not isinstance(_field(seg, "index", "pci", "condition_index",
                                                                      "pci_like"), (int, float))


def not_assessed_notice(segments: list | None) -> str:
    """A notice above the work list naming the stretches not assessed and why ('' when every one was): the list
    may miss defects there, and the road there is not known to be good."""
    bad = [s for s in segments or [] if _not_assessed(s)]
    if not bad:
        return ""
    def ends(s: object) -> tuple[object, object]:
        return _field(s, "start_m", "chainage_start_m"), _field(s, "end_m", "chainage_end_m")

    total = sum(float(b or 0) - float(a or 0) for a, b in map(ends, bad))
    items = "".join(f'<li>segment {_esc(_field(s, "id", "segment"))} ({_fmt(ends(s)[0], 0)}–{_fmt(ends(s)[1], 0)} '
                    f'm): {_esc(_field(s, "not_assessed_reason") or "no condition index")}</li>' for s in bad)
    return (f'<div class="notice not-assessed" id="not-assessed"><b>Not assessed: {len(bad)} of {len(segments or [])}'
            f' segments ({total:.0f} m).</b> The survey did not see them well enough to find the smallest defect the '
            f'policy cares about, so this list may miss defects there and their condition is unknown (not good).'
            f'<ul>{items}</ul></div>')


def detector_banner(metrics: dict | None) -> str:
    """A banner when the detector found almost nothing above tau_conf on this footage (metrics.json →
    maintenance → detector_confidence, :mod:`pavemap.maintain.assessment`); empty otherwise."""
    chk = ((metrics or {}).get("maintenance") or {}).get("detector_confidence") or {}
    if not chk.get("low"):
        return ""
    return ('<div id="detector-warning" role="alert" style="border:2px solid #8a6d00;background:#fffbe6;'
            f'padding:8px 12px;margin:0 0 12px"><b style="color:#8a6d00">Detector nearly blind on this footage</b>'
            f'<p>{_esc(chk.get("message", ""))}</p></div>')


def segment_strip(segments: list | None) -> str:
    """An inline SVG: the road's segments along chainage, coloured and labelled by their condition index."""
    segs = []
    for s in segments or []:
        a = _field(s, "start_m", "chainage_start_m", "chainage_start", "start")
        b = _field(s, "end_m", "chainage_end_m", "chainage_end", "end")
        idx = None if _not_assessed(s) else _field(s, "index", "pci", "condition_index", "pci_like")
        if isinstance(a, (int, float)) and isinstance(b, (int, float)) and b > a:
            counts = _field(s, "counts")
            n = sum(counts.values()) if isinstance(counts, dict) else _field(s, "defects")
            segs.append((float(a), float(b), idx, _field(s, "id", "segment"), _field(s, "rating", "grade"), n))
    if not segs:
        return ""
    x0, x1 = min(s[0] for s in segs), max(s[1] for s in segs)
    W, H = 1000.0, 46.0
    k = W / max(x1 - x0, 1e-9)
    parts = []
    for a, b, idx, sid, grade, n in segs:
        has = isinstance(idx, (int, float))
        col = index_colour(float(idx)) if has else NOT_ASSESSED_FILL
        x, w = (a - x0) * k, max((b - a) * k, 0.5)
        state = f"PCI-like index {_fmt(idx, 0)}" + (f" ({grade})" if grade else "") if has else "not assessed"
        tip = f"segment {sid}: {a:.0f}–{b:.0f} m, {state}" + (f", {n} defects" if n is not None else "")
        label = _fmt(idx, 0) if has else "n/a"
        parts.append(f'<g class="seg{"" if has else " not-assessed"}" data-seg="{_esc(sid)}"><title>{_esc(tip)}'
                     f'</title><rect x="{x:.2f}" y="0" width="{w:.2f}" height="{H - 16:.0f}" fill="{col}" '
                     f'stroke="#fff"/>' + (f'<text x="{x + w / 2:.2f}" y="20" text-anchor="middle">{label}</text>'
                                          if w > 22 else "") + "</g>")
    ticks = "".join(f'<text class="tick" x="{(c - x0) * k:.2f}" y="{H - 3:.0f}" text-anchor="'
                    f'{"start" if c == x0 else "end" if c == x1 else "middle"}">{c:.0f} m</text>'
                    for c in sorted({x0, x1, *(s[0] for s in segs[1:])}) if c in (x0, x1) or len(segs) <= 12)
    legend = " ".join(f'<span class="sw" style="background:{index_colour(v)}"></span>{lab}'
                      for v, lab in ((10, "&lt;25"), (30, "25–40"), (50, "40–55"), (60, "55–70"), (80, "70–85"),
                                     (90, "≥85")))
    legend += f' <span class="sw" style="background:{NOT_ASSESSED_FILL}"></span>not assessed (not seen well enough)'

    return (f'<section id="segments"><h2>Road condition by segment (PCI-like index 0–100, along chainage)</h2>'
            f'<svg id="segment-strip" viewBox="0 0 {W:.0f} {H:.0f}" preserveAspectRatio="none">{"".join(parts)}'
            f'{ticks}</svg><div class="legend">{legend}</div></section>')


FIELD_CSS = r"""
.muted { color:var(--muted); font-size:11.5px; }
.first { display:grid; grid-template-columns:minmax(0,1.25fr) minmax(0,1fr); gap:16px; margin-bottom:16px; }
@media (max-width:1100px) { .first { grid-template-columns:1fr; } }
.first > section, .side { margin-bottom:0; min-width:0; }
.side > section { margin-bottom:16px; } .side > section:last-child { margin-bottom:0; }
#worklist .tablewrap { max-height:calc(100vh - 190px); min-height:300px; }
#worklist-table { font-size:13px; }
#worklist-table th { position:sticky; top:0; background:#eef1f6; text-align:left; padding:6px; white-space:nowrap;
  border-bottom:1px solid var(--line); z-index:1; }
#worklist-table td { padding:4px 6px; border-bottom:1px solid #eef0f4; vertical-align:middle; }
#worklist-table td.num { text-align:right; font-variant-numeric:tabular-nums; white-space:nowrap; }
#worklist-table td.id { font-weight:650; }
#worklist-table tbody tr { cursor:pointer; }
#worklist-table tbody tr:hover { background:#f3f7fd; }
#worklist-table tbody tr.sel { background:#d8f5fb; outline:2px solid var(--sel); outline-offset:-2px; }
#worklist-table tr.repair-now td:first-child { box-shadow:inset 4px 0 0 var(--repair); }
img.thumb { height:64px; width:auto; max-width:128px; display:block; border-radius:3px; border:1px solid #ccd; }
td.nophoto { color:#8a3b00; font-size:11.5px; max-width:220px; white-space:normal; }
.lvl { font-weight:600; } .lvl.high { color:var(--repair); } .lvl.medium { color:#b35c00; } .lvl.low { color:#5c6677; }
.pill.schedule { background:var(--inspect); } .pill.monitor { background:#f1c40f; color:#222; }
.cards.small .card { min-width:90px; padding:4px 10px; } .cards.small .card .v { font-size:18px; }
.card.schedule .v { color:var(--inspect); } .card.monitor .v { color:#b7950b; }
#segment-strip { width:100%; height:64px; display:block; }
#segment-strip text { font-size:13px; fill:#111; } #segment-strip text.tick { font-size:11px; fill:#5c6677; }
#segments .legend { font-size:12px; color:var(--muted); margin-top:4px; }
.notice.not-assessed { background:#eeeeee; border-left:4px solid #757575; margin-bottom:8px; }
.notice.not-assessed ul { margin:4px 0 0 18px; padding:0; font-size:12px; }
details#research > summary { cursor:pointer; font-size:16px; font-weight:600; }
details#research[open] > summary { margin-bottom:10px; }
.plegend { font-size:12px; }
"""

PRINT_CSS = r"""
@page { size: A4; margin: 12mm 10mm; }
@media print {
  body { background:#fff; font-size:10pt; }
  header { background:none; color:#000; padding:0 0 3mm; border-bottom:1px solid #000; }
  header .sub { color:#333; }
  main { padding:0; max-width:none; }
  #map-section, #defects-section, #figures, #research, #settings, .toolbar, #selected, #maphelp, footer,
  details { display:none !important; }
  .first, .side { display:block; }
  section { border:none; border-radius:0; padding:0; margin:3mm 0; background:#fff; }
  #worklist .tablewrap { max-height:none; min-height:0; overflow:visible; border:none; }
  #worklist-table { font-size:9.5pt; }
  #worklist-table thead { display:table-header-group; }
  #worklist-table th { position:static; background:#eee; }
  #worklist-table tr { break-inside:avoid; page-break-inside:avoid; }
  #worklist-table td { border-bottom:1px solid #999; padding:1.5mm 1.5mm; }
  img.thumb { height:auto; width:48mm; max-width:48mm; max-height:36mm; object-fit:contain; }
  a { color:inherit; text-decoration:none; }
  .pill, .sw, #segment-strip rect { -webkit-print-color-adjust:exact; print-color-adjust:exact; }
}
"""

__all__ = ["FIELD_CSS", "NOT_ASSESSED_FILL", "PRINT_CSS", "PRIORITY_FILL", "PRIORITY_ORDER", "detector_banner",
           "not_assessed_notice", "order_records", "paper_severity", "segment_strip", "size_text", "worklist_table"]
