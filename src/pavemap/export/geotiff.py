"""BEV defect probability maps as a cloud-optimised GeoTIFF.

Band 1 is the total defect probability, bands 2-5 the per-class probabilities (D00, D10, D20,
D40), float32 in [0, 1].

Our BEV arrays have row 0 at the smallest y (rows go +y); a raster is stored north-up (row 0 at
the top). Cells outside the surveyed area (:mod:`pavemap.geo.coverage`) are ``NODATA`` (-9999),
so "not looked at" never reads as "no defect".

- With a geo origin the raster is in the drive's UTM zone (or the CRS asked for,
  :func:`pavemap.geo.crs.output_crs`), north-up: the BEV map is resampled (bilinear) onto it, with
  pixels of about the map's resolution. Over a survey of a few km the world -> UTM mapping is
  affine to a millimetre, so the resampling uses that affine (checked; else exact per pixel).
- Without one the transform maps pixels to world x, y metres and the CRS is the local engineering
  CRS (``ENGCRS``) of :func:`pavemap.geo.crs.local_crs`: never read as longitude / latitude.
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
from pyproj import CRS, Transformer
from rasterio.shutil import copy as rio_copy
from rasterio.transform import Affine
from rasterio.windows import Window
from scipy import ndimage

from pavemap.errors import PavemapError
from pavemap.geo.crs import crs_label, output_crs
from pavemap.geo.tangent import WGS84, local_tangent, origin_to_dict
from pavemap.geometry.grid import GridSpec
from pavemap.io.atomic import atomic_path
from pavemap.types import DEFECT_CODES, DEFECT_NAMES, GeoOrigin

NODATA = -9999.0  # outside the surveyed area; probabilities are in [0, 1]
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


ROWS = 256  # raster rows written at a time: the writer's memory is a strip, not the map
GDAL_CACHE_MB = 64  # GDAL's block cache while writing (its default, 5 % of RAM, would hold the whole map)


def check_bands(prob_map: np.ndarray, class_maps: np.ndarray, grid: GridSpec) -> list[np.ndarray]:
    """The five bands (total, then per class) as (H, W) arrays on ``grid`` (rows going +y), uncopied."""
    prob_map = np.asarray(prob_map)
    class_maps = np.asarray(class_maps)
    if prob_map.ndim != 2:
        raise PavemapError(f"prob_map must be (H, W), got shape {prob_map.shape}")
    if class_maps.shape != (len(DEFECT_CODES), *prob_map.shape):
        raise PavemapError(f"class_maps must be ({len(DEFECT_CODES)}, H, W) = "
                           f"({len(DEFECT_CODES)}, {prob_map.shape[0]}, {prob_map.shape[1]}), "
                           f"got {class_maps.shape}")
    check_grid(grid, prob_map.shape, "BEV map grid")
    return [prob_map, *class_maps]


def _clean(a: np.ndarray) -> np.ndarray:
    return np.nan_to_num(np.asarray(a, dtype=np.float32), nan=0.0, posinf=1.0, neginf=0.0)


def _local_strips(bands: list[np.ndarray], valid: np.ndarray, grid: GridSpec):  # noqa: ANN202
    """Local frame: raster rows from the top (our rows go +y), ``ROWS`` at a time: (row0, (B, h, W))."""
    H = grid.ny
    for r0 in range(0, H, ROWS):
        rows = slice(H - min(r0 + ROWS, H), H - r0)  # the strip's grid rows, bottom-up
        ok = valid[rows][::-1]
        yield r0, np.stack([np.where(ok, _clean(b[rows][::-1]), NODATA) for b in bands]).astype(np.float32)


def _local_transform(grid: GridSpec) -> Affine:
    """Pixel-corner affine of the north-up local raster to world x, y metres."""
    return Affine(grid.res, 0.0, grid.x0 - grid.res / 2, 0.0, -grid.res, grid.y1 + grid.res / 2)


def _world_affine(lt, to_crs: Transformer, grid: GridSpec) -> tuple[np.ndarray, float]:  # noqa: ANN001
    """(3, 2) least-squares affine from target-CRS (e, n, 1) to world (x, y) over the grid, and its
    largest error in metres on the control points (a UTM zone over a few km is affine to a millimetre)."""
    xmin, ymin, xmax, ymax = grid.bounds
    X, Y = np.meshgrid(np.linspace(xmin, xmax, 7), np.linspace(ymin, ymax, 7))
    lon, lat = lt.to_lonlat(X.ravel(), Y.ravel())
    e, n = to_crs.transform(lon, lat)
    A = np.column_stack([e, n, np.ones(len(e))])
    W = np.column_stack([X.ravel(), Y.ravel()])
    coef, *_ = np.linalg.lstsq(A, W, rcond=None)
    return coef, float(np.max(np.linalg.norm(A @ coef - W, axis=1)))


def _crs_raster(grid: GridSpec, origin: GeoOrigin, crs: CRS):  # noqa: ANN202
    """The north-up raster of ``crs`` covering ``grid``: (height, width, transform, sampler), where the sampler
    maps raster rows r0..r0+h to the grid's fractional (row, col); pixels of ``grid.res`` metres (in the CRS's
    own unit: aligned with other data of that CRS)."""
    lt = local_tangent(origin)
    fwd = Transformer.from_crs(WGS84, crs, always_xy=True)
    coef, err = _world_affine(lt, fwd, grid)
    inv = Transformer.from_crs(crs, WGS84, always_xy=True)
    xmin, ymin, xmax, ymax = grid.bounds
    lon, lat = lt.to_lonlat(np.array([xmin, xmax, xmin, xmax]), np.array([ymin, ymin, ymax, ymax]))
    e, n = (np.asarray(v) for v in fwd.transform(lon, lat))
    step = grid.res / float(crs.axis_info[0].unit_conversion_factor or 1.0)
    e0, n_top = math.floor(e.min() / step) * step, math.ceil(n.max() / step) * step
    Wo = int(math.ceil((e.max() - e0) / step))
    Ho = int(math.ceil((n_top - n.min()) / step))

    def sample(r0: int, h: int) -> tuple[np.ndarray, np.ndarray]:
        E, N = np.meshgrid(e0 + (np.arange(Wo) + 0.5) * step, n_top - (np.arange(r0, r0 + h) + 0.5) * step)
        if err < 0.01 * grid.res:
            X, Y = E * coef[0, 0] + N * coef[1, 0] + coef[2, 0], E * coef[0, 1] + N * coef[1, 1] + coef[2, 1]
        else:  # far from affine (a huge area or an odd CRS): exact per pixel
            lo, la = inv.transform(E.ravel(), N.ravel())
            X, Y = (a.reshape(E.shape) for a in lt.from_lonlat(np.asarray(lo), np.asarray(la)))
        return (Y - grid.y0) / grid.res, (X - grid.x0) / grid.res

    return Ho, Wo, Affine(step, 0.0, e0, 0.0, -step, n_top), sample


def _crs_strips(bands: list[np.ndarray], valid: np.ndarray, grid: GridSpec, Ho: int, sample):  # noqa: ANN001, ANN202
    """Bilinear resampling onto the CRS raster, ``ROWS`` at a time: (row0, (B, h, W')). Cells outside
    ``valid`` or the grid are NODATA; nodata cells do not bleed in (a sample needs a valid nearest cell)."""
    H, W = grid.shape
    for r0 in range(0, Ho, ROWS):
        fr, fc = sample(r0, min(ROWS, Ho - r0))
        ri, ci = np.rint(fr).astype(np.int64), np.rint(fc).astype(np.int64)
        near = (ri >= 0) & (ri < H) & (ci >= 0) & (ci < W)
        near[near] = valid[ri[near], ci[near]]
        out = np.full((len(bands), *fr.shape), NODATA, np.float32)
        if near.any():
            # bilinear reads the 2 x 2 cells around a sample: only the bands' window under this strip's samples
            j0, j1 = max(int(np.floor(fr[near].min())), 0), min(int(np.floor(fr[near].max())) + 2, H)
            i0, i1 = max(int(np.floor(fc[near].min())), 0), min(int(np.floor(fc[near].max())) + 2, W)
            for k, b in enumerate(bands):
                v = ndimage.map_coordinates(_clean(b[j0:j1, i0:i1]), [fr - j0, fc - i0], order=1, mode="nearest",
                                            prefilter=False)
                out[k] = np.where(near, v, NODATA)
        yield r0, out


def write_geotiff(path: str | os.PathLike, prob_map: np.ndarray, class_maps: np.ndarray, grid: GridSpec,
                  geo_origin: GeoOrigin | None = None, *, crs: str = "auto", valid: np.ndarray | None = None,
                  name: str = "") -> Path:
    """Write ``defect_map.tif`` (COG when GDAL has the driver, else tiled GTiff with overviews).

    ``prob_map`` (H, W) float, ``class_maps`` (4, H, W) float, ``grid`` a GridSpec, ``valid`` (H, W)
    bool the surveyed cells (others are NODATA; default all). With ``geo_origin`` the raster is in
    ``crs`` (``auto``: the drive's UTM zone), else in the local engineering CRS of ``name``. The raster is
    written in strips of ``ROWS`` rows to a tiled GTiff on disk, which GDAL's COG driver then copies with its
    overviews: memory stays a strip of the map, so a long drive's map never sits in memory twice.
    """
    bands = check_bands(prob_map, class_maps, grid)
    g = as_grid(grid)
    valid = np.ones(g.shape, dtype=bool) if valid is None else np.asarray(valid, dtype=bool)
    if valid.shape != g.shape:
        raise PavemapError(f"valid mask shape {valid.shape} does not match the map grid {g.shape}")
    target = output_crs(geo_origin, crs, name)
    if geo_origin is None:
        h, w, transform = g.ny, g.nx, _local_transform(g)
        strips = _local_strips(bands, valid, g)
    else:
        h, w, transform, sample = _crs_raster(g, geo_origin, target)
        strips = _crs_strips(bands, valid, g, h, sample)
    with rasterio.Env() as env:
        has_cog = "COG" in env.drivers()
    profile = {"driver": "GTiff", "width": w, "height": h, "count": len(bands), "dtype": "float32",
               "transform": transform, "compress": "DEFLATE", "predictor": 3, "nodata": NODATA,
               "crs": target.to_wkt(), "tiled": True, "blockxsize": 256, "blockysize": 256, "BIGTIFF": "IF_SAFER"}
    tags = {
        "PAVEMAP_BANDS": "; ".join(BAND_DESCRIPTIONS),
        "PAVEMAP_FRAME": (f"{crs_label(target)}, north-up" if geo_origin is not None
                          else "local world frame x, y metres (SPEC §0): not on the Earth"),
        "PAVEMAP_GRID": f"x0={g.x0} y0={g.y0} res={g.res} shape={g.ny}x{g.nx} (cell centres, rows going +y)",
        "PAVEMAP_GEO_ORIGIN": str(origin_to_dict(geo_origin)),
        "PAVEMAP_NODATA": f"{NODATA}: outside the surveyed area (no camera saw it within range)",
    }
    final = Path(path)
    with atomic_path(final) as tmp, rasterio.Env(GDAL_CACHEMAX=GDAL_CACHE_MB):
        strip_file = Path(f"{tmp}.strips.tif") if has_cog else Path(tmp)
        try:
            with rasterio.open(strip_file, "w", **profile) as ds:
                for r0, data in strips:
                    ds.write(data, window=Window(0, r0, w, data.shape[1]))
                for i, d in enumerate(BAND_DESCRIPTIONS, start=1):
                    ds.set_band_description(i, d)
                ds.update_tags(**tags)
                if not has_cog:
                    factors = [f for f in (2, 4, 8, 16) if min(h, w) // f >= 64]
                    if factors:
                        ds.build_overviews(factors, rasterio.enums.Resampling.average)
            if has_cog:
                rio_copy(strip_file, tmp, driver="COG", compress="DEFLATE", predictor=3, blocksize=256,
                         overviews="AUTO", resampling="average", BIGTIFF="IF_SAFER")
        except rasterio.errors.RasterioError as e:
            raise PavemapError(f"{final}: could not write the GeoTIFF ({e})") from None
        finally:
            if has_cog:
                strip_file.unlink(missing_ok=True)  # our own strip file, never the user's
    return final


__all__ = ["BAND_DESCRIPTIONS", "NODATA", "check_bands", "check_grid", "write_geotiff"]
