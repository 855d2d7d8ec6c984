"""Georeferencing and coordinate reference systems.

- :mod:`pavemap.geo.fit`: robust 2D similarity / rigid fit (RANSAC, then least squares with an
  adaptive inlier threshold);
- :mod:`pavemap.geo.georef`: the geo origin of a drive from its trajectory and a GPS track;
- :mod:`pavemap.geo.attach`: what the importers call (GPS file, poses.csv columns, EXIF, OXTS, by hand);
- :mod:`pavemap.geo.crs`: output CRS (the drive's UTM zone, ``--crs``, or a local engineering CRS);
- :mod:`pavemap.geo.coverage`: the surveyed area (what the cameras saw), for nodata and the survey layer.
"""
