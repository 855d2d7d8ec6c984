"""The compiled CPU ray march (``pavemap.geometry.march_cpu``) against the torch march it replaces on a CPU.

Two measurements on the mesh benchmark's synthetic drives (no depth):

1. the march alone: every pixel of a few views at the stage-1 render scale (0.25) cast on the drive's true
   surface, rays per second with each march (median of ``--repeats``), one and two threads, and how many rays
   get the same triangle from both;
2. stage 1 end to end: ``bench/mesh_bench.py`` in a fresh process per run with ``PAVEMAP_MARCH=torch`` and
   with the default (compiled), the two alternating, each ``--runs`` times: seconds, seconds per epoch,
   held-out PSNR, height RMSE over observed vertices, camera height.

Writes ``bench/results/march.json``.

    python bench/march_bench.py [--presets kitti-like,nuscenes-like] [--runs 1] [--skip-stage1]
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "src"))
sys.path.insert(0, str(Path(__file__).parent))

from common import git_commit, machine_entry, write_results  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "bench" / "results" / "march.json"


def march_alone(seq_dir: Path, views: int, repeats: int) -> dict:
    """Rays per second of both marches on ``views`` views' pixels against the drive's true surface."""
    from pavemap.geometry import march_cpu, pixel_grid, pixel_rays, surface_bounds
    from pavemap.geometry.heightfield import _find_roots
    from pavemap.io.sequence import read_sequence
    from pavemap.io.truth import read_truth_height

    seq = read_sequence(seq_dir)
    hf = read_truth_height(seq_dir)
    vs = [v for f in seq.frames[:: max(1, len(seq.frames) // views)] for v in f.views.values()][:views]
    os_, ds = [], []
    for v in vs:
        cam = seq.cameras[v.camera]
        w, h = int(cam.width * 0.25), int(cam.height * 0.25)
        K = torch.as_tensor(cam.K, dtype=torch.float64).clone()
        K[:2] *= 0.25
        o, d = pixel_rays(K, torch.as_tensor(v.T_world_cam, dtype=torch.float64), pixel_grid(w, h, dtype=torch.float64))
        os_.append(o.float())
        ds.append(d.float())
    o, d = torch.cat(os_), torch.cat(ds)
    b = surface_bounds(hf, torch.float32)
    out = {"rays": int(o.shape[0]), "views": len(vs)}
    for threads in (1, 2):
        torch.set_num_threads(threads)
        for name, fn in (("torch", _find_roots), ("compiled", march_cpu.find_roots_cpu)):
            fn(hf, o[:100], d[:100], 200.0, 0.5, 16, 40, b)  # warm-up (compiles once)
            ts = []
            for _ in range(repeats):
                t = time.perf_counter()
                fn(hf, o, d, 200.0, 0.5, 16, 40, b)
                ts.append(time.perf_counter() - t)
            out[f"{name}_rays_per_s_{threads}t"] = round(o.shape[0] / statistics.median(ts))
        fast, slow = out[f"compiled_rays_per_s_{threads}t"], out[f"torch_rays_per_s_{threads}t"]
        out[f"speedup_{threads}t"] = round(fast / slow, 1)
    ref = _find_roots(hf, o, d, 200.0, 0.5, 16, 40, b)
    new = march_cpu.find_roots_cpu(hf, o, d, 200.0, 0.5, 16, 40, b)
    key = lambda r: {int(k): (int(i), int(j), bool(lw)) for k, i, j, lw in zip(r[0], r[2], r[3], r[4], strict=True)}  # noqa: E731
    kr, kn = key(ref), key(new)
    out["hits_torch"], out["hits_compiled"] = len(kr), len(kn)
    out["same_triangle_share"] = round(sum(kr.get(k) == t for k, t in kn.items()) / max(1, len(kr)), 6)
    return out


def stage1(preset: str, march: str, data: Path) -> dict:
    """One mesh_bench run of ``preset`` (no depth) in a fresh process with the given march."""
    env = dict(os.environ, PAVEMAP_MARCH="torch" if march == "torch" else "")
    with tempfile.TemporaryDirectory() as tmp:
        res = Path(tmp) / "mesh.json"
        subprocess.run([sys.executable, str(ROOT / "bench" / "mesh_bench.py"), "--presets", preset,
                        "--data", str(data), "--results", str(res)], check=True, env=env,
                       stdout=subprocess.DEVNULL)
        r = json.loads(res.read_text())["cpu"]["presets"][preset]
    keep = ("seconds_total", "seconds_per_epoch", "psnr_db", "height_rmse_observed_m", "height_bias_observed_m",
            "height_rmse_all_m", "camera_height_used_m", "camera_height_true_m", "peak_rss_mb", "load_avg")
    return {"march": march, **{k: r.get(k) for k in keep}}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--presets", default="kitti-like,nuscenes-like")
    ap.add_argument("--data", type=Path, default=Path(os.environ.get("PAVEMAP_BENCH_DATA", "/tmp/pavemap-bench")))
    ap.add_argument("--views", type=int, default=6)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--runs", type=int, default=1)
    ap.add_argument("--skip-stage1", action="store_true")
    a = ap.parse_args()
    from mesh_bench import bench_drive

    commit = git_commit()
    results = {"benchmark": "compiled CPU ray march vs the torch march (stage-1 renderer)", "commit": commit.strip(),
               **machine_entry(), "march_alone": {}, "stage1": {}}
    for preset in a.presets.split(","):
        seq_dir = bench_drive(a.data, preset, "none", "cpu")
        results["march_alone"][preset] = march_alone(seq_dir, a.views, a.repeats)
        print(preset, results["march_alone"][preset], flush=True)
        if a.skip_stage1:
            continue
        rows = []
        for k in range(a.runs):
            for march in (("torch", "compiled") if k % 2 == 0 else ("compiled", "torch")):
                rows.append(stage1(preset, march, a.data))
                print(rows[-1], flush=True)
        med = {m: statistics.median(r["seconds_total"] for r in rows if r["march"] == m) for m in ("torch", "compiled")}
        results["stage1"][preset] = {"runs": rows, "median_s": med, "speedup": round(med["torch"] / med["compiled"], 2)}
        results["load_avg_end"] = os.getloadavg()
        write_results(RESULTS, results)
    write_results(RESULTS, results)


if __name__ == "__main__":
    main()
