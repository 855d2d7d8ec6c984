"""Issue 45: the same drives on the CPU and on CUDA of one machine, end to end and per stage, in one run.

Drives (synthesised once into ``--data``, simulated detector, no depth: the monocular case):

- ``demo``: what ``pavemap demo`` runs (nuScenes-like, 16 frames x 6 cameras, image scale 0.25, render scale 0.5);
- ``nuscenes40``: nuScenes-like, 40 frames x 6 cameras, image scale 0.5 (the mesh bench's size);
- ``kitti00``: kitti-like along KITTI-00's poses (``pavemap synth --trajectory``, ``--kitti-frames`` of them, all
  4541 by default; image scale 0.5), as bench/scale_bench.py. ``--poses`` names 00.txt (``../shared`` does not
  travel to a lent GPU machine: carry a copy).

Each (drive, device) is ``pavemap run --device D`` in its own process (CUDA's start-up is paid as a user pays
it), into a fresh folder: wall seconds, the stages' seconds from ``metrics.json``, defects, F1. Per drive the
two devices' defects are compared (count, class, nearest position: the issue's "same defects within 1 cm").

``--blas-ab DRIVES``: on the CPU, ``mesh.blas_threads`` 1 (the default) against 0 (one BLAS thread per core), in
turn, ``--blas-pairs`` pairs; ``--blas-busy`` repeats it with one spinning process beside it.

``--profile DRIVE``: that drive is also run in this process under cProfile (per module and the 25 functions of
most own time) and, on CUDA, torch's profiler (host<->device copies: count and time, and the 15 CUDA ops of
most time). On a machine without CUDA the CUDA rows say so; the CPU rows are still measured.

    python bench/cuda_bench.py [--drives demo,nuscenes40,kitti00] [--devices cpu,cuda] [--profile demo]
                               [--kitti-frames 4541] [--poses PATH/00.txt] [--data DIR] [--results FILE]
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))

from common import fresh_run_folder, machine_entry, write_results  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "bench" / "results" / "cuda.json"
PAVEMAP = str(Path(sys.executable).parent / "pavemap")
# drive -> (preset of synth, frames, image scale, run config, extra run settings)
DRIVES = {
    "demo": ("nuscenes-like", 16, 0.25, "nuscenes", ["mesh.render_scale=0.5"]),
    "nuscenes40": ("nuscenes-like", 40, 0.5, "nuscenes", []),
    "kitti00": ("kitti-like", 4541, 0.5, "kitti", []),
}


def synth(seq: Path, drive: str, frames: int, poses: Path | None, device: str) -> float | None:
    """Synthesise the drive once (on ``device``); its seconds (None: it was there)."""
    if (seq / "sequence.json").is_file():
        return None
    preset, _, scale, _, _ = DRIVES[drive]
    cmd = [PAVEMAP, "synth", "--preset", preset, "--frames", str(frames), "--scale", str(scale), "--depth", "none",
           "--seed", "0", "-o", str(seq), "--overwrite", "--device", device]
    if drive == "kitti00":
        if poses is None or not poses.is_file():
            raise SystemExit(f"{poses}: KITTI-00's poses are needed for kitti00 (--poses .../00.txt)")
        cmd += ["--trajectory", str(poses)]
    t = time.perf_counter()
    p = subprocess.run(cmd, capture_output=True, text=True)
    if p.returncode:
        raise SystemExit(f"{' '.join(cmd)} failed:\n{p.stderr[-3000:]}")
    return round(time.perf_counter() - t, 1)


def run(seq: Path, out: Path, drive: str, device: str, extra: tuple[str, ...] = ()) -> dict:
    """``pavemap run --device`` in a child process: wall and CPU seconds, per-stage seconds, defects, F1."""
    fresh_run_folder(out)  # a resumed run would lend its stages: no measurement
    _, _, _, config, sets = DRIVES[drive]
    cmd = [PAVEMAP, "run", str(seq), "-o", str(out), "--config", config, "--overwrite", "--device", device,
           *sum((["--set", s] for s in (*sets, *extra)), [])]
    cpu0 = _child_cpu()
    t = time.perf_counter()
    p = subprocess.run(cmd, capture_output=True, text=True)
    wall = time.perf_counter() - t
    if p.returncode:
        raise SystemExit(f"{' '.join(cmd)} failed:\n{p.stderr[-3000:]}")
    m = json.loads((out / "metrics.json").read_text())
    ev = m.get("evaluation") or {}
    return {"wall_s": round(wall, 1), "cpu_s": round(_child_cpu() - cpu0, 1), "seconds": m.get("seconds"),
            "defects": len(_defects(out)),
            "f1": ev.get("f1"), "mesh_device": (m.get("mesh") or {}).get("device"),
            "height_rmse_m": (m.get("mesh") or {}).get("height_rmse"), "psnr": (m.get("mesh") or {}).get("psnr")}


def _child_cpu() -> float:
    import resource

    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime


def blas_ab(seq: Path, work: Path, drive: str, pairs: int, busy: bool) -> dict:
    """``mesh.blas_threads`` 1 (A, the default) against 0 (B, the BLAS libraries' own pools) on the CPU, A and B in
    turn; ``busy``: one spinning process beside them all along (a shared machine, another job on a core)."""
    spinner = subprocess.Popen([sys.executable, "-c", "while True: pass"]) if busy else None
    try:
        rows = [(run(seq, work / f"cuda-{drive}-blas-a", drive, "cpu", ("mesh.blas_threads=1",)),
                 run(seq, work / f"cuda-{drive}-blas-b", drive, "cpu", ("mesh.blas_threads=0",))) for _ in range(pairs)]
    finally:
        if spinner is not None:
            spinner.kill()
    med = {k: float(np.median([a[k] / b[k] for a, b in rows])) for k in ("wall_s", "cpu_s")}
    return {"pairs": pairs, "busy_core": busy, "wall_s": [[a["wall_s"], b["wall_s"]] for a, b in rows],
            "cpu_s": [[a["cpu_s"], b["cpu_s"]] for a, b in rows], "median_ratio_wall": round(med["wall_s"], 3),
            "median_ratio_cpu": round(med["cpu_s"], 3), "same_defects": [a["defects"] == b["defects"] for a, b in rows]}


def _defects(out: Path) -> list[tuple[str, float, float]]:
    with (out / "defects.csv").open(newline="") as fh:
        return [(r["code"], float(r["x_m"]), float(r["y_m"])) for r in csv.DictReader(fh)]


def same_defects(a: Path, b: Path) -> dict:
    """Whether two runs mapped the same defects: counts, and for each of ``a``'s the nearest of ``b``'s of its class."""
    da, db = _defects(a), _defects(b)
    dists = []
    for code, x, y in da:
        pts = np.array([(bx, by) for c, bx, by in db if c == code])
        dists.append(float(np.min(np.hypot(pts[:, 0] - x, pts[:, 1] - y))) if len(pts) else float("inf"))
    worst = max(dists) if dists else 0.0
    return {"count": [len(da), len(db)], "max_nearest_m": None if worst == float("inf") else round(worst, 4),
            "within_1cm": len(da) == len(db) and worst <= 0.01}


def profile(seq: Path, out: Path, drive: str, device: str) -> dict:
    """The drive run in this process under cProfile (and torch's profiler on CUDA): where the time goes."""
    import cProfile
    import pstats

    import torch

    import pavemap

    _, _, _, config, sets = DRIVES[drive]
    cfg = pavemap.load_config(config, overrides=[f"device={device}", *sets])
    fresh_run_folder(out)
    prof = cProfile.Profile()
    acts = [torch.profiler.ProfilerActivity.CPU]
    cuda = device.startswith("cuda")
    if cuda:
        acts.append(torch.profiler.ProfilerActivity.CUDA)
    with torch.profiler.profile(activities=acts) as tp:
        prof.enable()
        pavemap.run(seq, cfg, out, overwrite=True, progress=False)
        prof.disable()
    st = pstats.Stats(prof)
    by_module: dict[str, float] = {}
    funcs = []
    for (file, line, name), (_, _, tottime, _, _) in st.stats.items():  # type: ignore[attr-defined]
        mod = _module(file)
        by_module[mod] = by_module.get(mod, 0.0) + tottime
        funcs.append((tottime, f"{mod}:{name}:{line}"))
    rec = {"device": device,
           "by_module_s": {k: round(v, 2) for k, v in sorted(by_module.items(), key=lambda kv: -kv[1])[:25]},
           "top_functions_own_s": [{"function": f, "s": round(t, 3)} for t, f in sorted(funcs, reverse=True)[:25]]}
    if cuda:
        ev = tp.key_averages()
        copies = [e for e in ev if "Memcpy" in e.key]
        rec["copies"] = [{"kind": e.key, "count": e.count, "ms": round(_device_us(e) / 1000, 2)} for e in copies]
        kernels = sorted((e for e in ev if _device_us(e) > 0), key=_device_us, reverse=True)[:15]
        rec["top_cuda_ops"] = [{"op": e.key, "count": e.count, "ms": round(_device_us(e) / 1000, 2)} for e in kernels]
    return rec


def _device_us(e: object) -> float:
    return float(getattr(e, "device_time_total", 0.0) or getattr(e, "cuda_time_total", 0.0) or 0.0)


def _module(file: str) -> str:
    """A profiler entry's home: ``pavemap.mesh.bake`` for pavemap's files, else the package (torch, numpy, ...)."""
    parts = Path(file).with_suffix("").parts
    homes = [i for i, p in enumerate(parts) if p == "pavemap" and i > 0 and parts[i - 1] in ("src", "site-packages")]
    if homes:
        return ".".join(parts[homes[-1]:])
    if "site-packages" in parts and parts[-1] != "site-packages":
        return parts[parts.index("site-packages") + 1]
    return "builtins" if file.startswith("~") or file.startswith("<") else Path(file).name


def main() -> None:
    import torch

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--drives", default="demo,nuscenes40,kitti00")
    ap.add_argument("--devices", default="cpu,cuda")
    ap.add_argument("--profile", default="", help="drive to profile in-process on each device ('' none)")
    ap.add_argument("--blas-ab", default="", help="drives whose CPU runs compare mesh.blas_threads 1 against 0")
    ap.add_argument("--blas-pairs", type=int, default=3)
    ap.add_argument("--blas-busy", action="store_true", help="also the A/B with one spinning process beside it")
    ap.add_argument("--kitti-frames", type=int, default=4541)
    ap.add_argument("--poses", type=Path, default=ROOT.parent / "shared" / "data" / "kitti-odometry-poses" / "00.txt")
    ap.add_argument("--data", type=Path, default=Path(os.environ.get("PAVEMAP_BENCH_DATA", "/tmp/pavemap-bench")))
    ap.add_argument("--results", type=Path, default=RESULTS)
    a = ap.parse_args()
    has_cuda = torch.cuda.is_available()
    devices = [d for d in a.devices.split(",") if d]
    synth_dev = "cuda" if has_cuda else "cpu"
    res: dict = {"benchmark": "the same drives on CPU and CUDA of one machine, end to end and per stage (issue 45)",
                 **machine_entry(), "cpu_threads": torch.get_num_threads(), "load_avg_1m": round(os.getloadavg()[0], 2),
                 "cuda_device": torch.cuda.get_device_name(0) if has_cuda else None, "drives": {}, "profiles": {},
                 "blas_threads": {}}
    for drive in [d for d in a.drives.split(",") if d]:
        frames = a.kitti_frames if drive == "kitti00" else DRIVES[drive][1]
        seq = a.data / f"cuda-{drive}-{frames}"
        entry: dict = {"frames": frames, "synth_s": synth(seq, drive, frames, a.poses, synth_dev), "runs": {}}
        for dev in devices:
            if dev.startswith("cuda") and not has_cuda:
                entry["runs"][dev] = {"skipped": "torch sees no CUDA device on this machine"}
                continue
            entry["runs"][dev] = run(seq, a.data / f"cuda-{drive}-{frames}-run-{dev}", drive, dev)
            print(drive, dev, json.dumps(entry["runs"][dev]), flush=True)
        done = [d for d in devices if "wall_s" in entry["runs"].get(d, {})]
        if "cpu" in done and len(done) > 1:
            other = next(d for d in done if d != "cpu")
            entry["speedup"] = round(entry["runs"]["cpu"]["wall_s"] / entry["runs"][other]["wall_s"], 2)
            entry["same_defects"] = same_defects(a.data / f"cuda-{drive}-{frames}-run-cpu",
                                                 a.data / f"cuda-{drive}-{frames}-run-{other}")
        res["drives"][drive] = entry
        if drive in a.blas_ab.split(","):
            res["blas_threads"][drive] = blas_ab(seq, a.data, drive, a.blas_pairs, False)
            print(drive, "blas", json.dumps(res["blas_threads"][drive]), flush=True)
            if a.blas_busy:
                res["blas_threads"][f"{drive}-busy"] = blas_ab(seq, a.data, drive, a.blas_pairs, True)
                print(drive, "blas busy", json.dumps(res["blas_threads"][f"{drive}-busy"]), flush=True)
        if drive == a.profile:
            for dev in [d for d in devices if not d.startswith("cuda") or has_cuda]:
                res["profiles"][f"{drive}-{dev}"] = profile(seq, a.data / f"cuda-{drive}-profile-{dev}", drive, dev)
    res["load_avg_1m_end"] = round(os.getloadavg()[0], 2)
    write_results(a.results, res)


if __name__ == "__main__":
    main()
