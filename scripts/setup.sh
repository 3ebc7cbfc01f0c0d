#!/usr/bin/env bash
# Idempotent set-up of the active Python environment (a venv, ideally): usl (editable) with its
# dependencies, then a check that offscreen OpenGL works for pyrender. Needs no root: system
# packages are installed only when something is missing and root or password-less sudo is at hand;
# otherwise it names the missing package and stops.
#   bash scripts/setup.sh            # what the main job needs: usl and its own dependencies
#   bash scripts/setup.sh --tests    # also the test and Ray extras, and headless Chromium if it can
#                                    # (the HTML viewer's test renders with it, and skips without it)
# USL_DEPS=lock (default) installs the versions pinned in scripts/requirements.lock, the ones the
# figures in docs/results.md were measured with; USL_DEPS=newest the newest versions pyproject.toml
# allows; USL_DEPS=none installs nothing (an environment made with uv, conda or poetry) and only
# checks it. A torch already installed is kept (a CUDA or CPU build you chose) if pyproject.toml
# allows it (2.13 or newer); pip installs torch otherwise (a local CPU wheel where pip is configured
# to find one, else PyPI's default build).
set -euo pipefail
cd "$(dirname "$0")/.."
TESTS=0
[[ ${1:-} == --tests ]] && TESTS=1
PY=${PYTHON:-python3}
DEPS=${USL_DEPS:-lock}
say() { echo "[setup] $*"; }

# Root, password-less sudo, or nothing: system packages are a fallback, never a requirement of its own.
as_root() {
  if [ "$(id -u)" -eq 0 ]; then "$@"
  elif command -v sudo >/dev/null && sudo -n true 2>/dev/null; then sudo "$@"
  else return 1
  fi
}
apt_install() {  # apt_install PACKAGE... : Debian/Ubuntu packages, if this user may install them
  command -v apt-get >/dev/null || return 1
  as_root apt-get update -qq && DEBIAN_FRONTEND=noninteractive as_root apt-get install -y -qq "$@" >/dev/null
}

EXTRAS=""
((TESTS)) && EXTRAS="[test,ray]"
CONSTRAINTS=$(mktemp)
trap 'rm -f "$CONSTRAINTS"' EXIT
# A torch the environment already has, if pyproject.toml allows it, pinned to itself (its
# distribution's version): neither the lock nor an eager upgrade swaps a build someone chose.
KEPT_TORCH=$($PY scripts/lib/kept_torch.py)
case $DEPS in
  lock)
    grep -v '^torch==' scripts/requirements.lock >"$CONSTRAINTS"
    if [[ -n $KEPT_TORCH ]]; then
      echo "$KEPT_TORCH" >>"$CONSTRAINTS"
    else
      grep '^torch==' scripts/requirements.lock >>"$CONSTRAINTS" || true
    fi
    say "installing usl (editable)${EXTRAS:+ with the extras $EXTRAS} at the versions of scripts/requirements.lock"
    $PY -m pip install -q --root-user-action=ignore -c "$CONSTRAINTS" -e ".$EXTRAS"
    ;;
  newest)
    [[ -z $KEPT_TORCH ]] || echo "$KEPT_TORCH" >"$CONSTRAINTS"
    say "installing usl (editable)${EXTRAS:+ with the extras $EXTRAS} with the newest versions pyproject.toml allows${KEPT_TORCH:+ (keeping $KEPT_TORCH)}"
    $PY -m pip install -q --root-user-action=ignore --upgrade --upgrade-strategy eager -c "$CONSTRAINTS" -e ".$EXTRAS"
    ;;
  none) ;;
  *)
    echo "setup: USL_DEPS=$DEPS: expected 'lock', 'newest' or 'none'" >&2
    exit 2
    ;;
esac
$PY -c 'import sys, torch; print(f"[setup] Python {sys.version.split()[0]}, torch {torch.__version__}")'

# Offscreen OpenGL for pyrender (Scene-Shapes builds, the tests' oracles): EGL through libglvnd,
# with whichever vendor the machine has (NVIDIA's driver on a GPU node, Mesa's llvmpipe on a CPU).
egl_works() {
  PYOPENGL_PLATFORM=${PYOPENGL_PLATFORM:-egl} $PY -c \
    'import pyrender; r = pyrender.OffscreenRenderer(8, 8); r.delete()' >/dev/null 2>&1
}
if ! egl_works; then
  EGL_PACKAGES="libegl1 libegl-mesa0 libgl1-mesa-dri libgles2"
  say "offscreen OpenGL (EGL) does not work here; installing Debian's $EGL_PACKAGES"
  if ! apt_install $EGL_PACKAGES || ! egl_works; then
    echo "setup: pyrender cannot open an offscreen EGL context: this machine needs libEGL.so.1 and an EGL" \
      "vendor library (Debian/Ubuntu packages: $EGL_PACKAGES; a GPU node's NVIDIA driver provides both);" \
      "ask an administrator to install them, or see docs/getting_started.md#install-without-root" >&2
    exit 1
  fi
fi

if ((TESTS)) && ! command -v chromium >/dev/null && ! command -v chromium-browser >/dev/null; then
  say "installing Debian's chromium for the HTML viewer's test (about 350 MB)"
  apt_install chromium || say "chromium is not installed and cannot be here: the viewer's test will be skipped"
fi
