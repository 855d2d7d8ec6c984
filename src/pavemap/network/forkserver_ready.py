"""The one module the workers' forkserver preloads (:func:`pavemap.network.workers.start_worker_forkserver`),
for its side effects: it imports :data:`pavemap.network.workers.WORKER_IMPORTS`, skipping one that fails in
any way (a worker then imports it in its task, or reports why), then collects and freezes the heap
(:func:`gc.freeze`).

Frozen, those objects are not walked again, neither by the garbage collections of the workers forked from the
server (each walk would write to, and so copy, pages the forks share) nor by the server's own exit, which
otherwise spends ~1 s in final collections over what torch leaves after the client has gone (a caller
reading the client's output through a pipe waits for that, since the server holds the pipe open).
"""

import importlib

from pavemap.network.workers import WORKER_IMPORTS
from pavemap.shutdown import prepare_quick_exit

for _name in WORKER_IMPORTS:
    try:
        importlib.import_module(_name)
    except Exception:  # noqa: BLE001, S112 - a preload is an optimisation; the task imports (or fails) itself
        continue

prepare_quick_exit()
