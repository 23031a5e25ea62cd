#!/usr/bin/env bash
# Set up gmmgp_app on this machine, then optionally run a job.
#
#   bash scripts/setup.sh          # set up only
#   bash scripts/setup.sh demo     # set up (if needed), then map the bundled demo scan into out/demo/
#   bash scripts/setup.sh test     # set up (if needed), then run the whole test suite
#
# Set-up = system libraries Open3D needs (installed with apt-get when running as root,
# otherwise the exact command is printed), a virtual environment in .venv, and the
# package installed in editable mode with its test extra, at the versions of
# requirements.lock. A second run skips every step whose inputs did not change
# (stamp: hash of pyproject.toml + requirements.lock + python version).
set -euo pipefail
cd "$(dirname "$0")/.."
ROOT=$(pwd)
PY=${PYTHON:-python3}

# --------------------------------------------------------------- system libraries
# open3d imports need libusb/libgl/libegl/libgomp; its GUI and offscreen renderer
# draw through Vulkan (mesa's CPU driver); GUI tests need a virtual display (xvfb).
SYS_PKGS="libusb-1.0-0 libgl1 libegl1 libgomp1 libvulkan1 mesa-vulkan-drivers xvfb xauth"
missing=""
for p in $SYS_PKGS; do
  dpkg -s "$p" >/dev/null 2>&1 || missing="$missing $p"
done
if [ -n "$missing" ]; then
  if [ "$(id -u)" = "0" ] && command -v apt-get >/dev/null; then
    echo "[setup] installing system libraries:$missing"
    export DEBIAN_FRONTEND=noninteractive
    (apt-get install -y -qq --no-install-recommends $missing >/dev/null 2>&1) || {
      apt-get update -qq >/dev/null 2>&1 || true
      apt-get install -y -qq --no-install-recommends $missing >/dev/null
    }
  else
    echo "[setup] missing system libraries:$missing"
    echo "[setup] install them with:  sudo apt-get install -y$missing"
  fi
fi

# --------------------------------------------------------------- python environment
if [ ! -x .venv/bin/python ]; then
  echo "[setup] creating .venv with $($PY --version)"
  $PY -m venv .venv
fi
stamp=$( (cat pyproject.toml requirements.lock; .venv/bin/python --version) | sha256sum | cut -d' ' -f1)
if [ "$(cat .venv/.setup-stamp 2>/dev/null)" != "$stamp" ]; then
  echo "[setup] installing gmmgp_app and its dependencies into .venv (first run: a few minutes)"
  .venv/bin/python -m pip install -q --upgrade pip
  .venv/bin/python -m pip install -q -r requirements.lock      # pinned: reproducible installs
  .venv/bin/python -m pip install -q --no-deps -e ".[test]"
  echo "$stamp" > .venv/.setup-stamp
else
  echo "[setup] .venv is up to date"
fi

.venv/bin/python scripts/warm_cache.py --if-stale  # numba kernels compiled into their cache once
# --------------------------------------------------------------- jobs
case "${1:-}" in
  "") ;;
  demo)
    shift
    exec .venv/bin/gmmgp run assets/demo_street.npz --out out/demo --rrd out/demo/demo.rrd "$@" ;;
  test)
    shift
    exec .venv/bin/python -m pytest -q -m "slow or not slow" "$@" ;;
  *)
    echo "usage: bash scripts/setup.sh [demo|test]" >&2; exit 2 ;;
esac
