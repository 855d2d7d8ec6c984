"""Many drives of a road network: batch processing on dask.distributed and the defect register.

- :mod:`pavemap.network.manifest`: the YAML manifest of drives (path, date, name, vehicle);
- :mod:`pavemap.network.batch`: ``run_batch`` (every drive a task; ``network.json``) and the task ``run_drive``;
- :mod:`pavemap.network.register`: ``register.gpkg``, one record per physical defect across drives and surveys;
- :mod:`pavemap.network.report`: ``network.html``;
- :mod:`pavemap.network.workers`: how a LocalCluster's workers start (a preloaded forkserver).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:  # pragma: no cover
    from pavemap.network.batch import run_batch, run_drive
    from pavemap.network.manifest import load_manifest
    from pavemap.network.register import build_register

__all__ = ["build_register", "load_manifest", "run_batch", "run_drive"]
_LAZY = {"run_batch": "pavemap.network.batch", "run_drive": "pavemap.network.batch",
         "load_manifest": "pavemap.network.manifest", "build_register": "pavemap.network.register"}


def __getattr__(name: str) -> Any:
    # Lazy, as `pavemap` itself: the CLI starts the workers' forkserver (pavemap.network.workers) before
    # it imports anything heavy.
    if name in _LAZY:
        import importlib

        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'pavemap.network' has no attribute {name!r}")
