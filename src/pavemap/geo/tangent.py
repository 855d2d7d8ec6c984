"""Local world metres <-> WGS84 longitude/latitude.

The world frame (SPEC §0) is a flat metric frame whose origin sits at ``GeoOrigin`` (lat, lon)
and whose +x axis points at compass heading ``heading_deg`` (clockwise from north). We map it
onto the Earth with an azimuthal equidistant projection centred on the origin (exact distances
from the origin, sub-millimetre distortion over a few km) after rotating world x, y into
east, north. World +y is 90 degrees counter-clockwise from +x (right-handed, z up), so:

    east  = x sin(h) - y cos(h)
    north = x cos(h) + y sin(h)

which is a proper rotation (det = +1): polygon winding is preserved.
"""

from __future__ import annotations

import math
from functools import lru_cache

import numpy as np
from pyproj import CRS, Transformer

from pavemap.errors import PavemapError
from pavemap.types import GeoOrigin

WGS84 = "EPSG:4326"


def check_origin(origin: GeoOrigin) -> None:
    """Raise PavemapError naming the bad field of a geo origin."""
    for name in ("lat", "lon", "alt", "heading_deg"):
        v = getattr(origin, name)
        if not isinstance(v, (int, float)) or not math.isfinite(float(v)):
            raise PavemapError(f"geo_origin: {name} must be a finite number, got {v!r}")
    if not -90.0 <= origin.lat <= 90.0:
        raise PavemapError(f"geo_origin: lat must be in [-90, 90], got {origin.lat}")
    if not -180.0 <= origin.lon <= 180.0:
        raise PavemapError(f"geo_origin: lon must be in [-180, 180], got {origin.lon}")


class LocalTangent:
    """The local tangent frame of one geo origin: world x, y metres <-> east/north <-> lon/lat."""

    def __init__(self, origin: GeoOrigin) -> None:
        check_origin(origin)
        self.origin = origin
        self.crs = CRS.from_proj4(
            f"+proj=aeqd +lat_0={float(origin.lat)!r} +lon_0={float(origin.lon)!r} "
            "+x_0=0 +y_0=0 +datum=WGS84 +units=m +no_defs +type=crs"
        )
        self._to_geo = Transformer.from_crs(self.crs, WGS84, always_xy=True)
        self._from_geo = Transformer.from_crs(WGS84, self.crs, always_xy=True)
        h = math.radians(float(origin.heading_deg))
        # (2, 2): [east, north]^T = R [x, y]^T
        self.R = np.array([[math.sin(h), -math.cos(h)], [math.cos(h), math.sin(h)]], dtype=np.float64)

    @property
    def axis_aligned(self) -> bool:
        """True when world x is east and world y is north (heading 90)."""
        return bool(np.allclose(self.R, np.eye(2), atol=1e-12))

    def world_to_enu(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        x = np.asarray(x, dtype=np.float64)
        y = np.asarray(y, dtype=np.float64)
        return self.R[0, 0] * x + self.R[0, 1] * y, self.R[1, 0] * x + self.R[1, 1] * y

    def enu_to_world(self, e: np.ndarray, n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        e = np.asarray(e, dtype=np.float64)
        n = np.asarray(n, dtype=np.float64)
        # R is orthonormal: inverse = transpose
        return self.R[0, 0] * e + self.R[1, 0] * n, self.R[0, 1] * e + self.R[1, 1] * n

    def to_lonlat(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """World metres (any shape) -> (lon, lat) degrees, same shape."""
        e, n = self.world_to_enu(x, y)
        return _apply(self._to_geo, e, n)

    def from_lonlat(self, lon: np.ndarray, lat: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(lon, lat) degrees -> world metres x, y."""
        e, n = _apply(self._from_geo, np.asarray(lon, dtype=np.float64), np.asarray(lat, dtype=np.float64))
        return self.enu_to_world(e, n)

    def geometry_to_lonlat(self, geom: object) -> object:
        """A shapely geometry in world metres -> the same geometry in lon/lat."""
        return _transform_geometry(geom, self.to_lonlat)

    def geometry_from_lonlat(self, geom: object) -> object:
        return _transform_geometry(geom, self.from_lonlat)


def _apply(tr: Transformer, a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Vectorised transform of same-shape arrays; flattened first because pyproj treats size-1
    arrays as scalars (a NumPy deprecation path)."""
    a, b = np.broadcast_arrays(np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64))
    shp = a.shape
    fa, fb = a.ravel(), b.ravel()
    if fa.size == 1:
        ra, rb = tr.transform(float(fa[0]), float(fb[0]))
    else:
        ra, rb = tr.transform(np.ascontiguousarray(fa), np.ascontiguousarray(fb))
    return np.asarray(ra, dtype=np.float64).reshape(shp), np.asarray(rb, dtype=np.float64).reshape(shp)


def _transform_geometry(geom: object, fn) -> object:
    import shapely

    def apply(coords: np.ndarray) -> np.ndarray:
        a, b = fn(coords[:, 0], coords[:, 1])
        return np.column_stack([a, b])

    return shapely.transform(geom, apply)


@lru_cache(maxsize=16)
def _cached(lat: float, lon: float, alt: float, heading: float) -> LocalTangent:
    return LocalTangent(GeoOrigin(lat, lon, alt, heading))


def local_tangent(origin: GeoOrigin) -> LocalTangent:
    """A (cached) LocalTangent for ``origin``."""
    check_origin(origin)
    return _cached(float(origin.lat), float(origin.lon), float(origin.alt), float(origin.heading_deg))


def origin_to_dict(origin: GeoOrigin | None) -> dict | None:
    if origin is None:
        return None
    return {"lat": float(origin.lat), "lon": float(origin.lon), "alt": float(origin.alt),
            "heading_deg": float(origin.heading_deg)}


def origin_from_dict(d: dict | None, where: str = "geo_origin") -> GeoOrigin | None:
    if d is None:
        return None
    try:
        o = GeoOrigin(float(d["lat"]), float(d["lon"]), float(d.get("alt", 0.0)), float(d.get("heading_deg", 90.0)))
    except (KeyError, TypeError, ValueError) as e:
        raise PavemapError(f"{where}: needs numeric lat, lon (optional alt, heading_deg): {e}") from None
    check_origin(o)
    return o


__all__ = ["WGS84", "LocalTangent", "check_origin", "local_tangent", "origin_from_dict", "origin_to_dict"]
