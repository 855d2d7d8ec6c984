"""The report a field crew works from (issue 16): evidence photos, the work list, printing to PDF.

A run on the tiny synthetic drive gives ``evidence/<id>.jpg`` per defect (the box drawn in magenta);
a defect without a usable view gets a note that the report shows; in headless Chromium the work list
fills the first screen, most urgent first, and ``--print-to-pdf`` gives a PDF with the work list and
every defect id. The PDF's text is read with a minimal parser (no PDF library is a dependency).
"""

from __future__ import annotations

import copy
import json
import re
import shutil
import subprocess
import zlib
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

import pavemap
from browser_support import ARGS, CHROMIUM, launched, open_page, require_chromium
from pavemap.config import load_config
from pavemap.export.evidence import BOX_COLOUR, crop_with_box, view_scores, write_evidence
from pavemap.export.report import build_report_html, write_report
from pavemap.export.sample import sample_inputs
from pavemap.io.sequence import read_sequence


def magenta(a: np.ndarray) -> np.ndarray:
    """(H, W) bool: pixels of the evidence box colour (JPEG-tolerant)."""
    a = a.astype(np.int16)
    return (np.abs(a - np.array(BOX_COLOUR, dtype=np.int16)) < 70).all(axis=-1)


@pytest.fixture(scope="module")
def field_run(tiny_seq, tmp_path_factory):
    cfg = load_config("kitti")
    cfg.device = "cpu"
    cfg.mesh.epochs = 1
    cfg.output.overlay_frames = 1
    out = tmp_path_factory.mktemp("field") / "run"
    res = pavemap.run(tiny_seq, cfg, out, progress=False)
    assert res.defects, "the tiny drive should map at least one defect"
    return res, out


def test_evidence_photo_for_each_defect(field_run):
    res, out = field_run
    recs = [json.loads(line) for line in (out / "detections_mapped.jsonl").read_text().splitlines()]
    seen = {r["instance"] for r in recs if r.get("kept") and r.get("instance") is not None}
    layer = {f["properties"]["id"]: f["properties"] for f in json.loads((out / "defects.geojson").read_text())
             ["features"]}
    manifest = json.loads((out / ".pavemap-owner.json").read_text())["files"]
    for inst in res.defects:
        if inst.id not in seen:
            assert "no usable view" in layer[inst.id]["evidence_note"]
            continue
        rel = f"evidence/{inst.id}.jpg"
        assert inst.extra["evidence"] == rel and layer[inst.id]["evidence"] == rel  # the records carry it
        assert rel in manifest  # the run owns it (replaced or removed with the run)
        with Image.open(out / rel) as im:
            assert im.format == "JPEG"
            a = np.asarray(im.convert("RGB"))
        assert min(a.shape[:2]) >= 200
        box = magenta(a)
        # the box outline: magenta pixels in several rows and columns, a closed ring around the centre
        assert box.sum() > 100 and box.any(axis=1).sum() >= 6 and box.any(axis=0).sum() >= 20


def test_view_scores_prefer_close_steep_confident_untruncated():
    nan = np.nan
    s = view_scores(np.array([3.0, 30.0, 3.0, 3.0, 3.0, nan]), np.array([0.4, 0.4, 0.05, 0.4, 0.4, nan]),
                    np.array([0.8, 0.8, 0.8, 0.2, 0.8, 0.8]), np.full(6, 0.9),
                    np.array([False, False, False, False, True, False]))
    assert s.shape == (6,) and np.argmax(s) == 0
    assert s[0] > s[1] and s[0] > s[2] and s[0] > s[3] and s[0] > s[4]  # far, grazing, unsure, truncated
    assert np.isfinite(s[5])  # no surface hit: scored from the box position


def test_crop_draws_the_box_around_the_defect():
    img = np.full((120, 300, 3), 90, np.uint8)
    out = crop_with_box(img, (140.0, 60.0, 160.0, 64.0), "#1 D10")
    assert out.dtype == np.uint8 and min(out.shape[:2]) >= 240
    m = magenta(out)
    rows, cols = np.nonzero(m)
    cy, cx = out.shape[0] / 2, out.shape[1] / 2
    assert rows.min() < cy < rows.max() and cols.min() < cx < cols.max()  # the box is around the crop centre
    assert not m[int(cy), int(cx)]  # drawn outside the (thin) box: the defect itself stays visible


def test_defect_without_usable_view(field_run, tiny_seq, tmp_path):
    res, out = field_run
    seq_dir = tmp_path / "seq"
    shutil.copytree(tiny_seq.root, seq_dir)
    seq = read_sequence(seq_dir, validate=False)
    recs = [json.loads(line) for line in (out / "detections_mapped.jsonl").read_text().splitlines()]
    insts = copy.deepcopy(res.defects)
    lost = insts[0]
    # every image showing the first defect is gone (deleted from the copy of the drive)
    for r in recs:
        if r.get("instance") == lost.id:
            view = seq.frame_by_index()[r["frame"]].views[r["camera"]]
            (seq_dir / view.image).unlink(missing_ok=True)
    ghost = copy.deepcopy(lost)
    ghost.id = 99  # no detection was fused into it
    insts.append(ghost)
    ev = tmp_path / "ev"
    (ev / "evidence").mkdir(parents=True)
    (ev / "evidence" / "98.jpg").write_bytes(b"stale")  # of an earlier run: removed
    paths = write_evidence(ev, insts, recs, seq)
    assert not (ev / "evidence" / "98.jpg").exists()
    assert "evidence" not in lost.extra and "unreadable" in lost.extra["evidence_note"]
    assert "no kept detection" in ghost.extra["evidence_note"]
    assert f"evidence/{lost.id}.jpg" not in paths and "evidence/99.jpg" not in paths
    page = build_report_html(insts, detections=recs)
    row = re.search(rf'<tr class="wl[^"]*" data-id="{lost.id}"[^>]*>(.*?)</tr>', page, re.S)
    assert row and "unreadable" in row.group(1) and "<img" not in row.group(1)
    assert "no evidence photo" in page


def test_worklist_order_and_columns():
    kw = sample_inputs(9, seed=5)
    insts = kw["instances"]
    for k, inst in enumerate(reversed(insts)):  # rank 1 = the last id: not the id order
        inst.extra.pop("certainty", None)  # a key no record has gives no column
        inst.extra.update(priority_rank=k + 1, severity_level="high" if k < 3 else "low", chainage_m=10.0 * k)
    insts[-1].cls = 3
    insts[-1].extra.update(depth_max_mm=None, measurable=False, measure_note="unobserved ground")
    page = build_report_html(insts, detections=kw["detections"])
    table = page[page.index('id="worklist-table"'):page.index("</table>", page.index('id="worklist-table"'))]
    ids = [int(v) for v in re.findall(r'<tr class="wl[^"]*" data-id="(\d+)"', table)]
    assert ids == [i.id for i in reversed(insts)]
    for head in ("rank", "severity", "size / depth", "chainage m", "photo"):
        assert f">{head}</th>" in table
    assert "certainty" not in table and "lat, lon" not in table  # no record has them: no column
    assert "depth not measurable (unobserved ground)" in table


def _pdf_objects(data: bytes) -> dict[int, tuple[bytes, bytes]]:
    """{object number: (dictionary, decoded stream)} of an uncompressed-xref PDF (Skia's)."""
    out = {}
    for m in re.finditer(rb"(\d+)\s+0\s+obj(.*?)endobj", data, re.S):
        body = m.group(2)
        s = body.find(b"stream")
        if s < 0:
            out[int(m.group(1))] = (body, b"")
            continue
        raw = body[s + 6:].lstrip(b"\r\n")
        raw = raw[:raw.rfind(b"endstream")]
        if b"/FlateDecode" in body[:s]:
            raw = zlib.decompressobj().decompress(raw)
        out[int(m.group(1))] = (body[:s], raw)
    return out


def _cmap(text: bytes) -> dict[int, str]:
    cmap: dict[int, str] = {}
    pair = rb"<([0-9A-Fa-f]+)>\s*<([0-9A-Fa-f]+)>"
    for block in re.findall(rb"beginbfchar(.*?)endbfchar", text, re.S):
        for src, dst in re.findall(pair, block):
            cmap[int(src, 16)] = bytes.fromhex(dst.decode()).decode("utf-16-be", "replace")
    for block in re.findall(rb"beginbfrange(.*?)endbfrange", text, re.S):
        for lo, hi, dst in re.findall(pair + rb"\s*<([0-9A-Fa-f]+)>", block):
            for k, code in enumerate(range(int(lo, 16), int(hi, 16) + 1)):
                cmap[code] = chr(int(dst, 16) + k)
    return cmap


def pdf_text(data: bytes) -> str:
    """The text of a Chromium PDF: hex glyph strings mapped through each font's ToUnicode CMap."""
    objs = _pdf_objects(data)
    fonts: dict[bytes, dict[int, str]] = {}
    for head, _ in objs.values():
        for fd in re.findall(rb"/Font\s*<<(.*?)>>", head, re.S):
            for name, num in re.findall(rb"/([\w.+-]+)\s+(\d+)\s+0\s+R", fd):
                tu = re.search(rb"/ToUnicode\s+(\d+)\s+0\s+R", objs.get(int(num), (b"", b""))[0])
                if tu:
                    fonts[name] = _cmap(objs.get(int(tu.group(1)), (b"", b""))[1])
    out, cur = [], {}
    for _, raw in objs.values():
        if b"BT" not in raw:
            continue
        for m in re.finditer(rb"/([\w.+-]+)\s+[\d.]+\s+Tf|<([0-9A-Fa-f\s]*)>|\bET\b", raw):
            if m.group(1):
                cur = fonts.get(m.group(1), {})
            elif m.group(2) is not None:
                h = re.sub(rb"\s", b"", m.group(2)).decode()
                out.append("".join(cur.get(int(h[i:i + 4], 16), "") for i in range(0, len(h) - 3, 4)))
            else:
                out.append("\n")
    return "".join(out)


def test_print_to_pdf_has_the_work_list(field_run, tmp_path):
    require_chromium()
    res, out = field_run
    pdf = tmp_path / "report.pdf"
    proc = subprocess.run([CHROMIUM, *ARGS, "--no-pdf-header-footer", f"--print-to-pdf={pdf}",
                           (out / "report.html").resolve().as_uri()], capture_output=True, timeout=120)
    assert proc.returncode == 0 and pdf.is_file(), proc.stderr[-2000:]
    data = pdf.read_bytes()
    assert data.startswith(b"%PDF") and b"/MediaBox [0 0 594" in data.replace(b"\n", b" ")  # A4: 595 x 842 pt
    text = re.sub(r"\s+", "", pdf_text(data))
    assert "Worklist" in text
    for inst in res.defects:
        assert re.search(rf"#{inst.id}(?!\d)", text), inst.id
    assert "wheel:zoom" not in text and "Allmeasures" not in text  # print hides the interactive parts
    # the photos are in the PDF as images
    assert len(re.findall(rb"/Subtype\s*/Image", data)) >= sum(bool(i.extra.get("evidence")) for i in res.defects)


def test_print_stylesheet_is_present():
    page = build_report_html([])
    assert "@page { size: A4" in page and "@media print" in page and "break-inside:avoid" in page


@pytest.fixture(scope="module")
def browser():
    with launched() as b:
        yield b


def _open(browser, path: Path, size=(1920, 1080)):
    return open_page(browser, path, size, wait_load=True)


def test_worklist_is_the_first_screen(browser, field_run):
    res, out = field_run
    page, problems = _open(browser, out / "report.html")
    first = page.locator("#worklist-table tbody tr").first
    box = first.bounding_box()
    assert box is not None and box["y"] + box["height"] <= 1080  # the first row is on the first screen
    assert page.locator("#map-wrap").bounding_box()["y"] < 1080  # and so is the map
    ids = [int(v) for v in page.eval_on_selector_all("#worklist-table tbody tr", "els => els.map(e => e.dataset.id)")]
    assert sorted(ids) == sorted(i.id for i in res.defects)
    ranks = {i.id: i.extra.get("priority_rank") for i in res.defects}
    if all(isinstance(r, int) for r in ranks.values()):
        assert ranks[ids[0]] == 1 and [ranks[i] for i in ids] == sorted(ranks.values())
    # every photo loaded (relative links next to the report)
    widths = page.eval_on_selector_all("#worklist-table img.thumb", "els => els.map(e => e.naturalWidth)")
    assert len(widths) == sum(bool(i.extra.get("evidence")) for i in res.defects) and all(w > 0 for w in widths)
    assert not page.locator("details#research").evaluate("e => e.open")  # research metrics folded away
    assert not problems, problems
    page.close()


def test_worklist_rank_one_first_in_the_browser(browser, tmp_path):
    kw = sample_inputs(12, seed=3, geo=True)
    kw.pop("trajectory")
    insts = kw["instances"]
    order = np.random.default_rng(0).permutation(len(insts))
    for rank, k in enumerate(order, start=1):
        insts[k].extra["priority_rank"] = rank
    path = write_report(tmp_path, insts, **{k: v for k, v in kw.items() if k not in ("instances", "class_maps")})
    page, problems = _open(browser, path)
    rows = page.locator("#worklist-table tbody tr")
    assert rows.count() == len(insts)
    assert int(rows.first.get_attribute("data-id")) == insts[order[0]].id
    assert rows.first.bounding_box()["y"] < 1080
    assert "lat, lon" in page.inner_text("#worklist-table thead")
    # clicking a work-list row selects the defect on the map
    rows.nth(2).click()
    pick = rows.nth(2).get_attribute("data-id")
    assert "sel" in page.get_attribute(f'#map path.d[data-id="{pick}"]', "class")
    assert not problems, problems
    page.close()


def test_segment_strip_along_chainage():
    from pavemap.maintain.segments import Segment

    segs = [Segment(id=k + 1, start_m=100.0 * k, end_m=100.0 * (k + 1), polygon=None, corridor_area_m2=700.0,
                    counts={"D40": k}, pci=pci, rating=r) for k, (pci, r) in enumerate([(92.0, "good"), (35.0, "poor"),
                                                                                      (61.0, "fair")])]
    page = build_report_html([], segments=segs)
    strip = page[page.index('<svg id="segment-strip"'):page.index("</svg>", page.index('<svg id="segment-strip"'))]
    assert strip.count("<rect") == 3
    fills = re.findall(r'<rect[^>]*fill="(#[0-9a-f]+)"', strip)
    assert len(set(fills)) == 3  # three condition bands, three colours
    assert [int(v) for v in re.findall(r'text-anchor="middle">(\d+)</text>', strip)] == [92, 35, 61]
    assert "segment 2: 100–200 m, PCI-like index 35 (poor), 1 defects" in strip
    assert "<svg id=\"segment-strip\"" not in build_report_html([])  # no segments: no strip


def test_report_says_where_the_texture_may_hold_a_vehicle():
    """Stage 1's texture check (mesh/metrics.json -> texture_check) shows as a banner with its patches; none
    when nothing is contested."""
    tc = {"contested_m2": 53.8, "patch_count": 7, "few_views_m2": 60.0,
          "patches": [{"area_m2": 40.0 - k, "x_m": 44.1 + k, "y_m": 1.3} for k in range(7)]}
    page = build_report_html([], metrics={"mesh": {"texture_check": tc}})
    banner = page[page.index('id="texture-warning"'):page.index("</div>", page.index('id="texture-warning"'))]
    assert "53.8 m²" in banner and "40.0 m² at x 44.1, y 1.3 m" in banner and "… 2 more" in banner
    assert banner.count("<li>") == 6  # five patches and the rest counted
    layer = page[page.index('id="layer-contested"'):page.index("</g>", page.index('id="layer-contested"'))]
    assert layer.count("<circle") == 7 and 'cx="44.10" cy="-1.30"' in layer  # on the map, y up
    assert 'data-layer="layer-contested"' in page  # with its checkbox
    clean = build_report_html([], metrics={"mesh": {"texture_check": {**tc, "contested_m2": 0.0, "patches": []}}})
    assert 'id="texture-warning"' not in clean and 'id="texture-warning"' not in build_report_html([])
    assert 'id="layer-contested"' not in clean
    # a defect that lies where the texture may hold a vehicle says so in its work-list row
    kw = sample_inputs(2, seed=1)
    kw["instances"][0].extra["texture_contested"] = True
    kw["instances"][1].extra["texture_contested"] = False
    rows = re.findall(r'<tr class="wl[^"]*" data-id="(\d+)"[^>]*>(.*?)</tr>', build_report_html(
        kw["instances"], detections=kw["detections"]), re.S)
    flagged = {int(i) for i, row in rows if "a vehicle may have been here" in row}
    assert flagged == {kw["instances"][0].id}
