"""Fusion's crack join (``fusion.crack_join_m``) on a finished long drive: the same mesh and detections fused
with the join off and on, scored against the truth (F1, split defects at the seams and anywhere).

Stages 2-3 only (``pavemap fuse``), so the comparison holds the surface fixed. Writes
``bench/results/crack_join.json``.

    python bench/crack_join_bench.py [--run /tmp/pavemap-bench/scale-run-4541-default]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).parent))

from common import git_commit, machine_entry, write_results  # noqa: E402
from scale_bench import PAVEMAP, per_segment, scored_run  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "bench" / "results" / "crack_join.json"


def fuse(seq: Path, run: Path, out: Path, join_m: float) -> float:
    t = time.perf_counter()
    subprocess.run([PAVEMAP, "fuse", str(seq), "--mesh", str(run / "mesh"), "--detections",
                    str(run / "detections.jsonl"), "-o", str(out), "--config", "kitti", "--set", "device=cpu",
                    "--set", f"fusion.crack_join_m={join_m}"], check=True, capture_output=True)
    return time.perf_counter() - t


def score(seq: Path, out: Path, mesh_m: dict) -> dict:
    from pavemap.evaluate.gt import score_instances

    _, split = per_segment(seq, out, mesh_m)
    truth, preds, visible = scored_run(seq, out)
    sc = score_instances(preds, truth, visible)
    return {"instances": len(preds), **{k: round(float(sc[k]), 4) for k in ("f1", "precision", "recall",
                                                                            "median_error_m")},
            "split_defects": split}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    data = Path(os.environ.get("PAVEMAP_BENCH_DATA", "/tmp/pavemap-bench"))
    ap.add_argument("--run", type=Path, default=data / "scale-run-4541-default")
    ap.add_argument("--seq", type=Path, default=data / "scale-k00-4541-s0.5")
    ap.add_argument("--join", type=float, nargs="+", default=[0.0, 1.0])
    args = ap.parse_args()
    metrics = json.loads((args.run / "metrics.json").read_text())
    rows = []
    for j in args.join:
        out = args.run.parent / f"{args.run.name}-fuse-join{j:g}"
        s = fuse(args.seq, args.run, out, j)
        rows.append({"crack_join_m": j, "fuse_s": round(s, 1), **score(args.seq, out, metrics["mesh"])})
        print(json.dumps(rows[-1]), flush=True)
    commit = git_commit()
    # earlier results (another mesh or join rule) stay, under their commit
    old = json.loads(OUT.read_text()) if OUT.is_file() else {}
    history = old.get("history", []) + ([{k: old.get(k) for k in ("commit", "run", "rows", "machine")}]
                                        if old.get("rows") else [])
    write_results(OUT, {"benchmark": "fusion.crack_join_m on a finished drive (stages 2-3 only)", "history": history,
                        "run": str(args.run), "frames": len(json.loads((args.seq / "sequence.json").read_text())
                                                             .get("frames", [])),
                        "rows": rows, "commit": commit.strip(), **machine_entry()})


if __name__ == "__main__":
    main()
