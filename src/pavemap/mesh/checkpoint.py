"""Stage-1 checkpoint: ``OUT/checkpoint.pt`` after every epoch, and resuming from it.

A checkpoint resumes only the run it belongs to: same grid and crop, same class table, same number of
pose groups, and the same settings (every MeshConfig field but ``epochs`` and ``resume``; a checkpoint
already past the configured epochs does not match either); anything else starts afresh (with a warning
from the caller). More epochs than the checkpoint's continue its training (``pavemap reconstruct
--resume``), which is not the mesh an uninterrupted run of that length gives (the learning-rate
schedule spans the run): ``pavemap run`` therefore resumes only an interrupted stage of identical
settings (:mod:`pavemap.run_folder`).

Safe to load: a checkpoint holds only tensors, numbers, strings, None and lists / tuples / dicts of them
(:func:`plain` converts numpy values and paths on save, and refuses any other object), so it is read with
``torch.load(..., weights_only=True)``: a run folder from someone else cannot run code on resume. A file
that needs more than that (an older pavemap's, or a doctored one) is not loaded: a PavemapError says to
rerun with ``--overwrite`` / ``--no-resume`` or delete the checkpoint.
"""

from __future__ import annotations

import dataclasses
import pickle
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from pavemap.errors import PavemapError
from pavemap.io.atomic import atomic_path
from pavemap.mesh.config import MeshConfig
from pavemap.mesh.model import MeshGrid, RoadMeshModel
from pavemap.mesh.step import MultiOptimizer

CHECKPOINT = "checkpoint.pt"


@dataclass
class Resumed:
    """What a resumed run continues from: epochs done, per-epoch history, seconds already spent."""

    epoch: int
    history: list[dict]
    seconds: float


def plain(obj: object, where: str = "checkpoint") -> object:
    """``obj`` as what ``torch.load(weights_only=True)`` reads back: tensors (detached, on the CPU), bool /
    int / float / str / None, lists, tuples and str-keyed dicts of them; numpy scalars and arrays become
    numbers and tensors, paths strings, dataclasses dicts. Anything else is a TypeError naming where."""
    if obj is None or isinstance(obj, bool | int | float | str):
        return obj
    if isinstance(obj, torch.Tensor):
        return obj.detach().cpu()
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return torch.from_numpy(np.ascontiguousarray(obj))
    if isinstance(obj, Path):
        return str(obj)
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        obj = {f.name: getattr(obj, f.name) for f in dataclasses.fields(obj)}
    if isinstance(obj, dict):
        return {str(k) if not isinstance(k, int) else k: plain(v, f"{where}.{k}") for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return type(obj)(plain(v, f"{where}[{i}]") for i, v in enumerate(obj))
    raise TypeError(f"{where}: {type(obj).__name__} cannot go into a checkpoint (not loadable with weights_only)")


def save_checkpoint(path: Path, model: RoadMeshModel, opt: MultiOptimizer, delta: torch.Tensor | None, epoch: int,
                    history: list[dict], gen: torch.Generator, cfg: MeshConfig, seconds: float) -> None:
    """Write the model, optimizer, pose corrections ``delta`` (G, 6), sampling generator and history."""
    grid = model.grid
    state = plain({
        "model": model.state_dict(), "opt": opt.state_dict(), "delta": delta, "epoch": int(epoch),
        "history": history, "gen": gen.get_state(), "config": cfg.to_dict(), "seconds": float(seconds),
        "grid": {**grid.spec.to_dict(), "valid_sum": grid.vertices},
    })
    with atomic_path(path) as tmp:
        torch.save(state, tmp)


#: MeshConfig fields a checkpoint may differ in and still resume.
RESUMABLE_CHANGES = ("epochs", "resume")


def settings_match(saved: object, cfg: MeshConfig) -> bool:
    """Whether a checkpoint's saved config (a dict) has the settings of ``cfg`` (RESUMABLE_CHANGES aside)."""
    if not isinstance(saved, dict):
        return False
    now = cfg.to_dict()
    return all(saved.get(k) == v for k, v in now.items() if k not in RESUMABLE_CHANGES)


def load_checkpoint(path: Path, grid: MeshGrid, num_classes: int, num_groups: int, device: torch.device,
                    cfg: MeshConfig | None = None) -> dict | None:
    """The checkpoint's state when it belongs to this grid / class table / pose groups (and, given ``cfg``,
    these settings, no more epochs done than ``cfg.epochs``), else None (also for a missing or damaged file).

    Read with ``weights_only=True``; a file that holds anything else is a PavemapError (never loaded).
    """
    state = read_checkpoint(path, device)
    if state is None:
        return None
    if not isinstance(state, dict) or not isinstance(state.get("model"), dict):
        return None
    if cfg is not None and (not settings_match(state.get("config"), cfg) or int(state.get("epoch", 0)) > cfg.epochs):
        return None
    g, spec = state.get("grid", {}), grid.spec
    same = (abs(g.get("x0", 1e18) - spec.x0) < 1e-9 and abs(g.get("y0", 1e18) - spec.y0) < 1e-9
            and g.get("nx") == spec.nx and g.get("ny") == spec.ny and g.get("valid_sum") == grid.vertices)
    sem = state["model"].get("sem")
    if not same or sem is None or sem.shape[1] != num_classes:
        return None
    if state.get("delta") is not None and state["delta"].shape[0] != num_groups:
        return None
    return state


def read_checkpoint(path: Path, device: torch.device | str = "cpu") -> dict | None:
    """The checkpoint at ``path`` loaded with ``weights_only=True``; None when missing or damaged.

    PavemapError when the file holds objects the safe loader refuses (code could run on loading it).
    """
    if not Path(path).is_file():
        return None
    try:
        return torch.load(path, map_location=device, weights_only=True)
    except pickle.UnpicklingError as e:
        if "weights_only" not in str(e) and "Weights only" not in str(e):
            return None  # a damaged file: just not resumable
        raise PavemapError(
            f"{path}: this checkpoint holds objects that cannot be loaded safely (an older pavemap's format, or "
            "not written by pavemap); it was not loaded. Rerun with --overwrite (pavemap run) or --no-resume "
            "(pavemap reconstruct), or delete the checkpoint") from None
    except Exception:  # noqa: BLE001 - a truncated or corrupt checkpoint is just not resumable
        return None


def resume(out_dir: Path, model: RoadMeshModel, opt: MultiOptimizer, gen: torch.Generator, num_groups: int,
           device: torch.device, cfg: MeshConfig | None = None) -> tuple[Resumed, torch.Tensor | None] | None:
    """Load ``out_dir/checkpoint.pt`` into the model, optimizer and generator when it matches this run.

    Returns where to continue and the saved pose corrections (G, 6) (None without pose refinement), or
    None when there is no matching checkpoint (nothing is changed then).
    """
    path = Path(out_dir) / CHECKPOINT
    state = load_checkpoint(path, model.grid, model.sem.shape[1], num_groups, device, cfg)
    if state is None:
        return None
    model.load_state_dict(state["model"])
    opt.load_state_dict(state["opt"])
    gen.set_state(state["gen"])
    done = Resumed(int(state["epoch"]), state["history"], float(state.get("seconds", 0.0)))
    return done, state.get("delta")
