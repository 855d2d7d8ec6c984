"""Per-vertex accumulators (SPEC §3) and the defect probability, over the observed vertices only.

A long drive's vertex grid holds tens of millions of cells of which detections touch a few per cent, so the
state lives on the observed vertices (``seen``, sorted flat ids ``j*nx+i``) and never on the whole grid.

The EMA ``sev <- alpha*w + (1-alpha)*sev`` applied to a vertex's observations in order (frame
order, then detection order within a frame; every detection hitting the vertex counts) has the
closed form ``sev = sum_m alpha (1-alpha)^(K-1-m) w_m`` from ``sev = 0``, for the m-th of K
observations. So all frames are applied at once: sort the pairs by (vertex, order), rank them
within each vertex, and sum the weighted terms with ``index_add`` - no loop over frames.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from pavemap.types import NUM_DEFECT_CLASSES


@dataclass
class Accumulators:
    """State of M vertices: counts (M, 4) int32, sev (M,) float64, conf (M,) float64; ``seen`` (M,) long their
    sorted flat ids on the vertex grid (None: the rows are the vertices 0..M-1)."""

    counts: torch.Tensor
    sev: torch.Tensor
    conf: torch.Tensor
    seen: torch.Tensor | None = None

    @property
    def n(self) -> torch.Tensor:
        """(M,) total observations per vertex."""
        return self.counts.sum(1)


def accumulate(det: torch.Tensor, vid: torch.Tensor, order: torch.Tensor,
               cls: torch.Tensor, conf: torch.Tensor, alpha: float,
               severity_weights: tuple[float, ...]) -> Accumulators:
    """Apply (detection, vertex) pairs (P,) to fresh accumulators of the vertices they observe.

    vid (P,) long flat vertex ids; order (N,) long: the detections' application order (rank by frame, then
    input order); cls (N,) long; conf (N,) float.
    """
    dev = vid.device
    C = NUM_DEFECT_CLASSES
    if vid.numel() == 0:
        f64 = torch.zeros(0, dtype=torch.float64, device=dev)
        return Accumulators(torch.zeros((0, C), dtype=torch.int32, device=dev), f64, f64.clone(),
                            torch.zeros(0, dtype=torch.long, device=dev))
    seen, local = torch.unique(vid, return_inverse=True)
    m = len(seen)
    c = cls[det]
    counts = torch.bincount(local * C + c, minlength=m * C).reshape(m, C).to(torch.int32)
    conf_v = torch.zeros(m, dtype=torch.float64, device=dev).scatter_reduce(
        0, local, conf[det].double(), reduce="amax", include_self=True)
    w = torch.as_tensor(severity_weights, dtype=torch.float64, device=dev)[c]
    key = local * (int(order.max()) + 1) + order[det]
    perm = torch.argsort(key)
    ls, ws = local[perm], w[perm]
    _, inv, group = torch.unique_consecutive(ls, return_inverse=True, return_counts=True)
    first = torch.cumsum(group, 0) - group
    rank = torch.arange(len(ls), device=dev) - first[inv]
    expo = (group[inv] - 1 - rank).double()
    sev = torch.zeros(m, dtype=torch.float64, device=dev).index_add_(0, ls, alpha * (1.0 - alpha) ** expo * ws)
    return Accumulators(counts, sev, conf_v, seen)


def probability(acc: Accumulators, mode: str = "tanh", eps: float = 1e-9) -> tuple[torch.Tensor, torch.Tensor]:
    """Defect probability (M,) and per class (M, 4), float64.

    ``x = sev * log(1 + n)``; ``tanh``: ``P = 2 sigma(x) - 1`` (SPEC erratum, 0 when unobserved);
    ``sigmoid``: the paper's ``P = sigma(x)``. ``P(c) = obs[c] / (n + eps) * P``.
    """
    n = acc.n.double()
    x = acc.sev * torch.log1p(n)
    p = 2.0 * torch.sigmoid(x) - 1.0 if mode == "tanh" else torch.sigmoid(x)
    pc = acc.counts.double() / (n + eps)[:, None] * p[:, None]
    return p, pc
