#!/usr/bin/env bash
# One-time, idempotent set-up of a fresh machine: offscreen OpenGL (EGL/Mesa), torch (CPU build where
# no GPU build is wanted), and usl itself in editable mode.
#   bash scripts/setup.sh            # what the main job needs: usl and its own dependencies
#   bash scripts/setup.sh --tests    # also the test and Ray extras, and headless Chromium, which the
#                                    # HTML viewer's test renders with
set -euo pipefail
cd "$(dirname "$0")/.."
TESTS=0
[[ ${1:-} == --tests ]] && TESTS=1

if ! ldconfig -p | grep -q 'libEGL_mesa.so'; then
  echo "[setup] installing Debian's EGL/Mesa packages for offscreen rendering"
  SUDO=""; [ "$(id -u)" -ne 0 ] && SUDO="sudo"
  $SUDO apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq libegl1 libegl-mesa0 libgl1-mesa-dri libgles2 >/dev/null
fi

if ((TESTS)) && ! command -v chromium >/dev/null; then  # ~1.5 min and ~350 MB: the tests alone need it
  echo "[setup] installing Debian's chromium"
  SUDO=""; [ "$(id -u)" -ne 0 ] && SUDO="sudo"
  $SUDO apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq chromium >/dev/null
fi

PY=${PYTHON:-python3}
if ! $PY -c 'import torch' 2>/dev/null; then
  echo "[setup] installing torch 2.13.0"
  $PY -m pip install -q --root-user-action=ignore torch==2.13.0
fi
# The extras are the tests' (pytest, pandas, datasets, ruff, TensorBoard, Ray): on a fresh machine
# they add half again to the install of torch and usl (pip's cache off: 42 s without them, 63 s
# with them on an idle 2-core host; 95 s and 180 s on a busy one), time the main job trains instead.
EXTRAS=""
((TESTS)) && EXTRAS="[test,ray]"
echo "[setup] installing usl (editable) and its dependencies${EXTRAS:+ with the extras $EXTRAS}"
$PY -m pip install -q --root-user-action=ignore -e ".$EXTRAS"
