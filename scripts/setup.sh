#!/usr/bin/env bash
# Set up ari-sfm in ./.venv on a fresh Linux machine (Python >= 3.10):
# the system library open3d needs (libusb-1.0-0, via apt-get where possible),
# then the package and its test extras, editable.
set -euo pipefail
cd "$(dirname "$0")/.."

need_apt=()
ldconfig -p 2>/dev/null | grep -q 'libusb-1.0.so.0' || need_apt+=(libusb-1.0-0)
if [ ${#need_apt[@]} -gt 0 ]; then
  if command -v apt-get >/dev/null 2>&1; then
    sudo=""
    [ "$(id -u)" -ne 0 ] && command -v sudo >/dev/null 2>&1 && sudo="sudo"
    echo "setup: installing system packages: ${need_apt[*]}" >&2
    { $sudo apt-get update -qq && $sudo apt-get install -y -qq "${need_apt[@]}" >/dev/null; } \
      || echo "setup: warning: could not install ${need_apt[*]}; open3d will not import (ari-sfm doctor tells)" >&2
  else
    echo "setup: warning: install ${need_apt[*]} with your package manager (open3d needs it)" >&2
  fi
fi

PY="${PYTHON:-python3}"
if [ ! -x .venv/bin/python ]; then
  "$PY" -m venv .venv
fi
.venv/bin/python -m pip install -q --disable-pip-version-check --upgrade pip
.venv/bin/python -m pip install -q --disable-pip-version-check -e ".[test]"
echo "setup: ready (.venv/bin/ari-sfm)" >&2
