"""The one regular grid of the project: height field, mesh vertices, fusion maps, rasters, truth files.

Cell / vertex ``(row j, col i)`` sits at ``(x0 + i*res, y0 + j*res)`` in world metres: rows go +y,
columns go +x. Every module that stores or passes a grid uses :class:`GridSpec`, and every file
that records one writes :meth:`GridSpec.to_dict` (``x0, y0, res, nx, ny`` plus ``shape`` for
readers that want ``(ny, nx)``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np


@dataclass(frozen=True)
class GridSpec:
    """A regular grid: origin ``(x0, y0)`` of cell (0, 0), step ``res`` metres, ``nx`` columns, ``ny`` rows."""

    x0: float
    y0: float
    res: float
    nx: int
    ny: int

    def __post_init__(self) -> None:
        if not (math.isfinite(self.x0) and math.isfinite(self.y0)):
            raise ValueError(f"grid origin must be finite, got ({self.x0}, {self.y0})")
        if not (math.isfinite(self.res) and self.res > 0):
            raise ValueError(f"grid res must be a positive number, got {self.res}")
        if int(self.nx) < 1 or int(self.ny) < 1:
            raise ValueError(f"grid size must be at least 1 x 1, got nx={self.nx}, ny={self.ny}")
        object.__setattr__(self, "x0", float(self.x0))
        object.__setattr__(self, "y0", float(self.y0))
        object.__setattr__(self, "res", float(self.res))
        object.__setattr__(self, "nx", int(self.nx))
        object.__setattr__(self, "ny", int(self.ny))

    # ------------------------------------------------------------------ construction
    @classmethod
    def covering(cls, lo: tuple[float, float], hi: tuple[float, float], res: float, snap: bool = True) -> GridSpec:
        """The grid whose nodes cover the box ``lo..hi`` (origin snapped to multiples of ``res``)."""
        lo_a = np.asarray(lo, dtype=np.float64)
        hi_a = np.asarray(hi, dtype=np.float64)
        if snap:
            lo_a = np.floor(lo_a / res) * res
            hi_a = np.ceil(hi_a / res) * res
        nx = int(round((hi_a[0] - lo_a[0]) / res)) + 1
        ny = int(round((hi_a[1] - lo_a[1]) / res)) + 1
        return cls(float(lo_a[0]), float(lo_a[1]), float(res), max(nx, 1), max(ny, 1))

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> GridSpec:
        """Read ``{x0, y0, res, nx, ny}``; older files' ``shape: [ny, nx]``, ``x_min`` and ``resolution`` too."""
        x0 = d.get("x0", d.get("x_min"))
        y0 = d.get("y0", d.get("y_min"))
        res = d.get("res", d.get("resolution"))
        if "nx" in d and "ny" in d:
            nx, ny = d["nx"], d["ny"]
        elif "shape" in d:
            ny, nx = d["shape"][-2], d["shape"][-1]
        else:
            raise ValueError("grid needs nx and ny (or shape)")
        if x0 is None or y0 is None or res is None:
            raise ValueError("grid needs x0, y0 and res")
        return cls(float(x0), float(y0), float(res), int(nx), int(ny))

    def to_dict(self) -> dict[str, Any]:
        return {"x0": self.x0, "y0": self.y0, "res": self.res, "nx": self.nx, "ny": self.ny,
                "shape": [self.ny, self.nx]}

    # ------------------------------------------------------------------ geometry
    @property
    def shape(self) -> tuple[int, int]:
        """``(ny, nx)``: the numpy shape of a raster on this grid."""
        return (self.ny, self.nx)

    @property
    def x1(self) -> float:
        """x of the last column."""
        return self.x0 + (self.nx - 1) * self.res

    @property
    def y1(self) -> float:
        """y of the last row."""
        return self.y0 + (self.ny - 1) * self.res

    @property
    def bounds(self) -> tuple[float, float, float, float]:
        """``(xmin, ymin, xmax, ymax)`` of the cells' outer edges (nodes are cell centres)."""
        h = 0.5 * self.res
        return (self.x0 - h, self.y0 - h, self.x1 + h, self.y1 + h)

    def xs(self) -> np.ndarray:
        """(nx,) float64 column x coordinates."""
        return self.x0 + self.res * np.arange(self.nx, dtype=np.float64)

    def ys(self) -> np.ndarray:
        """(ny,) float64 row y coordinates."""
        return self.y0 + self.res * np.arange(self.ny, dtype=np.float64)

    def centres(self) -> tuple[np.ndarray, np.ndarray]:
        """Two (ny, nx) float64 arrays: x and y of every node."""
        return np.meshgrid(self.xs(), self.ys())

    def to_cell(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Nearest (col i, row j) of world points (int64, may lie outside the grid)."""
        i = np.rint((np.asarray(x, dtype=np.float64) - self.x0) / self.res).astype(np.int64)
        j = np.rint((np.asarray(y, dtype=np.float64) - self.y0) / self.res).astype(np.int64)
        return i, j

    def contains(self, i: np.ndarray, j: np.ndarray) -> np.ndarray:
        """Bool mask of cells inside the grid."""
        return (i >= 0) & (i < self.nx) & (j >= 0) & (j < self.ny)

    def resampled(self, res: float) -> GridSpec:
        """The grid over the same area with another step."""
        return GridSpec.covering((self.x0, self.y0), (self.x1, self.y1), res, snap=False)
