"""Per-vertex accumulators (SPEC §3) and the defect probability, as dense tensors.

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
    """Dense per-vertex state, flat ``j*nx+i``: counts (V, 4) int32, sev (V,) float64, conf (V,) float64."""

    counts: torch.Tensor
    sev: torch.Tensor
    conf: torch.Tensor
    seen: torch.Tensor | None = None  # (M,) long sorted ids of the observed vertices, when known

    @property
    def n(self) -> torch.Tensor:
        """(V,) total observations per vertex."""
        return self.counts.sum(1)


def accumulate(num_vertices: int, det: torch.Tensor, vid: torch.Tensor, order: torch.Tensor,
               cls: torch.Tensor, conf: torch.Tensor, alpha: float,
               severity_weights: tuple[float, ...]) -> Accumulators:
    """Apply (detection, vertex) pairs (P,) to fresh accumulators.

    order (N,) long: the detections' application order (rank by frame, then input order);
    cls (N,) long; conf (N,) float.
    """
    dev = vid.device
    V = num_vertices
    C = NUM_DEFECT_CLASSES
    counts = torch.zeros((V, C), dtype=torch.int32, device=dev)
    sev = torch.zeros(V, dtype=torch.float64, device=dev)
    conf_v = torch.zeros(V, dtype=torch.float64, device=dev)
    if vid.numel() == 0:
        return Accumulators(counts, sev, conf_v, torch.zeros(0, dtype=torch.long, device=dev))
    # Work on the observed vertices only (a few thousand of millions), then scatter into the dense state.
    seen, local = torch.unique(vid, return_inverse=True)
    m = len(seen)
    c = cls[det]
    counts[seen] = torch.bincount(local * C + c, minlength=m * C).reshape(m, C).to(torch.int32)
    conf_v[seen] = torch.zeros(m, dtype=torch.float64, device=dev).scatter_reduce(
        0, local, conf[det].double(), reduce="amax", include_self=True)
    w = torch.as_tensor(severity_weights, dtype=torch.float64, device=dev)[c]
    key = local * (int(order.max()) + 1) + order[det]
    perm = torch.argsort(key)
    ls, ws = local[perm], w[perm]
    _, inv, group = torch.unique_consecutive(ls, return_inverse=True, return_counts=True)
    first = torch.cumsum(group, 0) - group
    rank = torch.arange(len(ls), device=dev) - first[inv]
    expo = (group[inv] - 1 - rank).double()
    sev[seen] = torch.zeros(m, dtype=torch.float64, device=dev).index_add_(0, ls, alpha * (1.0 - alpha) ** expo * ws)
    return Accumulators(counts, sev, conf_v, seen)


def probability(acc: Accumulators, mode: str = "tanh", eps: float = 1e-9) -> tuple[torch.Tensor, torch.Tensor]:
    """Defect probability (V,) and per class (V, 4), float64.

    ``x = sev * log(1 + n)``; ``tanh``: ``P = 2 sigma(x) - 1`` (SPEC erratum, 0 when unobserved);
    ``sigmoid``: the paper's ``P = sigma(x)``. ``P(c) = obs[c] / (n + eps) * P``.
    """
    n = acc.n.double()
    x = acc.sev * torch.log1p(n)
    p = 2.0 * torch.sigmoid(x) - 1.0 if mode == "tanh" else torch.sigmoid(x)
    pc = acc.counts.double() / (n + eps)[:, None] * p[:, None]
    return p, pc
