"""Peak resident memory of this process, measured so that a child process does not inherit its parent's.

``getrusage(RUSAGE_SELF).ru_maxrss`` is kept across ``exec`` on Linux: a process that pytest or a Dask nanny
forks and execs starts with the parent's high-water mark, so a fresh 300 MB process under a 1.5 GB parent reads
1.5 GB and its own growth reads 0. The kernel's per-address-space high-water mark,
``VmHWM`` in ``/proc/self/status``, starts anew at ``exec``; ``ru_maxrss`` is the fallback off Linux.
"""

from __future__ import annotations

import resource
from pathlib import Path

_STATUS = Path("/proc/self/status")


def peak_rss_mb() -> float:
    """Peak resident memory of this process's own address space so far (MiB)."""
    try:
        for line in _STATUS.read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024.0  # kB
    except (OSError, ValueError, IndexError):
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
