"""Many drives: one after another vs a dask LocalCluster of 2 worker processes -> bench/results/network.json.

Drives: one synthetic kitti-like world (24 frames at 4 Hz, half-resolution images), driven in up to
4 surveys by 2 vehicles (right and left lane): 8 distinct drives, of which the first 2, 4 and 8 make the
three networks; and one long drive of the same world (96 frames, ~215 m) in 25 m segments, to measure a long
drive's segments as tasks. Config (``--config``): the kitti preset's defaults (-> network.json) or the test's
light one (tests/test_network.py; -> network-light.json), figures, report pages and overlays off in both. Each
(network, mode) runs in a fresh process into a fresh network folder, so nothing is reused and each peak RSS is
its own.

Reported per network: wall seconds of the batch (serial: the drives one by one in one process, the same
task function with every thread pool at one thread, as on a worker; serial-all-threads: the same with the
process's default threads, what one drive after another on both cores gives; dask: including the
cluster's start and close, workers forked from a preloaded forkserver as `pavemap batch` starts them, and
dask-2-workers-spawn: workers spawned as fresh interpreters, dask's default), ``process_s`` (the whole
process: imports and exit too, what a user waits), speedup (serial / dask, of both, and serial-all-threads
/ dask), peak RSS per worker process (MiB, from the tasks' ``getrusage``), register build time, and the
machine's load (``uptime``) before and after, since the 2 cores are shared.

``--drive-size preset``: the same 8 drives at the kitti-like preset's own length, rate and image size (80
frames at 10 Hz, ~12 s a drive instead of ~3 s) -> network-preset.json; data in /tmp/pavemap-network-bench-preset.

    nice -n 10 .venv/bin/python bench/network_bench.py [--config default|light] [--sizes 2,4,8,long]
        [--drive-size small|preset] [--data DIR]
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))
sys.path.insert(0, str(ROOT / "bench"))

SURVEYS = 4  # x 2 vehicles = 8 drives


def _world(size: str) -> dict:
    """The drives' world: the test's small one (24 frames at 4 Hz, half-size images: ~3 s a drive), or the
    kitti-like preset's own drive length, rate and image size (80 frames at 10 Hz: ~12 s a drive, what
    `pavemap run` maps end to end in the run bench)."""
    from test_network import WORLD

    if size == "small":
        return WORLD
    return {k: v for k, v in WORLD.items() if k not in ("frames", "hz", "scale", "road_after")}


def _drives(data: Path, size: str = "small") -> list[dict]:
    """The 8 drives (synthesised once; kept in ``data`` between bench runs)."""
    from pavemap.synth import synthesize

    world = _world(size)
    out = []
    for k in range(SURVEYS):
        for lane, vehicle in ((0, "van1"), (1, "van2")):
            name = f"s{k}-{vehicle}"
            seq = data / "seqs" / name
            if not (seq / "sequence.json").is_file():
                synthesize(seq, **world, survey=k, ego_lane=lane, overwrite=True)
            out.append({"path": str(seq), "date": f"2026-{1 + 3 * k:02d}-05", "name": name, "vehicle": vehicle})
    return out


# The test's light settings (1 mesh epoch, 10 % render scale: ~12 s a drive, startup-bound) and the preset's
# defaults (~20 s a drive, what `pavemap batch` runs); figures, report pages and overlays off in both.
CONFIGS = {"light": None, "default": ["device=cpu", "output.figures=false", "output.report=false",
                                       "output.overlay_frames=0"]}
LONG = {"frames": 96, "segment_m": 25.0, "overlap_m": 5.0}


def _long_drive(data: Path, size: str = "small") -> dict:
    from pavemap.synth import synthesize

    world = _world(size)
    seq = data / "seqs" / "long"
    if not (seq / "sequence.json").is_file():
        synthesize(seq, **{**world, "frames": LONG["frames"]}, overwrite=True)
    return {"path": str(seq), "date": "2026-01-05", "name": "long", "vehicle": "van1"}


def _one(mode: str, manifest: Path, net: Path) -> dict:
    """Run one batch in this (fresh) process; print its figures as JSON."""
    from pavemap.network.batch import run_batch

    t = time.perf_counter()
    serial = mode.startswith("serial")
    s = run_batch(manifest, net, scheduler="serial" if serial else None, workers=None if serial else 2,
                  echo=lambda _: None, threads=0 if mode == "serial-all-threads" else 1,
                  worker_start="spawn" if mode.endswith("-spawn") else "forkserver")
    wall = time.perf_counter() - t
    peak: dict[str, float] = {}
    for e in s["drives"]:
        for r in [e, *e.get("segment_tasks", [])]:
            peak[r.get("worker", "?")] = max(peak.get(r.get("worker", "?"), 0.0), float(r.get("peak_rss_mb") or 0))
    reg = s.get("register") or {}
    return {"wall_s": round(wall, 2), "batch_s": s.get("batch_seconds"), "failed": s["failed"],
            "peak_rss_mb_per_worker": sorted(peak.values(), reverse=True), "register_s": reg.get("seconds"),
            "register_defects": reg.get("defects"), "observations": reg.get("observations"),
            "drive_seconds": [e.get("seconds") for e in s["drives"]],
            "segment_tasks": sum(len(e.get("segment_tasks", [])) for e in s["drives"])}


def _load() -> str:
    return subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip()


def main() -> None:
    from common import git_commit, machine_entry, write_results
    from test_network import OVERRIDES

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", default="2,4,8,long")
    ap.add_argument("--config", choices=sorted(CONFIGS), default="default",
                    help="drive settings: the preset's defaults, or the test's light ones (startup-bound)")
    ap.add_argument("--drive-size", choices=("small", "preset"), default="small",
                    help="small: the test's 3 s drives; preset: the kitti-like preset's own drives (~12 s)")
    ap.add_argument("--data", type=Path, help="default: /tmp/pavemap-network-bench[-preset]")
    ap.add_argument("--results", type=Path, help="default: bench/results/network.json (network-light.json)")
    ap.add_argument("--one", nargs=3, metavar=("MODE", "MANIFEST", "NET"), help=argparse.SUPPRESS)
    a = ap.parse_args()
    if a.one:
        from pavemap.shutdown import prepare_quick_exit

        print(json.dumps(_one(a.one[0], Path(a.one[1]), Path(a.one[2]))))
        prepare_quick_exit()  # as the CLI does: process_s is what a user of `pavemap batch` waits
        return
    data = a.data or Path("/tmp/pavemap-network-bench" + ("-preset" if a.drive_size == "preset" else ""))
    name = "network" + ("-light" if a.config == "light" else "") + ("-preset" if a.drive_size == "preset" else "")
    results = a.results or ROOT / "bench" / "results" / f"{name}.json"
    drives = _drives(data, a.drive_size)
    commit = git_commit()
    base = CONFIGS[a.config] or OVERRIDES
    rows = []
    for n in a.sizes.split(","):
        manifest = data / f"manifest-{n}.yaml"
        if n == "long":
            over = [*base, f"mesh.segment_m={LONG['segment_m']}", f"mesh.segment_overlap_m={LONG['overlap_m']}"]
            doc, row = {"config": "kitti", "set": over, "drives": [_long_drive(data, a.drive_size)]}, {"drives": 1,
                                                                                                 "long": LONG}
        else:
            doc, row = {"config": "kitti", "set": base, "drives": drives[:int(n)]}, {"drives": int(n)}
        manifest.write_text(json.dumps(doc))  # JSON is YAML
        row["load_before"] = _load()
        for mode in ("serial", "dask-2-workers", "serial-all-threads", "dask-2-workers-spawn"):
            net = data / f"net-{n}-{mode}"
            if net.exists():  # the bench's own network folder (every drive is run afresh); nothing else
                from pavemap.io.owned import check_replaceable

                check_replaceable(net, "network", overwrite=True)
                shutil.rmtree(net)
            t = time.perf_counter()
            p = subprocess.run([sys.executable, __file__, "--one", mode, str(manifest), str(net)],
                               capture_output=True, text=True, env={**os.environ, "PYTHONWARNINGS": "ignore"})
            process_s = round(time.perf_counter() - t, 2)
            if p.returncode:
                raise SystemExit(f"{mode} with {n} drives failed:\n{p.stderr[-3000:]}")
            row[mode] = {**json.loads(p.stdout.strip().splitlines()[-1]), "process_s": process_s}
            print(n, mode, row[mode], flush=True)
        row["speedup"] = round(row["serial"]["wall_s"] / row["dask-2-workers"]["wall_s"], 2)
        row["speedup_process"] = round(row["serial"]["process_s"] / row["dask-2-workers"]["process_s"], 2)
        row["speedup_vs_all_threads"] = round(row["serial-all-threads"]["wall_s"] / row["dask-2-workers"]["wall_s"], 2)
        row["speedup_spawned_workers"] = round(row["serial"]["wall_s"] / row["dask-2-workers-spawn"]["wall_s"], 2)
        row["load_after"] = _load()
        rows.append(row)
    write_results(results, {**machine_entry(), "commit": commit, "config": a.config, "set": base,
                            "drive_size": a.drive_size, "world": _world(a.drive_size),
                            "target_speedup": 1.7, "networks": rows,
                              "note": "2-core machine shared with other jobs; see load_before/after"})


if __name__ == "__main__":
    main()
