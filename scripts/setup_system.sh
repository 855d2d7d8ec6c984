#!/usr/bin/env bash
# System packages the test suite uses (headless Chromium for the report test).
# Installed only when missing and only where we may (root); otherwise the report test says what to install.
set -u
if ! command -v chromium >/dev/null 2>&1 && [ "$(id -u)" = "0" ] && command -v apt-get >/dev/null 2>&1; then
  (apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium >/dev/null) \
    || echo "setup_system: could not install chromium; the report browser test will be skipped" >&2
fi
exit 0
