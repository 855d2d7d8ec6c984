"""Issue 17: long drives along KITTI-00's trajectory, stage 1 in segments.

kitti-like worlds synthesised along the first N poses of ``kitti-odometry-poses/00.txt`` (``pavemap synth
--trajectory``, no depth), each run end to end (``pavemap run --config kitti``, simulated detector) in its own
process under ``/usr/bin/time -v`` (peak RSS of the whole run). Per drive: stage-1 seconds per frame, peak RSS,
held-out PSNR, height RMSE, F1; per segment: height RMSE and F1 on the road it owns; the seams (how neighbouring
segments agree where they overlap) and the defects split at seams. ``--whole N`` also runs drive N as one
piece (``mesh.segment_m=0``), the path before this issue; ``--cut N:M`` also runs drive N in segments of M m
(the same data one piece and cut: what segmenting costs). Writes ``bench/results/scale.json``, keeping the rows
this run did not redo (each row names its commit), so ``--frames 4541 --cut`` adds the long row alone.

    python bench/scale_bench.py --frames 300 1200 --cut 300:75 [--whole 1200] [--scale 0.5]
"""

from __future__ import annotations

import argparse
import json
import os
import re
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))

from common import fresh_run_folder, git_commit, machine_entry, write_results  # noqa: E402
from pavemap.mesh.config import MeshConfig  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "bench" / "results" / "scale.json"
POSES = ROOT.parent / "shared" / "data" / "kitti-odometry-poses" / "00.txt"
PAVEMAP = str(Path(sys.executable).parent / "pavemap")


def synth(seq: Path, frames: int, scale: float, poses: Path) -> float | None:
    """Synthesise the drive once; its seconds (None: it was there)."""
    if (seq / "sequence.json").is_file():
        return None
    t = time.perf_counter()
    subprocess.run([PAVEMAP, "synth", "--preset", "kitti-like", "--trajectory", str(poses), "--frames", str(frames),
                    "--scale", str(scale), "--depth", "none", "--seed", "0", "-o", str(seq), "--overwrite"],
                   check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                   env={**os.environ, "OMP_NUM_THREADS": "1"})
    return round(time.perf_counter() - t, 1)


def run(seq: Path, out: Path, sets: list[str]) -> dict:
    """``pavemap run`` in a child process; its metrics.json and peak RSS (GiB)."""
    # A fresh folder: an earlier commit's run would lend its stages (their stamps hold the inputs and the
    # settings, not the code), and a resumed run is no measurement.
    fresh_run_folder(out)
    cmd = ["/usr/bin/time", "-v", PAVEMAP, "run", str(seq), "-o", str(out), "--config", "kitti", "--overwrite",
           "--set", "device=cpu", *sum((["--set", s] for s in sets), [])]
    t = time.perf_counter()
    p = subprocess.run(cmd, capture_output=True, text=True)
    wall = time.perf_counter() - t
    if p.returncode:
        raise SystemExit(f"{' '.join(cmd)} failed:\n{p.stderr[-3000:]}")
    rss_kb = int(re.search(r"Maximum resident set size \(kbytes\): (\d+)", p.stderr).group(1))
    return {"metrics": json.loads((out / "metrics.json").read_text()), "peak_rss_gib": round(rss_kb / 2**20, 3),
            "wall_s": round(wall, 1)}


def scored_run(seq: Path, out: Path) -> tuple[list[dict], list[dict], set | None]:
    """The truth defects of ``seq``, the instances of the run folder ``out`` and the ids of the true defects its
    detector saw (None without the truth's detection lines)."""
    from pavemap.evaluate.gt import _read_instances, _read_jsonl, _truth_lines, load_truth, visible_defects
    from pavemap.export.gis import run_defects_path

    records = _read_jsonl(out / "detections_mapped.jsonl")
    lines, _ = _truth_lines(seq, out, len(records))
    return (load_truth(seq), _read_instances(*run_defects_path(out, "defects")),
            visible_defects(records, lines) if lines is not None else None)


def per_segment(seq: Path, out: Path, mesh_m: dict) -> tuple[list[dict], dict]:
    """F1 per segment (truth and instances by the path coordinate of their centroid) and the splits: visible
    true defects that two or more instances of their class cover, at the seams and anywhere."""
    from pavemap.evaluate.gt import score_instances
    from pavemap.io.sequence import read_sequence
    from pavemap.mesh.segments import path_metres

    traj = read_sequence(seq).trajectory()[:, :2]
    s = path_metres(traj)
    truth, preds, visible = scored_run(seq, out)

    def along(xy: np.ndarray) -> np.ndarray:
        from scipy.spatial import cKDTree

        return s[cKDTree(traj).query(xy)[1]] if len(xy) else np.zeros(0)

    ts = along(np.array([[t["polygon"].centroid.x, t["polygon"].centroid.y] for t in truth]).reshape(-1, 2))
    ps = along(np.array([p["centroid"] for p in preds], dtype=float).reshape(-1, 2))
    rows = []
    segs = mesh_m.get("segments") or [{"index": 0, "core_m": [None, None]}]
    cuts = [r["core_m"][1] for r in segs[:-1]]
    for r in segs:
        lo = -np.inf if r["core_m"][0] is None else r["core_m"][0]
        hi = np.inf if r["core_m"][1] is None else r["core_m"][1]
        ti = [i for i in range(len(truth)) if lo <= ts[i] < hi]
        pi = [i for i in range(len(preds)) if lo <= ps[i] < hi]
        sc = score_instances([preds[i] for i in pi], [truth[i] for i in ti], visible)
        rows.append({"index": r["index"], "f1": round(sc["f1"], 3), "recall": round(sc["recall"], 3),
                     "precision": round(sc["precision"], 3), "truth_visible": sc["truth"],
                     "height_rmse_m": r.get("height_rmse"), "height_rmse_seen_m": r.get("height_rmse_seen"),
                     "psnr": r.get("psnr"), "seconds": r.get("seconds"), "frames": r.get("own_frames"),
                     "revisit_frames": r.get("revisit_frames"), "seam_median_abs_m": r.get("seam_median_abs_m"),
                     "pass_median_abs_m": r.get("pass_median_abs_m")})
    split = {"anywhere": 0, "at_seams": 0, "on_seams_visible": 0, "with_slivers_anywhere": 0}
    overlap = (mesh_m.get("config") or {}).get("segment_overlap_m", 20.0)
    for i, t in enumerate(truth):
        if visible is not None and t["id"] not in visible:
            continue
        on_seam = any(abs(ts[i] - c) < overlap / 2 for c in cuts)
        parts = [p["polygon"].area for p in preds if p["cls"] == t["cls"] and p["polygon"].intersects(t["polygon"])]
        n = sum(a >= 0.1 for a in parts)  # a few-cell sliver beside a crack is not a second instance
        split["on_seams_visible"] += on_seam
        split["anywhere"] += n >= 2
        split["at_seams"] += on_seam and n >= 2
        split["with_slivers_anywhere"] += len(parts) >= 2
    return rows, split


def row(seq: Path, out: Path, frames: int, got: dict, synth_s: float | None, segmented: bool) -> dict:
    m = got["metrics"]
    mesh_m, ev = m.get("mesh") or {}, m.get("evaluation") or {}
    segs, split = per_segment(seq, out, mesh_m)
    from pavemap.io.sequence import read_sequence
    from pavemap.mesh.segments import path_metres

    path = float(path_metres(read_sequence(seq).trajectory()[:, :2])[-1])
    stage1 = m["seconds"]["mesh"]
    # views stage 1 processed: a segment's own frames (with the overlaps) and other passes' frames (revisits)
    views = sum((r.get("train_views") or 0) + (r.get("heldout_views") or 0) for r in mesh_m.get("segments") or [])
    views = views or (mesh_m.get("train_views") or 0) + (mesh_m.get("heldout_views") or 0)
    return {"frames": frames, "segmented": bool(mesh_m.get("segmented")), "path_m": round(path, 1),
            "segments": len(mesh_m.get("segments") or [1]), "synth_s": synth_s,
            "stage1_s": round(stage1, 1), "stage1_s_per_frame": round(stage1 / frames, 3),
            "views_processed": views, "stage1_s_per_view": round(stage1 / views, 3) if views else None,
            "total_s": round(m["seconds"]["total"], 1), "peak_rss_gib": got["peak_rss_gib"],
            "grid_cells": (mesh_m.get("grid") or {}).get("nx", 0) * (mesh_m.get("grid") or {}).get("ny", 0),
            "vertices": mesh_m.get("vertices"), "psnr": mesh_m.get("psnr"),
            "height_rmse_m": mesh_m.get("height_rmse"), "height_rmse_seen_m": mesh_m.get("height_rmse_seen"),
            "camera_height_m": ((mesh_m.get("geometry") or {}).get("camera_height") or {}).get("used_m"),
            "seams": mesh_m.get("seams"), "passes": mesh_m.get("passes"), "f1": ev.get("f1"),
            "recall": ev.get("recall"),
            "precision": ev.get("precision"), "median_error_m": ev.get("median_error_m"),
            "split_defects": split, "per_segment": segs}


def _merged(rows: list[dict], commit: str) -> tuple[list[dict], list[dict]]:
    """This run's rows (each stamped with ``commit``) plus the rows of the results file that it did not rerun
    (frames, variant), which keep their own commit (the file's, for rows written before rows carried one): a
    long row can be measured on its own without losing the others. Also the history: the file's earlier
    history plus the summaries (no per-segment rows) of the rows this run replaced, so that the figures the
    README quotes for earlier commits stay in the results."""
    for r in rows:
        r.setdefault("commit", commit)
    try:
        old = json.loads(OUT.read_text())
    except (OSError, ValueError):
        return rows, []
    done = {(r["frames"], r["variant"]) for r in rows}
    previous = [{**r, "commit": r.get("commit", old.get("commit"))} for r in old.get("rows", [])]
    kept = [r for r in previous if (r.get("frames"), r.get("variant")) not in done]
    replaced = [{k: v for k, v in r.items() if k != "per_segment"} for r in previous
                if (r.get("frames"), r.get("variant")) in done]
    return (sorted(kept + rows, key=lambda r: (r["frames"], r["variant"] != "default", r["variant"])),
            old.get("history", []) + replaced)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, nargs="+", default=[300, 1200])
    ap.add_argument("--whole", type=int, nargs="*", default=[], help="drives also run as one piece")
    ap.add_argument("--cut", nargs="*", default=["300:75"], help="N:M: drive N also in segments of M m")
    ap.add_argument("--scale", type=float, default=0.5)
    ap.add_argument("--poses", type=Path, default=POSES)
    ap.add_argument("--data", type=Path, default=Path(os.environ.get("PAVEMAP_BENCH_DATA", "/tmp/pavemap-bench")))
    args = ap.parse_args()
    if not args.poses.is_file():
        raise SystemExit(f"{args.poses}: KITTI-00 poses not found (pass --poses)")
    rows = []
    for n in args.frames:
        seq = args.data / f"scale-k00-{n}-s{args.scale:g}"
        synth_s = synth(seq, n, args.scale, args.poses)
        variants = [("default", [])] + ([("whole", ["mesh.segment_m=0"])] if n in args.whole else [])
        variants += [(f"cut{m}", [f"mesh.segment_m={m}"]) for c in args.cut for k, m in [c.split(":")] if int(k) == n]
        for name, sets in variants:
            out = args.data / f"scale-run-{n}-{name}"
            got = run(seq, out, sets)
            rows.append({"variant": name, "sets": sets, **row(seq, out, n, got, synth_s, name != "whole"),
                         "load_avg_end": [round(x, 2) for x in os.getloadavg()]})
            print(json.dumps({k: v for k, v in rows[-1].items() if k != "per_segment"}), flush=True)
    commit = git_commit()
    rows, history = _merged(rows, commit.strip())
    seg = [r for r in rows if r["variant"] == "default"]
    spf = [r["stage1_s_per_frame"] for r in seg]
    write_results(OUT, {
        "benchmark": "long drives along KITTI-00's trajectory, stage 1 in segments (issue 17)",
        "drive": f"kitti-like, pavemap synth --trajectory 00.txt, image scale {args.scale}, no depth, seed 0; "
                 "pavemap run --config kitti (the default mesh.epochs, 0 since 7b4866e; 7 before), simulated "
                 "detector, CPU, each run its own process",
        "targets": "stage-1 s/frame flat within 1.3x; peak RSS <= 4 GiB, independent of length; seams <= 5 mm",
        "note": f"the default cuts a path longer than 1.5 x mesh.segment_m ({MeshConfig().segment_m:g} m) into "
                "segments; shorter drives are one piece (the short-drive reference)",
        "rows": rows, "s_per_frame_ratio_max_min": round(max(spf) / min(spf), 3) if spf else None,
        "history": history,
        "load_avg_end": os.getloadavg(), "commit": commit.strip(), **machine_entry()})


if __name__ == "__main__":
    main()
