"""The BEV grid, its trajectory crop, and the learnable vertex attributes (SPEC §1).

Height ``z_i = b_i + MLP1([Phi(p_i); MLP0(Phi(p_i))])`` with ``p_i`` the vertex x, y normalised to
[-1, 1]^2 over the grid. ``b_i`` is a fixed initial surface (the ground under the trajectory: camera
heights minus the mount height, interpolated between frames) so that the MLP, which starts at 0, only
learns the relief relative to it (a drive can climb metres); it is part of the model, so the outputs
carry no hidden offset. RGB (init N(0, 0.01)) and semantic logits (init 0) are per-vertex tensors over the kept
(valid) vertices only, in the compact order of ``torch.nonzero(valid.reshape(-1))``.
"""

from __future__ import annotations

import dataclasses
import math
import typing
from dataclasses import dataclass

import numpy as np
import torch
from scipy import ndimage
from torch import nn

from pavemap.geometry import GridSpec, HeightField
from pavemap.types import SemanticClass


@dataclass(frozen=True)
class MeshGrid:
    """The vertex grid of the mesh (:class:`GridSpec`) and its trajectory crop ``valid`` (ny, nx) bool."""

    spec: GridSpec
    valid: np.ndarray

    @property
    def vertices(self) -> int:
        return int(self.valid.sum())

    @property
    def faces(self) -> int:
        v = self.valid
        quad = v[:-1, :-1] & v[1:, 1:]
        return int((quad & v[:-1, 1:]).sum() + (quad & v[1:, :-1]).sum())

    def vertex_xy(self) -> np.ndarray:
        """(Nv, 2) float64 world x, y of the kept vertices, in compact order (``flatnonzero(valid)``)."""
        g = self.spec
        vid = np.flatnonzero(self.valid.reshape(-1))
        return np.stack([g.x0 + (vid % g.nx) * g.res, g.y0 + (vid // g.nx) * g.res], 1)


def dense_polyline(t: np.ndarray, step: float) -> np.ndarray:
    """(F, 2) polyline -> (M, 2) points along it at most ``step`` apart (its vertices included)."""
    pts = [t[:1]]
    for a, b in zip(t[:-1], t[1:], strict=True):
        n = max(2, int(math.ceil(np.linalg.norm(b - a) / step)) + 1)
        pts.append(a + np.linspace(0, 1, n)[:, None] * (b - a))
    return np.concatenate(pts)


def build_grid(trajectory_xy: np.ndarray, res: float, crop_m: float,
               extra_paths: typing.Sequence[np.ndarray] = ()) -> MeshGrid:
    """Grid over the trajectory's bounding box grown by ``crop_m``; keep vertices within ``crop_m`` of it.

    trajectory_xy: (F, 2) rig positions in order; the distance is to the polyline through them
    (a one-frame sequence gives a disc). ``extra_paths``: more (K, 2) polylines kept the same way (the
    road the end frames' cameras look at beyond the trajectory). Origin snapped to multiples of ``res``.
    """
    t = np.asarray(trajectory_xy, dtype=np.float64).reshape(-1, 2)
    # Rasterise the polylines densely (half-cell spacing), then an exact Euclidean distance transform.
    p = np.concatenate([dense_polyline(q, 0.5 * res) for q in
                        (t, *(np.asarray(e, dtype=np.float64).reshape(-1, 2) for e in extra_paths))])
    spec = GridSpec.covering(p.min(0) - crop_m, p.max(0) + crop_m, res)
    lo = np.array([spec.x0, spec.y0])
    ij = np.rint((p - lo) / res).astype(np.int64)
    seeds = np.ones(spec.shape, dtype=bool)
    seeds[np.clip(ij[:, 1], 0, spec.ny - 1), np.clip(ij[:, 0], 0, spec.nx - 1)] = False
    dist = ndimage.distance_transform_edt(seeds) * res
    # The snapping of seeds to vertices costs up to res/sqrt(2); keep the crop generous by that much.
    return MeshGrid(spec, dist <= crop_m + 0.5 * res)


def scatter_dense(values: torch.Tensor, flat_ids: torch.Tensor, shape: tuple[int, int],
                  fill: float = 0.0) -> torch.Tensor:
    """Per-vertex values (Nv, ...) at flat ids ``j*nx+i`` (Nv,) -> (ny, nx, ...) with ``fill`` elsewhere."""
    ny, nx = shape
    out = values.new_full((ny * nx, *values.shape[1:]), fill)
    out = out.index_copy(0, flat_ids.to(values.device), values)
    return out.reshape(ny, nx, *values.shape[1:])


def positional_encoding(p: torch.Tensor, levels: int) -> torch.Tensor:
    """Phi(p) = [p, sin(2^0 pi p), cos(2^0 pi p), ..., sin(2^(L-1) pi p), cos(2^(L-1) pi p)]: (N, 2) -> (N, 4L+2)."""
    out = [p]
    for k in range(levels):
        a = (2.0**k) * math.pi * p
        out += [torch.sin(a), torch.cos(a)]
    return torch.cat(out, dim=1)


def _mlp(sizes: list[int]) -> nn.Sequential:
    layers: list[nn.Module] = []
    for a, b in zip(sizes[:-1], sizes[1:], strict=True):
        layers += [nn.Linear(a, b), nn.ReLU()]
    return nn.Sequential(*layers[:-1])  # no activation after the last linear layer


class HeightMLP(nn.Module):
    """MLP0: d_Phi->128->128->128->128; MLP1: d_Phi+128->128->128->128->1 (4 linear layers each)."""

    def __init__(self, levels: int, hidden: int = 128):
        super().__init__()
        self.levels = levels
        d = 4 * levels + 2
        self.mlp0 = _mlp([d, hidden, hidden, hidden, hidden])
        self.mlp1 = _mlp([d + hidden, hidden, hidden, hidden, 1])
        # Start as the flat initial plane: a random MLP would add a random relief of ~0.1 m.
        nn.init.zeros_(self.mlp1[-1].weight)
        nn.init.zeros_(self.mlp1[-1].bias)

    def forward(self, p: torch.Tensor) -> torch.Tensor:
        """p (N, 2) normalised x, y -> height offsets (N,)."""
        phi = positional_encoding(p, self.levels)
        return self.mlp1(torch.cat([phi, self.mlp0(phi)], dim=1)).squeeze(1)


class RoadMeshModel(nn.Module):
    """Learnable stage-1 parameters over a :class:`MeshGrid`: height MLP, per-vertex RGB and semantic logits."""

    def __init__(self, grid: MeshGrid, num_classes: int, levels: int, hidden: int = 128,
                 z_base: float | np.ndarray = 0.0,
                 generator: torch.Generator | None = None):
        super().__init__()
        self.grid = grid
        g = grid.spec
        flat_valid = torch.from_numpy(grid.valid.reshape(-1).copy())
        vid = torch.nonzero(flat_valid).squeeze(1)
        self.register_buffer("valid_t", torch.from_numpy(grid.valid.copy()))  # (ny, nx) bool crop
        self.register_buffer("vertex_flat_ids", vid)  # compact -> flat id j*nx+i
        lut = torch.full((g.nx * g.ny,), -1, dtype=torch.long)
        lut[vid] = torch.arange(vid.numel())
        self.register_buffer("flat_to_compact", lut)
        i, j = vid % g.nx, vid // g.nx
        sx = max((g.nx - 1) * g.res, 1e-9)
        sy = max((g.ny - 1) * g.res, 1e-9)
        p = torch.stack([2.0 * i.double() * g.res / sx - 1.0, 2.0 * j.double() * g.res / sy - 1.0], 1)
        self.register_buffer("p_norm", p.float())
        base = np.broadcast_to(np.asarray(z_base, dtype=np.float32), (vid.numel(),)).copy()
        self.register_buffer("z_base", torch.from_numpy(base))  # (Nv,) initial surface per kept vertex
        self.height_mlp = HeightMLP(levels, hidden)
        self.rgb = nn.Parameter(0.01 * torch.randn(vid.numel(), 3, generator=generator))
        self.sem = nn.Parameter(torch.zeros(vid.numel(), num_classes))

    @property
    def num_vertices(self) -> int:
        return int(self.vertex_flat_ids.numel())

    def heights(self, compact_ids: torch.Tensor | None = None, chunk: int | None = None) -> torch.Tensor:
        """Heights (M,) of compact vertices ``compact_ids`` (all when None), world z.

        Without autograd the MLP runs in chunks of ``chunk`` vertices (default: 4,096 on a CPU, where a
        chunk's 128-wide activations then stay in cache: measured 2x faster than 65,536 on one core; 262,144
        on a GPU, where fewer launches matter more)."""
        p = self.p_norm if compact_ids is None else self.p_norm[compact_ids]
        b = self.z_base if compact_ids is None else self.z_base[compact_ids]
        chunk = chunk or (4096 if p.device.type == "cpu" else 1 << 18)
        if p.shape[0] <= chunk or torch.is_grad_enabled():
            return self.height_mlp(p) + b
        return torch.cat([self.height_mlp(p[s:s + chunk]) for s in range(0, p.shape[0], chunk)]) + b

    def dense(self, values: torch.Tensor, fill: float = 0.0) -> torch.Tensor:
        """Compact per-vertex values (Nv, ...) -> dense (ny, nx, ...) with ``fill`` off the crop."""
        return scatter_dense(values, self.vertex_flat_ids, self.grid.spec.shape, fill)

    @torch.no_grad()
    def current_heights(self) -> torch.Tensor:
        """(Nv,) heights of every kept vertex (no autograd), computed once per state of the height MLP and
        ``z_base``: the fit reads the whole surface ~7 times between optimiser steps (baking, anchoring,
        visibility, evaluation), each a full MLP pass (~40 % of a small drive's stage 1 without the cache).
        The key is every input's storage and in-place version counter, so any change invalidates it."""
        key = (*((q.data_ptr(), q._version) for q in self.height_mlp.parameters()),
               (self.z_base.data_ptr(), self.z_base._version), (self.p_norm.data_ptr(), self.p_norm._version))
        cached = self.__dict__.get("_heights_cache")
        if cached is None or cached[0] != key:
            cached = (key, self.heights())
            self.__dict__["_heights_cache"] = cached
        return cached[1]

    @torch.no_grad()
    def dense_heights(self, fill: float) -> torch.Tensor:
        """(ny, nx) float32 current heights, ``fill`` off the crop (no autograd)."""
        return self.dense(self.current_heights(), fill=fill).float()

    def field(self, heights: torch.Tensor) -> HeightField:
        """Dense heights (ny, nx) (or flat (ny*nx,)) on this grid and crop, as a height field."""
        g = self.grid.spec
        return HeightField(g.x0, g.y0, g.res, heights.reshape(g.ny, g.nx), self.valid_t)


@torch.no_grad()
def to_road_mesh(model: RoadMeshModel, class_ids: list[int], has_semantics: bool) -> RoadMesh:
    """The trained model as a RoadMesh (CPU tensors): dense heights, per-vertex colours and logits."""
    g = model.grid.spec
    heights = model.dense(model.current_heights(), fill=0.0).float().cpu()
    surf = HeightField(g.x0, g.y0, g.res, heights, torch.from_numpy(model.grid.valid.copy()))
    # copies, never the parameters themselves (a later step would change the mesh)
    return RoadMesh(surf, model.rgb.detach().clamp(0, 1).float().cpu().clone(),
                    model.sem.detach().float().cpu().clone(), list(class_ids), has_semantics)


@dataclass
class RoadMesh:
    """The stage-1 result. surface: heights from the trained MLP (dense (ny, nx): the ray march reads them),
    valid = crop; rgb (Nv, 3) in [0, 1] and sem_logits (Nv, C) per kept vertex, in flat order of the crop
    (:attr:`vertex_ids`): a long drive's grid box holds ~10x the cells of its road, so what is per vertex is
    stored per vertex (dense (ny, nx, ...) arrays given here are taken to the kept vertices);
    class_ids maps channel -> the sequence's class id; observed (ny, nx) bool the vertices whose height was
    measured (None: unknown, e.g. an old mesh file): elsewhere the heights are a guess; samples (N, 3) float32
    the height measurements themselves (triangulated ground points, a subsample of the depth pixels), or
    None: finer than the surface, they measure what it smooths (a pothole's floor); contested (ny, nx) bool
    the vertices whose texture some views disagree with (a vehicle may be in it:
    :mod:`pavemap.mesh.texture_check`), or None: not checked."""

    surface: HeightField
    rgb: torch.Tensor
    sem_logits: torch.Tensor
    class_ids: list[int]
    has_semantics: bool = True
    observed: torch.Tensor | None = None
    samples: np.ndarray | None = None
    contested: torch.Tensor | None = None

    def __post_init__(self) -> None:
        shape = tuple(self.surface.valid.shape)
        n = self.vertex_ids.numel()
        for name in ("rgb", "sem_logits"):
            a = getattr(self, name)
            if a.dim() == 3 and tuple(a.shape[:2]) == shape:
                setattr(self, name, a.reshape(-1, a.shape[-1])[self.vertex_ids.to(a.device)])
            elif a.dim() != 2 or a.shape[0] != n:
                raise ValueError(f"RoadMesh.{name}: expected ({n}, C) per kept vertex or {shape} + (C,), "
                                 f"got {tuple(a.shape)}")

    @property
    def vertex_ids(self) -> torch.Tensor:
        """(Nv,) long sorted flat ids ``j*nx+i`` of the kept vertices (the rows of rgb / sem_logits)."""
        got = self.__dict__.get("_vertex_ids")
        valid = self.surface.valid
        if got is None or got[0] is not valid:
            got = (valid, torch.nonzero(valid.reshape(-1)).squeeze(1))
            self.__dict__["_vertex_ids"] = got
        return got[1]

    def vertex_of(self, flat_ids: torch.Tensor) -> torch.Tensor:
        """Row of each flat cell id (any shape) in the per-vertex arrays; -1 where the cell is not kept."""
        vid = self.vertex_ids.to(flat_ids.device)
        if vid.numel() == 0:
            return torch.full_like(flat_ids, -1)
        k = torch.searchsorted(vid, flat_ids.contiguous()).clamp(max=vid.numel() - 1)
        return torch.where(vid[k] == flat_ids, k, torch.full_like(k, -1))

    def at_hits(self, hit, values: torch.Tensor) -> torch.Tensor:  # noqa: ANN001 - a heightfield RayHits
        """Per-vertex ``values`` (Nv, C) interpolated at ray hits -> (N, C), 0 for misses (a hit's triangle has
        three kept corners)."""
        k = self.vertex_of(hit.vertex_ids)
        rows = dataclasses.replace(hit, vertex_ids=k.clamp(min=0), bary=hit.bary * (k >= 0).to(hit.bary.dtype))
        return rows.interpolate(values)

    def dense(self, values: torch.Tensor, fill: float = 0.0) -> torch.Tensor:
        """Per-vertex values (Nv, ...) -> (ny, nx, ...) with ``fill`` off the crop."""
        return scatter_dense(values, self.vertex_ids, tuple(self.surface.valid.shape), fill)

    def vertex_labels(self) -> torch.Tensor:
        """(Nv,) long class id of each kept vertex's argmax channel; -1 without semantics."""
        if not self.has_semantics or not self.sem_logits.shape[-1]:
            return torch.full((self.vertex_ids.numel(),), -1, dtype=torch.long)
        ids = torch.tensor(self.class_ids, dtype=torch.long, device=self.sem_logits.device)
        return ids[self.sem_logits.argmax(dim=-1)]

    def labels(self) -> torch.Tensor:
        """(ny, nx) long class id of the argmax channel; -1 off the crop or without semantics."""
        return self.dense(self.vertex_labels().to(self.surface.valid.device), fill=-1)

    def road_mask(self, classes: list[SemanticClass]) -> torch.Tensor:
        """(ny, nx) bool: the argmax class is a road class (the whole footprint without semantics)."""
        valid = self.surface.valid
        if not self.has_semantics or not self.class_ids:
            return valid.clone()
        road_ids = {c.id for c in classes if c.road}
        is_road = torch.tensor([cid in road_ids for cid in self.class_ids], dtype=torch.bool)
        return self.dense(is_road[self.sem_logits.argmax(dim=-1).cpu()].to(valid.device), fill=False)

    @property
    def grid(self) -> GridSpec:
        """The vertex grid (``to_dict()`` is what ``grid.json`` and ``metrics.json`` record)."""
        return self.surface.grid
