"""CSS and JavaScript inlined into ``report.html`` (kept apart from the Python that fills it in).

No external resources: system font stacks only, no CDN, no network requests.
"""

CSS = r"""
:root { --fg:#1d2430; --muted:#5c6677; --line:#d9dee7; --bg:#f4f6f9; --card:#fff; --accent:#1565c0;
  --sel:#00b8d4; --D00:#2ca02c; --D10:#f5d300; --D20:#ff7f0e; --D40:#d62728;
  --repair:#c0392b; --inspect:#e67e22; --none:#7f8c8d; }
* { box-sizing:border-box; }
body { margin:0; font:14px/1.45 system-ui,-apple-system,"Segoe UI",Roboto,"Helvetica Neue",Arial,sans-serif;
  color:var(--fg); background:var(--bg); }
header { background:#17202e; color:#fff; padding:14px 24px; display:flex; align-items:baseline; gap:18px;
  flex-wrap:wrap; }
header h1 { margin:0; font-size:20px; font-weight:600; }
header .sub { color:#b8c2d3; font-size:13px; }
main { padding:16px 24px 8px; max-width:1700px; margin:0 auto; }
section { background:var(--card); border:1px solid var(--line); border-radius:8px; padding:14px 16px;
  margin-bottom:16px; }
h2 { font-size:16px; margin:0 0 10px; }
.cards { display:flex; flex-wrap:wrap; gap:10px; margin-bottom:10px; }
.card { border:1px solid var(--line); border-radius:6px; padding:8px 12px; min-width:112px; background:#fafbfd; }
.card .v { font-size:22px; font-weight:650; }
.card .k { color:var(--muted); font-size:12px; }
.card.repair .v { color:var(--repair); } .card.inspect .v { color:var(--inspect); }
.card.none .v { color:var(--none); }
.notice { border-left:4px solid var(--accent); background:#eef4fc; padding:10px 14px; margin:8px 0;
  border-radius:4px; font-size:15px; }
table { border-collapse:collapse; width:100%; }
table.kv { width:auto; min-width:200px; font-size:13px; }
table.kv td, table.kv th { padding:3px 10px 3px 0; border-bottom:1px solid #eef0f4; text-align:left;
  vertical-align:top; }
table.kv td.num { font-variant-numeric:tabular-nums; }
.kvgrid { display:flex; gap:22px; flex-wrap:wrap; align-items:flex-start; }
.split { display:grid; grid-template-columns:minmax(0,1.1fr) minmax(0,1fr); gap:16px; }
@media (max-width:1100px) { .split { grid-template-columns:1fr; } }
.split > section { margin-bottom:0; min-width:0; }
.toolbar { display:flex; flex-wrap:wrap; gap:6px 14px; align-items:center; margin-bottom:8px; font-size:13px; }
.toolbar button { border:1px solid var(--line); background:#fff; border-radius:4px; padding:2px 9px;
  cursor:pointer; font-size:14px; }
.toolbar button:hover { background:#eef2f7; }
.toolbar label { cursor:pointer; white-space:nowrap; }
.sw { display:inline-block; width:11px; height:11px; border:1px solid #333; border-radius:2px;
  vertical-align:-1px; margin-right:3px; }
#map-wrap { position:relative; height:620px; border:1px solid var(--line); border-radius:6px; overflow:hidden;
  background:#2b2f36; }
#map { width:100%; height:100%; display:block; cursor:grab; touch-action:none; user-select:none; }
#map.dragging { cursor:grabbing; }
#map .d { stroke:#111; stroke-width:1.2px; vector-effect:non-scaling-stroke; fill-opacity:0.6; cursor:pointer; }
#map .mk { stroke:#111; stroke-width:1px; vector-effect:non-scaling-stroke; fill-opacity:0.95; cursor:pointer; }
#map .d:hover, #map .mk:hover { stroke:#fff; stroke-width:2px; }
#map .sel { stroke:var(--sel) !important; stroke-width:3.5px !important; fill-opacity:0.85; }
#map .traj { fill:none; stroke:#7fd3ff; stroke-width:1.5px; stroke-dasharray:5 4; vector-effect:non-scaling-stroke;
  opacity:0.8; }
.hidden { display:none !important; }
#tooltip { position:absolute; pointer-events:none; background:rgba(20,24,32,0.94); color:#fff; padding:7px 10px;
  border-radius:5px; font-size:12px; line-height:1.35; max-width:300px; z-index:5; box-shadow:0 2px 8px #0006; }
#tooltip b { font-size:13px; }
#tooltip table td { padding:0 8px 0 0; color:#e9eef6; }
#scalebar { position:absolute; left:12px; bottom:12px; color:#fff; font-size:12px; text-shadow:0 0 3px #000; }
#scalebar .bar { height:6px; border:2px solid #fff; border-top:none; margin-top:2px; }
#compass { position:absolute; right:12px; top:12px; width:40px; height:40px; color:#fff; font-weight:700;
  font-size:12px; text-align:center; text-shadow:0 0 3px #000; }
#maphelp { position:absolute; right:12px; bottom:10px; color:#cfd6e2; font-size:11px; text-shadow:0 0 3px #000; }
#selected { margin-top:8px; min-height:22px; font-size:13px; color:var(--muted); }
#selected b { color:var(--fg); }
.tablewrap { max-height:620px; overflow:auto; border:1px solid var(--line); border-radius:6px; }
#defects { font-size:12.5px; }
#defects th { position:sticky; top:0; background:#eef1f6; text-align:left; padding:6px 6px; cursor:pointer;
  white-space:nowrap; border-bottom:1px solid var(--line); user-select:none; }
#defects th .arrow { color:var(--muted); font-size:11px; }
#defects td { padding:4px 6px; border-bottom:1px solid #eef0f4; white-space:nowrap; }
#defects td.num { text-align:right; font-variant-numeric:tabular-nums; }
#defects tbody tr { cursor:pointer; }
#defects tbody tr:hover { background:#f3f7fd; }
#defects tbody tr.sel { background:#d8f5fb; outline:2px solid var(--sel); outline-offset:-2px; }
.pill { display:inline-block; padding:0 7px; border-radius:9px; font-size:12px; color:#fff; }
.pill.repair-now { background:var(--repair); } .pill.inspect { background:var(--inspect); }
.pill.no-action { background:var(--none); }
.figs { display:grid; grid-template-columns:repeat(auto-fill,minmax(520px,1fr)); gap:14px; }
figure { margin:0; border:1px solid var(--line); border-radius:6px; padding:8px; background:#fff; }
figure img { width:100%; height:auto; display:block; }
figcaption { color:var(--muted); font-size:12px; margin-top:4px; }
details pre { background:#f6f8fa; padding:10px; border-radius:6px; overflow:auto; max-height:420px; font-size:12px; }
details.allm { margin-top:10px; font-size:13px; }
details.allm summary { cursor:pointer; color:var(--accent); }
details.allm .cols { column-width:330px; column-gap:28px; margin-top:6px; }
details.allm table.kv { width:100%; min-width:0; }
details.allm table.kv td:first-child { word-break:break-all; }
footer { color:var(--muted); font-size:12px; text-align:center; padding:4px 0 18px; }
"""

JS = r"""
(function () {
  "use strict";
  var data = JSON.parse(document.getElementById("pavemap-data").textContent);
  var svg = document.getElementById("map");
  var table = document.getElementById("defects");
  var tip = document.getElementById("tooltip");
  var wrap = document.getElementById("map-wrap");
  var selectedBox = document.getElementById("selected");
  var byId = {};
  data.defects.forEach(function (d) { byId[String(d.id)] = d; });
  var current = null;

  function fmt(v, nd) {
    if (v === null || v === undefined) return "–";
    if (typeof v === "number") return nd === undefined ? String(v) : v.toFixed(nd);
    return String(v);
  }
  function describe(d) {
    var sev = d.paper_severity !== undefined ? d.paper_severity : d.severity;
    var sevMax = d.paper_severity_max !== undefined ? d.paper_severity_max : d.severity_max;
    var rows = [["urgency", d.priority + (d.priority_rank ? " (rank " + d.priority_rank + ")" : "")]];
    if (d.severity_level) rows.push(["severity level", d.severity_level]);
    if (d.chainage_m !== undefined && d.chainage_m !== null) rows.push(["chainage", fmt(d.chainage_m, 1) + " m"]);
    if (d.depth_max_mm !== undefined && d.depth_max_mm !== null) rows.push(["depth", fmt(d.depth_max_mm, 0) + " mm"]);
    rows = rows.concat([["EMA severity", fmt(sev, 3) + " (max " + fmt(sevMax, 3) + ")"],
      ["confidence", fmt(d.confidence, 2)], ["observations", fmt(d.observations)],
      ["probability", fmt(d.probability, 2)], ["area", fmt(d.area_m2, 3) + " m²"],
      ["length", fmt(d.length_m, 2) + " m"], ["position", "x " + fmt(d.x_m, 2) + ", y " + fmt(d.y_m, 2) + " m"]]);
    if (d.lat !== undefined && d.lat !== null) rows.push(["lat, lon", fmt(d.lat, 7) + ", " + fmt(d.lon, 7)]);
    return rows;
  }

  // ---------------------------------------------------------------- map: zoom and pan on the viewBox
  var vb = null, home = null;
  function upp() {  // world units (metres) per screen pixel, viewBox with preserveAspectRatio "meet"
    var r = svg.getBoundingClientRect();
    return Math.max(vb.w / Math.max(r.width, 1), vb.h / Math.max(r.height, 1));
  }
  function setView(v) {
    vb = v;
    svg.setAttribute("viewBox", [v.x, v.y, v.w, v.h].join(" "));
    var u = upp();
    var mks = svg.querySelectorAll(".mk");
    for (var i = 0; i < mks.length; i++) mks[i].setAttribute("r", String(6 * u));
    updateScale(u);
  }
  function updateScale(u) {
    var el = document.getElementById("scalebar");
    if (!el) return;
    var target = 110 * u, steps = [1, 2, 5], best = 0.01;
    for (var e = -2; e < 6; e++) for (var s = 0; s < 3; s++) {
      var m = steps[s] * Math.pow(10, e); if (m <= target) best = m;
    }
    el.innerHTML = "";
    var label = document.createElement("div");
    label.textContent = best >= 1000 ? (best / 1000) + " km" : (best < 1 ? best.toFixed(2) : best) + " m";
    var bar = document.createElement("div"); bar.className = "bar"; bar.style.width = (best / u) + "px";
    el.appendChild(label); el.appendChild(bar);
  }
  function toWorld(evt) {
    var p = svg.createSVGPoint(); p.x = evt.clientX; p.y = evt.clientY;
    var m = svg.getScreenCTM();
    return m ? p.matrixTransform(m.inverse()) : { x: vb.x + vb.w / 2, y: vb.y + vb.h / 2 };
  }
  function zoomAt(cx, cy, f) {
    var w = vb.w / f;
    if (w < home.w / 800 || w > home.w * 6) return;
    setView({ x: cx - (cx - vb.x) / f, y: cy - (cy - vb.y) / f, w: w, h: vb.h / f });
  }
  if (svg) {
    var v0 = data.view;
    home = { x: v0[0], y: v0[1], w: v0[2], h: v0[3] };
    // fit the map box to the map's shape: a long road strip gets a short box, a square scene a tall one
    var ww = wrap.getBoundingClientRect().width;
    if (ww > 0) wrap.style.height = Math.round(Math.min(640, Math.max(340, ww * v0[3] / v0[2] + 24))) + "px";
    setView(home);
    window.addEventListener("resize", function () { setView(vb); });
    svg.addEventListener("wheel", function (e) {
      e.preventDefault();
      var p = toWorld(e);
      zoomAt(p.x, p.y, Math.exp(-e.deltaY * 0.0015));
    }, { passive: false });
    var drag = null;
    svg.addEventListener("pointerdown", function (e) {
      if (e.button !== 0) return;
      drag = { sx: e.clientX, sy: e.clientY, v: { x: vb.x, y: vb.y, w: vb.w, h: vb.h }, u: upp(), moved: false };
    });
    svg.addEventListener("pointermove", function (e) {
      if (drag) {
        var dx = e.clientX - drag.sx, dy = e.clientY - drag.sy;
        if (!drag.moved && Math.abs(dx) + Math.abs(dy) > 3) {
          drag.moved = true; svg.classList.add("dragging");
          try { svg.setPointerCapture(e.pointerId); } catch (err) { /* pointer already released */ }
          hideTip();
        }
        if (drag.moved) setView({ x: drag.v.x - dx * drag.u, y: drag.v.y - dy * drag.u, w: drag.v.w, h: drag.v.h });
        return;
      }
      moveTip(e);
    });
    function endDrag(e) {
      if (drag && drag.moved) {
        svg.classList.remove("dragging");
        svg.dataset.justDragged = "1";
        setTimeout(function () { delete svg.dataset.justDragged; }, 0);
      }
      drag = null;
    }
    svg.addEventListener("pointerup", endDrag);
    svg.addEventListener("pointercancel", endDrag);
    svg.addEventListener("mouseover", function (e) {
      var id = e.target.getAttribute && e.target.getAttribute("data-id");
      if (id !== null && id !== undefined && !drag) showTip(byId[id], e);
    });
    svg.addEventListener("mouseout", function (e) {
      if (e.target.getAttribute && e.target.getAttribute("data-id") !== null) hideTip();
    });
    svg.addEventListener("click", function (e) {
      if (svg.dataset.justDragged) return;
      var id = e.target.getAttribute && e.target.getAttribute("data-id");
      if (id !== null && id !== undefined) select(id, "map"); else select(null, "map");
    });
    document.getElementById("zoom-in").addEventListener("click", function () {
      zoomAt(vb.x + vb.w / 2, vb.y + vb.h / 2, 1.6);
    });
    document.getElementById("zoom-out").addEventListener("click", function () {
      zoomAt(vb.x + vb.w / 2, vb.y + vb.h / 2, 1 / 1.6);
    });
    document.getElementById("zoom-home").addEventListener("click", function () { setView(home); });
    var layerBoxes = document.querySelectorAll("input[data-layer]");
    for (var i = 0; i < layerBoxes.length; i++) layerBoxes[i].addEventListener("change", function (e) {
      var el = document.getElementById(e.target.getAttribute("data-layer"));
      if (el) el.classList.toggle("hidden", !e.target.checked);
    });
  }

  // ---------------------------------------------------------------- tooltip
  function showTip(d, e) {
    if (!d || !tip) return;
    tip.innerHTML = "";
    var h = document.createElement("b");
    h.textContent = "#" + d.id + " " + d.code + " " + d.name;
    tip.appendChild(h);
    var t = document.createElement("table");
    describe(d).forEach(function (r) {
      var tr = document.createElement("tr"), a = document.createElement("td"), b = document.createElement("td");
      a.textContent = r[0]; b.textContent = r[1]; tr.appendChild(a); tr.appendChild(b); t.appendChild(tr);
    });
    tip.appendChild(t);
    tip.hidden = false;
    moveTip(e);
  }
  function moveTip(e) {
    if (!tip || tip.hidden) return;
    var r = wrap.getBoundingClientRect();
    var x = e.clientX - r.left + 14, y = e.clientY - r.top + 14;
    if (x + tip.offsetWidth > r.width - 4) x = e.clientX - r.left - tip.offsetWidth - 14;
    if (y + tip.offsetHeight > r.height - 4) y = e.clientY - r.top - tip.offsetHeight - 14;
    tip.style.left = Math.max(2, x) + "px"; tip.style.top = Math.max(2, y) + "px";
  }
  function hideTip() { if (tip) tip.hidden = true; }

  // ---------------------------------------------------------------- selection (map <-> table)
  function select(id, from) {
    var old = document.querySelectorAll(".sel");
    for (var i = 0; i < old.length; i++) old[i].classList.remove("sel");
    current = id;
    if (id === null || !byId[id]) {
      current = null;
      if (selectedBox) {
        selectedBox.textContent = data.defects.length ? "Click a defect on the map or in the table." : "";
      }
      return;
    }
    var els = document.querySelectorAll('[data-id="' + id + '"]');
    for (var j = 0; j < els.length; j++) els[j].classList.add("sel");
    var d = byId[id];
    if (selectedBox) {
      selectedBox.innerHTML = "";
      var b = document.createElement("b");
      b.textContent = "Selected #" + d.id + " " + d.code + " " + d.name + ": ";
      selectedBox.appendChild(b);
      selectedBox.appendChild(document.createTextNode(describe(d).map(function (r) {
        return r[0] + " " + r[1];
      }).join(" · ")));
    }
    var row = table ? table.querySelector('tr[data-id="' + id + '"]') : null;
    if (row && from === "map") {
      var box = row.closest(".tablewrap");
      if (box) {
        var top = row.offsetTop - box.clientHeight / 2;
        box.scrollTop = Math.max(0, top);
      }
    }
    if (from === "table" && svg && d.bbox) {
      var bw = d.bbox[2] - d.bbox[0], bh = d.bbox[3] - d.bbox[1];
      var w = Math.min(vb.w, Math.max(6 * Math.max(bw, bh), 6));
      var h = w * vb.h / vb.w;
      var cx = (d.bbox[0] + d.bbox[2]) / 2, cy = -(d.bbox[1] + d.bbox[3]) / 2;
      setView({ x: cx - w / 2, y: cy - h / 2, w: w, h: h });
    }
  }
  window.pavemapSelect = function (id) { select(String(id), "table"); };

  // ---------------------------------------------------------------- table: sorting and filters
  if (table) {
    var tbody = table.tBodies[0];
    table.addEventListener("click", function (e) {
      var tr = e.target.closest("tbody tr");
      if (tr && tr.getAttribute("data-id") !== null) select(tr.getAttribute("data-id"), "table");
    });
    var sortState = { key: null, dir: 1 };
    var ths = table.tHead.rows[0].cells;
    function sortBy(col, dir) {
      var type = ths[col].getAttribute("data-type");
      var rows = Array.prototype.slice.call(tbody.rows);
      var sevCol = -1;
      for (var k = 0; k < ths.length; k++) {
        var dk = ths[k].getAttribute("data-key");
        if (dk === "severity" || dk === "paper_severity") sevCol = k;
      }
      function val(tr, c) {
        var v = tr.cells[c].getAttribute("data-v");
        return (type === "str" && c === col) ? v : parseFloat(v);
      }
      rows.sort(function (a, b) {
        var x = val(a, col), y = val(b, col);
        if (x < y) return -dir; if (x > y) return dir;
        if (sevCol >= 0) {  // ties: more severe first
          var sa = parseFloat(a.cells[sevCol].getAttribute("data-v"));
          var sb = parseFloat(b.cells[sevCol].getAttribute("data-v"));
          if (sa !== sb) return sb - sa;
        }
        return parseFloat(a.getAttribute("data-id")) - parseFloat(b.getAttribute("data-id"));
      });
      rows.forEach(function (r) { tbody.appendChild(r); });
      for (var i = 0; i < ths.length; i++) {
        var ar = ths[i].querySelector(".arrow");
        if (ar) ar.textContent = i === col ? (dir > 0 ? " ▲" : " ▼") : "";
      }
      sortState = { key: col, dir: dir };
    }
    for (var c = 0; c < ths.length; c++) (function (col) {
      ths[col].addEventListener("click", function () {
        var def = ths[col].getAttribute("data-type") === "num" && ths[col].getAttribute("data-key") !== "id" ? -1 : 1;
        sortBy(col, sortState.key === col ? -sortState.dir : def);
      });
    })(c);
    for (var c2 = 0; c2 < ths.length; c2++) if (ths[c2].getAttribute("data-key") === "priority") sortBy(c2, 1);
  }
  var worklist = document.getElementById("worklist-table");
  if (worklist) worklist.addEventListener("click", function (e) {
    if (e.target.closest("a")) return;  // the photo link opens the full crop
    var tr = e.target.closest("tbody tr");
    if (tr && tr.getAttribute("data-id") !== null) select(tr.getAttribute("data-id"), "table");
  });
  var classBoxes = document.querySelectorAll("input[data-code]");
  function applyFilters() {
    var on = {};
    for (var i = 0; i < classBoxes.length; i++) on[classBoxes[i].getAttribute("data-code")] = classBoxes[i].checked;
    var els = document.querySelectorAll("[data-code-of]");
    var shown = 0;
    for (var j = 0; j < els.length; j++) {
      var vis = on[els[j].getAttribute("data-code-of")] !== false;
      els[j].classList.toggle("hidden", !vis);
      if (vis && els[j].tagName === "TR" && els[j].closest("#defects")) shown++;
    }
    var sc = document.getElementById("shown-count");
    if (sc) sc.textContent = String(shown);
  }
  for (var i2 = 0; i2 < classBoxes.length; i2++) classBoxes[i2].addEventListener("change", applyFilters);
  applyFilters();
  select(null, "init");
  document.body.setAttribute("data-ready", "1");
})();
"""
