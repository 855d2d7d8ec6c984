"""What stage 1 costs without depth, against the same drive with sparse depth (issue 12: at most 1.5x).

Runs ``pavemap.mesh.reconstruct`` on mesh_bench's drives (the same settings: ``--presets``, render and eval scale
0.25, one torch thread, CPU) without depth and with sparse depth in turn, none / sparse / none / sparse ..., and
takes the ratio pair by pair: on this shared, noisy machine two runs minutes apart differ by more than the
gap being measured. Reports every run, the median of each mode and the median and range of the pair ratios.
Writes ``bench/results/depth_cost.json`` (earlier runs kept under ``history``).

    python bench/depth_cost_bench.py [--pairs 5] [--presets kitti-like,nuscenes-like]
"""

from __future__ import annotations

import json
import os
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "src"))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from common import bench_parser, git_commit, machine_entry, write_results  # noqa: E402
from mesh_bench import SETTINGS, bench_drive  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "bench" / "results" / "depth_cost.json"


def one_run(preset: str, data: Path, depth: str) -> float:
    from pavemap.io.sequence import read_sequence
    from pavemap.mesh import MeshConfig, reconstruct

    seq = read_sequence(bench_drive(data, preset, depth, "cpu"))
    cfg = MeshConfig.preset(SETTINGS[preset]["mesh_preset"])
    cfg.render_scale = SETTINGS[preset]["render_scale"]
    cfg.eval_scale, cfg.device, cfg.resume, cfg.threads = 0.25, "cpu", False, 1
    t = time.perf_counter()
    reconstruct(seq, None, cfg, progress=False)
    return time.perf_counter() - t


def main() -> None:
    ap = bench_parser(__doc__, "kitti-like,nuscenes-like", RESULTS)
    ap.add_argument("--pairs", type=int, default=5)
    a = ap.parse_args()
    out: dict = {"benchmark": "stage 1 without depth vs with sparse depth, same drive, runs in turn",
                 "target": "none / sparse <= 1.5", "presets": {}}
    for preset in a.presets.split(","):
        one_run(preset, a.data, "none")  # warm-up: numba's compiled kernels, the page cache
        runs: dict[str, list[float]] = {"none": [], "sparse": []}
        for _ in range(a.pairs):
            for depth in ("none", "sparse"):
                runs[depth].append(round(one_run(preset, a.data, depth), 2))
        ratios = [n / s for n, s in zip(runs["none"], runs["sparse"], strict=True)]
        out["presets"][preset] = {
            "seconds": runs, "median_none_s": statistics.median(runs["none"]),
            "median_sparse_s": statistics.median(runs["sparse"]),
            "ratio_median": round(statistics.median(ratios), 3),
            "ratio_min": round(min(ratios), 3), "ratio_max": round(max(ratios), 3)}
        print(preset, json.dumps(out["presets"][preset]), flush=True)
    commit = git_commit()
    try:
        old = json.loads(a.results.read_text())
        history = old.pop("history", []) + [old]
    except (OSError, ValueError):
        history = []
    write_results(a.results, {**out, "load_avg": os.getloadavg(), "commit": commit.strip(), **machine_entry(),
                              "history": history})


if __name__ == "__main__":
    main()
