"""Shared geometry: pinhole rays/projection and the height-field surface with exact ray casting."""

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

__all__ = [
    "HeightField", "HitCells", "RayHit", "SurfaceBounds", "find_hits", "hits_to_rayhit", "intersect_rays",
    "surface_bounds",
    "GridSpec", "pixel_grid", "pixel_rays", "project",
]
