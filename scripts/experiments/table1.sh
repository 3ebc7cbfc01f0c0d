#!/usr/bin/env bash
# The paper's Table 1 (Scene-Shapes) at CPU scale: train every row with several seeds on the main
# job's Scene-Shapes build, score each run as the main job scores its model (every input view of the
# train split of the held-out builds with seeds 1, 2, 3: other shape models, other scenes; a run's
# figure is its mean over the three builds), score the fixed- and random-depth spheres once the same
# way, and write a Markdown table of mean ± std over seeds with the paper's orderings judged on it.
#
#   bash scripts/experiments/table1.sh                  # every row, seeds 0,1,2, the tiny recipe's own budget
#   bash scripts/experiments/table1.sh --dry-run        # print the budget (iterations, runs, estimated time) only
#   bash scripts/experiments/table1.sh --quick          # smoke run: 10-scene training build, 3-scene held-out builds, 10 iterations, 2 seeds (~4 min)
#   bash scripts/experiments/table1.sh --seeds 0,1,2,3,4 --iters 600 --out runs/table1_600
#   bash scripts/experiments/table1.sh --record docs/results/table1   # also keep the scores in the checkout
#
# Options: --seeds LIST (train.seed values; default 0,1,2, --quick 0,1), --iters N (per run;
# default the recipe's optim.max_iter, and the recipe's schedule is scaled to another N),
# --out DIR (default runs/table1, --quick runs/table1_quick), --data DIR (the training build and
# DATA/heldout/seed<k>; default runs/experiments/data, the builds of
# scripts/experiments/recipe_experiment.sh, --quick OUT/data),
# --jobs N (runs side by side, one thread each; default: the cores), --config RECIPE (default tiny),
# --record DIR (keep every finished run's scores, the baselines', the plan and the table in DIR, a
# small tree in OUT's layout without checkpoints or pictures; a run recorded there and missing from
# OUT is copied into OUT first, so the table resumes from DIR on a machine that lacks OUT).
# Rows and their overrides: scripts/experiments/table1_plan.py. A row whose config key this checkout lacks is
# reported as "skipped: key not available". The budget is printed before anything runs.
#
# Resumable: a run with its final checkpoint and its eval/summary.json (written once every build is
# scored) is not redone; a run stopped while scoring keeps the builds it scored (seed<k>/metrics.json)
# and scores only the others; a run stopped while training resumes from its last checkpoint;
# finished builds are kept; more seeds can be added later with the same options. Writes
# OUT/table1.md (and table1.json), OUT/runs/<row>/seed<k>/{train,train.log,eval}, each eval folder
# holding usl-eval's report of every build (seed<k>/, its log and CPU time seed<k>.log, seed<k>.time)
# and their summary.json; OUT/baselines/eval the same; OUT/progress.log.
set -euo pipefail
cd "$(dirname "$0")/../.."
export PYOPENGL_PLATFORM=${PYOPENGL_PLATFORM:-egl}
# this checkout's code (python -m, not the console scripts), whatever pip last installed
export PYTHONPATH="$PWD${PYTHONPATH:+:$PYTHONPATH}"
source scripts/lib/scene_shapes_builds.sh
ARGS="$*" QUICK=0 DRY=0 SEEDS= ITERS= OUT= DATA= JOBS=$(cores) CONFIG=tiny RECORD=
# one thread per process: --jobs processes share the cores (oversubscribed threads slow every op)
export OMP_NUM_THREADS=1 MKL_NUM_THREADS=1
usage() { sed -n '2,/^set -e/p' "$0" | sed '$d' | sed 's/^# \{0,1\}//'; }
value() { [[ -n ${2:-} ]] || { echo "table1.sh: error: $1 needs a value" >&2; exit 2; }; }
while (($#)); do
  case $1 in
    --quick) QUICK=1 ;;
    --dry-run) DRY=1 ;;
    --seeds) value "$@"; SEEDS=$2; shift ;;
    --iters) value "$@"; ITERS=$2; shift ;;
    --out) value "$@"; OUT=$2; shift ;;
    --data) value "$@"; DATA=$2; shift ;;
    --jobs) value "$@"; JOBS=$2; shift ;;
    --config) value "$@"; CONFIG=$2; shift ;;
    --record) value "$@"; RECORD=$2; shift ;;
    -h|--help) usage; exit 0 ;;
    *) echo "table1.sh: error: unknown option $1 (see --help)" >&2; exit 2 ;;
  esac
  shift
done

EXTRA=() EVAL_OPTS=() PICTURES=2 HELDOUT_OPTS=()
if ((QUICK)); then
  SEEDS=${SEEDS:-0,1} ITERS=${ITERS:-10} OUT=${OUT:-runs/table1_quick} DATA=${DATA:-$OUT/data}
  # small held-out builds so scoring stays a smoke test too: 3 scenes (one in the train split, 8 input
  # views) of 9 shape models, the fewest that give each split a model of every category (this
  # --num-models comes after, so replaces, the scene count build_scene_shapes passes)
  SCENES=10 HELDOUT_SCENES=3 HELDOUT_OPTS=(--num-models 9) EXTRA=(val.period=0) EVAL_OPTS=(--samples-3d 2000) PICTURES=1
else
  SEEDS=${SEEDS:-0,1,2} OUT=${OUT:-runs/table1} DATA=${DATA:-runs/experiments/data} SCENES=$TRAIN_SCENES
fi
[[ $SEEDS =~ ^[0-9]+(,[0-9]+)*$ ]] || { echo "table1.sh: error: --seeds $SEEDS is not a comma-separated list of integers" >&2; exit 2; }
[[ $JOBS =~ ^[1-9][0-9]*$ ]] || { echo "table1.sh: error: --jobs $JOBS is not a positive integer" >&2; exit 2; }
IFS=, read -ra SEED_LIST <<< "$SEEDS"
TRAIN=$DATA/train_seed0_$SCENES  # as recipe_experiment.sh names it; heldout_builds makes DATA/heldout/seed<k>
HELDOUT="$DATA/heldout/seed{$(IFS=,; echo "${HELDOUT_SEEDS[*]}")}"  # for the log
start=$(date +%s)

record() {  # WHAT...: runs/<row>/seed<k>, baselines or files of OUT, into RECORD (see table1_record.py)
  [[ -z $RECORD ]] || python3 scripts/experiments/table1_record.py save "$OUT" "$RECORD" "$@"
}

echo "== Table 1 at CPU scale -> $OUT${RECORD:+ (scores recorded in $RECORD)}"
mkdir -p "$OUT"
[[ -z $RECORD ]] || python3 scripts/experiments/table1_record.py restore "$RECORD" "$OUT"
# the builds are named by what makes them (seeds and sizes), not by where they are, so a recorded
# table resumes on another machine whose builds lie elsewhere
python3 scripts/experiments/table1_plan.py --config "$CONFIG" ${ITERS:+--iters "$ITERS"} --seeds "$SEEDS" --jobs "$JOBS" --out "$OUT" \
  --data "train=Scene-Shapes seed 0 ($SCENES scenes) heldout=Scene-Shapes seeds $(IFS=,; echo "${HELDOUT_SEEDS[*]}") ($HELDOUT_SCENES scenes each${HELDOUT_OPTS[*]:+, ${HELDOUT_OPTS[*]}}, split train, input views all)" \
  --heldout-builds ${#HELDOUT_SEEDS[@]} --heldout-scenes "$HELDOUT_SCENES" \
  ${EXTRA[@]+"${EXTRA[@]}"} | tee "$OUT/plan.txt"
((DRY)) && exit 0
record budget.txt plan.tsv plan.txt

echo "== builds: $TRAIN, $HELDOUT"
build_scene_shapes "$TRAIN" 0 "$SCENES" --quiet
heldout_builds "$DATA" --quiet ${HELDOUT_OPTS[@]+"${HELDOUT_OPTS[@]}"}

mkdir -p "$OUT/runs"
# this invocation's finished runs (their durations) and failures: its own folder, so that invocations
# for other seeds may share OUT
THIS_RUN=$(mktemp -d "$OUT/.this_run.XXXXXX")
trap 'rm -rf "$THIS_RUN"' EXIT
mapfile -t PLAN < "$OUT/plan.tsv"
total=$(( $(cut -f3 "$OUT/plan.tsv" | grep -cx train || true) * ${#SEED_LIST[@]} ))

progress() {  # one line per finished run: runs done, time so far, estimate of what is left
  local done timed left=""
  done=$(for seed in "${SEED_LIST[@]}"; do ls "$OUT"/runs/*/seed"$seed"/eval/summary.json 2>/dev/null; done | wc -l)
  timed=$(cat "$THIS_RUN"/*.s 2>/dev/null | awk '{ s += $1; n++ } END { if (n) printf "%d", s / n }' || true)
  if [[ -n $timed ]] && ((done < total)); then left=", ~$(( (total - done) * timed / JOBS / 60 + 1 )) min left"; fi
  echo "[$done/$total runs, $(( ($(date +%s) - start) / 60 )) min$left] $*" | tee -a "$OUT/progress.log"
}

fail() {  # RUN_ID MESSAGE LOG
  touch "$THIS_RUN/$1.failed"
  progress "FAILED $2 (see $3):"
  tail -n 3 "$3" | sed 's/^/    /'
  return 1
}

score() {  # RUN_ID LABEL EVAL usl-eval options...: every held-out build EVAL lacks, then EVAL/summary.json
  # as the main job's evaluate_heldout, but one build after another (JOBS runs already share the cores)
  local id=$1 label=$2 eval=$3 seed shown
  shift 3
  mkdir -p "$eval"
  for seed in "${HELDOUT_SEEDS[@]}"; do
    [[ -f $eval/seed$seed/metrics.json ]] && continue  # scored before this invocation
    shown=0
    [[ $seed == "${HELDOUT_SEEDS[0]}" ]] && shown=$PICTURES  # pictures of the first build only, as the main job
    rm -rf "$eval/seed$seed.partial"
    /usr/bin/time -o "$eval/seed$seed.time" -f "%e %U" \
      python3 -m usl.cli.evaluate "$DATA/heldout/seed$seed" --split train --input-views all --device cpu \
      --out "$eval/seed$seed.partial" --quiet --pictures "$shown" ${EVAL_OPTS[@]+"${EVAL_OPTS[@]}"} "$@" \
      > "$eval/seed$seed.log" 2>&1 || fail "$id" "$label: usl-eval on held-out build $seed" "$eval/seed$seed.log" || return 1
    mv "$eval/seed$seed.partial" "$eval/seed$seed"
  done
  python3 scripts/experiments/table1_summary.py --combine "$eval" > "$eval/summary.log" 2>&1 \
    || fail "$id" "$label: the summary over the builds" "$eval/summary.log" || return 1
}

baselines() {
  if [[ ! -f $OUT/baselines/eval/summary.json ]]; then
    score baselines baselines "$OUT/baselines/eval" --rows fixed,random || return 1
    progress "Fixed and Random depth scored"
  fi
  record baselines
}

run_one() {  # SLUG LABEL SEED OVERRIDES...: train (or resume), then score on the held-out builds
  local slug=$1 label=$2 seed=$3
  shift 3
  local run=$OUT/runs/$slug/seed$seed began iters what resume=()
  began=$(date +%s)
  for o in "$@"; do [[ $o == optim.max_iter=* ]] && iters=${o#*=}; done
  if [[ -f $run/eval/summary.json ]]; then
    progress "$label, seed $seed: done before: $(python3 scripts/experiments/table1_summary.py --run "$run/eval")"
    record "runs/$slug/seed$seed"
    return 0
  fi
  mkdir -p "$run"
  if [[ -f $run/train/checkpoints/last_checkpoint && $(< "$run/train/checkpoints/last_checkpoint") == "$(printf 'model_%07d.pt' "$iters")" ]]; then
    what="trained before"
  else
    local last=$run/train/checkpoints/last_checkpoint from=0 name
    if [[ -f $last ]]; then
      resume=(--resume) name=$(< "$last") && from=$((10#${name:6:7}))  # model_<7 digits>.pt
    else
      rm -rf "$run/train"
    fi
    # CPU time is the figure that holds on a shared machine (table1_plan.py estimates from it): wall
    # and CPU seconds of this invocation, and the iterations it trained (fewer when it resumed)
    /usr/bin/time -o "$run/train_time.txt" -f "%e %U $((iters - from))" \
      python3 -m usl.cli.train ${resume[@]+"${resume[@]}"} --config "$CONFIG" --out "$run/train" data.root="$TRAIN" \
      train.seed="$seed" train.cpu_threads=1 "$@" > "$run/train.log" 2>&1 \
      || fail "${slug}_$seed" "$label, seed $seed: usl-train" "$run/train.log" || return 1
    what=$(awk -v from="$from" '{ printf "trained %d iterations%s in %d s wall, %d s CPU (%.2f s per iteration, start-up included)", $3, from ? " from " from : "", $1, $2, $2 / $3 }' \
      "$run/train_time.txt")
  fi
  local scoring
  scoring=$(date +%s)
  score "${slug}_$seed" "$label, seed $seed" "$run/eval" --checkpoint "$run/train" --rows model || return 1
  echo $(( $(date +%s) - began )) > "$THIS_RUN/${slug}_$seed.s"
  progress "$label, seed $seed: $what; scored in $(( $(date +%s) - scoring )) s: $(python3 scripts/experiments/table1_summary.py --run "$run/eval")"
  record "runs/$slug/seed$seed"
}

launch() {  # run "$@" in the background once fewer than JOBS runs are going
  while (( $(jobs -rp | wc -l) >= JOBS )); do wait -n || true; done
  "$@" < /dev/null &
}

echo "== training and scoring ($total runs, $JOBS at a time; logs in $OUT/runs/<row>/seed<k>/)"
for line in "${PLAN[@]}"; do
  IFS=$'\t' read -r slug label status overrides <<< "$line"
  [[ $status == train ]] || echo "$label: $status" | tee -a "$OUT/progress.log"
done
launch baselines
for line in "${PLAN[@]}"; do
  IFS=$'\t' read -r slug label status overrides <<< "$line"
  [[ $status == train ]] || continue
  read -ra row_overrides <<< "$overrides"
  for seed in "${SEED_LIST[@]}"; do
    launch run_one "$slug" "$label" "$seed" "${row_overrides[@]}"
  done
done
wait

echo "== table: $OUT/table1.md"
python3 scripts/experiments/table1_summary.py "$OUT"
{
  echo
  echo "Command: \`bash scripts/experiments/table1.sh${ARGS:+ $ARGS}\`; this invocation took $(( ($(date +%s) - start) / 60 )) min wall."
  sed 's/^/    /' "$OUT/plan.txt"
} >> "$OUT/table1.md"
record table1.md table1.json
failed=$(find "$THIS_RUN" -name '*.failed' | wc -l)
if ((failed)); then echo "table1.sh: $failed run(s) failed; the table holds the others (re-run to retry)" >&2; exit 1; fi
