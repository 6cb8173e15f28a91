#!/usr/bin/env bash
# Run ON the GPU machine lent by the device tool (see docs/GPU.md), in the repo root, with .whl
# carried (scripts/gpu_wheels.sh). Each section fits one 10-minute device command; files land
# in $OUT (or ./gpu_out when OUT is unset).
#   bash scripts/gpu_checks.sh speed   # DPT speed vs torch on the GPU (base seg / depth, large seg)
#   STEPS=1000 bash scripts/gpu_checks.sh demo   # the README's demo on the GPU, plus NeRF throughput
set -uo pipefail
OUT=${OUT:-gpu_out}
mkdir -p "$OUT"
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl || exit 1
export PYTHONPATH=/tmp/site:$PWD PYTHONUNBUFFERED=1
nvidia-smi -L
python3 -c "import jax, torch; print('jax', jax.__version__, jax.devices(), 'torch', torch.__version__, torch.cuda.is_available())"
case "${1:-speed}" in
  speed)
    python3 benchmarks/dpt_speed.py --torch-device cuda --iters 20 --stages --out "$OUT/dpt_speed_gpu.json"
    python3 benchmarks/dpt_speed.py --torch-device cuda --iters 20 --stages --task depth --out "$OUT/dpt_speed_gpu_depth.json"
    python3 benchmarks/dpt_speed.py --torch-device cuda --iters 10 --arch large --out "$OUT/dpt_speed_gpu_large.json"
    ;;
  demo)
    python3 -m jaxnerf_grid demo --out /tmp/demo --steps "${STEPS:-1000}" --quiet 2>&1 | tee "$OUT/demo.log"
    cp /tmp/demo/run/report.md /tmp/demo/run/report_views.png "$OUT/" 2>/dev/null
    python3 benchmarks/throughput.py --steps 20 --out "$OUT/throughput_gpu.json"
    ;;
  *) echo "usage: $0 speed|demo"; exit 2 ;;
esac
