#!/usr/bin/env bash
# Installs vio-testbed on a fresh Debian/Ubuntu machine: the offscreen-GL system packages (EGL, with
# OSMesa as fallback) and the Python package with its test extra. Works as root or inside a venv
# (with sudo for the apt step when not root).
set -euo pipefail
cd "$(dirname "$0")/.."

GL_PACKAGES="libegl1 libegl-mesa0 libgl1-mesa-dri libgbm1 libopengl0 libosmesa6"
if command -v apt-get >/dev/null 2>&1; then
  SUDO=""
  if [ "$(id -u)" -ne 0 ]; then SUDO="sudo"; fi
  export DEBIAN_FRONTEND=noninteractive
  missing=""
  for p in $GL_PACKAGES; do dpkg -s "$p" >/dev/null 2>&1 || missing="$missing $p"; done
  if [ -n "$missing" ]; then
    $SUDO apt-get update -qq
    # shellcheck disable=SC2086
    $SUDO apt-get install -y -qq --no-install-recommends $missing python3-pip python3-venv >/dev/null
  fi
fi

PY="${PYTHON:-python3}"
# Outside a virtual environment, Debian's system Python refuses pip installs (PEP 668) unless told.
if [ -z "${VIRTUAL_ENV:-}" ]; then export PIP_BREAK_SYSTEM_PACKAGES=1; fi
"$PY" -m pip install -q --upgrade pip >/dev/null 2>&1 || true
"$PY" -m pip install -q -e ".[test]"
echo "vio-testbed installed: $("$PY" -c 'import viotb; print(viotb.__version__)')"
