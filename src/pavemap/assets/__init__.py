"""Run-time assets: a project-local ultralytics config folder with a local font.

ultralytics downloads ``Arial.ttf`` into its config folder the first time it draws
labels, and keeps its settings there. pavemap never lets it reach the network: before
ultralytics is imported, :func:`prepare_ultralytics` sets ``YOLO_OFFLINE=1``, points
``YOLO_CONFIG_DIR`` at a folder of ours (``ultralytics/`` in the user's cache,
:mod:`pavemap.user_cache`, unless the user set ``YOLO_CONFIG_DIR`` or ``PAVEMAP_YOLO_DIR``: never the
working directory) and copies matplotlib's bundled
DejaVuSans there under the names ultralytics looks for. Nothing big is committed: the
font is copied from the installed matplotlib at run time.
"""

from __future__ import annotations

import os
import shutil
from pathlib import Path

FONT_NAMES = ("Arial.ttf", "Arial.Unicode.ttf")


def _matplotlib_font() -> Path | None:
    try:
        import matplotlib
    except ImportError:
        return None
    font = Path(matplotlib.get_data_path()) / "fonts" / "ttf" / "DejaVuSans.ttf"
    return font if font.is_file() else None


def prepare_ultralytics(config_dir: str | os.PathLike | None = None) -> Path:
    """Set the environment for an offline ultralytics; returns its settings folder.

    Must run before ``import ultralytics`` (ultralytics reads the variables at import).
    ``config_dir`` overrides the folder; the default is ``$YOLO_CONFIG_DIR``, else
    ``$PAVEMAP_YOLO_DIR``, else ``<user cache>/ultralytics``. Returns ``<config_dir>/Ultralytics``, where
    ultralytics keeps settings.json and looks for its fonts.
    """
    os.environ["YOLO_OFFLINE"] = "1"
    os.environ.setdefault("YOLO_VERBOSE", "False")
    if config_dir is not None:
        base = Path(config_dir)
    elif os.environ.get("YOLO_CONFIG_DIR"):
        base = Path(os.environ["YOLO_CONFIG_DIR"])
    else:
        from pavemap.user_cache import user_cache_dir

        base = Path(os.environ.get("PAVEMAP_YOLO_DIR") or user_cache_dir() / "ultralytics")
    base = base.expanduser().resolve()
    os.environ["YOLO_CONFIG_DIR"] = str(base)
    settings_dir = base / "Ultralytics"
    settings_dir.mkdir(parents=True, exist_ok=True)
    src = _matplotlib_font()
    if src is not None:
        for name in FONT_NAMES:
            dst = settings_dir / name
            if not dst.is_file():
                tmp = dst.with_name(f".{name}.partial-{os.getpid()}")
                shutil.copyfile(src, tmp)
                os.replace(tmp, dst)
    return settings_dir
