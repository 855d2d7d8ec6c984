"""Many drives of a road network: batch processing on dask.distributed and the defect register.

- :mod:`pavemap.network.manifest`: the YAML manifest of drives (path, date, name, vehicle);
- :mod:`pavemap.network.batch`: ``run_batch`` (every drive a task; ``network.json``) and the task ``run_drive``;
- :mod:`pavemap.network.register`: ``register.gpkg``, one record per physical defect across drives and surveys;
- :mod:`pavemap.network.report`: ``network.html``.
"""

from pavemap.network.batch import run_batch, run_drive
from pavemap.network.manifest import load_manifest
from pavemap.network.register import build_register

__all__ = ["build_register", "load_manifest", "run_batch", "run_drive"]
