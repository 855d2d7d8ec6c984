"""Issue 12 item 4: the mesh over the road the cameras see beyond the trajectory's ends.

The kitti-like drive of the issue (seed 23, 60 frames, ``--preset kitti``): before, detections on road
20-40 m ahead of the last frames hit no mesh. Runs it without depth (the default) and with sparse depth,
with ``mesh.view_range_m`` 0 (trajectory crop only) and the default, and reports MSR, recall, F1, the
median localisation error, the mesh's vertex count and stage-1 seconds. Target: MSR >= 0.95, recall >= 0.85
with and without depth. Writes ``bench/results/ahead.json``.

    python bench/ahead_bench.py [--frames 60] [--seed 23]
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).parent))

from common import fresh_run_folder, git_commit, machine_entry, write_results  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "bench" / "results" / "ahead.json"


def one(seq_dir: Path, run_dir: Path, view_range: float) -> dict:
    import pavemap
    from pavemap.mesh.config import MeshConfig

    cfg = pavemap.load_config("kitti")
    cfg.mesh.view_range_m = view_range
    cfg.device = "cpu"
    fresh_run_folder(run_dir)  # a fresh run, not a resumed one
    t = time.perf_counter()
    res = pavemap.run(seq_dir, cfg, run_dir, overwrite=True, progress=False)
    ev = res.evaluation or {}
    m = res.metrics
    fused = ev.get("fused", ev)
    assert isinstance(cfg.mesh, MeshConfig)
    return {"view_range_m": view_range, "seconds": round(time.perf_counter() - t, 1),
            "mesh_seconds": round(m["seconds"].get("mesh", 0.0), 1), "msr": m.get("msr"),
            "recall": fused.get("recall"), "precision": fused.get("precision"), "f1": fused.get("f1"),
            "median_error_m": fused.get("median_error_m", fused.get("median_distance_m")),
            "vertices": (m.get("mesh") or {}).get("vertices"),
            "height_rmse_m": (m.get("mesh") or {}).get("height_rmse"), "psnr": (m.get("mesh") or {}).get("psnr")}


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--frames", type=int, default=60)
    ap.add_argument("--seed", type=int, default=23)
    ap.add_argument("--data", type=Path, default=Path(os.environ.get("PAVEMAP_BENCH_DATA", "/tmp/pavemap-bench")))
    args = ap.parse_args()
    from pavemap.synth import synthesize

    rows = []
    for depth in ("none", "sparse"):
        seq_dir = args.data / f"ahead-kitti-{args.seed}-{args.frames}-{depth}"
        if not (seq_dir / "sequence.json").is_file():
            synthesize(seq_dir, preset="kitti-like", seed=args.seed, frames=args.frames, depth=depth, progress=False)
        for vr in (0.0, 30.0):
            r = one(seq_dir, args.data / f"ahead-run-{depth}-{vr:g}", vr)
            r["depth"] = depth
            rows.append(r)
            print(r, flush=True)
    load = os.getloadavg()
    commit = git_commit()
    import json

    from pavemap.mesh.config import MeshConfig

    try:  # the earlier runs stay in the file, their figures quoted in the README
        old = json.loads(OUT.read_text())
        history = old.pop("history", []) + [old]
    except (OSError, ValueError):
        history = []
    epochs = MeshConfig.preset("kitti").epochs
    write_results(OUT, {"benchmark": "mesh over the road seen beyond the trajectory (issue 12 item 4)",
                        "drive": f"kitti-like seed {args.seed}, {args.frames} frames, preset kitti, "
                                 f"{epochs} epochs (the default), CPU",
                        "target": "MSR >= 0.95 and recall >= 0.85, with and without depth",
                        "rows": rows, "load_avg": load, "commit": commit.strip(), **machine_entry(),
                        "history": history})


if __name__ == "__main__":
    main()
