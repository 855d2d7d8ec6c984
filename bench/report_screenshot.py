"""Screenshot of the report's first screen (the work list, the map, the segment strip) for docs/.

    .venv/bin/python bench/report_screenshot.py                      # a small synthetic run, then the shot
    .venv/bin/python bench/report_screenshot.py --report demo_out/run/report.html   # shoot an existing run

Writes docs/report_worklist.png (1920 x 1080 by default), quantised to a palette to stay small
(~400 kB at most). The synthetic run is a nuScenes-like drive with few frames, one mesh epoch, on
the CPU: a few minutes on a laptop. Needs headless Chromium (``/usr/bin/chromium``) and playwright.
"""

from __future__ import annotations

import argparse
import io
import shutil
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
CHROMIUM = shutil.which("chromium") or "/usr/bin/chromium"
ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage", "--no-first-run"]


def synthetic_run(work: Path, frames: int, scale: float, seed: int) -> Path:
    """A small nuScenes-like run folder in ``work``; returns its report.html."""
    import pavemap
    from pavemap.config import load_config
    from pavemap.io.sequence import read_sequence
    from pavemap.synth import detect_sequence, synthesize

    seq_dir = work / "scene"
    if not (seq_dir / "sequence.json").is_file():
        synthesize(seq_dir, preset="nuscenes-like", seed=seed, frames=frames, scale=scale, progress=False)
        detect_sequence(read_sequence(seq_dir), seed=seed)
    cfg = load_config("nuscenes")
    cfg.device = "cpu"
    cfg.mesh.epochs = 1
    cfg.output.overlay_frames = 1
    run = pavemap.run(read_sequence(seq_dir), cfg, work / "run", progress=False, overwrite=True)
    print(f"run: {len(run.defects)} defects in {work / 'run'}")
    return work / "run" / "report.html"


def shoot(report: Path, out: Path, width: int, height: int, max_bytes: int = 400_000) -> Path:
    """The first viewport of ``report`` as a palette PNG at ``out``."""
    from PIL import Image
    from playwright.sync_api import sync_playwright

    with sync_playwright() as pw:
        browser = pw.chromium.launch(executable_path=CHROMIUM, args=ARGS, headless=True)
        page = browser.new_page(viewport={"width": width, "height": height})
        page.goto(report.resolve().as_uri())
        page.wait_for_selector('body[data-ready="1"]', timeout=30000)
        page.wait_for_load_state("load")  # the evidence thumbnails
        png = page.screenshot()
        browser.close()
    im = Image.open(io.BytesIO(png)).convert("RGB")
    out.parent.mkdir(parents=True, exist_ok=True)
    for colours in (256, 128, 64):
        buf = io.BytesIO()
        im.quantize(colours, method=Image.Quantize.MEDIANCUT).save(buf, format="PNG", optimize=True)
        if buf.tell() <= max_bytes:
            break
    out.write_bytes(buf.getvalue())
    print(f"{out}: {im.size[0]}x{im.size[1]}, {buf.tell() / 1024:.0f} kB, {colours} colours")
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--report", type=Path, help="an existing report.html (default: make a small synthetic run)")
    ap.add_argument("--work", type=Path, default=ROOT / "bench" / "work" / "report_screenshot")
    ap.add_argument("--out", type=Path, default=ROOT / "docs" / "report_worklist.png")
    ap.add_argument("--frames", type=int, default=10)
    ap.add_argument("--scale", type=float, default=0.2)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--size", default="1920x1080", help="viewport WIDTHxHEIGHT")
    a = ap.parse_args(argv)
    if not Path(CHROMIUM).exists():
        print(f"headless Chromium not found at {CHROMIUM}", file=sys.stderr)
        return 2
    t = time.perf_counter()
    report = a.report or synthetic_run(a.work, a.frames, a.scale, a.seed)
    w, h = (int(v) for v in a.size.lower().split("x"))
    shoot(report, a.out, w, h)
    print(f"{time.perf_counter() - t:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
