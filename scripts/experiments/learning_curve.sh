#!/usr/bin/env bash
# Held-out metrics against training iterations: scores every checkpoint of a run (or the ones
# named) on a build the model never saw, and prints one Markdown row per checkpoint. This is how
# "what it takes" is measured: train once with train.keep_checkpoints=0, then read the curve.
#
#   bash scripts/experiments/learning_curve.sh RUN HELDOUT [ITER ...]
#   bash scripts/experiments/learning_curve.sh runs/experiments/long/train runs/experiments/data/heldout/seed1 1000 2000 4000
#
# Environment: USL_CURVE_VIEWS (input views per held-out scene, default every:8: one view a scene, quicker than the main job's all, for curves).
# Each checkpoint's report goes to RUN/curve/ITER/; a checkpoint already scored is not redone.
set -euo pipefail
cd "$(dirname "$0")/../.."
export PYOPENGL_PLATFORM=${PYOPENGL_PLATFORM:-egl}
export PYTHONPATH="$PWD${PYTHONPATH:+:$PYTHONPATH}"
RUN=${1:?usage: learning_curve.sh RUN HELDOUT [ITER ...]}
HELDOUT=${2:?usage: learning_curve.sh RUN HELDOUT [ITER ...]}
shift 2
if (( $# )); then
  checkpoints=(); for it in "$@"; do checkpoints+=("$(printf '%s/checkpoints/model_%07d.pt' "$RUN" "$it")"); done
else
  checkpoints=("$RUN"/checkpoints/model_*.pt)
fi
for ckpt in "${checkpoints[@]}"; do
  [[ -f $ckpt ]] || { echo "learning_curve: $ckpt: no such checkpoint" >&2; exit 1; }
  it=$(basename "$ckpt" .pt); it=$((10#${it#model_}))
  out=$RUN/curve/$it
  [[ -f $out/metrics.json ]] || python3 -m usl.cli.evaluate "$HELDOUT" --split train \
    --input-views "${USL_CURVE_VIEWS:-every:8}" --checkpoint "$ckpt" --rows model --out "$out" --quiet --pictures 0 >/dev/null
done
python3 - "$RUN/curve" <<'EOF'
import json, sys
from pathlib import Path
print("| Iteration | Ch. ↓ | F1@0.1 | Mask IoU input | Mask IoU views |")
print("|---:|:---:|:---:|:---:|:---:|")
for folder in sorted(Path(sys.argv[1]).iterdir(), key=lambda p: int(p.name)):
    m = next(p for p in json.loads((folder / "metrics.json").read_text())["predictors"] if p["name"] == "USL")["metrics"]
    print(f"| {int(folder.name)} | {m['chamfer']:.3f} | {m['f1']:.1f} | {100 * m['mask_iou_input']:.1f} | {100 * m['mask_iou_views']:.1f} |")
EOF
