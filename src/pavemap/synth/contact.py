"""Contact sheet: a PNG grid of a few frames (RGB with detections, semantics coloured)."""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
from PIL import Image, ImageDraw

from pavemap.io.atomic import atomic_path
from pavemap.io.sequence import DETECTIONS_FILE, load_rgb, load_semantics, read_detections, read_sequence
from pavemap.palette import DEFECT_RGB, semantic_palette

DEFECT_COLOURS = DEFECT_RGB
PREFERRED_ORDER = ("CAM_FRONT_LEFT", "CAM_FRONT", "CAM_FRONT_RIGHT", "CAM_BACK_LEFT", "CAM_BACK", "CAM_BACK_RIGHT")


def _palette(seq) -> np.ndarray:
    return semantic_palette(seq.classes)[:256]


def _dashed_rect(draw: ImageDraw.ImageDraw, box, colour, dash: int = 5, width: int = 2) -> None:
    x1, y1, x2, y2 = box
    for (a, b), (c, d) in (((x1, y1), (x2, y1)), ((x2, y1), (x2, y2)), ((x2, y2), (x1, y2)), ((x1, y2), (x1, y1))):
        length = max(abs(c - a), abs(d - b))
        n = max(1, int(length // (2 * dash)))
        for i in range(n):
            t0, t1 = (2 * i) / (2 * n), (2 * i + 1) / (2 * n)
            draw.line([(a + (c - a) * t0, b + (d - b) * t0), (a + (c - a) * t1, b + (d - b) * t1)], fill=colour,
                      width=width)


def contact_sheet(seq_root: str | os.PathLike, out_png: str | os.PathLike, n_frames: int = 3,
                  tile_width: int = 400) -> Path:
    """Write a PNG grid: per chosen frame one row of RGB tiles with detections, one of semantics.

    Detections use the class colours D00 green, D10 yellow, D20 orange, D40 red; when the
    simulated detector's truth file is present, false positives are dashed and tagged "FP".
    """
    root = Path(seq_root)
    seq = read_sequence(root, validate=False)
    cams = [c for c in PREFERRED_ORDER if c in seq.cameras] + [c for c in seq.cameras if c not in PREFERRED_ORDER]
    idx = np.unique(np.linspace(0, len(seq.frames) - 1, max(1, n_frames)).round().astype(int))
    frames = [seq.frames[i] for i in idx]
    dets = read_detections(root / DETECTIONS_FILE) if (root / DETECTIONS_FILE).is_file() else []
    truth_path = root / "truth" / "detections_truth.jsonl"
    truth = None
    if dets and truth_path.is_file():
        lines = [json.loads(x) for x in truth_path.read_text(encoding="utf-8").splitlines() if x.strip()]
        truth = lines if len(lines) == len(dets) else None
    by_view: dict[tuple[int, str], list[tuple]] = {}
    for i, d in enumerate(dets):
        by_view.setdefault((d.frame, d.camera), []).append((d, truth[i] if truth else None))
    pal = _palette(seq)
    tile_width = max(tile_width, 1200 // len(cams))  # room for the legend with a single camera
    tiles_h = {c: round(seq.cameras[c].height * tile_width / seq.cameras[c].width) for c in cams}
    th = max(tiles_h.values())
    header = 18
    legend = 26
    sheet = Image.new("RGB", (tile_width * len(cams), len(frames) * (2 * th + header) + legend), (25, 25, 28))
    draw = ImageDraw.Draw(sheet)
    for r, f in enumerate(frames):
        y0 = r * (2 * th + header)
        draw.text((4, y0 + 3), f"frame {f.index}  t={f.timestamp:.1f}s", fill=(235, 235, 235))
        for c_i, cam in enumerate(cams):
            v = f.views.get(cam)
            if v is None:
                continue
            x0 = c_i * tile_width
            draw.text((x0 + 150, y0 + 3), cam, fill=(200, 200, 200))
            rgb = load_rgb(root / v.image)
            s = tile_width / rgb.shape[1]
            tile = Image.fromarray(rgb).resize((tile_width, tiles_h[cam]), Image.BILINEAR)
            td = ImageDraw.Draw(tile)
            for d, t in by_view.get((f.index, cam), []):
                box = [d.box[0] * s, d.box[1] * s, d.box[2] * s, d.box[3] * s]
                col = DEFECT_COLOURS.get(d.cls, (255, 255, 255))
                if t is not None and not t["true"]:
                    _dashed_rect(td, box, col, width=2)
                    td.text((box[0] + 1, max(0, box[1] - 11)), f"FP {d.code}", fill=col)
                else:
                    td.rectangle(box, outline=col, width=2)
                    td.text((box[0] + 1, max(0, box[1] - 11)), f"{d.code} {d.conf:.2f}", fill=col)
            sheet.paste(tile, (x0, y0 + header))
            if v.semantics:
                sem = load_semantics(root / v.semantics)
                over = (0.45 * rgb + 0.55 * pal[sem]).astype(np.uint8)
                sheet.paste(Image.fromarray(over).resize((tile_width, tiles_h[cam]), Image.NEAREST),
                            (x0, y0 + header + th))
    ly = sheet.height - legend + 6
    x = 6
    for k, name in ((0, "D00 longitudinal"), (1, "D10 transverse"), (2, "D20 alligator"), (3, "D40 pothole")):
        draw.rectangle([x, ly, x + 14, ly + 12], outline=DEFECT_COLOURS[k], width=2)
        draw.text((x + 20, ly), name, fill=(230, 230, 230))
        x += 150
    draw.text((x, ly), "solid = true detection, dashed FP = false positive (off-road objects, shadows)",
              fill=(230, 230, 230))
    x = max(sheet.width - 8 * 95, 1040)
    ly2 = ly if x == sheet.width - 8 * 95 else ly
    for c in seq.classes:
        if x > sheet.width - 80:
            break
        draw.rectangle([x, ly2, x + 12, ly2 + 12], fill=tuple(int(v) for v in pal[c.id]))
        draw.text((x + 16, ly2), c.name[:10], fill=(230, 230, 230))
        x += 95
    out = Path(out_png)
    with atomic_path(out) as tmp:
        sheet.save(tmp, format="PNG")
    return out
