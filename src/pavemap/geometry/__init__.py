"""Shared geometry: pinhole rays/projection and the height-field surface with exact ray casting.

The names below load on first use, so that a light module of this package (``chainage``, ``grid``) does not
import torch with the package (the CLI starts without torch).
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:  # pragma: no cover
    from pavemap.geometry.camera import pixel_grid, pixel_rays, project
    from pavemap.geometry.grid import GridSpec
    from pavemap.geometry.heightfield import (
        HeightField,
        HitCells,
        RayHit,
        SurfaceBounds,
        find_hits,
        hits_to_rayhit,
        intersect_rays,
        surface_bounds,
    )

_LAZY = {
    **dict.fromkeys(("pixel_grid", "pixel_rays", "project"), "pavemap.geometry.camera"),
    "GridSpec": "pavemap.geometry.grid",
    **dict.fromkeys(("HeightField", "HitCells", "RayHit", "SurfaceBounds", "find_hits", "hits_to_rayhit",
                     "intersect_rays", "surface_bounds"), "pavemap.geometry.heightfield"),
}


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


__all__ = [
    "HeightField", "HitCells", "RayHit", "SurfaceBounds", "find_hits", "hits_to_rayhit", "intersect_rays",
    "surface_bounds",
    "GridSpec", "pixel_grid", "pixel_rays", "project",
]
