"""Hashes that key a stage's reuse: the sequence folder, a file or folder, a list of parts.

:mod:`pavemap.run_folder` keeps the stamps; the mesh tiles and the segmenter key their own reuse with these.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

from pavemap.io.sequence import SEQUENCE_FILE
from pavemap.types import Sequence


def hash_sequence(seq: Sequence) -> str:
    """Hash of ``sequence.json``, the truth files and each layer file's size and mtime."""
    h = hashlib.sha256()
    assert seq.root is not None
    h.update((seq.root / SEQUENCE_FILE).read_bytes())
    for rel in ("truth/height.npy", "truth/defects.geojson"):
        p = seq.root / rel
        if p.is_file():
            h.update(p.read_bytes())
    # Image contents are not hashed (too slow for long drives); size + mtime catch edits.
    for f in seq.frames:
        for v in f.views.values():
            for rel in (v.image, v.semantics, v.depth):
                if rel:
                    st = (seq.root / rel).stat()
                    h.update(f"{rel}:{st.st_size}:{st.st_mtime_ns}".encode())
    return h.hexdigest()[:16]


def hash_parts(*parts: object) -> str:
    return hashlib.sha256(json.dumps(parts, sort_keys=True, default=str).encode()).hexdigest()[:16]


def path_hash(path: str | Path | None) -> str | None:
    """Content hash of a file, or of every file under a folder (names and bytes); None for no path."""
    if path is None:
        return None
    p = Path(path)
    if p.is_file():
        return hashlib.sha256(p.read_bytes()).hexdigest()[:16]
    if p.is_dir():
        h = hashlib.sha256()
        for f in sorted(q for q in p.rglob("*") if q.is_file()):
            h.update(f.relative_to(p).as_posix().encode() + b"\0" + f.read_bytes())
        return h.hexdigest()[:16]
    return "missing"
