"""A quick interpreter exit for processes that ran a stage (the CLI, dask workers).

A process that imported torch and ran a drive spends 2.3-2.6 s in the interpreter's own exit, measured here:
its final garbage collections walk the millions of objects torch, torch._dynamo and sympy leave behind. A
LocalCluster's close waits for that in every worker (2.7 s of a 4-drive batch's 40 s) and the CLI makes its
user wait for it after the last line. Collected once and then frozen, what is left is not walked again: the
same exit takes 0.3-0.5 s.
"""

from __future__ import annotations

import gc


def prepare_quick_exit() -> None:
    """Collect what is garbage now (its finalisers run, as in the exit's own collections), then freeze the rest
    so that the exit does not walk it again. What is still referenced is freed as the interpreter clears its
    modules, as without this (an open file is flushed then). Call it when the process's work is done, or when
    what it has built stays for good (the workers' forkserver after its imports: its forks share it)."""
    gc.collect()
    gc.freeze()
