#!/usr/bin/env bash
# README command (1): the main job, end to end on the built-in Scene-Shapes default, on CPU.
#   build a small Scene-Shapes set, and three held-out ones with other seeds (other shape models,
#   other scenes) -> validate + contact sheet -> train a recipe (`tiny`) -> evaluate USL against
#   the paper's baselines on every input view of the held-out builds -> report (Markdown table of
#   mean ± std over the builds, JSON, pictures).
# Re-running resumes every stage (the builds keep finished shards, training continues from its
# last checkpoint). Recipe: $USL_MAIN_CONFIG (default tiny; tiny_long trains 5,000 iterations,
# about 25 minutes or more of a 2-core CPU). Output folder: $USL_MAIN_OUT (default runs/main for
# tiny, runs/main_RECIPE for another, so that no run resumes under another recipe's name).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
export PYOPENGL_PLATFORM=${PYOPENGL_PLATFORM:-egl}

CONFIG=${USL_MAIN_CONFIG:-tiny}
OUT=${USL_MAIN_OUT:-runs/main$([[ $CONFIG == tiny ]] || echo "_$CONFIG")}
DATA=$OUT/scene_shapes
RUN=$OUT/train
EVAL=$OUT/eval
mkdir -p "$OUT"
start=$(date +%s)
stage() { echo "== $* ($(( $(date +%s) - start )) s in)"; }  # each stage's start, for the time it takes

source scripts/lib/scene_shapes_builds.sh
stage "1/4 build Scene-Shapes ($DATA) and held-out builds with seeds ${HELDOUT_SEEDS[*]} ($OUT/heldout/seed*)"
build_scene_shapes "$DATA" 0 "$TRAIN_SCENES"
heldout_builds "$OUT"

stage "2/4 validate and summarise"
for build in "$DATA" "${HELDOUT_SEEDS[@]/#/$OUT/heldout/seed}"; do
  usl-records validate "$build"
done
usl-records info "$DATA" --sheet "$OUT/contact_sheet.png"

stage "3/4 train the $CONFIG recipe on CPU"
# One process per core (DDP over gloo) on 2+ cores, each with half of the recipe's batch: the
# same batches as one process, ~1.4x the iterations per second. USL_MAIN_PROCS=1 forces one.
source scripts/lib/train_procs.sh
PROCS=${USL_MAIN_PROCS:-$(( $(cores) >= 2 ? 2 : 1 ))}
# the recipe's batch is global: train_with_procs splits it over the processes
USL_TRAIN_BATCH=$(recipe_batch "$CONFIG")
export USL_TRAIN_BATCH
if compgen -G "$RUN/checkpoints/model_*.pt" >/dev/null; then
  # --resume continues the run's own saved recipe, whatever --config says
  resumed=$(sed -n 's/^name: *//p' "$RUN/config.yaml")
  if [[ $resumed != "$CONFIG" ]]; then
    echo "main_job: $RUN/config.yaml: the run there trained recipe '$resumed', not '$CONFIG'; set USL_MAIN_OUT to another folder" >&2
    exit 2
  fi
  train_with_procs "$PROCS" --config "$CONFIG" --out "$RUN" --resume
else
  train_with_procs "$PROCS" --config "$CONFIG" --out "$RUN" data.root="$DATA"
fi

stage "4/4 evaluate on every input view of the held-out builds against the baselines"
# the diagnostic rows (USL's layout with spheres, and with its own detections) on the first build only
evaluate_heldout "$OUT" "$RUN" "$EVAL" random,fixed,model layout_only,detections 6
echo "main job done in $(( $(date +%s) - start )) s: report in $EVAL/table.md, pictures in $EVAL/seed${HELDOUT_SEEDS[0]}/pictures/"
