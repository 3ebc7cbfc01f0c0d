#!/usr/bin/env bash
# One prepared check for a machine with a CUDA GPU (never part of CI), within 8.5 minutes of GPU steps:
#   1. the CUDA tests            (tests that skip themselves without a GPU)
#   2. bench/rasterizer.py       --device cuda
#   3. bench/train.py            hypersim recipe at the paper's 768x1024, 2 images x 5 views per GPU,
#                                against the paper's 16 images per 1.1 s on 8 V100s (1.82 images/s per GPU),
#                                and the fraction of wall time the GPU is busy (torch.profiler)
#   4. bench/predict.py          both recipes and modes at the paper's sizes, against 8 / 3 fps (V100)
#   5. bench/segment.py          usl-segment's PointRend on 640x480 frames (random weights), frames/s
# and one summary table. Each step has its own time limit, so a hung step costs only its budget;
# a failed step is reported and the others still run. Logs go to $USL_GPU_CHECK_LOGS (default a
# temporary folder). Exit status: 0 if every step passed.
#
#   bash scripts/gpu_check.sh               # on the GPU machine
#   bash scripts/gpu_check.sh --cpu-smoke   # every piece on the CPU at tiny sizes (is the script sound?)
set -u -o pipefail
cd "$(dirname "$0")/.."
export PYTHONPATH="${PYTHONPATH:-$PWD}"
export PYOPENGL_PLATFORM="${PYOPENGL_PLATFORM:-egl}"
PYTHON="${PYTHON:-python3}"
LOGS="${USL_GPU_CHECK_LOGS:-$(mktemp -d /tmp/usl-gpu-check.XXXXXX)}"
mkdir -p "$LOGS"

if [[ "${1:-}" == "--cpu-smoke" ]]; then
  MODE=cpu-smoke
  TESTS=(-m pytest -q -n 0 -rs tests/model/test_cuda.py)
  RASTER=(scripts/bench/rasterizer.py --device cpu --repeats 1 --threads 1)
  TRAIN=(scripts/bench/train.py --config tiny --device cpu --iters 1 --warmup 0 --size 64 64 --objects 2 --threads 1)
  PREDICT=(scripts/bench/predict.py --device cpu --config scene_shapes --size 96 128 --objects 2 --images 1 --warmup 0 --threads 1)
  SEGMENT=(scripts/bench/segment.py --device cpu --frames 1 --size 96 72 --threads 1 --score-thresholds 0.5)
  LIMITS=(300 300 300 300 300)
else
  MODE=cuda
  if ! "$PYTHON" -c "import torch, sys; sys.exit(0 if torch.cuda.is_available() else 1)"; then
    echo "gpu_check: FAILED: torch sees no CUDA device (use --cpu-smoke to check the script on a CPU)" >&2
    exit 2
  fi
  "$PYTHON" -c "import torch; p = torch.cuda.get_device_properties(0); print(f'gpu_check: {p.name}, {p.total_memory / 2**30:.0f} GiB, torch {torch.__version__}')"
  TESTS=(-m pytest -q -n 0 -rs tests/model/test_cuda.py)
  RASTER=(scripts/bench/rasterizer.py --device cuda --repeats 3)
  TRAIN=(scripts/bench/train.py --config hypersim --device cuda --iters 5 --warmup 2)
  PREDICT=(scripts/bench/predict.py --device cuda --images 20 --warmup 2)
  SEGMENT=(scripts/bench/segment.py --device cuda --frames 20 --threads 1)
  LIMITS=(120 60 150 120 60)  # seconds; 8.5 minutes in all
fi

NAMES=("cuda tests" "rasterizer" "train hypersim" "predict" "segment")
STATUS=()
SECONDS_TAKEN=()
FIGURES=()

run_step() {  # index, command...
  local index=$1
  shift
  local log="$LOGS/step$index.log"
  local start=$SECONDS
  echo "gpu_check: [$((index + 1))/5] ${NAMES[$index]}: $PYTHON $* (limit ${LIMITS[$index]} s)"
  timeout --kill-after=10 "${LIMITS[$index]}" "$PYTHON" "$@" >"$log" 2>&1
  local rc=$?
  SECONDS_TAKEN[$index]=$((SECONDS - start))
  if [[ $rc -eq 0 ]]; then
    STATUS[$index]=ok
  elif [[ $rc -eq 124 || $rc -eq 137 ]]; then
    STATUS[$index]="TIMEOUT"
    echo "gpu_check: FAILED: ${NAMES[$index]} ran past ${LIMITS[$index]} s; log: $log" >&2
  else
    STATUS[$index]="FAILED rc=$rc"
    echo "gpu_check: FAILED: ${NAMES[$index]} exited $rc; last lines of $log:" >&2
    tail -n 5 "$log" | sed 's/^/    /' >&2
  fi
}

run_step 0 "${TESTS[@]}"
FIGURES[0]="$(tail -n 1 "$LOGS/step0.log")"
run_step 1 "${RASTER[@]}"
FIGURES[1]="$(grep -m 1 'render_dynamic' "$LOGS/step1.log" | sed 's/.*-> *//; s/ *(.*//')"
run_step 2 "${TRAIN[@]}"
train_ips="$(grep -m 1 'images/s:' "$LOGS/step2.log" | awk '{print $2}')"
train_mem="$(grep -m 1 -E 'peak (GPU memory|process RSS)' "$LOGS/step2.log" | awk '{print $(NF-1), $NF}')"
train_busy="$(grep -m 1 'GPU busy:' "$LOGS/step2.log" | awk '{print $3}')"
if [[ -n "$train_ips" && $MODE == cuda ]]; then
  FIGURES[2]="$train_ips images/s/GPU ($(awk -v x="$train_ips" 'BEGIN { printf "%.2f", x / (16 / 1.1 / 8) }')x paper's 1.82), GPU busy ${train_busy:-?}, peak $train_mem"
else
  FIGURES[2]="${train_ips:+$train_ips images/s, peak $train_mem}"
fi
run_step 3 "${PREDICT[@]}"
FIGURES[3]="$(grep -E '^ +(scene_shapes|hypersim|tiny|scannet) ' "$LOGS/step3.log" | awk '{printf "%s/%s %s fps; ", $1, $2, $4}')"
run_step 4 "${SEGMENT[@]}"
FIGURES[4]="$(awk '$1 ~ /^[0-9]+$/ {printf "score>%s: %s frames/s (%s dets); ", $2, $4, $3}' "$LOGS/step4.log")"

echo
echo "gpu_check summary ($MODE; logs in $LOGS)"
printf '%-16s %-14s %7s  %s\n' step status seconds "key figures"
failed=0
for index in 0 1 2 3 4; do
  printf '%-16s %-14s %7s  %s\n' "${NAMES[$index]}" "${STATUS[$index]}" "${SECONDS_TAKEN[$index]}" "${FIGURES[$index]:-}"
  [[ "${STATUS[$index]}" == ok ]] || failed=1
done
if [[ -f "$LOGS/step3.log" ]]; then
  echo
  sed -n '/^model.predict/,$p' "$LOGS/step3.log"
fi
exit $failed
