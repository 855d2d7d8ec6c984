"""A run's defects as a (Geo)DataFrame: geopandas when installed, else pandas, else a list of dicts."""

from __future__ import annotations

from pyproj import CRS

from pavemap.errors import PavemapError
from pavemap.export.geojson import instances_to_geojson
from pavemap.export.tables import to_dataframe
from pavemap.types import DefectInstance, GeoOrigin


def defects_geojson(instances: list[DefectInstance], geo_origin: GeoOrigin | None) -> dict:
    """RFC 7946 FeatureCollection (WGS84 lon/lat); refused without a geo origin, because any GeoJSON
    reader would take local metres for degrees."""
    if geo_origin is None:
        raise PavemapError("this run has no geo origin: GeoJSON is WGS84 longitude/latitude only (RFC 7946); "
                           "use to_dataframe() (local metres) or the run's survey.gpkg, or georeference the "
                           "sequence (`pavemap import gps SEQ --gps FILE` or --geo-origin)")
    return instances_to_geojson(instances, geo_origin)


def defects_frame(instances: list[DefectInstance], geo_origin: GeoOrigin | None, crs: str | None = None,
                  name: str = ""):  # noqa: ANN201 - the type depends on what is installed
    """One row per defect (the CSV columns, lon/lat with a geo origin).

    With geopandas: a GeoDataFrame of the polygons in ``crs`` — default EPSG:4326 with a geo origin,
    ``auto`` for the drive's UTM zone, any projected CRS; without a geo origin the local engineering
    CRS. Without geopandas: :func:`pavemap.export.tables.to_dataframe` (pandas or a list of dicts).
    """
    try:
        import geopandas as gpd
    except ImportError:
        return to_dataframe(instances, geo_origin)
    from pavemap.export.gis import _multi, _Projector
    from pavemap.geo.crs import WGS84, output_crs

    df = to_dataframe(instances, geo_origin)
    if geo_origin is not None and crs in (None, "EPSG:4326", "epsg:4326", "4326"):
        target, wgs84 = CRS.from_user_input(WGS84), True
    else:
        target, wgs84 = output_crs(geo_origin, crs or "auto", name), False
    proj = _Projector(geo_origin, target, wgs84=wgs84)
    by_id = {i.id: i for i in instances}
    geoms = [None if (m := _multi(by_id[int(r)].polygon)) is None else proj.geometry(m) for r in df["id"]]
    return gpd.GeoDataFrame(df, geometry=geoms, crs=target)


__all__ = ["defects_frame", "defects_geojson"]
