"""A detector's pretrained start: YOLOv5's COCO checkpoint read without YOLOv5's code.

ultralytics' ``yolov5n.pt`` release is a pickled dict whose ``model`` entry is YOLOv5's own
``models.yolo.Model`` object, so a plain ``torch.load`` needs the ``models`` / ``utils``
packages of the YOLOv5 repository. :func:`read_yolov5_state` unpickles it with those classes
replaced by an inert stand-in (only an allow-list of torch and collection classes is
resolved for real, so the file can run no code) and collects every module's parameters and
buffers under their dotted names: the backbone and neck (layers 0–23) have the same names
and shapes as ultralytics' own ``yolov5n.yaml`` model; only the anchor-based head differs.

:func:`coco_start_checkpoint` builds that ultralytics model for pavemap's four classes,
copies the matching tensors in and saves an ultralytics checkpoint to train from
(``pavemap train-detector --init-from``).
"""

from __future__ import annotations

import logging
import os
import pickle
from pathlib import Path
from typing import Any

import torch

from pavemap.errors import PavemapError

log = logging.getLogger(__name__)

#: module prefixes of the YOLOv5 repository whose classes become :class:`_StandIn`
_FOREIGN_PREFIXES = ("models.", "utils.", "__main__")
#: real classes and functions a checkpoint may name (torch's tensor rebuilds, containers, nn layers)
_ALLOWED = {
    ("collections", "OrderedDict"),
    ("torch._utils", "_rebuild_tensor_v2"),
    ("torch._utils", "_rebuild_parameter"),
    ("torch", "HalfStorage"),
    ("torch", "FloatStorage"),
    ("torch", "LongStorage"),
    ("torch", "BoolStorage"),
    ("torch", "float16"),
    ("torch", "float32"),
    ("torch", "Size"),
    ("torch", "device"),
    ("torch", "DoubleStorage"),
    ("builtins", "set"),
    ("__builtin__", "set"),
    ("builtins", "slice"),
}


class _StandIn:
    """Inert object for any class the checkpoint names that pavemap does not load for real."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        pass

    def __setstate__(self, state: Any) -> None:
        if isinstance(state, tuple) and len(state) == 2:  # (dict state, slot state)
            state = state[0] or {}
        if isinstance(state, dict):
            self.__dict__.update(state)


def _find_class(module: str, name: str, foreign: tuple[str, ...] = _FOREIGN_PREFIXES) -> Any:
    if module.startswith(foreign) or module.startswith("torch.nn.modules") or module.startswith("numpy"):
        return _StandIn
    if (module, name) in _ALLOWED:
        module = "builtins" if module == "__builtin__" else module
        return getattr(__import__(module, fromlist=[name]), name)
    raise pickle.UnpicklingError(f"class {module}.{name} is not allowed in a pretrained checkpoint")


def _pickle_module(foreign: tuple[str, ...]) -> Any:
    """What ``torch.load(pickle_module=...)`` needs: an Unpickler whose classes come from :func:`_find_class`
    (``foreign`` prefixes become :class:`_StandIn`) and a ``load``."""

    class _Unpickler(pickle.Unpickler):
        def find_class(self, module: str, name: str) -> Any:
            return _find_class(module, name, foreign)

    class _PickleModule:
        Unpickler = _Unpickler
        __name__ = "pavemap_standin_pickle"

        @staticmethod
        def load(f: Any, **kwargs: Any) -> Any:
            return _Unpickler(f, **kwargs).load()

    return _PickleModule


def inert_load(path: str | os.PathLike, foreign: tuple[str, ...] = _FOREIGN_PREFIXES) -> Any:
    """A foreign checkpoint unpickled without running its code: tensors for real, classes named under a
    ``foreign`` prefix (and torch.nn / numpy ones) as inert :class:`_StandIn` objects, anything else refused
    (``pickle.UnpicklingError``).

    ``weights_only=False`` is deliberate and safe here: a YOLOv5 / ultralytics pickle holds whole model
    objects, which torch's weights_only loader refuses; the allow-list unpickler above stands in for it
    (it resolves no class outside :data:`_ALLOWED`, so e.g. ``os.system`` in a ``__reduce__`` never runs).
    """
    return torch.load(Path(path), map_location="cpu", pickle_module=_pickle_module(foreign), weights_only=False)


def _collect(obj: Any, prefix: str, out: dict[str, torch.Tensor]) -> None:
    d = getattr(obj, "__dict__", {})
    for key in ("_parameters", "_buffers"):
        for name, t in (d.get(key) or {}).items():
            if isinstance(t, torch.Tensor):
                out[f"{prefix}{name}"] = t.detach().float().clone()
    for name, child in (d.get("_modules") or {}).items():
        if child is not None:
            _collect(child, f"{prefix}{name}.", out)


def read_yolov5_state(path: str | os.PathLike) -> dict[str, torch.Tensor]:
    """Tensors of a YOLOv5 release checkpoint by dotted name (``model.0.conv.weight`` …), float32.

    Raises PavemapError naming the file when it is missing, not a YOLOv5 checkpoint or unreadable.
    """
    p = Path(path)
    if not p.is_file():
        raise PavemapError(
            f"pretrained checkpoint {p} not found (put ultralytics' COCO yolov5n.pt there; pavemap never downloads)"
        )
    try:
        ckpt = inert_load(p)
    except Exception as e:  # a truncated file or a foreign pickle: one line naming the file
        raise PavemapError(f"{p}: not a readable YOLOv5 checkpoint ({type(e).__name__}: {e})") from None
    model = ckpt.get("ema") or ckpt.get("model") if isinstance(ckpt, dict) else None
    if model is None:
        raise PavemapError(f"{p}: not a YOLOv5 checkpoint (no 'model' entry)")
    out: dict[str, torch.Tensor] = {}
    _collect(model, "", out)
    if not out:
        raise PavemapError(f"{p}: the checkpoint's model holds no tensors")
    return out


def transfer(state: dict[str, torch.Tensor], model: torch.nn.Module) -> tuple[int, list[str]]:
    """Copy every tensor of ``state`` whose name and shape match ``model``'s; returns (copied, skipped names)."""
    own = model.state_dict()
    copied, skipped = 0, []
    with torch.no_grad():
        for k, v in own.items():
            src = state.get(k)
            if src is not None and tuple(src.shape) == tuple(v.shape):
                v.copy_(src.to(v.dtype))
                copied += 1
            else:
                skipped.append(k)
    return copied, skipped


def coco_start_checkpoint(
    yolov5_pt: str | os.PathLike, out: str | os.PathLike, model_yaml: str = "yolov5n.yaml",
    names: dict[int, str] | None = None, min_copied: int = 300,
) -> Path:
    """An ultralytics checkpoint of ``model_yaml`` for ``names`` with YOLOv5's COCO backbone and neck copied in.

    The detection head stays as initialised (anchor-free in ultralytics). Fewer than ``min_copied``
    matching tensors (the wrong model size or a different architecture) → PavemapError naming the file.
    """
    from pavemap.detect.yolo import _import_ultralytics

    names = names or {0: "D00", 1: "D10", 2: "D20", 3: "D40"}
    state = read_yolov5_state(yolov5_pt)
    _import_ultralytics()
    from ultralytics.nn.tasks import DetectionModel

    model = DetectionModel(model_yaml, nc=len(names), verbose=False)
    copied, skipped = transfer(state, model)
    if copied < min_copied:
        raise PavemapError(
            f"{yolov5_pt}: only {copied} of its tensors fit {model_yaml} (expected >= {min_copied}); "
            "is it a YOLOv5 checkpoint of the same size (n, s, …)?"
        )
    log.info("COCO start: %d tensors copied from %s, %d left as initialised (the head)", copied,
             yolov5_pt, len(skipped))
    model.names = dict(names)
    model.yaml["nc"] = len(names)
    ckpt = {"model": model.half(), "train_args": {}, "date": None, "version": None,
            "license": "AGPL-3.0 (COCO-pretrained YOLOv5n by Ultralytics)", "epoch": -1}
    from pavemap.io.atomic import atomic_path

    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(out) as tmp:
        torch.save(ckpt, tmp)
    return out


__all__ = ["coco_start_checkpoint", "read_yolov5_state", "transfer"]
