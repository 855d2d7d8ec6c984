"""The one device resolver: every stage and command turns a user's ``--device`` into a torch device here.

Behaviour (documented in docs/guide/configuration.md): ``auto`` picks ``cuda`` when torch sees a GPU, else ``cpu``;
``cpu``; ``cuda`` / ``gpu`` means ``cuda:0``; ``cuda:N`` or a bare ``N`` names a GPU. Asking for a GPU
that torch does not see, or an unknown name, is a :class:`PavemapError` (never a silent fallback:
a run that asked for CUDA and ran on the CPU would report timings that mean something else).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from pavemap.errors import PavemapError

if TYPE_CHECKING:
    import torch

CHOICES = "auto, cpu, cuda or cuda:N"


def _canonical(name: str) -> str | None:
    """``cpu`` / ``cuda:N`` / ``auto`` for a name this module accepts, else None."""
    n = name.strip().lower()
    if n in ("auto", "cpu"):
        return n
    if n in ("cuda", "gpu"):
        return "cuda:0"
    if n.isdigit():
        return f"cuda:{n}"
    if n.startswith("cuda:") and n[5:].isdigit():
        return n
    return None


def is_device_name(name: str) -> bool:
    """Whether ``name`` is spelled like a device (config validation; says nothing about what exists)."""
    return isinstance(name, str) and _canonical(name) is not None


def resolve_device(device: str | torch.device | None = "auto") -> torch.device:
    """``auto`` / ``cpu`` / ``cuda`` / ``cuda:N`` / ``N`` → a torch device that exists on this machine."""
    import torch  # lazily: config validation uses this module without loading torch

    if isinstance(device, torch.device):
        device = str(device)
    name = _canonical(device or "auto")
    if name == "auto":
        return torch.device("cuda:0" if torch.cuda.is_available() else "cpu")
    if name == "cpu":
        return torch.device("cpu")
    if name is not None:
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
