#!/usr/bin/env bash
# Run HERE (not on the GPU machine), in the repo root, before a device-tool run: downloads the
# wheels the GPU machine's image lacks (jaxopt, OpenEXR, pyproj, laspy, plotly; it has jax, torch,
# transformers, opencv, scikit-image, scipy, matplotlib, tqdm) for its Python 3.12 into .whl/
# (git-ignored via .git/info/exclude).
# Then call the device tool with carry [".whl"] and `bash scripts/gpu_checks.sh speed|demo|train`.
set -euo pipefail
grep -qx '/.whl/' .git/info/exclude 2>/dev/null || echo '/.whl/' >> .git/info/exclude
mkdir -p .whl
python3 -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
  --platform manylinux_2_28_x86_64 --platform manylinux_2_17_x86_64 --platform manylinux2014_x86_64 \
  -d .whl jaxopt==0.8.5 openexr pyproj laspy plotly
ls -la .whl
