"""Perception on real footage, as a user's run sees it: the segmenter and the detector on one frame of each shared
nuScenes clip (no defect truth exists for them: this counts and shows, it does not score).

Each clip is imported as a user would (``pavemap import folder --poses sfm``, shared with bench/refine_real.py) and
run with the defaults (``pavemap run``: the shipped detector at its operating point, the segmenter's labels from
the import). Per clip the figure row shows the frame whose detection is the most confident (kept ones first):
left the segmenter's labels over the image (road, sidewalk, vehicles and people, the bonnet), right the
detector's boxes (solid: at or above the run's ``filter.tau_conf``, with class and confidence; dashed: the boxes
below it down to 0.05). Per clip the JSON records the chosen frame, its boxes, the label shares of that frame and
the run's counts. Writes ``bench/results/real_footage.json`` and ``docs/real_footage.jpg``.

    python bench/real_footage.py [--data ../shared/data] [--work DIR] [--figure docs/real_footage.jpg]
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "src"))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from common import git_commit, machine_entry, write_results  # noqa: E402
from detector_clips import CLIPS, _one  # noqa: E402
from refine_real import imported  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
#: label colours of the overlay (RGB): the classes the run uses, everything else left as it is
COLOURS = {"road": (150, 60, 200), "sidewalk": (240, 170, 40), "movable": (30, 120, 255), "ego": (250, 230, 0)}
CLASS_COLOURS = {"D00": "#2ca02c", "D10": "#ffbf00", "D20": "#ff7f0e", "D40": "#d62728"}


def _frame_choice(run: Path) -> tuple[int, list[dict]]:
    """(frame, its detections) of the most confident detection, kept ones first; every detection as
    detections_mapped.jsonl has it."""
    dets = [json.loads(ln) for ln in (run / "detections_mapped.jsonl").read_text().splitlines() if ln.strip()]
    if not dets:
        return -1, []
    top = max(dets, key=lambda d: (bool(d.get("kept")), d["conf"]))
    return int(top["frame"]), [d for d in dets if d["frame"] == top["frame"]]


def _overlay(rgb: np.ndarray, labels: np.ndarray, classes: list[dict]) -> tuple[np.ndarray, dict]:
    """The image (H, W, 3) uint8 with the label groups of COLOURS blended in; the share of each group."""
    by = {c["id"]: c for c in classes}
    group = np.full(labels.shape, "", dtype=object)
    for cid, c in by.items():
        name = ("ego" if c["name"] == "ego" else "road" if c["road"] else "movable" if c["movable"]
                else "sidewalk" if c["name"] == "sidewalk" else "")
        if name:
            group[labels == cid] = name
    out = rgb.astype(np.float32)
    shares = {}
    for name, col in COLOURS.items():
        m = group == name
        shares[name] = round(float(m.mean()), 4)
        out[m] = 0.45 * out[m] + 0.55 * np.array(col, np.float32)
    return out.clip(0, 255).astype(np.uint8), shares


def clip_entry(seq: Path, run: Path, ax_seg, ax_det, title: str) -> dict:
    """Draw one clip's row (matplotlib axes) and return what it shows."""
    from matplotlib.patches import Patch, Rectangle

    from pavemap.io.sequence import load_rgb, load_semantics, read_sequence

    s = read_sequence(seq)
    cfg_tau = json.loads((run / "metrics.json").read_text())["config"]["filter"]["tau_conf"]
    frame, dets = _frame_choice(run)
    f = next(fr for fr in s.frames if fr.index == (frame if frame >= 0 else s.frames[0].index))
    view = next(iter(f.views.values()))
    rgb = load_rgb(s.path(view.image))
    classes = json.loads((seq / "sequence.json").read_text())["classes"]
    over, shares = _overlay(rgb, load_semantics(s.path(view.semantics)), classes) if view.semantics else (rgb, {})
    ax_seg.imshow(over)
    ax_seg.set_title(f"{title}, frame {f.index}: segmenter labels", fontsize=9)
    ax_seg.legend(handles=[Patch(color=np.array(c) / 255, label=n) for n, c in COLOURS.items()], fontsize=7,
                  loc="upper right", framealpha=0.8)
    ax_det.imshow(rgb)
    boxes = []
    for d in sorted(dets, key=lambda d: d["conf"]):
        if d["conf"] < 0.05:
            continue
        x0, y0, x1, y1 = d["box"]
        name = ("D00", "D10", "D20", "D40")[int(d["cls"])]
        strong = d["conf"] >= cfg_tau
        ax_det.add_patch(Rectangle((x0, y0), x1 - x0, y1 - y0, fill=False, lw=2.0 if strong else 1.0,
                                   ls="-" if strong else "--", ec=CLASS_COLOURS[name]))
        if strong:
            ax_det.text(x0, y0 - 6, f"{name} {d['conf']:.2f}", color="white", fontsize=7,
                        bbox={"facecolor": CLASS_COLOURS[name], "pad": 1, "lw": 0})
        boxes.append({"cls": name, "conf": d["conf"], "box": [round(v, 1) for v in d["box"]],
                      "kept_on_road": bool(d.get("kept")), "reason": d.get("reason")})
    ax_det.set_title(f"detector: solid >= tau_conf {cfg_tau:g}, dashed 0.05-{cfg_tau:g}", fontsize=9)
    for ax in (ax_seg, ax_det):
        ax.set_axis_off()
    m = json.loads((run / "metrics.json").read_text())
    return {"frame": f.index, "image": view.image, "tau_conf": cfg_tau, "boxes_on_frame": boxes,
            "label_shares_on_frame": shares, "run_boxes": m["input_detections"],
            "run_boxes_at_or_above_tau": m["input_detections"] - m["below_conf"],
            "run_kept_on_road": m["valid_detections"], "semantics": m.get("semantics")}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=ROOT.parent / "shared" / "data", help="the shared samples")
    ap.add_argument("--results", type=Path, default=ROOT / "bench" / "results" / "real_footage.json")
    ap.add_argument("--work", type=Path, default=Path(tempfile.gettempdir()) / "pavemap-bench" / "real")
    ap.add_argument("--figure", type=Path, default=ROOT / "docs" / "real_footage.jpg")
    a = ap.parse_args()
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(len(CLIPS), 2, figsize=(16, 4.6 * len(CLIPS)))
    res = {"clips": {}}
    (a.work / "runs").mkdir(parents=True, exist_ok=True)
    for row, name in enumerate(CLIPS):
        seq = imported(a.data, a.work, name)
        run = a.work / "runs" / f"{name}-footage"
        counts = _one(seq, run, None)
        entry = clip_entry(seq, run, axes[row, 0], axes[row, 1], name)
        entry["run_defects"] = len(counts["defects"])
        entry["defects"] = counts["defects"]
        res["clips"][name] = entry
        print(name, json.dumps({k: entry[k] for k in ("frame", "run_boxes", "run_boxes_at_or_above_tau",
                                                       "run_kept_on_road", "run_defects")}), flush=True)
    fig.tight_layout()
    a.figure.parent.mkdir(parents=True, exist_ok=True)
    tmp = a.figure.with_suffix(".tmp.jpg")
    fig.savefig(tmp, dpi=80, pil_kwargs={"quality": 80})
    tmp.replace(a.figure)
    res["figure"] = str(a.figure.relative_to(ROOT)) if a.figure.is_relative_to(ROOT) else str(a.figure)
    write_results(a.results, {"commit": git_commit(), **machine_entry(), **res})


if __name__ == "__main__":
    main()
