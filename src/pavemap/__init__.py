"""pavemap: 3D road defect mapping from driving video.

Python API (mirrors the CLI)::

    import pavemap
    seq = pavemap.read_sequence("path/to/SEQ")
    result = pavemap.run(seq, pavemap.load_config("nuscenes"), "runs/seq")
    result.defects, result.prob_map, result.metrics, result.to_geojson(), result.to_dataframe()
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from pavemap.version import __version__ as __version__  # the version lives at the ground layer

if TYPE_CHECKING:  # pragma: no cover
    from pavemap.config import load_config, preset_config, preset_for
    from pavemap.io.sequence import read_sequence
    from pavemap.pipeline import RunResult, run
    from pavemap.synth import synthesize

_LAZY = {
    "run": "pavemap.pipeline",
    "RunResult": "pavemap.pipeline",
    "load_config": "pavemap.config",
    "preset_config": "pavemap.config",
    "preset_for": "pavemap.config",
    "read_sequence": "pavemap.io.sequence",
    "synthesize": "pavemap.synth",
}


def __getattr__(name: str) -> Any:
    # Lazy so that `import pavemap` stays fast (torch is imported only when a stage runs).
    if name in _LAZY:
        import importlib

        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'pavemap' has no attribute {name!r}")


__all__ = ["RunResult", "load_config", "preset_config", "preset_for", "read_sequence", "run", "synthesize"]
