#!/usr/bin/env bash
# Set up radarslam on a fresh Debian/Ubuntu machine: system library for open3d, a virtual
# environment in .venv, torch's CPU wheel first (a bare "torch" would pull a multi-GB CUDA build),
# then the project with its test extras. Idempotent: a second run only checks.
set -euo pipefail
cd "$(dirname "$0")/.."

if ! ldconfig -p 2>/dev/null | grep -q 'libusb-1.0.so.0'; then
  SUDO=""; [ "$(id -u)" -eq 0 ] || SUDO="sudo"
  $SUDO apt-get update -qq
  $SUDO apt-get install -y -qq libusb-1.0-0
fi

PY=${PYTHON:-python3}
[ -x .venv/bin/python ] || "$PY" -m venv .venv
. .venv/bin/activate
python -c "import torch" 2>/dev/null || python -m pip install -q "torch==2.13.0"
python -m pip install -q -e ".[dev,faiss]"
# The devkit is a test-time cross-check only; it declares numpy<2, so install it without deps.
python -c "import nuscenes" 2>/dev/null || python -m pip install -q --no-deps "nuscenes-devkit==1.2.0"
