"""Lane-paint false positives (issue 13): ``python bench/paint_bench.py`` → ``bench/results/paint.json``.

A synthetic drive per preset, the simulated detector with ``paint_share`` (default 10 %) of its
detections on lane paint, then the stage-2 filter with the paint rule (``filter.tau_paint``) and
without it (``tau_paint = 1``). Scores: the share of paint false positives removed (target ≥ 90 %) and
the share of true detections the rule removes that the filter kept without it (target ≤ 3 %).

    .venv/bin/python bench/paint_bench.py [--frames 30] [--paint 0.1] [--work /tmp/pavemap-paint]
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from pavemap.detect.config import PAPER_TAU_CONF, FilterConfig
from pavemap.detect.filter import filter_detections
from pavemap.io.atomic import atomic_write_json
from pavemap.io.sequence import read_detections, read_sequence
from pavemap.synth import SimDetectorConfig, detect_sequence, read_detection_truth, synthesize

OUT = Path(__file__).resolve().parent / "results" / "paint.json"
PRESETS = {"kitti-like": 1.0, "nuscenes-like": 0.25}  # render scale


def score(root: Path, paint: float, seed: int) -> dict:
    seq = read_sequence(root)
    detect_sequence(seq, seed=seed, config=SimDetectorConfig(paint_share=paint))
    dets = read_detections(root / "detections.jsonl")
    truth = read_detection_truth(root)
    src = np.array([t["source"] for t in truth])
    true = np.array([bool(t["true"]) for t in truth])
    t0 = time.perf_counter()
    on = filter_detections(seq, dets, FilterConfig(tau_conf=PAPER_TAU_CONF["nuscenes"]))
    t_on = time.perf_counter() - t0
    off = filter_detections(seq, dets, FilterConfig(tau_conf=PAPER_TAU_CONF["nuscenes"], tau_paint=1.0))
    kept_on = np.array([r["kept"] for r in on.records])
    kept_off = np.array([r["kept"] for r in off.records])
    by_paint = np.array([r["reason"] == "paint" for r in on.records])
    is_paint = src == "paint"
    return {
        "n_paint_removed": int((~kept_on & is_paint).sum()), "n_true_kept_without_rule": int((true & kept_off).sum()),
        "n_true_lost_to_rule": int((by_paint & true & kept_off).sum()),
        "detections": len(dets), "paint_fp": int(is_paint.sum()), "true": int(true.sum()),
        "paint_removed": round(float((~kept_on & is_paint).sum() / max(1, is_paint.sum())), 4),
        "paint_removed_without_rule": round(float((~kept_off & is_paint).sum() / max(1, is_paint.sum())), 4),
        "true_lost_to_rule": round(float((by_paint & true & kept_off).sum() / max(1, (true & kept_off).sum())), 4),
        "other_fp_removed_by_rule": int((by_paint & ~true & ~is_paint).sum()),
        "filter_seconds": round(t_on, 2),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=30)
    ap.add_argument("--paint", type=float, default=0.1)
    ap.add_argument("--seeds", type=int, default=2)
    ap.add_argument("--work", type=Path, default=Path("/tmp/pavemap-paint"))
    ap.add_argument("--out", type=Path, default=OUT)
    a = ap.parse_args()
    rows = {}
    for preset, scale in PRESETS.items():
        for seed in range(a.seeds):
            root = a.work / f"{preset}-f{a.frames}-seed{seed}"
            if not (root / "sequence.json").is_file():
                synthesize(root, preset=preset, seed=seed, frames=a.frames, scale=scale, overwrite=True)
            rows[f"{preset}/seed{seed}"] = r = score(root, a.paint, seed)
            print(preset, seed, json.dumps(r), flush=True)
    total = {k: sum(r[k] for r in rows.values()) for k in ("paint_fp", "true")}
    out = {"paint_share": a.paint, "frames": a.frames, "rows": rows, "targets": {"paint_removed": 0.9,
                                                                                 "true_lost_to_rule": 0.03},
           "mean_paint_removed": round(float(np.mean([r["paint_removed"] for r in rows.values()])), 4),
           "mean_true_lost_to_rule": round(float(np.mean([r["true_lost_to_rule"] for r in rows.values()])), 4),
           "pooled_paint_removed": round(sum(r["n_paint_removed"] for r in rows.values())
                                         / max(1, total["paint_fp"]), 4),
           "pooled_true_lost_to_rule": round(sum(r["n_true_lost_to_rule"] for r in rows.values())
                                             / max(1, sum(r["n_true_kept_without_rule"] for r in rows.values())), 4),
           **total}
    a.out.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_json(a.out, out)
    print(f"-> {a.out}")


if __name__ == "__main__":
    main()
