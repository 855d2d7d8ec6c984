"""Where a 2-drive batch's time goes on 2 workers (issue 18) -> bench/results/network-ceiling.json.

The network bench's first 2 small drives (bench/network_bench.py: ~3 s each warm). Every row runs in fresh
processes; seconds are wall seconds of the batch call (imports before it not counted, as in network.json):

- ``one_drive``: one drive run twice in one process: the first run (lazy imports, caches) and a warm one;
- ``two_processes``: both drives at once in 2 processes that have each run a drive already (the ceiling of any
  scheduler on 2 cores: no worker start, no dispatch, warm code);
- ``serial``: ``run_batch(scheduler="serial")``, one thread per pool (network.json's serial row), and
  ``serial_warm``: the same in a process that has run a drive before;
- ``cold_cluster``: ``run_batch`` on a new LocalCluster of 2 forked workers (the default);
- ``standing_cluster``: ``run_batch(scheduler=ADDRESS)`` on a LocalCluster of 2 forked workers started
  beforehand (what ``--scheduler tcp://HOST:8786`` gives), its first batch (workers started, no drive run yet)
  and a second batch into a new folder (workers warm).

    python bench/network_ceiling.py [--data /tmp/pavemap-network-bench]
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "src"))
sys.path.insert(0, str(ROOT / "bench"))
sys.path.insert(0, str(ROOT / "tests"))

RESULTS = ROOT / "bench" / "results" / "network-ceiling.json"
SCRATCH = "network-ceiling scratch"


def _task(manifest: Path, k: int, out: Path) -> dict:
    from pavemap.network.batch import _plan
    from pavemap.network.manifest import load_manifest

    _, tasks = _plan(load_manifest(manifest), out, {}, 1)
    return {**tasks[k], "segment_tasks": False, "retries": 0}


def child_drive(manifest: Path, k: int, out: Path, barrier: Path | None) -> None:
    """Run drive k twice; with a barrier, wait between the runs until the parent says go."""
    from pavemap.network.batch import run_drive

    times = []
    for rep in range(2):
        task = _task(manifest, k, out / f"rep{rep}")
        if rep == 1 and barrier is not None:
            (barrier / f"ready-{k}").touch()
            while not (barrier / "go").exists():
                time.sleep(0.01)
        t = time.perf_counter()
        run_drive(task)
        times.append(round(time.perf_counter() - t, 3))
    print(json.dumps(times))


def child_batch(manifest: Path, net: Path, scheduler: str | None, warm: bool = False) -> None:
    from pavemap.network.batch import run_batch, run_drive

    if warm:  # this process has run a drive already, as a standing cluster's workers have
        run_drive(_task(manifest, 0, net.parent / f"{net.name}-warm-up"))
    t = time.perf_counter()
    s = run_batch(manifest, net, scheduler=scheduler, workers=None if scheduler == "serial" else 2,
                  echo=lambda _: None, threads=1)
    print(json.dumps({"wall_s": round(time.perf_counter() - t, 2), "failed": s["failed"],
                      "drive_seconds": [e.get("seconds") for e in s["drives"]]}))


def child_cluster(ready: Path) -> None:
    """A LocalCluster of 2 forked workers, as `pavemap batch` starts one; its address in ``ready``."""
    from pavemap.network.batch import cluster
    from pavemap.network.workers import start_worker_forkserver

    start_worker_forkserver()
    with cluster(None, 2, "auto", 2, lambda _: None, "forkserver") as client:
        client.wait_for_workers(2)
        ready.write_text(client.scheduler.address)
        while True:
            time.sleep(1)


def _py(*args: str) -> dict | list:
    p = subprocess.run([sys.executable, __file__, *args], capture_output=True, text=True, check=True)
    return json.loads(p.stdout.strip().splitlines()[-1])


def main() -> None:
    from common import git_commit, machine_entry, write_results
    from network_bench import CONFIGS, _drives

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=Path("/tmp/pavemap-network-bench"))
    ap.add_argument("--results", type=Path, default=RESULTS)
    ap.add_argument("--child", nargs="+", help=argparse.SUPPRESS)
    a = ap.parse_args()
    if a.child:
        kind, *rest = a.child
        if kind == "drive":
            child_drive(Path(rest[0]), int(rest[1]), Path(rest[2]), Path(rest[3]) if len(rest) > 3 else None)
        elif kind == "batch":
            child_batch(Path(rest[0]), Path(rest[1]), None if rest[2] == "new" else rest[2], rest[3:] == ["warm"])
        else:
            child_cluster(Path(rest[0]))
        return
    from pavemap.io.owned import check_replaceable, mark_written

    work = a.data / "ceiling"
    if work.exists():  # only the scratch folder a finished run of this bench marked as pavemap's
        check_replaceable(work, SCRATCH, overwrite=True)
        shutil.rmtree(work)
    work.mkdir(parents=True)
    manifest = work / "manifest.yaml"
    manifest.write_text(json.dumps({"config": "kitti", "set": CONFIGS["default"], "drives": _drives(a.data)[:2]}))
    load = [subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip()]
    rows: dict = {"one_drive": _py("--child", "drive", str(manifest), "0", str(work / "alone"))}
    barrier = work / "barrier"
    barrier.mkdir()
    procs = [subprocess.Popen([sys.executable, __file__, "--child", "drive", str(manifest), str(k), str(work / f"p{k}"),
                               str(barrier)], stdout=subprocess.PIPE, text=True) for k in (0, 1)]
    while not all((barrier / f"ready-{k}").exists() for k in (0, 1)):
        time.sleep(0.01)
    (barrier / "go").touch()
    outs = [json.loads(p.communicate()[0].strip().splitlines()[-1]) for p in procs]
    # both start at the go signal: the wall is the slower drive (the processes' exits are not the drives')
    rows["two_processes"] = {"wall_s": max(o[1] for o in outs), "drive_seconds": [o[1] for o in outs]}
    rows["serial"] = _py("--child", "batch", str(manifest), str(work / "serial"), "serial")
    rows["serial_warm"] = _py("--child", "batch", str(manifest), str(work / "serial-warm"), "serial", "warm")
    rows["cold_cluster"] = _py("--child", "batch", str(manifest), str(work / "cold"), "new")
    ready = work / "address"
    server = subprocess.Popen([sys.executable, __file__, "--child", "cluster", str(ready)])
    try:
        while not ready.exists():
            time.sleep(0.1)
        address = ready.read_text()
        rows["standing_cluster"] = [_py("--child", "batch", str(manifest), str(work / f"standing{k}"), address)
                                    for k in (0, 1)]
    finally:
        server.terminate()
        server.wait(timeout=30)
    mark_written(work, SCRATCH)
    load.append(subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip())
    serial = rows["serial"]["wall_s"]
    # the batch's own seconds besides its drives (plan, register, network page): serial in every mode
    rows["batch_overhead_s"] = round(serial - sum(rows["serial"]["drive_seconds"]), 2)
    rows["speedup_vs_serial"] = {
        "two_processes_plus_batch_overhead": round(serial / (rows["two_processes"]["wall_s"]
                                                             + rows["batch_overhead_s"]), 2),
        "cold_cluster": round(serial / rows["cold_cluster"]["wall_s"], 2),
        "standing_cluster_first": round(serial / rows["standing_cluster"][0]["wall_s"], 2),
        "standing_cluster_warm": round(serial / rows["standing_cluster"][1]["wall_s"], 2)}
    warm = rows["serial_warm"]["wall_s"]  # both sides warm: what a standing cluster gains over a warm process
    rows["speedup_vs_serial_warm"] = {"standing_cluster_warm": round(warm / rows["standing_cluster"][1]["wall_s"], 2),
                                      "two_processes_plus_batch_overhead": round(
                                          warm / (rows["two_processes"]["wall_s"] + rows["batch_overhead_s"]), 2)}
    commit = git_commit()
    write_results(a.results, {**machine_entry(), "commit": commit, "load": load, "drives": 2, **rows})
    print(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
