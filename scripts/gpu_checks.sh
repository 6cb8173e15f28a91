#!/usr/bin/env bash
# Run ON the GPU machine lent by the device tool (see docs/GPU.md), in the repo root, with .whl
# carried (scripts/gpu_wheels.sh). Each section fits one 10-minute device command; files land
# in $OUT (or ./gpu_out when OUT is unset).
#   bash scripts/gpu_checks.sh speed   # DPT speed vs torch on the GPU (base seg / depth, large seg)
#   STEPS=1000 bash scripts/gpu_checks.sh demo   # the README's demo on the GPU, plus NeRF throughput
#   bash scripts/gpu_checks.sh train   # train rays/s (ours, ours-fast, ours-lean, lazy Adam; 1024 and
#                                      # 8192 rays), the step's profile, the demo and ours-fast's demo
#   STEPS_LIST="1000 1200 1600" bash scripts/gpu_checks.sh steps   # ours-fast's demo at
#        fewer steps (and ours at the first count), no video; then DPT-base segmentation's speed
#   bash scripts/gpu_checks.sh table1   # Table 1's robust rows (robust, dpt+robust) at
#        --standard, 3 seeds, sets A and B; the other rows are read back from the committed results
#   WHL=.whl_t1 bash scripts/gpu_checks.sh table1r   # seeds 1-2: the robust rows on
#        scenes made here (`python scripts/gpu_table1_runs.py --cache .t1cache --prepare`) and carried
#        (.t1cache/scenes, .t1cache/variants; .whl_t1 = the jaxopt and OpenEXR wheels), then robustprof
#   WHL=.t1carry VARIANTS="base: rf5:robust_refine=0.5" bash scripts/gpu_checks.sh table1v   # a sweep of
#        train.* variants of the robust rows (ROWS, SETS, SEEDS) on carried scenes (docs/GPU.md)
#   bash scripts/gpu_checks.sh robustprof   # why a robust run trains 5x longer than a plain one on the
#        GPU (docs/GPU.md): the step profile of ours-fast plain and with train.robust=robust
set -uo pipefail
OUT=${OUT:-gpu_out}
# ours-fast's proposal grid (recipes.SAMPLERS) as a --set, for a demo run against ours
FAST='model.sampler.field.grid={"num_levels":3,"max_resolution":64,"log2_table_size":15}'
mkdir -p "$OUT"
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site "${WHL:-.whl}"/*.whl || exit 1
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
  train)
    # Each part under its own timeout, the most wanted first, so one that hangs costs only itself.
    timeout 150 python3 -m benchmarks.throughput --configs demo,ours-fast,ours-lean,demo-sparse-adam --steps 20 \
      --repeats 3 --out "$OUT/throughput_gpu.json"
    ( time timeout 240 python3 -m jaxnerf_grid demo --out /tmp/demo --quiet ) 2>&1 | tee "$OUT/demo.log"
    for f in report_views.png metrics.json; do cp "/tmp/demo/run/$f" "$OUT/demo_$f"; done  # 8 files come back
    timeout 100 python3 -m benchmarks.throughput --configs demo,ours-fast,ours-lean,demo-sparse-adam --steps 20 \
      --repeats 3 --batch-rays 8192 --out "$OUT/throughput_gpu_8192.json"
    timeout 90 python3 -m benchmarks.step_profile --repeats 10 --out "$OUT/step_profile_gpu.json"
    ( time timeout 150 python3 -m jaxnerf_grid demo --data /tmp/demo/data --out /tmp/demofast --quiet \
      --set "$FAST" ) 2>&1 | tee "$OUT/demofast.log"
    cp /tmp/demofast/run/report_views.png "$OUT/demofast_report_views.png"
    ;;
  steps)
    timeout 120 python3 -m jaxnerf_grid demo --out /tmp/demo --steps 10 --no-video --quiet > /dev/null 2>&1
    first=${STEPS_LIST%% *}
    for n in ${STEPS_LIST:-1000 1200 1600}; do
      echo "ours-fast $n steps:"; timeout 90 python3 -m jaxnerf_grid demo --data /tmp/demo/data --out "/tmp/fast$n" \
        --steps "$n" --no-video --quiet --set "$FAST" 2>&1 | grep "demo done"
      cp "/tmp/fast$n/run/report_views.png" "$OUT/fast${n}_report_views.png"
    done 2>&1 | tee "$OUT/steps.log"
    echo "ours $first steps:" | tee -a "$OUT/steps.log"
    timeout 90 python3 -m jaxnerf_grid demo --data /tmp/demo/data --out /tmp/ours$first --steps "$first" --no-video \
      --quiet 2>&1 | grep "demo done" | tee -a "$OUT/steps.log"
    cp "/tmp/ours$first/run/report_views.png" "$OUT/ours${first}_report_views.png"
    timeout 90 python3 benchmarks/dpt_speed.py --torch-device cuda --iters 20 --stages --out "$OUT/dpt_speed_gpu.json"
    ;;
  table1)
    # Scenes and the DPT's masks are made here (too large to carry); --budget-min stops launching
    # runs in time for the tables to be written.
    python3 -m experiments.table1_foreground --standard --seeds 3 --cache /tmp/t1cache --results "$OUT/t1" \
      --budget-min "${BUDGET_MIN:-7}" --quiet \
      --train-only '^t1-(tower-small|plad-like)-(robust_no_masks|built-in_DPT_masks__Eq_7__robust) seed' \
      2>&1 | tee "$OUT/table1.log"
    ;;
  table1r)
    timeout "${T1_TIMEOUT:-480}" python3 scripts/gpu_table1_runs.py --cache .t1cache --seeds "${SEEDS:-1,2}" \
      --sets "${SETS:-B,A}" --out "$OUT" --budget-min "${BUDGET_MIN:-5.5}" 2>&1 | grep -v "^\[mask\]" | tee "$OUT/table1r.log"
    tar czf "$OUT/runs.tgz" -C "$OUT" runs && rm -rf "$OUT/runs"  # the device returns only a few files
    timeout "${PROF_TIMEOUT:-90}" python3 -m benchmarks.step_profile --recipe ours --repeats 10 --set train.robust=robust \
      --out "$OUT/step_profile_robust.json" 2>&1 | tail -14
    ;;
  table1v)
    # a sweep of train.* variants of the robust rows, each seed's variants one after another (paired);
    # .t1carry = the wheels plus t1.tgz (scenes and DPT variants made here by --prepare, without their
    # overlays and DPT depth: tar czf .t1carry/t1.tgz --exclude='*/overlays' --exclude='*/dpt_depth'
    # -C .t1cache scenes variants)
    mkdir -p .t1cache && tar xzf "${WHL:-.whl}/t1.tgz" -C .t1cache
    variants=(); for v in ${VARIANTS:-base:}; do variants+=(--variant "$v"); done
    timeout "${T1_TIMEOUT:-540}" python3 scripts/gpu_table1_runs.py --cache .t1cache --seeds "${SEEDS:-0,1,2}" \
      --sets "${SETS:-B,A}" --rows "${ROWS:-dpt+robust}" "${variants[@]}" --out "$OUT" \
      --budget-min "${BUDGET_MIN:-7.5}" 2>&1 | grep -v "^\[mask\]" | tee "$OUT/table1v.log"
    tar czf "$OUT/runs.tgz" -C "$OUT" runs && rm -rf "$OUT/runs"
    ;;
  robustprof)
    timeout 150 python3 -m benchmarks.step_profile --recipe ours-fast --repeats 20 --out "$OUT/step_profile_plain.json"
    timeout 150 python3 -m benchmarks.step_profile --recipe ours-fast --repeats 20 --set train.robust=robust \
      --out "$OUT/step_profile_robust.json"
    ;;
  *) echo "usage: $0 speed|demo|train|steps|table1|table1r|table1v|robustprof"; exit 2 ;;
esac
