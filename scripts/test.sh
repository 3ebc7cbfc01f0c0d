#!/usr/bin/env bash
# README command (2): set up a fresh machine if needed, then run the test suite (slow tests excluded).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
export PYOPENGL_PLATFORM=${PYOPENGL_PLATFORM:-egl}
exec ${PYTHON:-python3} -m pytest -n "${USL_TEST_WORKERS:-2}" -q "$@"
