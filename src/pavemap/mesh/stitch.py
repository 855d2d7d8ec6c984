"""Segments of a long drive blended into one surface (:mod:`pavemap.mesh.segments`).

Each segment owns the road whose nearest point on its own stretch of path lies inside its core interval of
path length; across a seam the weights of the two segments ramp linearly over ``overlap_m`` and sum to one, so
the blended heights, colours and logits are continuous. Road a later pass revisits is owned by the earlier
pass's segments (trained on both passes' views) through the later pass's frames: one surface, computed once.
A tile's cells no segment owns (the road the end frames look at past the drive) keep a tiny floor weight, so
that the segments whose crop holds them are averaged there.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch
from scipy.spatial import cKDTree

from pavemap.geometry import GridSpec, HeightField
from pavemap.mesh.model import MeshGrid, RoadMesh, dense_polyline

#: weight of a cell in a segment's crop that it does not own (only counts where no segment owns the cell)
FLOOR_WEIGHT = 1e-4
#: a cell counts as owned (for the observed layer, the seam statistics and the samples) above this weight
OWNED = 0.05


def own_path(traj_xy: np.ndarray, path_m: np.ndarray, step_m: float = 0.5) -> tuple[np.ndarray, np.ndarray]:
    """The points of a segment's own stretch of path (M, 2) at most ``step_m`` apart, with their path length
    (M,): traj_xy (F, 2) its own frames' positions in order, path_m (F,) their path length along the drive."""
    pts = dense_polyline(traj_xy, step_m)
    seg = np.linalg.norm(np.diff(traj_xy, axis=0), axis=1) if len(traj_xy) > 1 else np.zeros(0)
    along_own = np.concatenate([[0.0], np.cumsum(seg)])
    run = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(pts, axis=0), axis=1))])
    # Arc length of the dense points along the own polyline, mapped onto the drive's path length.
    return pts, np.interp(run, along_own, path_m) if len(traj_xy) > 1 else np.full(len(pts), path_m[0])


def core_ramp(s: np.ndarray, core: tuple[float, float], overlap_m: float) -> np.ndarray:
    """The share (0..1) of the road at path length ``s`` that a core interval owns: 1 inside, ramping linearly
    to 0 over ``overlap_m`` centred on each end (-inf / inf: no end), so that neighbouring cores sum to one."""
    ov = max(float(overlap_m), 1e-6)
    lo, hi = core
    return np.clip((s - (lo - 0.5 * ov)) / ov, 0.0, 1.0) * np.clip(((hi + 0.5 * ov) - s) / ov, 0.0, 1.0)


def segment_weights(grid: MeshGrid, path_xy: np.ndarray, path_s: np.ndarray, core: tuple[float, float],
                    overlap_m: float, reach_m: float, revisit_xy: np.ndarray | None = None,
                    revisit_at: np.ndarray | None = None, revisit_share: np.ndarray | None = None) -> np.ndarray:
    """(ny, nx) float32 blending weights of a segment's tile on its grid.

    path_xy (M, 2), path_s (M,): its own stretch of path (:func:`own_path`); core: the path-length interval it
    owns (-inf / inf at the drive's ends); a cell's path coordinate is that of the nearest path point, and only
    cells within ``reach_m`` of the path are owned (farther cells belong to another pass). revisit_xy (R, 2),
    revisit_at (R,), revisit_share (R,): frames of another pass that revisits this segment's road, the path
    length of the own road beside each and the share of their pass's road this segment owns
    (:class:`pavemap.mesh.segments.SegmentPlan`): cells within ``reach_m`` of them are owned as the own road
    beside them is, times the share."""
    xy = grid.vertex_xy()
    ov = max(float(overlap_m), grid.spec.res)
    d, s = _along_path(xy, path_xy, path_s)
    w = np.where(d <= reach_m, core_ramp(s, core, ov), 0.0)
    keep = None if revisit_share is None else np.asarray(revisit_share) > 0
    if keep is not None and keep.any():
        rxy = np.asarray(revisit_xy, np.float64)[keep]
        rw = core_ramp(np.asarray(revisit_at, np.float64)[keep], core, ov) * np.asarray(revisit_share)[keep]
        d2, w2 = _along_path(xy, rxy, rw)
        w = np.maximum(w, np.where(d2 <= reach_m, np.clip(w2, 0.0, 1.0), 0.0))
    w = w + FLOOR_WEIGHT
    out = np.zeros(grid.valid.shape, np.float32)
    out.reshape(-1)[np.flatnonzero(grid.valid.reshape(-1))] = w
    return out


def _along_path(xy: np.ndarray, path_xy: np.ndarray, values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For points xy (N, 2): the distance to the nearest of the path's points path_xy (M, 2) and ``values``
    (M,) there, carried linearly along the path's local direction (continuous, not in steps of the points'
    spacing)."""
    d, k = cKDTree(path_xy).query(xy)
    v = np.asarray(values, np.float64)[k]
    if len(path_xy) > 1:
        step = np.gradient(path_xy, axis=0)
        length = np.maximum(np.linalg.norm(step, axis=1), 1e-9)
        along = ((xy - path_xy[k]) * (step[k] / length[k, None])).sum(1) / length[k]
        v = v + np.clip(along, -1.0, 1.0) * np.gradient(np.asarray(values, np.float64))[k]
    return d, v


@dataclass
class Stitcher:
    """Weighted sums of the tiles on the drive's grid ``spec``; :meth:`add` a tile, then :meth:`mesh`.

    The sums exist only for the cells some tile holds (``cells``, sorted flat ids, grown as tiles come): a long
    drive's grid box holds ~10x the cells its road does (KITTI-00: 29 M cells, 3.2 M under the road's crop),
    so they are stored per held cell, not per box cell."""

    spec: GridSpec
    channels: int = -1  # semantic channels, set by the first tile
    sums: dict[str, np.ndarray] = field(default_factory=dict)
    samples: list[np.ndarray] = field(default_factory=list)
    cells: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    texture_checked: bool = False  # some tile has the texture check's layer (else the drive has none either)

    def _alloc(self, channels: int) -> None:
        self.channels = channels
        self.sums = {"w": np.zeros(0, np.float32), "h": np.zeros(0, np.float64), "rgb": np.zeros((0, 3), np.float32),
                     "sem": np.zeros((0, channels), np.float32), "observed": np.zeros(0, bool),
                     "contested": np.zeros(0, bool),
                     "owner": np.zeros(0, np.int32)}  # the last tile (number, from 1) that owned the cell

    def _rows(self, g: GridSpec, tile_ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(inside (M,) bool, rows (inside.sum(),) int64): which tile vertices (flat ids on tile grid ``g``) lie
        on the drive's grid, and their rows in the sums (cells not held yet are added, zero)."""
        ox = int(round((g.x0 - self.spec.x0) / self.spec.res))
        oy = int(round((g.y0 - self.spec.y0) / self.spec.res))
        tj, ti = np.divmod(tile_ids, g.nx)
        gi, gj = ti + ox, tj + oy
        inside = (gi >= 0) & (gi < self.spec.nx) & (gj >= 0) & (gj < self.spec.ny)
        flat = gj[inside] * self.spec.nx + gi[inside]
        new = np.setdiff1d(flat, self.cells, assume_unique=True)
        if new.size:
            merged = np.union1d(self.cells, new)
            at = np.searchsorted(merged, self.cells)
            for key, a in self.sums.items():
                grown = np.zeros((len(merged), *a.shape[1:]), a.dtype)
                grown[at] = a
                self.sums[key] = grown
            self.cells = merged
        return inside, np.searchsorted(self.cells, flat)

    def add(self, tile: RoadMesh, weight: np.ndarray, number: int = 0, seam_with: int | None = None) -> dict:
        """Blend tile ``number`` (from 1) with ``weight`` (its (ny, nx) :func:`segment_weights`) into the sums;
        returns how it agrees with the segments added before it where both own the road and measured its height:
        across its seam with tile ``seam_with`` (the segment before it along the path, where their cores meet)
        ``{"seam_cells", "seam_median_abs_m", "seam_median_m"}``, and with other passes' segments (crossings,
        the ends of a revisit) ``{"pass_cells", "pass_median_abs_m"}`` (None without such cells)."""
        s = tile.surface
        if abs(s.res - self.spec.res) > 1e-9:
            raise ValueError(f"tile resolution {s.res} differs from the drive's {self.spec.res}")
        if not self.sums:
            self._alloc(int(tile.sem_logits.shape[-1]))
        tv = tile.vertex_ids.cpu().numpy()
        found, k = self._rows(s.grid, tv)  # vertices off the drive's grid are left out, as any window would
        stats = {"seam_cells": 0, "seam_median_abs_m": None, "seam_median_m": None, "pass_cells": 0,
                 "pass_median_abs_m": None}
        if not found.any():
            return stats
        ids = tv[found]
        w = weight.reshape(-1)[ids].astype(np.float32)
        h = s.heights.detach().cpu().numpy().reshape(-1)[ids].astype(np.float64)
        observed = (np.ones(len(ids), bool) if tile.observed is None
                    else tile.observed.cpu().numpy().reshape(-1)[ids].astype(bool))
        sums = self.sums
        both = (sums["w"][k] > OWNED) & sums["observed"][k] & observed & (w > OWNED)
        seam = both & (sums["owner"][k] == (seam_with or -1))
        for name, cells in (("seam", seam), ("pass", both & ~seam)):
            if cells.any():
                diff = h[cells] - sums["h"][k][cells] / sums["w"][k][cells]
                stats.update({f"{name}_cells": int(cells.sum()),
                              f"{name}_median_abs_m": round(float(np.median(np.abs(diff))), 5)})
                if name == "seam":
                    stats["seam_median_m"] = round(float(np.median(diff)), 5)
        rows = np.flatnonzero(found)  # the tile's per-vertex rows of these cells
        sums["w"][k] += w  # k holds each cell once: a tile's vertices are distinct cells
        sums["h"][k] += w * h
        sums["rgb"][k] += w[:, None] * tile.rgb.cpu().numpy()[rows]
        sums["sem"][k] += w[:, None] * tile.sem_logits.cpu().numpy()[rows]
        sums["observed"][k] |= observed & (w > OWNED)
        if tile.contested is not None:
            sums["contested"][k] |= tile.contested.cpu().numpy().reshape(-1)[ids].astype(bool) & (w > OWNED)
            self.texture_checked = True
        sums["owner"][k] = np.where(w > OWNED, number, sums["owner"][k])
        if tile.samples is not None and len(tile.samples):
            self.samples.append(_owned_samples(tile.samples, s.grid, weight))
        return stats

    def mesh(self, class_ids: list[int], has_semantics: bool) -> RoadMesh:
        """The blended surface: every cell some tile holds, heights / colours / logits their weighted means.
        Consumes the sums."""
        if not self.sums:
            raise ValueError("no tile was added")
        sums, self.sums = self.sums, {}
        w = sums.pop("w")
        sums.pop("owner")
        k = np.flatnonzero(w > 0)
        inv = 1.0 / w[k]
        cells = self.cells[k]  # sorted: the mesh's vertex order
        g = self.spec
        n = g.nx * g.ny
        h = np.zeros(n, np.float32)
        h[cells] = (sums.pop("h")[k] * inv).astype(np.float32)
        valid = np.zeros(n, bool)
        valid[cells] = True
        observed = np.zeros(n, bool)
        observed[cells] = sums.pop("observed")[k]
        contested = np.zeros(n, bool)
        contested[cells] = sums.pop("contested")[k]
        contested_t = torch.from_numpy(contested.reshape(g.shape)) if self.texture_checked else None
        rgb = sums.pop("rgb")[k] * inv[:, None]
        sem = sums.pop("sem")[k] * inv[:, None]
        surf = HeightField(g.x0, g.y0, g.res, torch.from_numpy(h.reshape(g.shape)),
                           torch.from_numpy(valid.reshape(g.shape)))
        samples = np.concatenate(self.samples).astype(np.float32) if self.samples else None
        return RoadMesh(surf, torch.from_numpy(rgb), torch.from_numpy(sem), list(class_ids), has_semantics,
                        torch.from_numpy(observed.reshape(g.shape)), samples, contested_t)


def _owned_samples(samples: np.ndarray, g: GridSpec, weight: np.ndarray) -> np.ndarray:
    """The height measurements (N, 3) of a tile on the road it owns by at least half (each measurement then
    enters the drive once, except where two passes share the road)."""
    i = np.clip(np.rint((samples[:, 0] - g.x0) / g.res).astype(np.int64), 0, g.nx - 1)
    j = np.clip(np.rint((samples[:, 1] - g.y0) / g.res).astype(np.int64), 0, g.ny - 1)
    return samples[weight[j, i] >= 0.5]
