# Sourced by the job scripts: usl-train with one process, or DDP over PROCS processes on this machine.
#   train_with_procs PROCS usl-train-arguments...
# With PROCS > 1 each process takes train.batch_size / PROCS of the recipe's images (the recipe's
# batch is global): the same batches as one process, one process per core (gloo), each with the
# machine's cores over PROCS OpenMP threads unless OMP_NUM_THREADS says otherwise (set, so that
# torchrun has nothing to announce; a recipe's train.cpu_threads still rules torch's ops). The caller
# passes the recipe's batch as USL_TRAIN_BATCH (`recipe_batch` reads it; 4 when unset).
#   recipe_batch RECIPE [key=value ...]   # train.batch_size of the recipe with the overrides
source "$(dirname "${BASH_SOURCE[0]}")/cores.sh"

recipe_batch() {
  python3 -c "import sys; from usl.config import load_config; print(load_config(sys.argv[1], sys.argv[2:]).train.batch_size)" "$@"
}

train_with_procs() {
  local procs=$1
  shift
  if (( procs > 1 )); then
    local threads=$(( $(cores) / procs ))
    OMP_NUM_THREADS=${OMP_NUM_THREADS:-$(( threads > 1 ? threads : 1 ))} \
      torchrun --standalone --nproc_per_node "$procs" -m usl.cli.train "$@" train.batch_size=$(( ${USL_TRAIN_BATCH:-4} / procs ))
  else
    python3 -m usl.cli.train "$@"
  fi
}
