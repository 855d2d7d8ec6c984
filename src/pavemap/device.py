"""The one device resolver: every stage and command turns a user's ``--device`` into a torch device here.

Behaviour (documented in the README): ``auto`` picks ``cuda`` when torch sees a GPU, else ``cpu``;
``cpu``; ``cuda`` / ``gpu`` means ``cuda:0``; ``cuda:N`` or a bare ``N`` names a GPU. Asking for a GPU
that torch does not see, or an unknown name, is a :class:`PavemapError` (never a silent fallback:
a run that asked for CUDA and ran on the CPU would report timings that mean something else).
"""

from __future__ import annotations

import torch

from pavemap.errors import PavemapError

CHOICES = "auto, cpu, cuda or cuda:N"


def resolve_device(device: str | torch.device | None = "auto") -> torch.device:
    """``auto`` / ``cpu`` / ``cuda`` / ``cuda:N`` / ``N`` → a torch device that exists on this machine."""
    if isinstance(device, torch.device):
        device = str(device)
    name = (device or "auto").strip().lower()
    if name == "auto":
        return torch.device("cuda:0" if torch.cuda.is_available() else "cpu")
    if name == "cpu":
        return torch.device("cpu")
    if name in ("cuda", "gpu"):
        name = "cuda:0"
    if name.isdigit():
        name = f"cuda:{name}"
    if name.startswith("cuda:") and name[5:].isdigit():
        if not torch.cuda.is_available():
            raise PavemapError(f"device {device!r}: this torch sees no CUDA GPU; use --device cpu or auto")
        idx = int(name[5:])
        if idx >= torch.cuda.device_count():
            raise PavemapError(f"device {device!r}: valid GPUs are 0..{torch.cuda.device_count() - 1}")
        return torch.device(name)
    raise PavemapError(f"unknown device {device!r}; use {CHOICES}")


def ultralytics_device(device: torch.device) -> str:
    """A resolved torch device in ultralytics' spelling (``cpu``, ``0``, ``1`` …)."""
    return "cpu" if device.type == "cpu" else str(device.index or 0)
