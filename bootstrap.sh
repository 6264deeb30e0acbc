#!/usr/bin/env bash
# Create (once) the project's virtual environment, then run the given command inside it.
#
#   ./bootstrap.sh zoffload demo            # the built-in demo
#   ./bootstrap.sh python -m pytest -q      # the test suite
#
# Installs the system library open3d needs (libusb-1.0-0) when it is missing and we are root,
# then `pip install -e .[robot,edge,dev]` into .venv. Re-installs only when pyproject.toml changes.
# ZOFFLOAD_EXTRAS overrides the extras (e.g. "robot,edge,dev,train" to train policies).
set -euo pipefail
here=$(cd "$(dirname "$0")" && pwd)
cd "$here"
venv="${ZOFFLOAD_VENV:-$here/.venv}"
extras="${ZOFFLOAD_EXTRAS:-robot,edge,dev}"
python="${PYTHON:-python3}"

log() { printf '[bootstrap] %s\n' "$*" >&2; }

# System library: open3d's wheel links libusb-1.0 and fails to import without it.
if ! ldconfig -p 2>/dev/null | grep -q 'libusb-1.0.so.0'; then
  if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null; then
    log "installing libusb-1.0-0 (needed by open3d)"
    apt-get update -qq >/dev/null && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq libusb-1.0-0 >/dev/null
  else
    log "warning: libusb-1.0-0 is missing; install it (apt-get install libusb-1.0-0) or open3d will not import"
  fi
fi

if [ ! -x "$venv/bin/python" ]; then
  log "creating $venv"
  "$python" -m venv "$venv"
fi
stamp="$venv/.zoffload-installed"
want="$(sha256sum pyproject.toml | cut -d' ' -f1) $extras"
if [ ! -f "$stamp" ] || [ "$(cat "$stamp")" != "$want" ]; then
  log "installing zoffload[$extras] into $venv (first run takes a minute or two)"
  "$venv/bin/python" -m pip install -q --disable-pip-version-check --upgrade pip >/dev/null
  "$venv/bin/python" -m pip install -q --disable-pip-version-check -e ".[$extras]"
  echo "$want" > "$stamp"
fi

if [ "$#" -eq 0 ]; then
  log "environment ready: $venv (run e.g. ./bootstrap.sh zoffload demo)"
  exit 0
fi
export PATH="$venv/bin:$PATH"
exec "$@"
