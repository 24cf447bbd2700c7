#!/usr/bin/env bash
# Checks (and where possible installs) what the machine needs beyond pip:
# Python 3.11 with venv, and Mesa's EGL for headless MuJoCo rendering.
#   check_system.sh PYTHON            check python + GL libraries (install GL as root via apt)
#   check_system.sh --print-python P  print the python 3.11 interpreter to use
#   check_system.sh --gl-help         print how to get a GL backend, exit 1
set -euo pipefail

find_python() {
  for p in "$1" python3.11 python3; do
    if command -v "$p" >/dev/null 2>&1 && "$p" -c 'import sys; sys.exit(sys.version_info[:2] != (3, 11))' 2>/dev/null; then
      command -v "$p"; return 0
    fi
  done
  return 1
}

gl_help() {
  echo "hil: no headless OpenGL for MuJoCo. On Debian/Ubuntu: sudo apt-get install libegl1 libegl-mesa0 libgl1-mesa-dri (or libosmesa6)" >&2
  exit 1
}

case "${1:-}" in
  --print-python) find_python "${2:-python3.11}"; exit $? ;;
  --gl-help) gl_help ;;
esac

if ! py=$(find_python "${1:-python3.11}"); then
  echo "hil: Python 3.11 is required. On Debian: sudo apt-get install python3.11 python3.11-venv" >&2
  exit 1
fi
if ! "$py" -c 'import venv, ensurepip' 2>/dev/null; then
  echo "hil: $py lacks the venv module. On Debian: sudo apt-get install python3.11-venv" >&2
  exit 1
fi

have_lib() { ldconfig -p 2>/dev/null | grep -q "$1"; }
if ! have_lib 'libEGL.so.1' || ! have_lib 'libEGL_mesa.so.0'; then
  if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then
    echo "hil: installing Mesa EGL for headless rendering (apt-get)" >&2
    apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq libegl1 libegl-mesa0 libgl1-mesa-dri >/dev/null
  else
    gl_help
  fi
fi
