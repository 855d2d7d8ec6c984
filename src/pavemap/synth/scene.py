"""The World of the synthetic road: its rasters and item tables, cheap numpy queries, and the torch view the
renderer reads (:meth:`World.tensors`). :mod:`pavemap.synth.world` builds one; the defect, clutter, rig and ray
caster modules read it.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field

import numpy as np
import torch

from pavemap.geometry.grid import GridSpec
from pavemap.synth.params import CLASSES, DECOY_ID_OFFSET, WorldParams
from pavemap.synth.surface import bilinear_np, ground_label, markings


@dataclass
class World:
    """A generated world. Arrays are numpy; ``tensors(device)`` gives the torch view the renderer uses."""

    params: WorldParams
    # centreline samples (Nc,) every CENTRELINE_DS metres
    cl_s: np.ndarray
    cl_xy: np.ndarray  # (Nc, 2)
    cl_theta: np.ndarray  # (Nc,)
    cl_kappa: np.ndarray  # (Nc,)
    st_grid: GridSpec
    st: np.ndarray  # (2, ny, nx) float32: s and t of each coarse cell
    height_grid: GridSpec
    height: np.ndarray  # (ny, nx) float32, the exact surface
    shadow_grid: GridSpec
    shadow: np.ndarray  # (ny, nx) float32 in [0, 1], 1 = fully shadowed
    defects: list[dict]  # one dict per defect (see make_defects), id = index
    decoys: list[dict]  # off-road streaks, same layout as cracks
    boxes: np.ndarray  # (Nb, 12) float32: cx, cy, cz, hx, hy, hz, yaw, r, g, b, label, kind
    spheres: np.ndarray  # (Ns, 8) float32: cx, cy, cz, radius, r, g, b, label ; kind via sphere_kind
    sphere_kind: np.ndarray  # (Ns,) int: index into OBJECT_KINDS
    noise_tiles: np.ndarray  # (T, 128, 128) float32 value-noise tiles
    sun: np.ndarray  # (3,) unit vector towards the sun
    # along a given trajectory (params.path): the road's height by place, and the ego path length per sample
    base_grid: GridSpec | None = None
    base: np.ndarray | None = None  # (ny, nx) float32
    cl_ego_u: np.ndarray | None = None  # (Nc,)
    _cache: dict = field(default_factory=dict, repr=False)

    # -- cheap numpy queries (used for placement, poses and tests) ---------------------------
    def height_at(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """(N,) float64 exact surface height at world (x, y) (bilinear on the 0.05 m raster)."""
        return bilinear_np(self.height, self.height_grid, np.asarray(x, float), np.asarray(y, float))

    def st_at(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Road coordinates (s, t) of world points, each (N,) float64."""
        x = np.asarray(x, float)
        y = np.asarray(y, float)
        return (bilinear_np(self.st[0], self.st_grid, x, y), bilinear_np(self.st[1], self.st_grid, x, y))

    def label_at(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """(N,) uint8 ground material class (road, lane_marking, curb, sidewalk, terrain) at world (x, y)."""
        s, t = self.st_at(x, y)
        st = torch.as_tensor(np.stack([s, t]), dtype=torch.float32)
        cov, _ = markings(self.params, st[0], st[1], torch.full_like(st[0], 1e-3))
        lab = ground_label(self.params, st[0], st[1], cov)
        return lab.numpy().astype(np.uint8)

    def xy_of_st(self, s: np.ndarray, t: np.ndarray) -> np.ndarray:
        """(N, 2) world points at road coordinates (s, t) (linear interpolation of the centreline)."""
        s = np.asarray(s, float)
        t = np.asarray(t, float)
        x = np.interp(s, self.cl_s, self.cl_xy[:, 0])
        y = np.interp(s, self.cl_s, self.cl_xy[:, 1])
        th = np.interp(s, self.cl_s, np.unwrap(self.cl_theta))
        return np.stack([x - t * np.sin(th), y + t * np.cos(th)], axis=-1)

    def heading_at(self, s: np.ndarray) -> np.ndarray:
        return np.interp(np.asarray(s, float), self.cl_s, self.cl_theta)

    def tensors(self, device: str | torch.device = "cpu") -> dict:
        """Torch tensors of everything the renderer reads, cached per device."""
        key = str(torch.device(device))
        if key not in self._cache:
            self._cache[key] = _to_tensors(self, torch.device(device))
        return self._cache[key]

    def to_json(self) -> dict:
        p = asdict(self.params)
        p["class_mix"] = list(self.params.class_mix)
        return {
            "generator": "pavemap.synth",
            "params": p,
            "height_grid": self.height_grid.to_dict(),
            "classes": CLASSES,
            "defects": len(self.defects),
            "decoys": len(self.decoys),
            "objects": {"boxes": int(len(self.boxes)), "spheres": int(len(self.spheres))},
            "sun": self.sun.tolist(),
            "instance_encoding": {
                "file": "truth/instances/<camera>/<frame>.png (uint16)",
                "low_14_bits": f"0 none; 1..{DECOY_ID_OFFSET - 1} defect id + 1; "
                f">= {DECOY_ID_OFFSET}: off-road streak (decoy) index + {DECOY_ID_OFFSET}",
                "bit_14": "ground pixel in cast shadow",
            },
        }


def _lookup_grid(g: GridSpec) -> tuple[float, float, float, int, int]:
    """The ``(x0, y0, res, ny, nx)`` tuple :func:`bilinear_t` reads."""
    return (g.x0, g.y0, g.res, g.ny, g.nx)


def _to_tensors(w: World, dev: torch.device) -> dict:
    f32 = torch.float32
    p = w.params

    def ten(a, dtype=f32):
        return torch.as_tensor(np.ascontiguousarray(a), dtype=dtype, device=dev)

    hg, sg, shg = w.height_grid, w.st_grid, w.shadow_grid
    out = {
        "device": dev,
        "params": p,
        "height": ten(w.height).reshape(-1),
        "hgrid": _lookup_grid(hg),
        "st": ten(w.st).reshape(2, -1),
        "stgrid": _lookup_grid(sg),
        "shadow": ten(w.shadow).reshape(-1),
        "shgrid": _lookup_grid(shg) if w.shadow.size > 1 else None,
        "tiles": ten(w.noise_tiles),
        "kappa": ten(w.cl_kappa),
        "cl_s0": float(w.cl_s[0]),
        "sun": ten(w.sun),
        "boxes": ten(w.boxes),
        "spheres": ten(w.spheres),
        "sphere_kind": ten(w.sphere_kind, torch.long),
        "base": None if w.base is None else (ten(w.base).reshape(-1), _lookup_grid(w.base_grid)),
    }
    out["items"] = item_tables(w, dev)
    return out


def item_tables(w: World, dev: torch.device) -> dict:
    """Pack defects + decoys into padded tensors and an s-bin index (2 m bins → up to K items)."""
    items = list(w.defects) + list(w.decoys)
    n = len(items)
    M = 12
    lines = np.zeros((max(n, 1), M, 2), np.float32)
    prm = np.zeros((max(n, 1), 16), np.float32)
    aabb = np.zeros((max(n, 1), 4), np.float32)
    aabb[:] = [1e9, 1e9, -1e9, -1e9]
    for k, d in enumerate(items):
        aabb[k] = d["aabb"]
        decoy = k >= len(w.defects)
        code = (d["id"] + DECOY_ID_OFFSET) if decoy else (d["id"] + 1)
        cls = 4 if decoy else d["cls"]
        if d["kind"] == "line":
            ln = np.asarray(d["line"], np.float32)
            lines[k, : len(ln)] = ln
            lines[k, len(ln):] = ln[-1]
            prm[k, :5] = [cls, code, d["width_m"], d["band_m"], d["darkness"]]
        else:
            prm[k, :16] = [cls, code, d.get("width_m", 0.0), 0.0, d["darkness"], d["centre"][0], d["centre"][1],
                           d["ax"], d["ay"], d["rot"], d["harm"][0], d["harm"][1], d["phase"][0], d["phase"][1],
                           d.get("cell_m", 0.2), float(d["id"] % 997)]
    bin_m = 2.0
    s_min = float(w.cl_s[0]) - 60.0
    nb = int((float(w.cl_s[-1]) + 60.0 - s_min) / bin_m) + 1
    lists: list[list[int]] = [[] for _ in range(nb)]
    for k, d in enumerate(items):
        b0 = int((d["s_range"][0] - 1.0 - s_min) / bin_m)
        b1 = int((d["s_range"][1] + 1.0 - s_min) / bin_m)
        for b in range(max(0, b0), min(nb - 1, b1) + 1):
            lists[b].append(k)
    K = max(1, max((len(x) for x in lists), default=1))
    table = np.full((nb, K), -1, np.int64)
    for b, x in enumerate(lists):
        table[b, : len(x)] = x
    return {
        "n": n, "lines": torch.as_tensor(lines, device=dev), "prm": torch.as_tensor(prm, device=dev),
        "aabb": torch.as_tensor(aabb, device=dev), "table": torch.as_tensor(table, device=dev),
        "bin_m": bin_m, "s_min": s_min,
    }
