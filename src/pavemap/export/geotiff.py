"""BEV defect probability maps as a cloud-optimised GeoTIFF.

Band 1 is the total defect probability, bands 2-5 the per-class probabilities (D00, D10, D20,
D40), float32 in [0, 1].

Our BEV arrays have row 0 at the smallest y (rows go +y); a raster is stored north-up (row 0 at
the top), so rows are flipped and the transform has a negative y step.

- Without a geo origin the transform maps pixels to world x, y metres (no CRS: a local
  engineering frame, stated in the tags).
- With a geo origin the CRS is the azimuthal equidistant projection centred on the origin
  (see ``geo.py``) and the raster is north-up in east/north metres. When world +x is not east
  (heading != 90) the map is resampled (bilinear) onto a north-up east/north grid of the same
  resolution, because rotated geotransforms are poorly supported by GIS tools.
"""

from __future__ import annotations

import math
import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import rasterio
import rasterio.enums
from rasterio.transform import Affine
from scipy import ndimage

from pavemap.errors import PavemapError
from pavemap.export.geo import local_tangent, origin_to_dict
from pavemap.geometry.grid import GridSpec
from pavemap.io.atomic import atomic_path
from pavemap.types import DEFECT_CODES, DEFECT_NAMES, GeoOrigin

BAND_DESCRIPTIONS = ("total defect probability",
                     *(f"{c} {DEFECT_NAMES[c]} probability" for c in DEFECT_CODES))


def as_grid(grid: GridSpec | Mapping[str, Any], what: str = "grid") -> GridSpec:
    """A GridSpec, or a grid read back from a file (``GridSpec.from_dict``); PavemapError naming ``what``."""
    if isinstance(grid, GridSpec):
        return grid
    try:
        return GridSpec.from_dict(dict(grid))
    except (KeyError, TypeError, ValueError, IndexError) as e:
        raise PavemapError(f"{what}: needs x0, y0, res > 0 and nx, ny >= 1 (or shape [H, W]) ({e})") from None


def check_grid(grid: GridSpec | Mapping[str, Any], shape: tuple[int, ...] | None = None,
               what: str = "grid") -> tuple[float, float, float, int, int]:
    """Validate a grid (and an array shape on it); returns (x0, y0, res, H, W)."""
    g = as_grid(grid, what)
    x0, y0, res, (H, W) = g.x0, g.y0, g.res, g.shape
    if shape is not None and tuple(shape[-2:]) != (H, W):
        raise PavemapError(f"{what}: array shape {tuple(shape)} does not match grid shape {[H, W]}")
    return x0, y0, res, H, W


def stack_bands(prob_map: np.ndarray, class_maps: np.ndarray, grid: GridSpec) -> np.ndarray:
    """(5, H, W) float32: total then per class, rows going +y (the BEV convention)."""
    prob_map = np.asarray(prob_map, dtype=np.float32)
    class_maps = np.asarray(class_maps, dtype=np.float32)
    if prob_map.ndim != 2:
        raise PavemapError(f"prob_map must be (H, W), got shape {prob_map.shape}")
    if class_maps.shape != (len(DEFECT_CODES), *prob_map.shape):
        raise PavemapError(f"class_maps must be ({len(DEFECT_CODES)}, H, W) = "
                           f"({len(DEFECT_CODES)}, {prob_map.shape[0]}, {prob_map.shape[1]}), "
                           f"got {class_maps.shape}")
    check_grid(grid, prob_map.shape, "BEV map grid")
    bands = np.concatenate([prob_map[None], class_maps], axis=0)
    return np.nan_to_num(bands, nan=0.0, posinf=1.0, neginf=0.0)


def north_up(bands: np.ndarray, grid: GridSpec, geo_origin: GeoOrigin | None = None) -> tuple[np.ndarray, Affine]:
    """Rasterise BEV bands north-up.

    ``bands`` (B, H, W) rows going +y. Returns (B, H', W') with row 0 at the top and the affine
    transform (pixel corner convention) to world metres (no origin) or to the origin's
    east/north metres (with origin).
    """
    x0, y0, res, H, W = check_grid(grid, bands.shape, "BEV map grid")
    lt = local_tangent(geo_origin) if geo_origin is not None else None
    if lt is None or lt.axis_aligned:
        # cell (row r, col c) centre is (x0 + c res, y0 + r res); the top raster row is r = H-1
        out = np.ascontiguousarray(bands[:, ::-1, :])
        return out, Affine(res, 0.0, x0 - res / 2, 0.0, -res, y0 + (H - 1) * res + res / 2)
    # rotated frame: bound the cell centres in east/north, then sample the source bilinearly
    cx = x0 + np.array([0, W - 1, 0, W - 1], dtype=np.float64) * res
    cy = y0 + np.array([0, 0, H - 1, H - 1], dtype=np.float64) * res
    e, n = lt.world_to_enu(cx, cy)
    e0, n_top = float(e.min()), float(n.max())
    We = int(math.floor((e.max() - e0) / res + 1e-9)) + 1
    Hn = int(math.floor((n_top - n.min()) / res + 1e-9)) + 1
    ee = e0 + np.arange(We, dtype=np.float64) * res
    nn = n_top - np.arange(Hn, dtype=np.float64) * res
    E, N = np.meshgrid(ee, nn)  # (Hn, We)
    X, Y = lt.enu_to_world(E, N)
    coords = np.stack([(Y - y0) / res, (X - x0) / res])  # fractional (row, col) in the source
    out = np.stack([ndimage.map_coordinates(b, coords, order=1, mode="constant", cval=0.0, prefilter=False)
                    for b in bands]).astype(np.float32)
    return out, Affine(res, 0.0, e0 - res / 2, 0.0, -res, n_top + res / 2)


def write_geotiff(path: str | os.PathLike, prob_map: np.ndarray, class_maps: np.ndarray, grid: GridSpec,
                  geo_origin: GeoOrigin | None = None) -> Path:
    """Write ``defect_map.tif`` (COG when GDAL has the driver, else tiled GTiff with overviews).

    ``prob_map`` (H, W) float, ``class_maps`` (4, H, W) float, ``grid`` a GridSpec.
    """
    bands = stack_bands(prob_map, class_maps, grid)
    data, transform = north_up(bands, grid, geo_origin)
    _, h, w = data.shape
    crs = local_tangent(geo_origin).crs.to_wkt() if geo_origin is not None else None
    with rasterio.Env() as env:
        has_cog = "COG" in env.drivers()
    profile = {"width": w, "height": h, "count": data.shape[0], "dtype": "float32", "transform": transform,
               "compress": "DEFLATE", "predictor": 3}
    if crs is not None:
        profile["crs"] = crs
    if has_cog:
        profile.update(driver="COG", blocksize=256, overviews="AUTO", resampling="average")
    else:
        profile.update(driver="GTiff", tiled=True, blockxsize=256, blockysize=256)
    x0, y0, res, H, W = check_grid(grid)
    tags = {
        "PAVEMAP_BANDS": "; ".join(BAND_DESCRIPTIONS),
        "PAVEMAP_FRAME": ("east/north metres of the azimuthal equidistant projection at the geo origin"
                          if geo_origin is not None else "local world frame x, y metres (SPEC §0), no CRS"),
        "PAVEMAP_GRID": f"x0={x0} y0={y0} res={res} shape={H}x{W} (cell centres, rows going +y)",
        "PAVEMAP_GEO_ORIGIN": str(origin_to_dict(geo_origin)),
    }
    final = Path(path)
    with atomic_path(final) as tmp:
        try:
            with rasterio.open(tmp, "w", **profile) as ds:
                ds.write(data)
                for i, d in enumerate(BAND_DESCRIPTIONS, start=1):
                    ds.set_band_description(i, d)
                ds.update_tags(**tags)
                if not has_cog:
                    factors = [f for f in (2, 4, 8, 16) if min(h, w) // f >= 64]
                    if factors:
                        ds.build_overviews(factors, rasterio.enums.Resampling.average)
        except rasterio.errors.RasterioError as e:
            raise PavemapError(f"{final}: could not write the GeoTIFF ({e})") from None
    return final


__all__ = ["BAND_DESCRIPTIONS", "check_grid", "north_up", "stack_bands", "write_geotiff"]
