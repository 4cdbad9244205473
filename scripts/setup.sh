#!/usr/bin/env bash
# Set up icpbench on a fresh Debian machine with Python 3.11 (run as root, or with sudo available).
# Idempotent: a second run only checks what is already installed.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}

# Open3D loads libusb-1.0 at import time.
if ! ldconfig -p 2>/dev/null | grep -q "libusb-1.0.so.0"; then
  SUDO=""; [ "$(id -u)" -ne 0 ] && SUDO="sudo"
  $SUDO apt-get update -qq
  $SUDO apt-get install -y -qq libusb-1.0-0
fi

# The CPU build of torch (plain `torch` would pull several GB of CUDA packages).
if ! $PY -c "import torch" 2>/dev/null; then
  $PY -m pip install -q torch==2.13.0
fi

# icpbench itself (editable), the test tools, the optional GICP target and the Ray executor.
$PY -m pip install -q -e ".[test,gicp,ray]"
