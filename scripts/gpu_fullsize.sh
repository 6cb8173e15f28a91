#!/usr/bin/env bash
# Run ON the GPU machine lent by the device tool (docs/GPU.md), in the repo root, with .whl carried
# (scripts/gpu_wheels.sh) and a `jaxnerf-grid poses` dataset folder copied into an ignored folder of
# the checkout and carried too (the photos are never committed):
#
#   bash scripts/gpu_fullsize.sh DATA            # e.g. DATA=.gpu_data/fountain-P11
#
# The size trained is the dataset's: `poses --max-side 1600` writes 1599x1066 photos for
# fountain-P11 (4.4 MB of JPEGs, 9 training frames: 15.3 M training pixels, 9x the CPU's 533x355);
# `poses` without --max-side keeps the camera's 3072x2048 (about 31 MB to carry). Poses run here
# (pycolmap is not on the GPU image); carry the folder with .whl (64 MiB in all).
#
# Trains the demo's recipe on DATA at the photos' full size (MAX_SIDE=0; give MAX_SIDE=N for the
# largest working size that fits when full size does not) with BATCH rays a step (default 65536: at
# 1024 rays a step the H200 is launch-bound, 1.2 ms a step, docs/GPU.md), for at most MINUTES (4) of
# training: a 40-step probe measures the rays/s of this recipe, batch and size first, and the steps
# are what fits in MINUTES at that speed (the training budget's rule, budget.py, with the measured
# speed in place of its estimate; at least 200). Then the demo's evaluation. Writes to $OUT (default
# gpu_out): fullsize.log, fullsize.json (rays/s of the probe and of the run, steps, epochs, train and
# eval seconds, held-out PSNR / SSIM, the size trained), report.md, report_views.jpg (a JPEG of
# report_views.png, which at full size is over the device's file limit), metrics.json, budget.json.
# MASKS (default auto, as the demo) is passed to the demo's --masks. BUDGET=1 skips the probe and
# lets the training budget choose the steps within MINUTES, as the defaults do (the larger hash grid
# when 2 epochs leave time to spare).
set -uo pipefail
DATA=${1:?usage: bash scripts/gpu_fullsize.sh DATA (a poses dataset folder)}
OUT=${OUT:-gpu_out}
MAX_SIDE=${MAX_SIDE:-0}
BATCH=${BATCH:-65536}
MINUTES=${MINUTES:-4}
MASKS=${MASKS:-auto}
WORK=${WORK:-/tmp/fullsize}   # the probe's and the run's folders
mkdir -p "$OUT"
if [ -z "${NO_WHL:-}" ]; then  # NO_WHL=1: the environment has every package (a dry run on a CPU machine)
  python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site "${WHL:-.whl}"/*.whl || exit 1
fi
export PYTHONPATH=/tmp/site:$PWD PYTHONUNBUFFERED=1
nvidia-smi -L
nvidia-smi --query-gpu=memory.used,memory.total --format=csv
python3 -c "import jax; print('jax', jax.__version__, jax.devices())"
SETS=(--set "train.batch_rays=$BATCH" --set train.log_every=20 --set train.checkpoint_every=100000)
{
if [ -n "${BUDGET:-}" ]; then
  # BUDGET=1: the defaults' path, no probe: the demo times its step and the training budget chooses the
  # steps (and the larger hash grid when 2 epochs leave minutes) within --minutes MINUTES.
  echo "== the training budget's steps within $MINUTES min, $BATCH rays a step, max_side $MAX_SIDE"
  ( time timeout "${RUN_TIMEOUT:-420}" python3 -m jaxnerf_grid demo --data "$DATA" --out "$WORK"/full --max-side "$MAX_SIDE" \
      --masks "$MASKS" --minutes "$MINUTES" --no-video --quiet "${SETS[@]}" ) 2>&1
  RPS=$(python3 -c "import json; print(int(json.load(open('$WORK/full/run/budget.json'))['rays_per_second']))")
  STEPS=$(python3 -c "import json; print(int(json.load(open('$WORK/full/run/budget.json'))['steps']))")
else
  echo "== probe: 40 steps of $BATCH rays at max_side $MAX_SIDE"
  ( time timeout "${PROBE_TIMEOUT:-150}" python3 -m jaxnerf_grid demo --data "$DATA" --out "$WORK"/probe --max-side "$MAX_SIDE" \
      --masks "$MASKS" --steps 40 --no-video --quiet "${SETS[@]}" ) 2>&1 | grep -v "^warning: 40 steps"
  [ -f "$WORK"/probe/run/metrics.jsonl ] || { echo "the probe did not train"; exit 1; }
  RPS=$(python3 -c "
import json
recs = [json.loads(l) for l in open('$WORK/probe/run/metrics.jsonl')]
print(int(recs[-1]['rays_per_s']))   # the last window, after the compile")
  STEPS=$(python3 -c "print(max(200, int($MINUTES * 60 * $RPS / $BATCH) // 100 * 100))")
  echo "== probe: $RPS rays/s after the compile -> $STEPS steps for $MINUTES min"
  nvidia-smi --query-gpu=memory.used,memory.total --format=csv
  ( time timeout "${RUN_TIMEOUT:-420}" python3 -m jaxnerf_grid demo --data "$DATA" --out "$WORK"/full --max-side "$MAX_SIDE" \
      --masks "$MASKS" --steps "$STEPS" --no-video --quiet "${SETS[@]}" ) 2>&1
fi
  python3 - "$RPS" "$STEPS" "$BATCH" "$OUT/fullsize.json" "$WORK/full/run" <<'EOF'
import json, sys
rps, steps, batch, out, run = int(sys.argv[1]), int(sys.argv[2]), int(sys.argv[3]), sys.argv[4], sys.argv[5]
m = json.load(open(f"{run}/metrics.json"))
t = json.load(open(f"{run}/timings.json"))
log = [json.loads(l) for l in open(f"{run}/metrics.jsonl")]
late = [r["rays_per_s"] for r in log[len(log) // 2:]]
rec = {"probe_rays_per_s": rps, "steps": steps, "batch_rays": batch,
       "run_rays_per_s_median_late": sorted(late)[len(late) // 2] if late else None,
       "epochs": m.get("budget", {}).get("epochs"), "train_pixels": m.get("budget", {}).get("train_pixels"),
       "train_seconds": t.get("train"), "eval_seconds": t.get("eval"),
       "psnr": m["mean"]["psnr"], "ssim": m["mean"].get("ssim"), "resolution": m["resolution"]}
json.dump(rec, open(out, "w"), indent=1)
print(json.dumps(rec))
EOF
} 2>&1 | tee "$OUT/fullsize.log"
for f in report.md metrics.json budget.json; do cp "$WORK/full/run/$f" "$OUT/$f" 2>/dev/null; done
# report_views.png at full size is over the device's 16 MB a file: a JPEG of it comes back instead
python3 -c "
import cv2, sys
im = cv2.imread('$WORK/full/run/report_views.png')
im is None or cv2.imwrite('$OUT/report_views.jpg', im, [cv2.IMWRITE_JPEG_QUALITY, 92])"
