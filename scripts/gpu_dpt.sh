#!/usr/bin/env bash
# Run ON the GPU machine lent by the device tool (docs/GPU.md, docs/DPT.md "Built-in model"), in the
# repo root, with the data cache and the wheels carried: carry [".dpt_cache", ".whl_dpt"].
# Prepared HERE beforehand (CPU):
#   python -m experiments.dpt_scenes SCENES --repeats 3 --views 10            # synthetic training scenes
#   python -m experiments.dpt_data .dpt_cache/train.npz --scenes SCENES/* --real PHOTO_DIRS...   # <= 40 MB
#   mkdir -p .whl_dpt && cp .whl/jaxopt-*.whl .whl/openexr-*.whl .whl_dpt/   # (scripts/gpu_wheels.sh fills .whl)
# Then:  bash scripts/gpu_dpt.sh      (MINUTES=6 BATCH=32 ARCH=base-like MAX_SIDE=160 LR=1e-3 STEPS=20000;
#         INIT=DIR continues from the DPT in DIR, e.g. the shipped jaxnerf_grid/masks/assets/dpt_builtin)
# Writes to $OUT (or ./gpu_out): dpt_builtin/ (config.json + params.safetensors, the best checkpoint),
# train_log.json (loss curve, validation scores, step rate), loss_curve.png, train.log, env.log.
set -uo pipefail
OUT=${OUT:-gpu_out}
mkdir -p "$OUT"
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site \
  "${WHL:-.whl_dpt}"/*.whl || exit 1
export PYTHONPATH=/tmp/site:$PWD PYTHONUNBUFFERED=1
{ nvidia-smi -L; python3 -c "import jax; print('jax', jax.__version__, jax.devices())"; } 2>&1 | tee "$OUT/env.log"
python3 -c "import jax, sys; sys.exit(0 if jax.devices()[0].platform == 'gpu' else 1)" \
  || echo "gpu_dpt.sh: WARNING: JAX sees no GPU; training on the CPU" | tee -a "$OUT/env.log"
VAL=()
INIT_ARGS=()
[ -n "${INIT:-}" ] && INIT_ARGS=(--init "$INIT")
[ -f "${CACHE_DIR:-.dpt_cache}/val.npz" ] && VAL=(--val-cache "${CACHE_DIR:-.dpt_cache}/val.npz")
# The loop stops itself after MINUTES of training (compile excluded); the timeout is only a backstop.
timeout "${TIMEOUT_S:-540}" python3 -m experiments.train_dpt_mix --cache "${CACHE_DIR:-.dpt_cache}/train.npz" "${VAL[@]}" "${INIT_ARGS[@]}" \
  --arch "${ARCH:-base-like}" --max-side "${MAX_SIDE:-160}" --minutes "${MINUTES:-6}" --steps "${STEPS:-20000}" \
  --batch "${BATCH:-32}" --lr "${LR:-1e-3}" --workers "${WORKERS:-12}" --val-every "${VAL_EVERY:-30}" \
  --out "$OUT/dpt_builtin" --log-dir "$OUT" 2>&1 | grep --line-buffered -v "slow_operation_alarm"
echo "gpu_dpt.sh: exit ${PIPESTATUS[0]}"
ls -la "$OUT" "$OUT/dpt_builtin"
