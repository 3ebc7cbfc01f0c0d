# Sourced by the main job and the experiment scripts (main_job.sh, recipe_experiment.sh, table1.sh):
# the Scene-Shapes builds they train and score on, so every one of them sees the same data.
#
#   source scripts/lib/scene_shapes_builds.sh
#   build_scene_shapes OUT SEED SCENES [builder options]      # SCENES scenes and as many shape models
#   experiment_builds DATA TRAIN_SCENES HELDOUT_SCENES [builder options, e.g. --quiet]
#
# Both build the main job's format (8 views per scene at two heights, 128^2), or resume a build (a
# finished one is verified and kept). experiment_builds makes a training build (seed 0) in
# $TRAIN = DATA/train_seed0_TRAIN_SCENES and the held-out build with another seed (seed 1: other
# shape models, other scenes) in $HELDOUT = DATA/heldout_seed1. Every split of the held-out build
# is unseen; score its train split, the largest.

cores() { env -u OMP_NUM_THREADS -u OMP_THREAD_LIMIT nproc; }  # GNU nproc obeys OMP_NUM_THREADS

build_scene_shapes() {  # OUT SEED SCENES [builder options]
  local out=$1 seed=$2 scenes=$3
  shift 3
  python3 -m pipelines.scene_shapes.cli --out "$out" --seed "$seed" --num-scenes "$scenes" --num-models "$scenes" \
    --resolution 128 --views 8 --heights 2 --workers "$(cores)" "$@"
}

experiment_builds() {  # DATA TRAIN_SCENES HELDOUT_SCENES [builder options]
  local data=$1 train_scenes=$2 heldout_scenes=$3
  shift 3
  TRAIN=$data/train_seed0_$train_scenes
  HELDOUT=$data/heldout_seed1
  build_scene_shapes "$TRAIN" 0 "$train_scenes" "$@"
  build_scene_shapes "$HELDOUT" 1 "$heldout_scenes" "$@"
}
