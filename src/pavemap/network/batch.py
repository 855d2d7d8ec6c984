"""Many drives as tasks on dask.distributed: ``pavemap batch MANIFEST.yaml --out NETWORK``.

Each drive is one task, :func:`run_drive`: a pure function of a small dict (the sequence folder, the
run folder, the config as plain values) that runs :func:`pavemap.run` and returns a small dict. A task
ships paths, never pixels: the worker reads the images from the (shared) drive folder and writes its
run folder itself. On a cluster, a long drive's segments (issue 17) are tasks of their own,
:func:`run_segment`, submitted by the drive's task: it computes the tiles its run lacks on every worker
(:func:`pavemap.mesh.tiles.tiles_run_by`), then stitches them and goes on to stages 2 and 3.

The client process is the only writer of the network's own files: ``network.json`` (the status of
every drive, rewritten as each task ends), ``register.gpkg`` and ``network.html``, built after the
tasks finish. A drive whose run folder is complete (``metrics.json``) with stage stamps and config
that match the manifest's is not redone; a drive that fails is reported and the others finish.
"""

from __future__ import annotations

import contextlib
import dataclasses
import datetime as dt
import importlib.util
import json
import os
import time
from collections.abc import Callable, Iterator
from pathlib import Path

from pavemap.errors import PavemapError
from pavemap.io.atomic import atomic_write_json
from pavemap.memory import peak_rss_mb
from pavemap.network.folder import FORMAT, NETWORK_FILE, read_network
from pavemap.network.manifest import Drive, Manifest, load_manifest

DRIVES_DIR = "drives"
DEFAULT_RETRIES = 2
Echo = Callable[[str], None]


# ---------------------------------------------------------------------------- the task


def config_from_dict(d: dict):  # noqa: ANN201 - RunConfig, imported lazily
    """A RunConfig from :meth:`RunConfig.to_dict` values (what a task ships)."""
    from pavemap.config import apply_overrides, preset_config

    return apply_overrides(preset_config(d["preset"]), {k: v for k, v in d.items() if k != "preset"}, "<task>")


@contextlib.contextmanager
def thread_limit(n: int) -> Iterator[None]:
    """Every thread pool of this process (torch, OpenCV, the BLAS and OpenMP pools numpy / scipy load) at
    ``n`` threads, restored afterwards (``n`` <= 0: left as they are). A task is one core's work: two workers
    on two cores whose tasks each spawn a thread per core would fight over them."""
    if n <= 0:
        yield
        return
    import cv2
    import torch
    from threadpoolctl import threadpool_limits

    before = (torch.get_num_threads(), cv2.getNumThreads())
    torch.set_num_threads(n)
    cv2.setNumThreads(n)
    try:
        with threadpool_limits(limits=n):
            yield
    finally:
        torch.set_num_threads(before[0])
        cv2.setNumThreads(before[1])


def run_drive(task: dict) -> dict:
    """One drive end to end on a worker: ``task`` = {name, seq, out, config (plain dict), threads, and
    ``segment_tasks`` (bool): a long drive's segments as tasks of their own on the cluster}; returns {name,
    run, defects, seconds, peak_rss_mb, pid, host, segments (one row per segment task it ran)}. Pure: the same
    task gives the same run folder."""
    import socket

    from pavemap import pipeline as pavemap  # pavemap.run is the pipeline's run (the package face sits above)
    from pavemap.mesh.tiles import tiles_run_by

    t = time.perf_counter()
    rows: list[dict] = []
    runner = _cluster_tiles(int(task.get("threads", 1)), int(task.get("retries", DEFAULT_RETRIES)), rows) \
        if task.get("segment_tasks") else None
    with thread_limit(int(task.get("threads", 1))), (tiles_run_by(runner) if runner else contextlib.nullcontext()):
        result = pavemap.run(task["seq"], config_from_dict(task["config"]), task["out"], progress=False)
    return {"name": task["name"], "run": task["out"], "defects": len(result.defects),
            "seconds": round(time.perf_counter() - t, 3), "peak_rss_mb": round(peak_rss_mb(), 1),
            "pid": os.getpid(), "host": socket.gethostname(), "segments": rows}


def run_segment(job: object, threads: int = 1) -> dict:
    """One segment tile of a long drive on a worker (:func:`pavemap.mesh.tiles.run_tile` on ``job``, a
    TileJob); its result plus ``peak_rss_mb``, ``pid`` and ``host``."""
    import socket

    from pavemap.mesh.tiles import run_tile

    with thread_limit(threads):
        got = run_tile(job)  # type: ignore[arg-type]
    return {**got, "peak_rss_mb": round(peak_rss_mb(), 1), "pid": os.getpid(), "host": socket.gethostname()}


def _cluster_tiles(threads: int, retries: int, rows: list[dict]) -> Callable[[list], list[dict]]:
    """A tile runner (:func:`pavemap.mesh.tiles.tiles_run_by`) that submits a drive's missing segment tiles as
    tasks to the cluster this drive task runs on, and waits for them outside the worker's thread pool (so
    that the segments, this drive's and other drives', run on every worker). ``rows`` collects them."""

    def run(jobs: list) -> list[dict]:
        from distributed import worker_client

        if not jobs:
            return []
        with worker_client() as client:  # secedes from the worker's pool while the segments run
            futures = [client.submit(run_segment, j, threads, key=f"segment-{j.stamp}", retries=retries, pure=False)
                       for j in jobs]
            got = client.gather(futures)
        rows.extend({"segment": int(j.folder.name), "seconds": g["seconds"], "peak_rss_mb": g["peak_rss_mb"],
                     "worker": f"{g['host']}:{g['pid']}"} for j, g in zip(jobs, got, strict=True))
        return got

    return run


# ---------------------------------------------------------------------------- resuming


def drive_config(manifest: Manifest, drive: Drive, seq: object):  # noqa: ANN201 - RunConfig
    """The drive's config: the manifest's (else the preset that fits the rig), then the overrides."""
    from pavemap.config import load_config, mount_height_prior, preset_for

    where = f"{manifest.path}: drives ({drive.name})"
    overrides = (*manifest.overrides, *drive.overrides)
    try:
        cfg = load_config(manifest.config, default_preset=preset_for(seq)[0], overrides=overrides)
        mount_height_prior(cfg, seq, manifest.config, overrides)
        return cfg
    except PavemapError as e:
        raise PavemapError(f"{where}: {e}") from None


def config_hash(cfg: object) -> str:
    from pavemap.io.hashes import hash_parts

    return hash_parts(cfg.to_dict())  # type: ignore[attr-defined]


def _stamp_key(run: Path, stage: str) -> str | None:
    try:
        return json.loads((run / ".stages" / f"{stage}.json").read_text()).get("key")
    except (OSError, ValueError, AttributeError):
        return None


def is_current(seq: object, cfg: object, run: Path) -> bool:
    """Whether ``run`` is a complete run of ``seq`` with ``cfg``: ``metrics.json`` present and the mesh,
    detect and fuse stamps holding the keys :func:`pavemap.run` would compute now."""
    from pavemap.detect.backends import detector_model, resolve_backend, resolved_filter
    from pavemap.device import resolve_device
    from pavemap.io.hashes import hash_parts, hash_sequence
    from pavemap.run_folder import COMPLETE, detect_parts, mesh_parts

    if not (run / COMPLETE).is_file():
        return False
    try:
        device = str(resolve_device(cfg.device))  # type: ignore[attr-defined]
        detector, _ = resolve_backend(cfg.detector, seq)  # type: ignore[attr-defined, arg-type]
        filt, _ = resolved_filter(cfg.filter, cfg.preset,  # type: ignore[attr-defined]
                                  detector_model(detector, seq))  # type: ignore[arg-type]
        seq_key = hash_sequence(seq)  # type: ignore[arg-type]
    except (PavemapError, OSError, ValueError):
        return False  # the task will say what is wrong
    mesh = cfg.mesh  # type: ignore[attr-defined]
    mesh = dataclasses.replace(mesh, device=device) if hasattr(mesh, "device") else mesh
    keys = {"mesh": hash_parts(mesh_parts(seq_key, mesh)),
            "detect": hash_parts(detect_parts(seq_key, detector, device, seq))}  # type: ignore[arg-type]
    keys["fuse"] = hash_parts(keys["detect"], dataclasses.asdict(filt),
                              dataclasses.asdict(cfg.fusion))  # type: ignore[attr-defined]
    return all(_stamp_key(run, s) == k for s, k in keys.items())


# ---------------------------------------------------------------------------- the cluster


@contextlib.contextmanager
def cluster(scheduler: str | None, workers: int | None, memory_limit: str, retries: int,
            echo: Echo, worker_start: str = "forkserver") -> Iterator[object]:
    """A dask Client: on a new LocalCluster (``scheduler`` None: ``workers`` processes, one thread each,
    ``memory_limit`` each, started by ``worker_start``: :mod:`pavemap.network.workers`) or on the scheduler
    at ``scheduler`` (``tcp://HOST:8786``)."""
    from pavemap.network.workers import resolve_worker_start, worker_environ

    start = resolve_worker_start(worker_start) if not scheduler else "spawn"
    env = worker_environ() if start == "forkserver" else {}
    import logging

    import dask
    from distributed import Client, LocalCluster

    # a task that kills its worker is tried again on a fresh one, up to `retries` more times
    # A drive ran 1.4-1.8x slower on a worker than alone; two causes measured (4 drives, 2 workers: 32.6 ->
    # 27.3 s): the workers' statistical profiler (every task thread's stack sampled each 10 ms under the GIL)
    # and dask's MALLOC_TRIM_THRESHOLD_=65536, which returns freed memory to the OS after every large numpy
    # or torch free (+13 % on a drive alone). One thread per BLAS / OpenMP pool stays.
    with dask.config.set({"distributed.scheduler.allowed-failures": retries,
                          "distributed.worker.profile.enabled": False,
                          "distributed.nanny.pre-spawn-environ": {"OMP_NUM_THREADS": 1, "MKL_NUM_THREADS": 1,
                                                                  "OPENBLAS_NUM_THREADS": 1},
                          "distributed.worker.daemon": False,
                          "distributed.worker.multiprocessing-method": start,
                          "distributed.nanny.environ": env}):
        if scheduler:
            try:
                client = Client(scheduler, timeout="20s")
            except (OSError, TimeoutError) as e:
                raise PavemapError(f"--scheduler {scheduler}: cannot reach the dask scheduler ({e}); start one "
                                   "with `dask scheduler` and workers with `dask worker tcp://HOST:8786`") from None
            lc = None
        else:
            n = workers or os.cpu_count() or 1
            lc = LocalCluster(n_workers=n, threads_per_worker=1, processes=True, memory_limit=memory_limit,
                              dashboard_address=":0", silence_logs=logging.ERROR)
            client = Client(lc)
    try:
        from pavemap.network.plugins import QuickExit

        client.register_plugin(QuickExit(), name=QuickExit.name)
        if importlib.util.find_spec("bokeh") is not None:
            echo(f"dashboard: {client.dashboard_link}")
        else:
            echo(f"dashboard: not served (install bokeh for it; it would be {client.dashboard_link})")
        yield client
    finally:
        client.close()
        if lc is not None:
            lc.close()


def _submit_all(client: object, tasks: list[dict], task_fn: Callable[[dict], dict], retries: int,
                on_done: Callable[[dict, dict | None, str | None], None]) -> None:
    """Submit every task; call ``on_done(task, result, error)`` as each ends (in completion order)."""
    from distributed import as_completed

    futures = {}
    for t in tasks:
        f = client.submit(task_fn, t, key=f"drive-{t['name']}-{t['config_hash']}",  # type: ignore[attr-defined]
                          retries=retries, pure=False)
        futures[f.key] = (f, t)
    for f in as_completed([f for f, _ in futures.values()]):
        t = futures[f.key][1]
        try:
            on_done(t, f.result(), None)
        except Exception as e:  # noqa: BLE001 - a failed drive is reported; the others go on
            on_done(t, None, f"{type(e).__name__}: {e}")


def _run_serial(tasks: list[dict], task_fn: Callable[[dict], dict],
                on_done: Callable[[dict, dict | None, str | None], None]) -> None:
    for t in tasks:  # run_drive limits and restores the thread pools itself
        try:
            on_done(t, task_fn(t), None)
        except Exception as e:  # noqa: BLE001 - as on the cluster: report, go on
            on_done(t, None, f"{type(e).__name__}: {e}")


# ---------------------------------------------------------------------------- the driver


def _plan(manifest: Manifest, net: Path, previous: dict[str, dict], threads: int = 1
          ) -> tuple[list[dict], list[dict]]:
    """The status entry of every drive and the tasks still to run (finished, current drives are reused)."""
    from pavemap.io.sequence import read_sequence

    entries, tasks = [], []
    for d in manifest.drives:
        run = net / DRIVES_DIR / d.name
        e = {"name": d.name, "path": str(d.path), "date": d.date.isoformat(), "vehicle": d.vehicle,
             "camera": d.camera, "run": f"{DRIVES_DIR}/{d.name}", "status": "pending"}
        entries.append(e)
        try:
            seq = read_sequence(d.path)
            cfg = drive_config(manifest, d, seq)
        except (PavemapError, ValueError, OSError) as err:  # SequenceError is a ValueError
            e.update(status="failed", error=str(err))
            continue
        e["geo_origin"] = seq.geo_origin is not None
        e["config_hash"] = config_hash(cfg)
        prev = previous.get(d.name) or {}
        if prev.get("config_hash") in (None, e["config_hash"]) and is_current(seq, cfg, run):
            kept = ("seconds", "defects", "peak_rss_mb", "worker", "segment_tasks")
            e.update(status="done", reused=True, **{k: prev[k] for k in kept if k in prev})
            continue
        tasks.append({"name": d.name, "seq": str(d.path), "out": str(run), "config": cfg.to_dict(),
                      "config_hash": e["config_hash"], "threads": threads})
    return entries, tasks


def _write_status(net: Path, manifest: Manifest, entries: list[dict], extra: dict) -> None:
    atomic_write_json(net / NETWORK_FILE, {
        "format": FORMAT, "manifest": str(manifest.path),
        "updated_utc": dt.datetime.now(dt.UTC).isoformat(timespec="seconds"), **extra, "drives": entries})


def run_batch(manifest_path: str | os.PathLike, out: str | os.PathLike, scheduler: str | None = None,
              workers: int | None = None, memory_limit: str = "auto", retries: int = DEFAULT_RETRIES,
              register: bool = True, task_fn: Callable[[dict], dict] = run_drive,
              echo: Echo = print, threads: int = 1, worker_start: str = "forkserver") -> dict:
    """:func:`_run_batch` with the network folder locked (:mod:`pavemap.io.lock`): a second ``pavemap batch``
    into the same folder stops with an error naming this process."""
    from pavemap.io.lock import locked
    from pavemap.io.owned import check_outside_inputs
    from pavemap.network.workers import check_scheduler

    net = Path(out).resolve()
    check_outside_inputs(net, [d.path for d in load_manifest(manifest_path).drives])  # before the lock's mkdir
    if scheduler not in (None, "serial"):
        check_scheduler(scheduler)  # nothing listening: said at once, not after dask's 20 s timeout
    with locked(net):
        return _run_batch(manifest_path, out, scheduler, workers, memory_limit, retries, register, task_fn, echo,
                          threads, worker_start)


def _run_batch(manifest_path: str | os.PathLike, out: str | os.PathLike, scheduler: str | None = None,
               workers: int | None = None, memory_limit: str = "auto", retries: int = DEFAULT_RETRIES,
               register: bool = True, task_fn: Callable[[dict], dict] = run_drive,
               echo: Echo = print, threads: int = 1, worker_start: str = "forkserver") -> dict:
    """Run every drive of the manifest into ``out/drives/<name>``, then build the register and the page.

    ``scheduler``: None for a LocalCluster of ``workers`` processes (default: the cores), ``"serial"``
    for one drive after another in this process, or a dask scheduler address (``tcp://HOST:8786``).
    ``threads``: thread pools per task (1: one core each, what a worker has; 0: the process's defaults,
    e.g. to run the drives one by one on all cores). ``worker_start``: how a LocalCluster starts its
    workers (:mod:`pavemap.network.workers`: forkserver, or spawn). Returns the status written to ``network.json`` (plus
    ``failed``: the names of failed drives).
    """
    from pavemap.io.owned import claim

    if retries < 0:
        raise PavemapError(f"--retries must be >= 0, got {retries}")
    from pavemap.network.workers import check_worker_start, resolve_worker_start

    check_worker_start(worker_start)
    manifest = load_manifest(manifest_path)
    net = Path(out).resolve()  # the tasks carry this path to workers that may run elsewhere
    folder = claim(net, "network", False, inputs=[d.path for d in manifest.drives],
                   info={"manifest": str(manifest.path)}, same=lambda o: o.get("kind") == "network")
    if scheduler is None and not (net / NETWORK_FILE).exists():  # a new network: every drive will run, so the
        worker_start = resolve_worker_start(worker_start)  # workers' server imports while the plan is made
    try:
        previous = {e.get("name"): e for e in read_network(net)["drives"]}
    except PavemapError:
        previous = {}
    entries, tasks = _plan(manifest, net, previous, threads)
    if scheduler is None and tasks:  # a resumed network starts the server only when a drive is left to run
        worker_start = resolve_worker_start(worker_start)
    for task in tasks:  # on a cluster a long drive's segments are tasks of their own
        task.update(segment_tasks=scheduler != "serial", retries=retries)
    by_name = {e["name"]: e for e in entries}
    mode = "serial" if scheduler == "serial" else (scheduler or "LocalCluster")
    extra: dict = {"scheduler": mode, **({"worker_start": worker_start} if scheduler is None else {})}
    for e in entries:
        if e.get("reused"):
            echo(f"{e['name']}: done before, not redone")
        elif e["status"] == "failed":
            echo(f"{e['name']}: FAILED before start: {e['error']}")
    _write_status(net, manifest, entries, extra)

    def on_done(task: dict, result: dict | None, error: str | None) -> None:
        e = by_name[task["name"]]
        if error is None and result is not None:
            e.update(status="done", reused=False, seconds=result["seconds"], defects=result["defects"],
                     peak_rss_mb=result["peak_rss_mb"], worker=f"{result['host']}:{result['pid']}")
            e.pop("error", None)
            if result.get("segments"):
                e["segment_tasks"] = result["segments"]
            else:
                e.pop("segment_tasks", None)
            seg = result.get("segments") or []
            on = f" ({len(seg)} segment tasks on {len({r['worker'] for r in seg})} workers)" if seg else ""
            echo(f"{e['name']}: done, {result['defects']} defects in {result['seconds']:.1f} s{on}")
        else:
            e.update(status="failed", error=error)
            echo(f"{e['name']}: FAILED: {error}")
        _write_status(net, manifest, entries, extra)  # the client is the only writer of network.json

    t = time.perf_counter()
    if tasks and scheduler == "serial":
        _run_serial(tasks, task_fn, on_done)
    elif tasks:
        with cluster(scheduler, workers, memory_limit, retries, echo, worker_start) as client:
            extra["dashboard"] = client.dashboard_link  # type: ignore[attr-defined]
            extra["workers"] = len(client.scheduler_info().get("workers", {}))  # type: ignore[attr-defined]
            _submit_all(client, tasks, task_fn, retries, on_done)
    extra["batch_seconds"] = round(time.perf_counter() - t, 3)
    _finish(net, manifest, entries, extra, register, echo)
    folder.record()
    failed = [e["name"] for e in entries if e["status"] != "done"]
    return {**read_network(net), "failed": failed}


def _finish(net: Path, manifest: Manifest, entries: list[dict], extra: dict, register: bool, echo: Echo) -> None:
    """The register (when asked and every finished drive is georeferenced) and the network page."""
    from pavemap.network.register import build_register
    from pavemap.network.report import write_network_page

    if register and any(e["status"] == "done" for e in entries):
        _write_status(net, manifest, entries, extra)
        try:
            extra["register"] = build_register(net)
            echo(register_line(extra["register"]))
        except PavemapError as e:
            extra["register"] = {"error": str(e)}
            echo(f"register not built: {e}")
    _write_status(net, manifest, entries, extra)
    write_network_page(net)


def register_line(summary: dict) -> str:
    c = summary.get("status_counts", {})
    return (f"register: {summary['observations']} observations -> {summary['defects']} physical defects "
            f"(new {c.get('new', 0)}, grown {c.get('grown', 0)}, unchanged {c.get('unchanged', 0)}, "
            f"not seen again {c.get('not seen again', 0)}) in {summary['path']}")


__all__ = ["cluster", "config_from_dict", "drive_config", "is_current",
           "register_line", "run_batch", "run_drive"]
