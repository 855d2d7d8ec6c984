"""Coordinate reference systems of pavemap's outputs.

- With a geo origin: the drive's UTM zone (WGS84, EPSG:326NN north / 327NN south) by default,
  any projected CRS pyproj knows by ``--crs`` (``EPSG:<code>`` (e.g. ``EPSG:32633``), a WKT or a PROJ string).
- Without one: an explicit *local engineering* CRS (WKT2 ``ENGCRS``, Cartesian metres, named
  after the sequence), so GDAL and QGIS read the layers as local metres, never as longitude and
  latitude (a GeoJSON without a CRS is WGS84 by RFC 7946).
"""

from __future__ import annotations

from pyproj import CRS
from pyproj.exceptions import CRSError

from pavemap.errors import PavemapError
from pavemap.types import GeoOrigin

WGS84 = "EPSG:4326"
LOCAL_CRS_NAME = "pavemap local world frame"


def utm_epsg(lon: float, lat: float) -> int:
    """EPSG code of the WGS84 UTM zone holding (lon, lat); Norway/Svalbard exceptions included."""
    zone = int((lon + 180.0) // 6.0) % 60 + 1
    if 56.0 <= lat < 64.0 and 3.0 <= lon < 12.0:
        zone = 32
    elif 72.0 <= lat < 84.0 and 0.0 <= lon < 42.0:
        zone = 31 if lon < 9.0 else 33 if lon < 21.0 else 35 if lon < 33.0 else 37
    return (32600 if lat >= 0 else 32700) + zone


def local_crs(name: str = "") -> CRS:
    """The local engineering CRS of a sequence's world frame (x, y metres, z up)."""
    label = f"{LOCAL_CRS_NAME} ({name})" if name else LOCAL_CRS_NAME
    label = label.replace('"', "'")
    return CRS.from_wkt(
        f'ENGCRS["{label}",EDATUM["pavemap sequence origin (no geo origin: not on the Earth)"],'
        'CS[Cartesian,2],AXIS["x (world +x)",unspecified,ORDER[1],LENGTHUNIT["metre",1]],'
        'AXIS["y (world +y, 90 degrees counter-clockwise from x)",unspecified,ORDER[2],LENGTHUNIT["metre",1]]]'
    )


def parse_crs(code: str, where: str = "--crs") -> CRS:
    """A CRS from ``EPSG:<code>`` (e.g. ``EPSG:32633``), WKT or PROJ text.

    PavemapError naming ``where`` when it does not exist.
    """
    text = str(code).strip()
    if text.isdigit():
        text = f"EPSG:{text}"
    try:
        crs = CRS.from_user_input(text)
    except CRSError:
        raise PavemapError(f"{where}: {code!r} is not a coordinate reference system pyproj knows "
                           "(e.g. EPSG:32633 for UTM zone 33N, or 'auto' for the drive's UTM zone)") from None
    if not crs.is_projected:
        raise PavemapError(f"{where}: {code!r} ({crs.name}) is not a projected CRS; maps need x, y in a "
                           "linear unit (e.g. the drive's UTM zone: 'auto')")
    return crs


def check_crs_setting(code: str, where: str = "output.crs") -> None:
    """Validate an ``output.crs`` value (``auto`` or a projected CRS) without a sequence."""
    if str(code).strip().lower() != "auto":
        parse_crs(code, where)


def output_crs(origin: GeoOrigin | None, code: str = "auto", name: str = "") -> CRS:
    """The CRS of a run's maps and layers: the UTM zone of ``origin`` (``auto``), the named CRS, or
    the local engineering CRS when there is no origin (then ``code`` must be ``auto``)."""
    auto = str(code).strip().lower() in ("", "auto")
    if origin is None:
        if not auto:
            raise PavemapError(f"--crs {code}: the sequence has no geo origin, so its map cannot be put in a "
                               "projected CRS (give GPS or --geo-origin when importing)")
        return local_crs(name)
    if auto:
        return CRS.from_epsg(utm_epsg(float(origin.lon), float(origin.lat)))
    return parse_crs(code)


def crs_label(crs: CRS) -> str:
    """``EPSG:32632 (WGS 84 / UTM zone 32N)`` or the CRS name."""
    epsg = crs.to_epsg(min_confidence=90)
    return f"EPSG:{epsg} ({crs.name})" if epsg else crs.name


__all__ = ["LOCAL_CRS_NAME", "WGS84", "check_crs_setting", "crs_label", "local_crs", "output_crs", "parse_crs",
           "utm_epsg"]
