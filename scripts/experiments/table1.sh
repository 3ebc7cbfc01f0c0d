#!/usr/bin/env bash
# The paper's Table 1 (Scene-Shapes) at CPU scale: train every row with several seeds on the main
# job's Scene-Shapes build, score each run on the held-out build with another --seed (other shape
# models, other scenes; its train split, every 8th view an input view), score the fixed- and
# random-depth spheres once, and write a Markdown table of mean ± std over seeds.
#
#   bash scripts/experiments/table1.sh                  # every row, seeds 0,1,2, the tiny recipe's own budget
#   bash scripts/experiments/table1.sh --dry-run        # print the budget (iterations, runs, estimated time) only
#   bash scripts/experiments/table1.sh --quick          # smoke run: 10-scene builds, 10 iterations, 2 seeds (~3 min)
#   bash scripts/experiments/table1.sh --seeds 0,1,2,3,4 --iters 600 --out runs/table1_600
#
# Options: --seeds LIST (train.seed values; default 0,1,2, --quick 0,1), --iters N (per run;
# default the recipe's optim.max_iter, and the recipe's schedule is scaled to another N),
# --out DIR (default runs/table1, --quick runs/table1_quick), --data DIR (the builds; default
# runs/experiments/data, the builds of scripts/experiments/recipe_experiment.sh, --quick OUT/data),
# --jobs N (runs side by side, one thread each; default: the cores), --config RECIPE (default tiny).
# Rows and their overrides: scripts/experiments/table1_plan.py. A row whose config key this checkout lacks is
# reported as "skipped: key not available". The budget is printed before anything runs.
#
# Resumable: a run with its final checkpoint and its held-out metrics.json is not redone, a run
# stopped halfway resumes from its last checkpoint, finished builds are kept; more seeds can be
# added later with the same options. Writes OUT/table1.md (and table1.json), OUT/runs/<row>/seed<k>/
# {train,eval,train.log,eval.log}, OUT/baselines/eval and OUT/progress.log.
set -euo pipefail
cd "$(dirname "$0")/../.."
export PYOPENGL_PLATFORM=${PYOPENGL_PLATFORM:-egl}
# this checkout's code (python -m, not the console scripts), whatever pip last installed
export PYTHONPATH="$PWD${PYTHONPATH:+:$PYTHONPATH}"
source scripts/lib/scene_shapes_builds.sh
ARGS="$*" QUICK=0 DRY=0 SEEDS= ITERS= OUT= DATA= JOBS=$(cores) CONFIG=tiny
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
    -h|--help) usage; exit 0 ;;
    *) echo "table1.sh: error: unknown option $1 (see --help)" >&2; exit 2 ;;
  esac
  shift
done

EXTRA=() EVAL_OPTS=(--pictures 2)
if ((QUICK)); then
  SEEDS=${SEEDS:-0,1} ITERS=${ITERS:-10} OUT=${OUT:-runs/table1_quick} DATA=${DATA:-$OUT/data}
  SCENES=10 EXTRA=(val.period=0) EVAL_OPTS=(--pictures 1 --samples-3d 2000)
else
  SEEDS=${SEEDS:-0,1,2} OUT=${OUT:-runs/table1} DATA=${DATA:-runs/experiments/data} SCENES=60
fi
[[ $SEEDS =~ ^[0-9]+(,[0-9]+)*$ ]] || { echo "table1.sh: error: --seeds $SEEDS is not a comma-separated list of integers" >&2; exit 2; }
[[ $JOBS =~ ^[1-9][0-9]*$ ]] || { echo "table1.sh: error: --jobs $JOBS is not a positive integer" >&2; exit 2; }
IFS=, read -ra SEED_LIST <<< "$SEEDS"
TRAIN=$DATA/train_seed0_$SCENES HELDOUT=$DATA/heldout_seed1  # as experiment_builds names them
EVAL_VIEWS=every:8  # of the 8 views per scene: one input view per scene of the split (80% of the scenes)
start=$(date +%s)

echo "== Table 1 at CPU scale -> $OUT"
mkdir -p "$OUT"
python3 scripts/experiments/table1_plan.py --config "$CONFIG" ${ITERS:+--iters "$ITERS"} --seeds "$SEEDS" --jobs "$JOBS" --out "$OUT" \
  --data "train=$TRAIN ($SCENES scenes) heldout=$HELDOUT ($SCENES scenes, split train, input views $EVAL_VIEWS)" \
  --eval-views $((SCENES * 8 / 10)) \
  ${EXTRA[@]+"${EXTRA[@]}"} | tee "$OUT/plan.txt"
((DRY)) && exit 0

echo "== builds: $TRAIN, $HELDOUT"
experiment_builds "$DATA" "$SCENES" "$SCENES" --quiet

THIS_RUN=$OUT/.this_run  # this invocation's finished runs (their durations) and failures
rm -rf "$THIS_RUN" && mkdir -p "$THIS_RUN" "$OUT/runs"
mapfile -t PLAN < "$OUT/plan.tsv"
total=$(( $(cut -f3 "$OUT/plan.tsv" | grep -cx train || true) * ${#SEED_LIST[@]} ))

progress() {  # one line per finished run: runs done, time so far, estimate of what is left
  local done timed left=""
  done=$(find "$OUT/runs" -path '*/eval/metrics.json' | wc -l)
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

baselines() {
  [[ -f $OUT/baselines/eval/metrics.json ]] && return 0
  rm -rf "$OUT/baselines/eval.partial" && mkdir -p "$OUT/baselines"
  python3 -m usl.cli.evaluate "$HELDOUT" --split train --input-views "$EVAL_VIEWS" --rows fixed,random --device cpu \
    --out "$OUT/baselines/eval.partial" --quiet "${EVAL_OPTS[@]}" > "$OUT/baselines/eval.log" 2>&1 \
    || fail baselines "baselines: usl-eval" "$OUT/baselines/eval.log" || return 1
  mv "$OUT/baselines/eval.partial" "$OUT/baselines/eval"
  progress "Fixed and Random depth scored"
}

run_one() {  # SLUG LABEL SEED OVERRIDES...: train (or resume), then score on the held-out build
  local slug=$1 label=$2 seed=$3
  shift 3
  local run=$OUT/runs/$slug/seed$seed began iters what resume=()
  began=$(date +%s)
  for o in "$@"; do [[ $o == optim.max_iter=* ]] && iters=${o#*=}; done
  if [[ -f $run/eval/metrics.json ]]; then
    progress "$label, seed $seed: done before: $(python3 scripts/experiments/table1_summary.py --run "$run/eval")"
    return 0
  fi
  mkdir -p "$run"
  if [[ -f $run/train/checkpoints/last_checkpoint && $(< "$run/train/checkpoints/last_checkpoint") == "$(printf 'model_%07d.pt' "$iters")" ]]; then
    what="trained before"
  else
    if [[ -f $run/train/checkpoints/last_checkpoint ]]; then resume=(--resume); else rm -rf "$run/train"; fi
    # CPU time is the figure that holds on a shared machine (table1_plan.py estimates from it)
    /usr/bin/time -o "$run/train_time.txt" -f "%e %U" \
      python3 -m usl.cli.train ${resume[@]+"${resume[@]}"} --config "$CONFIG" --out "$run/train" data.root="$TRAIN" \
      train.seed="$seed" train.cpu_threads=1 "$@" > "$run/train.log" 2>&1 \
      || fail "${slug}_$seed" "$label, seed $seed: usl-train" "$run/train.log" || return 1
    what=$(awk -v n="$iters" '{ printf "trained %d iterations in %d s wall, %d s CPU (%.2f s per iteration, start-up included)", n, $1, $2, $2 / n }' \
      "$run/train_time.txt")
  fi
  local scoring
  scoring=$(date +%s)
  rm -rf "$run/eval.partial"
  /usr/bin/time -o "$run/eval_time.txt" -f "%e %U" \
    python3 -m usl.cli.evaluate "$HELDOUT" --split train --input-views "$EVAL_VIEWS" --checkpoint "$run/train" --rows model \
    --device cpu --out "$run/eval.partial" --quiet "${EVAL_OPTS[@]}" > "$run/eval.log" 2>&1 \
    || fail "${slug}_$seed" "$label, seed $seed: usl-eval" "$run/eval.log" || return 1
  mv "$run/eval.partial" "$run/eval"
  echo $(( $(date +%s) - began )) > "$THIS_RUN/${slug}_$seed.s"
  progress "$label, seed $seed: $what; scored in $(( $(date +%s) - scoring )) s: $(python3 scripts/experiments/table1_summary.py --run "$run/eval")"
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
failed=$(find "$THIS_RUN" -name '*.failed' | wc -l)
if ((failed)); then echo "table1.sh: $failed run(s) failed; the table holds the others (re-run to retry)" >&2; exit 1; fi
