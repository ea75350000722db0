#!/usr/bin/env bash
# Set up ari-sfm in ./.venv on a fresh Linux machine (Python >= 3.10):
# the system library open3d needs (libusb-1.0-0, via apt-get where possible),
# then the package and its test extras, editable, and its kernels compiled.
#   --tests  also install what the tests and the documentation need: the docs extra (MkDocs,
#            Material, mkdocstrings) and Chromium (Debian package chromium) to render report.html headless.
set -euo pipefail
cd "$(dirname "$0")/.."

tests=0
for arg in "$@"; do
  case "$arg" in
    --tests) tests=1 ;;
    *) echo "setup: unknown option $arg (known: --tests)" >&2; exit 2 ;;
  esac
done

need_apt=()
ldconfig -p 2>/dev/null | grep -q 'libusb-1.0.so.0' || need_apt+=(libusb-1.0-0)
if [ "$tests" -eq 1 ] && ! command -v chromium >/dev/null 2>&1 && ! command -v chromium-browser >/dev/null 2>&1; then
  need_apt+=(chromium)
fi
if [ ${#need_apt[@]} -gt 0 ]; then
  if command -v apt-get >/dev/null 2>&1; then
    sudo=""
    [ "$(id -u)" -ne 0 ] && command -v sudo >/dev/null 2>&1 && sudo="sudo"
    echo "setup: installing system packages: ${need_apt[*]}" >&2
    { $sudo apt-get update -qq && $sudo apt-get install -y -qq "${need_apt[@]}" >/dev/null; } \
      || echo "setup: warning: could not install ${need_apt[*]}; open3d needs libusb-1.0-0 (ari-sfm doctor tells), the report's browser test chromium" >&2
  else
    echo "setup: warning: install ${need_apt[*]} with your package manager (open3d needs it)" >&2
  fi
fi

PY="${PYTHON:-python3}"
if [ ! -x .venv/bin/python ]; then
  "$PY" -m venv .venv
fi
.venv/bin/python -m pip install -q --disable-pip-version-check --upgrade pip
extras="test"
if [ "$tests" -eq 1 ]; then extras="test,docs"; fi
.venv/bin/python -m pip install -q --disable-pip-version-check -e ".[$extras]"
# The kernels compiled as a built wheel ships them (ari_sfm/_compiled, ~1 min): the first run
# does not compile them (a kernel module edited later is compiled by numba on first use).
rm -rf ari_sfm/_compiled
.venv/bin/python -m ari_sfm.kernel_build ari_sfm/_compiled \
  || echo "setup: warning: the kernels were not compiled ahead; numba compiles them on first use" >&2
echo "setup: ready (.venv/bin/ari-sfm)" >&2
