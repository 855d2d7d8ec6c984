#!/usr/bin/env bash
# System packages the test suite uses (headless Chromium for the report test, GDAL's tools for the GIS tests).
# Installed only when missing and only where we may (root); otherwise the report test says what to install.
set -u
if ! command -v chromium >/dev/null 2>&1 && [ "$(id -u)" = "0" ] && command -v apt-get >/dev/null 2>&1; then
  (apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium >/dev/null) \
    || echo "setup_system: could not install chromium; the report browser test will be skipped" >&2
fi
# GDAL's command-line tools (ogrinfo, gdalinfo): the GIS-output tests open every written file with them.
if ! command -v ogrinfo >/dev/null 2>&1 && [ "$(id -u)" = "0" ] && command -v apt-get >/dev/null 2>&1; then
  (apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq gdal-bin >/dev/null) \
    || echo "setup_system: could not install gdal-bin; the GIS tests check the files through pyogrio/rasterio only" >&2
fi
exit 0
