"""How a LocalCluster's worker processes start: forked from one interpreter that has already imported
what a drive needs (a multiprocessing *forkserver*), instead of each spawning a fresh interpreter.

Spawned workers each import distributed, torch, OpenCV, scipy, numba, GDAL's bindings and pavemap
(~2 s of a core each) inside their first task, after the cluster has started them (another ~1.7 s); a
forkserver does those imports once, while the client reads the manifest and starts the scheduler, and
every worker (and every replacement for a killed one) is a fork of it that starts warm. Only the
standard library is imported here, so the CLI can start the server before it imports anything heavy.

A forked worker's environment is the server's, fixed when the server started, plus what
:func:`worker_environ` forwards as each worker starts (pavemap's and ultralytics' own variables);
a variable read when a library loads (``OMP_NUM_THREADS``) keeps its value from the server's start.
"""

from __future__ import annotations

import contextlib
import multiprocessing
import os
import sys
from collections.abc import Iterator

WORKER_START_METHODS = ("forkserver", "spawn")

# What a drive task imports (third-party first: they are most of the time). The server imports them through
# pavemap.network.forkserver_ready, which skips one that fails to import (multiprocessing's own preload stops
# every worker start on anything but an ImportError).
WORKER_IMPORTS = (
    "distributed", "torch", "cv2", "numpy", "scipy.ndimage", "scipy.sparse.linalg", "skimage.morphology",
    "numba", "matplotlib", "pyproj", "shapely", "geopandas", "pyogrio", "rasterio", "trimesh", "PIL.Image",
    "threadpoolctl", "pavemap.pipeline", "pavemap.mesh.train", "pavemap.mesh.tiles", "pavemap.mesh.texture_check",
    "pavemap.detect.paint", "pavemap.synth", "pavemap.fuse.core", "pavemap.maintain", "pavemap.maintain.measure",
    "pavemap.evaluate.gt", "pavemap.export.report", "pavemap.export.gis", "pavemap.export.evidence",
    "pavemap.export.kml", "pavemap.geo.coverage", "pavemap.network.batch", "pavemap.network.plugins",
)

# One core per worker: set before the server imports the libraries that read them at load (as dask's
# pre-spawn environ does for spawned workers); PYTHONHASHSEED as dask fixes it for its workers.
WORKER_ENV = {"OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1",
              "PYTHONHASHSEED": "6640"}
FORWARDED_PREFIXES = ("PAVEMAP_", "YOLO_")


def forkserver_available() -> bool:
    """Whether workers can be forked from a server here: Linux only (macOS lists a forkserver, but forking
    after Apple's frameworks are loaded is why Python spawns there by default)."""
    return sys.platform.startswith("linux") and "forkserver" in multiprocessing.get_all_start_methods()


@contextlib.contextmanager
def _environ(values: dict[str, str]) -> Iterator[None]:
    """``values`` in os.environ (an existing value is kept), restored on exit."""
    added = {k: v for k, v in values.items() if k not in os.environ}
    os.environ.update(added)
    try:
        yield
    finally:
        for k in added:
            os.environ.pop(k, None)


def start_worker_forkserver() -> bool:
    """Start this process's forkserver with :data:`WORKER_IMPORTS` preloaded, if the platform has one
    (False: it has not). Returns at once: the server imports in the background, and the first fork waits
    for it. Idempotent: a server already running is kept as it is."""
    if not forkserver_available():
        return False
    from multiprocessing import forkserver

    ctx = multiprocessing.get_context("forkserver")
    ctx.set_forkserver_preload(["pavemap.network.forkserver_ready"])
    with _environ(WORKER_ENV):
        forkserver.ensure_running()
    return True


def check_worker_start(method: str) -> None:
    """A clear error for a start method that is not one of :data:`WORKER_START_METHODS`."""
    if method not in WORKER_START_METHODS:
        from pavemap.errors import PavemapError

        raise PavemapError(f"--worker-start must be one of {', '.join(WORKER_START_METHODS)}, got {method!r}")


def resolve_worker_start(method: str) -> str:
    """The start method a LocalCluster will use: ``method`` (one of :data:`WORKER_START_METHODS`), with
    forkserver started here, or spawn where the platform has none."""
    check_worker_start(method)
    if method == "forkserver" and not start_worker_forkserver():
        return "spawn"
    return method


def worker_environ() -> dict[str, str]:
    """The client's variables that a forked worker gets as it starts (a spawned one inherits them all)."""
    return {k: v for k, v in os.environ.items() if k.startswith(FORWARDED_PREFIXES)}


def check_scheduler(address: str, timeout: float = 5.0) -> None:
    """PavemapError when nothing accepts a TCP connection at the dask scheduler ``address`` (``tcp://HOST:PORT``):
    connection refused, an unknown host, or no answer within ``timeout`` seconds."""
    import socket
    from urllib.parse import urlsplit

    from pavemap.errors import PavemapError

    hint = "start one with `dask scheduler` and workers with `dask worker tcp://HOST:8786`"
    try:
        u = urlsplit(address if "://" in address else f"tcp://{address}")
        host, port = u.hostname, u.port or 8786
    except ValueError as e:
        raise PavemapError(f"--scheduler {address}: not an address tcp://HOST:PORT ({e})") from None
    if u.scheme not in ("tcp", "tls") or not host:
        return  # another transport (ucx, inproc …): left to dask
    try:
        socket.create_connection((host, port), timeout=timeout).close()
    except ConnectionRefusedError:
        raise PavemapError(f"--scheduler {address}: connection refused (nothing listens at {host}:{port}); "
                           f"{hint}") from None
    except socket.gaierror as e:
        raise PavemapError(f"--scheduler {address}: unknown host {host!r} ({e.strerror or e})") from None
    except TimeoutError:
        raise PavemapError(f"--scheduler {address}: no answer from {host}:{port} within {timeout:g} s (a "
                           f"firewall, or the wrong host?); {hint}") from None
    except OSError as e:
        raise PavemapError(f"--scheduler {address}: cannot connect to {host}:{port} ({e.strerror or e}); "
                           f"{hint}") from None
