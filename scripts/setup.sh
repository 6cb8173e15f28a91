#!/usr/bin/env bash
# Creates .venv inside the checkout and installs jaxnerf-grid into it.
#   bash scripts/setup.sh          runtime only
#   bash scripts/setup.sh --test   plus the test extras (CPU torch, transformers, reference metrics) and
#                                  Debian's `chromium` (apt-get, only when /usr/bin/chromium is missing)
# Both install the `sfm` extra (pycolmap, for `jaxnerf-grid poses`) when the package registry
# has a wheel for this machine; without one the rest is installed and `poses` says what is missing.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-$(command -v python3.11 || command -v python3)}
if [ ! -x .venv/bin/python ]; then
  "$PY" -m venv .venv
fi
.venv/bin/python -m pip install -q --upgrade pip >/dev/null 2>&1 || true
if [ "${1:-}" = "--test" ]; then
  .venv/bin/python -m pip install -q -e '.[test,sfm]' || {
    echo "setup.sh: pycolmap (the sfm extra) could not be installed; the tests that run COLMAP will be skipped" >&2
    .venv/bin/python -m pip install -q -e '.[test]'
  }
  # lpips declares torchvision, which has no CPU build here: install it alone;
  # tests/conftest.py gives it a small stand-in for torchvision's AlexNet.
  .venv/bin/python -m pip install -q --no-deps lpips==0.1.4
  # headless Chromium screenshots report.html from a file:// URL (tests/report/test_html.py)
  if [ ! -x /usr/bin/chromium ]; then
    AS_ROOT=""
    if [ "$(id -u)" -ne 0 ]; then AS_ROOT="sudo -n"; fi
    if command -v apt-get >/dev/null 2>&1 \
        && $AS_ROOT apt-get update -qq \
        && $AS_ROOT env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium >/dev/null; then
      echo "setup.sh: installed Debian's chromium for the report.html screenshot test"
    else
      echo "setup.sh: could not install Debian's chromium (apt-get install chromium, as root); the report.html" \
           "screenshot test will be skipped (it fails instead where JAXNERF_GRID_REQUIRE_CHROMIUM=1)" >&2
    fi
  fi
else
  .venv/bin/python -m pip install -q -e '.[sfm]' || {
    echo "setup.sh: pycolmap (the sfm extra) could not be installed; jaxnerf-grid poses needs it" >&2
    .venv/bin/python -m pip install -q -e .
  }
fi
