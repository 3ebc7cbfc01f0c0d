#!/usr/bin/env bash
# Re-pins scripts/requirements.lock: every dependency of usl and of its test, ray, tensorboard and captures
# extras, for every Python pyproject.toml allows (one universal file, markers where versions
# differ), at the torch version the figures in docs/results.md were measured with. Run it when a
# dependency changes in pyproject.toml, then run the main job and the tests (.ci/run) on the result.
#   bash scripts/update_lock.sh
set -euo pipefail
cd "$(dirname "$0")/.."
TORCH=2.13.0
TOOLS=$(mktemp -d)
trap 'rm -rf "$TOOLS"' EXIT
python3 -m venv "$TOOLS/venv"
"$TOOLS/venv/bin/pip" install -q uv
echo "torch==$TORCH" >"$TOOLS/torch.txt"
"$TOOLS/venv/bin/uv" pip compile pyproject.toml --extra test --extra ray --extra tensorboard --extra captures \
  --universal --python-version 3.10 --constraint "$TOOLS/torch.txt" --no-header --quiet \
  --output-file scripts/requirements.lock.new
{
  echo "# The versions the main job, the tests and the figures in docs/results.md use (scripts/setup.sh"
  echo "# installs them as pip constraints). Written by scripts/update_lock.sh: do not edit by hand."
  cat scripts/requirements.lock.new
} >scripts/requirements.lock
rm scripts/requirements.lock.new
echo "scripts/requirements.lock: $(grep -c '^[a-z]' scripts/requirements.lock) pins"
