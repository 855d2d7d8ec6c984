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
    """Dense per-vertex state, flat ``j*nx+i``: counts (V, 4) long, sev (V,) float64, conf (V,) float64."""

    counts: torch.Tensor
    sev: torch.Tensor
    conf: torch.Tensor

    @property
    def n(self) -> torch.Tensor:
        """(V,) long total observations per vertex."""
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
    c = cls[det]
    counts = torch.bincount(vid * C + c, minlength=V * C).reshape(V, C)
    conf_v = torch.zeros(V, dtype=torch.float64, device=dev).scatter_reduce(
        0, vid, conf[det].double(), reduce="amax", include_self=True)
    sev = torch.zeros(V, dtype=torch.float64, device=dev)
    if vid.numel():
        w = torch.as_tensor(severity_weights, dtype=torch.float64, device=dev)[c]
        key = vid * (int(order.max()) + 1) + order[det]
        perm = torch.argsort(key)
        vs, ws = vid[perm], w[perm]
        _, inv, group = torch.unique_consecutive(vs, return_inverse=True, return_counts=True)
        first = torch.cumsum(group, 0) - group
        rank = torch.arange(len(vs), device=dev) - first[inv]
        expo = (group[inv] - 1 - rank).double()
        sev.index_add_(0, vs, alpha * (1.0 - alpha) ** expo * ws)
    return Accumulators(counts, sev, conf_v)


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
