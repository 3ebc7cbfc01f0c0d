#!/usr/bin/env bash
# README command (2): set up a fresh machine if needed, lint (style, format, import layering), then run the
# test suite (slow tests excluded).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh --tests
${PYTHON:-python3} -m ruff check .
${PYTHON:-python3} -m ruff format --check .
lint-imports  # the layering contracts in pyproject.toml
export PYOPENGL_PLATFORM=${PYOPENGL_PLATFORM:-egl}
# One torch/OpenMP thread per test process: pytest-xdist already runs one process per core, and
# oversubscribed thread pools make small tensor ops orders of magnitude slower.
export OMP_NUM_THREADS=${OMP_NUM_THREADS:-1}
exec ${PYTHON:-python3} -m pytest -n "${USL_TEST_WORKERS:-2}" -q "$@"
