#!/usr/bin/env bash
# README command (1): the main job, end to end on the built-in Scene-Shapes default, on CPU.
#   build a small Scene-Shapes set -> validate + contact sheet -> train the `tiny` recipe
#   -> evaluate USL against the paper's baselines -> report (Markdown table, JSON, pictures).
# Re-running resumes every stage (the build keeps finished shards, training continues from its
# last checkpoint). Output folder: $USL_MAIN_OUT (default runs/main).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
export PYOPENGL_PLATFORM=${PYOPENGL_PLATFORM:-egl}

OUT=${USL_MAIN_OUT:-runs/main}
DATA=$OUT/scene_shapes
RUN=$OUT/train
EVAL=$OUT/eval
mkdir -p "$OUT"
start=$(date +%s)

echo "== 1/4 build Scene-Shapes ($DATA)"
usl-build-scene-shapes --out "$DATA" --num-scenes 60 --num-models 60 --resolution 128 --views 8 --heights 2 \
  --workers "$(nproc)"

echo "== 2/4 validate and summarise"
usl-records validate "$DATA"
usl-records info "$DATA" --sheet "$OUT/contact_sheet.png"

echo "== 3/4 train the tiny recipe on CPU"
if compgen -G "$RUN/checkpoints/model_*.pt" >/dev/null; then
  usl-train --config tiny --out "$RUN" --resume
else
  usl-train --config tiny --out "$RUN" data.root="$DATA"
fi

echo "== 4/4 evaluate against the baselines"
usl-eval "$DATA" --split val --checkpoint "$RUN" --rows random,fixed,model,detections --out "$EVAL" --pictures 4

python3 scripts/main_job_verdict.py "$EVAL/metrics.json"
echo "main job done in $(( $(date +%s) - start )) s: report in $EVAL/table.md, pictures in $EVAL/pictures/"
