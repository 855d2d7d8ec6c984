"""Shared geometry: pinhole rays/projection and the height-field surface with exact ray casting."""

from pavemap.geometry.camera import pixel_grid, pixel_rays, project
from pavemap.geometry.heightfield import (
    HeightField,
    HitCells,
    RayHit,
    find_hits,
    hits_to_rayhit,
    intersect_rays,
)

__all__ = [
    "HeightField", "HitCells", "RayHit", "find_hits", "hits_to_rayhit", "intersect_rays",
    "pixel_grid", "pixel_rays", "project",
]
