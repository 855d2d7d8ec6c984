"""End-to-end benchmark: `pavemap run` on the nuScenes-like and kitti-like presets (CPU, simulated detector).

Each preset runs in its own subprocess so peak RSS is that run's alone. Without depth by default (the
monocular case); ``--depth sparse`` synthesizes the same drive with LiDAR-like sparse depth (the second
column). Writes ``bench/results/run.json`` with per-stage seconds, peak RSS and the evaluation scores, one
entry per depth mode (``results`` no depth, ``results_sparse`` with depth).

    python bench/run_bench.py [--presets nuscenes-like kitti-like] [--device cpu] [--depth none|sparse]
"""

from __future__ import annotations

import argparse
import json
import platform
import resource
import shutil
import subprocess
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).parent))

from common import write_results  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
WORK = ROOT / "bench" / "work"
OUT = ROOT / "bench" / "results" / "run.json"
CONFIG_OF = {"nuscenes-like": "nuscenes", "kitti-like": "kitti"}

CHILD = """
import json, sys, time
from pathlib import Path
import pavemap
from pavemap.memory import peak_rss_mb
from pavemap.synth import synthesize
preset, seq_dir, run_dir, device, depth = sys.argv[1], Path(sys.argv[2]), Path(sys.argv[3]), sys.argv[4], sys.argv[5]
t = time.perf_counter()
if not (seq_dir / "sequence.json").is_file():
    synthesize(seq_dir, preset=preset, seed=0, depth=depth)
synth_s = time.perf_counter() - t
cfg = pavemap.load_config({"nuscenes-like": "nuscenes", "kitti-like": "kitti"}[preset])
cfg.device = device
t = time.perf_counter()
res = pavemap.run(seq_dir, cfg, run_dir, overwrite=True, progress=False)
total = time.perf_counter() - t
m = res.metrics
print(json.dumps({
    "synth_seconds": synth_s, "run_seconds": total, "stage_seconds": m["seconds"],
    "peak_rss_mb": peak_rss_mb(),
    "defects": len(res.defects), "evaluation": res.evaluation,
    "mesh": {k: m.get("mesh", {}).get(k) for k in ("psnr", "sem_acc", "height_rmse", "height_rmse_seen",
                                                   "camera_height_init", "vertices")},
    "geometry": m.get("geometry"),
    "paper_metrics": {k: m.get(k) for k in ("filter_rate", "on_road_precision", "coverage", "obs_per_vertex",
                                             "mean_severity", "msr", "avg_distance_m")},
}))
"""


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--presets", nargs="+", default=["nuscenes-like", "kitti-like"])
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--depth", choices=("none", "sparse"), default="none")
    args = ap.parse_args()
    results = {}
    for preset in args.presets:
        seq_dir = WORK / f"run_{preset}-{args.depth}" / "scene"
        run_dir = WORK / f"run_{preset}-{args.depth}" / "run"
        if run_dir.exists():  # measure a fresh run, not a resumed one
            shutil.rmtree(run_dir)
        t = time.perf_counter()
        proc = subprocess.run(
            [sys.executable, "-c", CHILD, preset, str(seq_dir), str(run_dir), args.device, args.depth],
            capture_output=True, text=True, cwd=ROOT,
        )
        if proc.returncode != 0:
            print(proc.stderr[-4000:], file=sys.stderr)
            raise SystemExit(f"{preset}: run failed")
        rec = json.loads(proc.stdout.strip().splitlines()[-1])
        rec["wall_seconds"] = time.perf_counter() - t
        results[preset] = rec
        print(preset, json.dumps(rec["stage_seconds"]), f"peak {rec['peak_rss_mb']:.0f} MB")
    doc = json.loads(OUT.read_text()) if OUT.is_file() else {}
    if "results" in doc and "depth" not in doc:  # an older file: its rows were measured with sparse depth
        doc["results_sparse"] = doc.pop("results")
    doc.update({
        "benchmark": "pavemap run end to end (simulated detector)",
        "machine": {"cpu_count": __import__("os").cpu_count(), "platform": platform.platform(),
                    "python": platform.python_version()},
        "device": args.device,
        "goal": "nuScenes-like end to end <= 90 s on a 2-core CPU",
        "depth": "results: no depth; results_sparse: sparse depth",
        "results" if args.depth == "none" else "results_sparse": results,
        "load_avg": __import__("os").getloadavg(),
        "children_peak_rss_mb": resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024,
    })
    write_results(OUT, doc)


if __name__ == "__main__":
    main()
