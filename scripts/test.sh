#!/usr/bin/env bash
# README command (2): set up the active Python environment (scripts/setup.sh --tests), lint (style,
# format, import layering), then run the test suite (slow tests excluded). Arguments go to pytest.
# USL_DEPS=newest tests the newest dependency versions instead of scripts/requirements.lock's.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh --tests
PY=${PYTHON:-python3}
$PY -m ruff check .
$PY -m ruff format --check .
# the layering contracts in pyproject.toml (lint-imports lies beside the interpreter, venv or not)
"$($PY -c 'import os, sys; print(os.path.dirname(sys.executable))')/lint-imports"
export PYOPENGL_PLATFORM=${PYOPENGL_PLATFORM:-egl}
# One torch/OpenMP thread per test process: pytest-xdist already runs one process per core, and
# oversubscribed thread pools make small tensor ops orders of magnitude slower.
export OMP_NUM_THREADS=${OMP_NUM_THREADS:-1}
exec $PY -m pytest -n "${USL_TEST_WORKERS:-2}" -q "$@"
