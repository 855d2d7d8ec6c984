"""The pavemap version, and the identity of the code that made a result (a stage done by other code is redone)."""

from __future__ import annotations

import functools
import hashlib
from pathlib import Path

__version__ = "0.1.0"


@functools.cache
def code_version(root: Path | None = None) -> str:
    """The pavemap version and a hash of the package's own code and shipped configs (``*.py``, ``*.yaml`` under
    ``root``, the package by default): a stage done by other code is redone, not reused (the version alone stays
    the same between commits; a rerun of the long-drive bench into an old folder once reused an earlier commit's
    meshes)."""
    root = Path(__file__).resolve().parent if root is None else Path(root)
    h = hashlib.sha256()
    for f in sorted(q for pat in ("*.py", "*.yaml") for q in root.rglob(pat)):
        h.update(f.relative_to(root).as_posix().encode() + b"\0" + f.read_bytes())
    return f"{__version__}+{h.hexdigest()[:12]}"
