"""torchvision compatibility shim: a pure-torch ``torchvision::nms`` where the compiled op is missing.

Why this exists: the only torchvision matching torch 2.13.0 is 0.28.0, whose compiled
extension (``torchvision/_C.so``) links against CUDA libraries. On a CPU-only torch the
extension fails to load *silently*, and ``import torchvision`` then dies in
``torchvision/_meta_registrations.py`` with "operator torchvision::nms does not exist",
because it registers a fake kernel for an op nobody defined. ultralytics imports
torchvision for its NMS, so nothing of the detector would work.

:func:`ensure_torchvision` must run *before* the first ``import torchvision`` (the
pavemap YOLO backend calls it before importing ultralytics). It

1. does nothing if torchvision is already imported, or if the op already exists
   (torchvision's extension loaded fine: a CUDA build, or a matching CPU build);
2. otherwise tries to load the extension exactly as torchvision would, and only when
   that leaves ``torchvision::nms`` undefined, defines ``torchvision::nms`` and
   ``torchvision::qnms`` with the same schema as the C++ ops and a pure-torch kernel
   (CompositeExplicitAutograd, so it serves CPU and CUDA tensors alike), imports
   torchvision and lets ``torchvision.ops.boxes`` (nms, batched_nms) call it: that
   module's "is the extension loaded" check is replaced by "is nms registered".

Only NMS is provided: the other compiled ops (roi_align, deform_conv2d, ...) stay
unavailable, and torchvision's own registration code skips them when its extension
is missing. The result of :func:`nms` equals torchvision's (greedy, score-descending,
suppress IoU > threshold, indices sorted by decreasing score).
"""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import numpy as np
import torch

_STATE: dict[str, object] = {"checked": False, "shim": False, "library": None}


def _op_exists(name: str) -> bool:
    try:
        return torch._C._dispatch_has_kernel(f"torchvision::{name}") or hasattr(torch.ops.torchvision, name)
    except (RuntimeError, AttributeError):
        return False


def _try_load_extension() -> bool:
    """Load torchvision's compiled ops without importing torchvision; True when ``nms`` then exists."""
    spec = importlib.util.find_spec("torchvision")
    if spec is None or not spec.submodule_search_locations:
        return False
    for folder in spec.submodule_search_locations:
        for lib in sorted(Path(folder).glob("_C*.so")) + sorted(Path(folder).glob("_C*.pyd")):
            try:
                torch.ops.load_library(str(lib))
            except (OSError, ImportError, RuntimeError):
                continue
    return _op_exists("nms")


def box_iou(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """IoU between boxes ``a`` (N, 4) and ``b`` (M, 4), x1 y1 x2 y2 → (N, M)."""
    area_a = (a[:, 2] - a[:, 0]).clamp(min=0) * (a[:, 3] - a[:, 1]).clamp(min=0)
    area_b = (b[:, 2] - b[:, 0]).clamp(min=0) * (b[:, 3] - b[:, 1]).clamp(min=0)
    lt = torch.maximum(a[:, None, :2], b[None, :, :2])
    rb = torch.minimum(a[:, None, 2:], b[None, :, 2:])
    wh = (rb - lt).clamp(min=0)
    inter = wh[..., 0] * wh[..., 1]
    union = area_a[:, None] + area_b[None, :] - inter
    return torch.where(union > 0, inter / union.clamp(min=torch.finfo(torch.float32).tiny), 0.0)


def nms(boxes: torch.Tensor, scores: torch.Tensor, iou_threshold: float) -> torch.Tensor:
    """Greedy NMS in pure torch. ``boxes`` (N, 4) x1 y1 x2 y2, ``scores`` (N,) → kept indices (K,) int64.

    Blockwise: boxes are taken in score order in blocks of 512; inside a block the
    greedy pass runs over an IoU matrix of the block, then the block's survivors
    suppress all later boxes at once. The Python loop runs over blocks and over the
    survivors inside a block, never over pixel- or box-pair elements.
    """
    n = boxes.shape[0]
    if n == 0:
        return torch.empty(0, dtype=torch.long, device=boxes.device)
    order = torch.argsort(scores, descending=True, stable=True)
    b = boxes[order].float()
    alive = torch.ones(n, dtype=torch.bool, device=boxes.device)
    block = 512
    for start in range(0, n, block):
        stop = min(start + block, n)
        idx = torch.nonzero(alive[start:stop]).flatten() + start
        if idx.numel() == 0:
            continue
        # greedy inside the block: a box survives unless an earlier survivor overlaps it
        iou = box_iou(b[idx], b[idx])
        # over[i, j]: earlier box i suppresses later box j; the greedy pass is sequential by
        # nature, so it runs on a small host copy (no device sync per step on CUDA)
        over = torch.triu(iou > iou_threshold, diagonal=1).cpu().numpy()
        keep_np = np.ones(idx.numel(), dtype=bool)
        for i in range(idx.numel()):
            if keep_np[i]:
                keep_np &= ~over[i]
        keep_blk = torch.from_numpy(keep_np).to(boxes.device)
        alive[idx] = keep_blk
        survivors = idx[keep_blk]
        if stop < n and survivors.numel():
            later = torch.arange(stop, n, device=boxes.device)
            later = later[alive[stop:]]
            if later.numel():
                hit = (box_iou(b[survivors], b[later]) > iou_threshold).any(dim=0)
                alive[later[hit]] = False
    return order[alive]


def _qnms(dets: torch.Tensor, scores: torch.Tensor, iou_threshold: float) -> torch.Tensor:
    return nms(dets.dequantize() if dets.is_quantized else dets,
               scores.dequantize() if scores.is_quantized else scores, iou_threshold)


def ensure_torchvision() -> bool:
    """Make ``import torchvision`` work; returns True when the pure-torch NMS shim was installed.

    Idempotent and a no-op where torchvision's compiled ops load (or torchvision is
    already imported). Call it before anything imports torchvision (e.g. ultralytics).
    """
    if _STATE["checked"]:
        return bool(_STATE["shim"])
    _STATE["checked"] = True
    if "torchvision" in sys.modules or _op_exists("nms") or _try_load_extension():
        return False
    if importlib.util.find_spec("torchvision") is None:
        return False  # nothing to fix; whoever needs torchvision reports it missing
    lib = torch.library.Library("torchvision", "DEF")
    lib.define("nms(Tensor dets, Tensor scores, float iou_threshold) -> Tensor")
    lib.define("qnms(Tensor dets, Tensor scores, float iou_threshold) -> Tensor")
    lib.impl("nms", nms, "CompositeExplicitAutograd")
    lib.impl("qnms", _qnms, "CompositeExplicitAutograd")
    _STATE["library"] = lib  # the Library object must stay alive or the ops are deregistered
    _STATE["shim"] = True
    # torchvision.ops.nms checks "extension loaded" before calling the op; only the box ops
    # module is told the op is there, so roi_align & co. still report themselves missing.
    import torchvision.ops.boxes as tv_boxes

    tv_boxes._assert_has_ops = _nms_available
    return True


def _nms_available() -> None:
    if not _op_exists("nms"):
        raise RuntimeError("torchvision::nms is not registered")


def shim_installed() -> bool:
    """True when :func:`ensure_torchvision` had to install the pure-torch NMS."""
    return bool(_STATE["shim"])
