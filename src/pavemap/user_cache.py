"""The user's cache: the one place outside ``--out`` where pavemap keeps files (weights, ultralytics' settings).

``$XDG_CACHE_HOME/pavemap`` (default ``~/.cache/pavemap``), or ``$PAVEMAP_CACHE`` when set.
Weight files a user adds by hand go in its ``weights/`` folder, or in a folder named by
``$PAVEMAP_WEIGHTS``; :func:`weight_dirs` lists them in the order they are searched.
"""

from __future__ import annotations

import os
from pathlib import Path


def user_cache_dir() -> Path:
    """``$PAVEMAP_CACHE``, else ``$XDG_CACHE_HOME/pavemap``, else ``~/.cache/pavemap`` (not created here)."""
    if os.environ.get("PAVEMAP_CACHE"):
        return Path(os.environ["PAVEMAP_CACHE"]).expanduser()
    base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(base).expanduser() / "pavemap"


def weight_dirs() -> list[Path]:
    """Folders searched for weight files a user supplies: ``$PAVEMAP_WEIGHTS`` (when set), then the
    cache's ``weights/``."""
    dirs = []
    if os.environ.get("PAVEMAP_WEIGHTS"):
        dirs.append(Path(os.environ["PAVEMAP_WEIGHTS"]).expanduser())
    dirs.append(user_cache_dir() / "weights")
    return dirs


__all__ = ["user_cache_dir", "weight_dirs"]
