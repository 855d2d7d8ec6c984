"""The synthetic truth surface of a sequence: ``truth/height.npy`` on the grid of ``truth/height.json`` (SPEC §6).

``height.json`` is a :meth:`pavemap.geometry.GridSpec.to_dict` (older files' ``x_min``, ``y_min``,
``resolution``, ``shape`` keys are read too); ``height[j, i]`` is the surface at ``(x0 + i*res, y0 + j*res)``.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import torch

from pavemap.errors import SequenceError
from pavemap.geometry.grid import GridSpec
from pavemap.geometry.heightfield import HeightField
from pavemap.io.atomic import atomic_path, atomic_write_json

HEIGHT_NPY = Path("truth") / "height.npy"
HEIGHT_JSON = Path("truth") / "height.json"


def has_truth_height(seq_root: str | os.PathLike | None) -> bool:
    """Whether the sequence at ``seq_root`` carries a true surface (synthetic sequences do)."""
    return seq_root is not None and (Path(seq_root) / HEIGHT_NPY).is_file()


def read_truth_grid(seq_root: str | os.PathLike, extent: tuple[float, float, float, float] | None = None
                    ) -> tuple[np.ndarray, GridSpec]:
    """(ny, nx) float32 true heights (NaN where the world has none) and their grid; with ``extent``
    (x_min, x_max, y_min, y_max) only the window of the grid that covers it (at least 2 x 2 cells, clamped
    into the grid), read from a memory map: a kilometres-long drive's truth is hundreds of MB."""
    root = Path(seq_root)
    meta_f, arr_f = root / HEIGHT_JSON, root / HEIGHT_NPY
    for f in (meta_f, arr_f):
        if not f.is_file():
            raise SequenceError(f, "height truth not found")
    try:
        grid = GridSpec.from_dict(json.loads(meta_f.read_text(encoding="utf-8")))
    except (json.JSONDecodeError, AttributeError, KeyError, TypeError, ValueError) as e:
        raise SequenceError(meta_f, f"needs x0, y0, res, nx, ny ({e})") from None
    try:
        a = np.load(arr_f, mmap_mode="r")
    except (OSError, ValueError) as e:
        raise SequenceError(arr_f, f"cannot read ({e})") from None
    if a.ndim != 2 or tuple(a.shape) != grid.shape:
        raise SequenceError(arr_f, f"shape {list(a.shape)} does not match height.json shape {list(grid.shape)}")
    if extent is None:
        return np.asarray(a, dtype=np.float32).copy(), grid
    (i0, i1), (j0, j1) = (_window(lo, hi, o, grid.res, n) for lo, hi, o, n in
                          ((extent[0], extent[1], grid.x0, grid.nx), (extent[2], extent[3], grid.y0, grid.ny)))
    win = GridSpec(grid.x0 + i0 * grid.res, grid.y0 + j0 * grid.res, grid.res, i1 - i0, j1 - j0)
    return np.asarray(a[j0:j1, i0:i1], dtype=np.float32).copy(), win


def _window(lo: float, hi: float, origin: float, res: float, n: int) -> tuple[int, int]:
    """Index range [a, b) of grid lines at ``origin + k res`` (k < n) covering [lo, hi], one line of margin."""
    a = int(np.clip(np.floor((lo - origin) / res) - 1, 0, max(n - 2, 0)))
    b = int(np.clip(np.ceil((hi - origin) / res) + 2, a + min(2, n), n))
    return a, b


def read_truth_height(seq_root: str | os.PathLike, extent: tuple[float, float, float, float] | None = None
                      ) -> HeightField:
    """The true surface (or its window covering ``extent``, see :func:`read_truth_grid`) as a height field;
    non-finite heights become invalid vertices."""
    a, g = read_truth_grid(seq_root, extent)
    valid = np.isfinite(a)
    a[~valid] = 0.0
    return HeightField(g.x0, g.y0, g.res, torch.from_numpy(a), torch.from_numpy(valid))


def write_truth_height(seq_root: str | os.PathLike, heights: np.ndarray, grid: GridSpec,
                       extra: dict | None = None) -> None:
    """Write ``truth/height.npy`` (float32) and ``truth/height.json`` (the grid, plus ``extra`` keys)."""
    root = Path(seq_root)
    a = np.asarray(heights, dtype=np.float32)
    if a.shape != grid.shape:
        raise ValueError(f"heights {a.shape} do not match the grid {grid.shape}")
    (root / HEIGHT_NPY).parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(root / HEIGHT_NPY) as tmp, open(tmp, "wb") as f:
        np.save(f, a)
    atomic_write_json(root / HEIGHT_JSON, {**grid.to_dict(), **(extra or {})})


__all__ = ["HEIGHT_JSON", "HEIGHT_NPY", "has_truth_height", "read_truth_grid", "read_truth_height",
           "write_truth_height"]
