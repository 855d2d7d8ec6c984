"""The user's own folders: the only places outside ``--out`` where pavemap keeps files.

Both come from :mod:`platformdirs`, so each platform gets its usual place:

- the **cache** (ultralytics' settings and font, anything pavemap can rebuild): ``$PAVEMAP_CACHE`` when
  set, else ``platformdirs.user_cache_dir("pavemap")`` (Linux ``$XDG_CACHE_HOME/pavemap``, default
  ``~/.cache/pavemap``; macOS ``~/Library/Caches/pavemap``; Windows ``%LOCALAPPDATA%\\pavemap\\Cache``);
- the **weights** a user adds (``pavemap weights install``): ``$PAVEMAP_WEIGHTS`` when set, else
  ``weights/`` in ``platformdirs.user_data_dir("pavemap")`` (Linux ``$XDG_DATA_HOME/pavemap``, default
  ``~/.local/share/pavemap``): data the user chose to keep, not a cache a cleaner may empty.

:func:`weight_dirs` lists the weight folders in the order they are searched; the cache's ``weights/``
(where pavemap before platformdirs kept them) is searched last, so an older install keeps working.
Nothing here creates a folder: the writer does, when it writes.
"""

from __future__ import annotations

import os
from pathlib import Path

import platformdirs

APP = "pavemap"


def user_cache_dir() -> Path:
    """``$PAVEMAP_CACHE``, else the platform's user cache folder for pavemap (not created here)."""
    if os.environ.get("PAVEMAP_CACHE"):
        return Path(os.environ["PAVEMAP_CACHE"]).expanduser()
    return Path(platformdirs.user_cache_dir(APP, appauthor=False))


def user_data_dir() -> Path:
    """The platform's user data folder for pavemap (not created here)."""
    return Path(platformdirs.user_data_dir(APP, appauthor=False))


def install_dir() -> Path:
    """Where ``pavemap weights install`` puts a file: ``$PAVEMAP_WEIGHTS`` when set (searched first), else
    ``<user data>/weights``."""
    if os.environ.get("PAVEMAP_WEIGHTS"):
        return Path(os.environ["PAVEMAP_WEIGHTS"]).expanduser()
    return user_data_dir() / "weights"


def weight_dirs() -> list[Path]:
    """Folders searched for weight files a user supplies, in order: ``$PAVEMAP_WEIGHTS`` (when set), the
    user data folder's ``weights/``, then the cache's ``weights/`` (an earlier pavemap's place)."""
    dirs = []
    if os.environ.get("PAVEMAP_WEIGHTS"):
        dirs.append(Path(os.environ["PAVEMAP_WEIGHTS"]).expanduser())
    dirs += [user_data_dir() / "weights", user_cache_dir() / "weights"]
    return dirs


__all__ = ["install_dir", "user_cache_dir", "user_data_dir", "weight_dirs"]


def weight_search_dirs() -> list[Path]:
    """The folders searched for weight files, in order: the user's (:func:`weight_dirs`), then
    ``shared/data/pretrained`` beside a source checkout (the project's development machines)."""
    dirs = weight_dirs()
    here = Path(__file__).resolve()
    if len(here.parents) > 3:  # a source checkout: <work>/<repo>/src/pavemap/user_cache.py
        dirs.append(here.parents[3] / "shared" / "data" / "pretrained")
    return dirs
