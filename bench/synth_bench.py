"""Benchmark: time and peak memory to generate each synthetic preset at its defaults.

Each preset runs in a fresh subprocess (so peak RSS is that preset's own). Writes
``bench/results/synth.json``. The machine is shared: the load average is recorded next to the
wall time, and CPU time (which contention inflates much less) is reported too.

    .venv/bin/python bench/synth_bench.py [--presets nuscenes-like kitti-like] [--threads 1]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
WORK = ROOT / "bench" / "work"
OUT = ROOT / "bench" / "results" / "synth.json"
TARGET_S = {"nuscenes-like": 60.0}


def _one(preset: str, threads: int, device: str) -> dict:
    from pavemap.memory import peak_rss_mb
    from pavemap.synth import synthesize

    out = WORK / f"synth-{preset}"
    t0, c0 = time.perf_counter(), time.process_time()
    load0 = os.getloadavg()[0]
    seq = synthesize(out, preset=preset, seed=0, overwrite=True, threads=threads, device=device, progress=False)
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    cam = next(iter(seq.cameras.values()))
    views = sum(len(f.views) for f in seq.frames)
    size = sum(p.stat().st_size for p in out.rglob("*") if p.is_file())
    rec = {
        "preset": preset, "frames": len(seq.frames), "cameras": len(seq.cameras), "views": views,
        "image_size": [cam.width, cam.height], "threads": threads, "device": device,
        "seconds": round(wall, 2), "cpu_seconds": round(cpu, 2), "seconds_per_view": round(wall / views, 3),
        "peak_rss_mb": round(peak_rss_mb(), 1),
        "folder_mb": round(size / 2**20, 1), "load_avg_1m_start": round(load0, 2),
        "load_avg_1m_end": round(os.getloadavg()[0], 2),
    }
    if preset in TARGET_S:
        rec["target_seconds"] = TARGET_S[preset]
        rec["meets_target"] = wall <= TARGET_S[preset]
    shutil.rmtree(out, ignore_errors=True)
    return rec


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--presets", nargs="+", default=["nuscenes-like", "kitti-like"])
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--one", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.one:
        print(json.dumps(_one(args.one, args.threads, args.device)))
        return
    runs = []
    for preset in args.presets:
        cmd = [sys.executable, __file__, "--one", preset, "--threads", str(args.threads), "--device", args.device]
        res = subprocess.run(cmd, capture_output=True, text=True, check=False)
        if res.returncode != 0:
            sys.stderr.write(res.stderr)
            raise SystemExit(f"synth bench failed for {preset}")
        rec = json.loads(res.stdout.strip().splitlines()[-1])
        print(json.dumps(rec))
        runs.append(rec)
    from pavemap.io.atomic import atomic_write_json

    atomic_write_json(OUT, {
        "benchmark": "pavemap synth: generate each preset at defaults (seed 0)",
        "machine": {"cpus": os.cpu_count(), "platform": platform.platform(), "python": platform.python_version()},
        "note": "shared machine: compare cpu_seconds across runs; wall time depends on the load average",
        "runs": runs,
    })
    print(f"-> {OUT}")


if __name__ == "__main__":
    main()
