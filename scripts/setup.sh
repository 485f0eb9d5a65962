#!/usr/bin/env bash
# Set up licalib in ./.venv: system libraries (Debian/Ubuntu, as root), the virtual environment,
# and the package with its test, plot and batch extras. Safe to run again; only missing pieces are
# installed.
#   --tests   also what only the test suite uses: Debian's chromium (headless), which the report
#             tests render pages with, and ouster-sdk (in .venv/ouster) for the real Ouster data
set -euo pipefail
cd "$(dirname "$0")/.."

browser=0
for arg in "$@"; do
  case "$arg" in
    --tests) browser=1 ;;
    *) echo "setup: unknown option $arg (known: --tests)." >&2; exit 1 ;;
  esac
done

PYTHON=${PYTHON:-python3}
if ! command -v "$PYTHON" >/dev/null 2>&1; then
  echo "setup: $PYTHON not found; install Python >= 3.10 (Debian: apt-get install python3)." >&2
  exit 1
fi
if ! "$PYTHON" -c 'import sys; sys.exit(sys.version_info < (3, 10))'; then
  echo "setup: licalib needs Python >= 3.10, found $("$PYTHON" --version 2>&1)." >&2
  exit 1
fi

# System packages: venv support, and the shared libraries open3d's wheel links against.
need=()
if ! "$PYTHON" -c 'import ensurepip, venv' >/dev/null 2>&1; then
  need+=("python3-venv")
fi
if command -v dpkg >/dev/null 2>&1; then
  for pkg in libusb-1.0-0 libgl1 libegl1 libgomp1; do
    dpkg -s "$pkg" >/dev/null 2>&1 || need+=("$pkg")
  done
fi
if [ "$browser" -eq 1 ] && ! command -v chromium >/dev/null 2>&1 \
    && ! command -v chromium-browser >/dev/null 2>&1; then
  need+=("chromium")
fi
if [ ${#need[@]} -gt 0 ]; then
  if [ "$(id -u)" -eq 0 ] && command -v apt-get >/dev/null 2>&1; then
    echo "setup: installing system packages: ${need[*]}"
    export DEBIAN_FRONTEND=noninteractive
    apt-get update -qq
    apt-get install -y -qq --no-install-recommends "${need[@]}" >/dev/null
  else
    echo "setup: missing system packages: ${need[*]}; install them (e.g. sudo apt-get install ${need[*]}) and rerun." >&2
    exit 1
  fi
fi

if [ ! -x .venv/bin/python ]; then
  echo "setup: creating .venv"
  "$PYTHON" -m venv .venv
fi
stamp=.venv/.licalib-installed
if [ ! -f "$stamp" ] || [ pyproject.toml -nt "$stamp" ]; then
  echo "setup: installing licalib and its dependencies into .venv (first run takes a few minutes)"
  .venv/bin/python -m pip install -q --disable-pip-version-check --upgrade pip
  .venv/bin/python -m pip install -q --disable-pip-version-check -e ".[test,plot,batch]"
  touch "$stamp"
fi

# Test-only: ouster-sdk decodes the real Ouster captures of ../shared/data/real for tests/real.
# It pins rosbags==0.9.23 (licalib needs >= 0.11), so it gets a virtual environment of its own,
# .venv/ouster, and hands its output to the tests as numpy arrays. Without it those tests skip.
ouster=.venv/ouster
if [ "$browser" -eq 1 ] && [ ! -f "$ouster/.licalib-installed" ]; then
  echo "setup: installing ouster-sdk (test-only) into $ouster"
  if "$PYTHON" -m venv "$ouster" \
    && "$ouster/bin/python" -m pip install -q --disable-pip-version-check "ouster-sdk==1.0.1"; then
    touch "$ouster/.licalib-installed"
  else
    echo "setup: ouster-sdk could not be installed; the Ouster decoding tests will be skipped." >&2
  fi
fi
.venv/bin/licalib --version
