#!/usr/bin/env bash
# Creates .venv inside the checkout and installs jaxnerf-grid into it.
#   bash scripts/setup.sh          runtime only
#   bash scripts/setup.sh --test   plus the test extras (CPU torch, transformers, reference metrics)
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
else
  .venv/bin/python -m pip install -q -e '.[sfm]' || {
    echo "setup.sh: pycolmap (the sfm extra) could not be installed; jaxnerf-grid poses needs it" >&2
    .venv/bin/python -m pip install -q -e .
  }
fi
