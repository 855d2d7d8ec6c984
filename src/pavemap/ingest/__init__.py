"""Importers of own drives and KITTI: read the files (:mod:`pavemap.io`), pose them (given, or by SfM,
:mod:`pavemap.sfm`), georeference them (:mod:`pavemap.geo`) and write a sequence folder. Above io, geo and sfm;
below the commands."""
