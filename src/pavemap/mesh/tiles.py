"""A long drive's segment tiles on disk, and who computes them (issue 17 and 18).

Each segment of a segmented drive (:mod:`pavemap.mesh.segments`) is one tile in ``DIR/segments/NNN/``:
``mesh.npz``, then ``tile.json`` with the stamp of what it was computed from. A :class:`TileJob` is
everything one tile needs (the segment's frames, the settings, the drive's held-out frames, where to write)
and :func:`run_tile` computes and writes it: a pure task a dask worker can run. By default a drive's
missing tiles are computed one after another in the drive's own process; :func:`tiles_run_by` hands them
to another runner for the duration of a block (``pavemap batch`` submits them as tasks on its cluster).
"""

from __future__ import annotations

import contextlib
import contextvars
import dataclasses
import hashlib
import json
import time
import warnings
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pavemap.errors import PavemapError
from pavemap.io.atomic import atomic_write_json
from pavemap.mesh.config import MeshConfig
from pavemap.mesh.model import RoadMesh
from pavemap.types import Sequence

SEGMENTS_DIR = "segments"
TILE_FILE = "tile.json"


@dataclass(frozen=True)
class TileJob:
    """One segment's tile to compute: ``seq`` holds only the segment's frames (poses and image paths, no
    pixels); ``heldout`` the drive's held-out frame indices among them; ``label`` names it in warnings."""

    seq: Sequence
    cfg: MeshConfig
    heldout: frozenset[int]
    label: str
    folder: Path
    stamp: str


TileRunner = Callable[[list[TileJob]], list[dict]]
_runner: contextvars.ContextVar[TileRunner | None] = contextvars.ContextVar("pavemap_tile_runner", default=None)


@contextlib.contextmanager
def tiles_run_by(runner: TileRunner) -> Iterator[None]:
    """Within the block, a segmented drive hands its missing tiles to ``runner(jobs)``, which must write
    every tile (:func:`run_tile` does) and return :func:`run_tile`'s result for each, in order."""
    token = _runner.set(runner)
    try:
        yield
    finally:
        _runner.reset(token)


def tile_runner() -> TileRunner | None:
    """The runner set by :func:`tiles_run_by`, or None (the drive computes its tiles itself)."""
    return _runner.get()


def segment_tile(seq: Sequence, cfg: MeshConfig, heldout: set[int], label: str) -> tuple[RoadMesh, dict]:
    """Stage 1 on ``seq`` (a segment's frames) alone, holding out ``heldout`` (frame indices): the tile and
    its metrics. Its warnings are re-issued prefixed with ``label``."""
    from pavemap.mesh.train import reconstruct_piece

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        tile, metrics = reconstruct_piece(seq, None, cfg, progress=False, heldout_frames=heldout)
    for w in caught:
        warnings.warn(f"{label}: {w.message}", stacklevel=3)
    return tile, metrics


def run_tile(job: TileJob) -> dict:
    """Compute and write one tile; returns {folder, seconds, warnings (the tile's, labelled)}."""
    t = time.perf_counter()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        tile, metrics = segment_tile(job.seq, job.cfg, set(job.heldout), job.label)
    save_tile(job.folder, tile, metrics, job.stamp)
    return {"folder": str(job.folder), "seconds": round(time.perf_counter() - t, 3),
            "warnings": [str(w.message) for w in caught]}


def tile_stamp(conf: dict, plan: dict, seq: Sequence, positions: tuple[int, ...], heldout: set[int]) -> str:
    """What a tile depends on: the settings ``conf`` (without device, threads and resume), the segment's plan,
    its frames (images and poses) and which of them are held out."""
    frames = []
    for p in positions:
        f = seq.frames[p]
        frames.append([f.index, sorted((c, v.image, np.round(np.asarray(v.T_world_cam), 6).tolist())
                                       for c, v in f.views.items())])
    held = sorted(heldout & {seq.frames[p].index for p in positions})
    blob = json.dumps([conf, plan, frames, held], sort_keys=True, default=str)
    return hashlib.sha256(blob.encode()).hexdigest()[:20]


def stamp_config(cfg: MeshConfig) -> dict:
    """The settings a tile depends on, and the code that made it (:func:`pavemap.run_folder.code_version`)."""
    from pavemap.version import code_version

    return {**{k: v for k, v in cfg.to_dict().items() if k not in ("device", "threads", "resume")},
            "code": code_version()}


def tile_done(folder: Path, stamp: str) -> bool:
    """Whether ``folder`` holds a finished tile with ``stamp`` (``tile.json`` is written last)."""
    try:
        return json.loads((folder / TILE_FILE).read_text()).get("stamp") == stamp and (folder / "mesh.npz").is_file()
    except (OSError, ValueError, AttributeError):
        return False


def load_tile(folder: Path, stamp: str) -> tuple[RoadMesh, dict] | None:
    """The tile in ``folder`` and its metrics when its stamp is ``stamp``, else None."""
    from pavemap.mesh.outputs import load_mesh

    f = folder / TILE_FILE
    if not f.is_file():
        return None
    try:
        info = json.loads(f.read_text())
        if info.get("stamp") != stamp:
            return None
        return load_mesh(folder), info["metrics"]
    except (OSError, ValueError, KeyError, PavemapError):
        return None


def save_tile(folder: Path, tile: RoadMesh, metrics: dict, stamp: str) -> None:
    from pavemap.mesh.outputs import _json_safe, save_mesh

    folder.mkdir(parents=True, exist_ok=True)
    save_mesh(folder, tile)
    # tile.json last: a tile counts as done only once both files are complete
    atomic_write_json(folder / TILE_FILE, _json_safe({"stamp": stamp, "metrics": metrics}))


def drop_stale(out_dir: Path | None, n: int) -> None:
    """Remove the tiles of an earlier plan with more segments (only the two files pavemap writes there)."""
    if out_dir is None or not (Path(out_dir) / SEGMENTS_DIR).is_dir():
        return
    for folder in sorted((Path(out_dir) / SEGMENTS_DIR).iterdir()):
        if folder.is_dir() and folder.name.isdigit() and int(folder.name) >= n and (folder / TILE_FILE).is_file():
            for name in (TILE_FILE, "mesh.npz"):
                (folder / name).unlink(missing_ok=True)
            if not any(folder.iterdir()):
                folder.rmdir()


def sub_sequence(seq: Sequence, positions: tuple[int, ...]) -> Sequence:
    """``seq`` with only the frames at ``positions``."""
    return dataclasses.replace(seq, frames=[seq.frames[p] for p in positions])


__all__ = ["SEGMENTS_DIR", "TILE_FILE", "TileJob", "drop_stale", "load_tile", "run_tile", "save_tile",
           "segment_tile", "stamp_config", "sub_sequence", "tile_done", "tile_runner", "tile_stamp",
           "tiles_run_by"]
