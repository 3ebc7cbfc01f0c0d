# Sourced by the main job and the experiment scripts (main_job.sh, recipe_experiment.sh, table1.sh):
# the Scene-Shapes builds they train and score on, so every one of them sees the same data.
#
#   source scripts/lib/scene_shapes_builds.sh
#   build_scene_shapes OUT SEED SCENES [builder options]      # SCENES scenes and as many shape models
#   build_scene_shapes OUT 0 "$TRAIN_SCENES"                  # the main job's training build
#   heldout_builds DATA [builder options]                     # DATA/heldout/seed{1,2,3}, 20 scenes each
#   evaluate_heldout DATA CHECKPOINT EVAL ROWS FIRST_ROWS PICTURES   # every input view of those, mean ± std
#
# Both builders make the main job's format (8 views per scene at two heights, 128^2), or resume a
# build (a finished one is verified and kept). Every split of a held-out build is unseen; its train
# split, the largest, is scored. table1.sh scores each of its runs on the same builds, one after
# another, and sets HELDOUT_SCENES lower for its smoke run.

source "$(dirname "${BASH_SOURCE[0]}")/cores.sh"

build_scene_shapes() {  # OUT SEED SCENES [builder options]
  local out=$1 seed=$2 scenes=$3
  shift 3
  python3 -m pipelines.scene_shapes.cli --out "$out" --seed "$seed" --num-scenes "$scenes" --num-models "$scenes" \
    --resolution 128 --views 8 --heights 2 --workers "$(cores)" "$@"
}

# The main job's training build: scenes, and as many procedural shape models. `tiny` learns the
# scenes it trains on by heart: with Muon, 600 scenes score higher on unseen ones than 180 in the
# same iterations, for about 45 s more of building (docs/experiments/data.md, "More scenes").
TRAIN_SCENES=600

# The held-out protocol of the main job and of recipe_experiment.sh: three builds with other seeds
# (other shape models, other scenes), every view of every scene of their train split (the largest)
# an input view in turn, scored by usl-eval, then summarised as mean ± std over the builds.
HELDOUT_SEEDS=(1 2 3)
HELDOUT_SCENES=20  # per build: 16 train scenes x 8 views = 128 input views, 384 over the three

heldout_builds() {  # DATA [builder options]: DATA/heldout/seed<k> for each held-out seed
  local data=$1 seed
  shift
  for seed in "${HELDOUT_SEEDS[@]}"; do
    build_scene_shapes "$data/heldout/seed$seed" "$seed" "$HELDOUT_SCENES" "$@"
  done
}

evaluate_heldout() {  # DATA CHECKPOINT EVAL ROWS FIRST_ROWS PICTURES
  # usl-eval of each build into EVAL/seed<k> with ROWS (FIRST_ROWS and PICTURES pictures added on the
  # first build only, as scoring every view is the bulk of the job's time), then the summary
  local data=$1 checkpoint=$2 eval=$3 rows=$4 first_rows=$5 pictures=$6 seed status=0 pids=()
  mkdir -p "$eval"
  echo "evaluate_heldout: scoring builds ${HELDOUT_SEEDS[*]} side by side; progress in $eval/seed<k>.log"
  for seed in "${HELDOUT_SEEDS[@]}"; do  # side by side: they share the cores and end together
    local here=$rows shown=0
    if [[ $seed == "${HELDOUT_SEEDS[0]}" ]]; then
      here=$rows${first_rows:+,$first_rows}
      shown=$pictures
    fi
    OMP_NUM_THREADS=1 python3 -m usl.cli.evaluate "$data/heldout/seed$seed" --split train --input-views all \
      --checkpoint "$checkpoint" --rows "$here" --out "$eval/seed$seed" --pictures "$shown" \
      >"$eval/seed$seed.log" 2>&1 &
    pids+=($!)
  done
  for seed in "${HELDOUT_SEEDS[@]}"; do
    wait "${pids[0]}" || { status=1; echo "evaluate_heldout: usl-eval failed on $data/heldout/seed$seed:" >&2; tail -n 5 "$eval/seed$seed.log" >&2; }
    pids=("${pids[@]:1}")
  done
  [[ $status == 0 ]] || return 1
  python3 scripts/lib/main_job_verdict.py "$eval"
}
