#!/usr/bin/env bash
# Create .venv with the CPU build of torch, this project (editable) and its test/av2/export extras. Idempotent.
# Usage: bash setup.sh   (PYTHON=python3.11 bash setup.sh to pick the interpreter)
set -euo pipefail
cd "$(dirname "$0")"
python=${PYTHON:-python3}

# open3d needs the system library libusb-1.0 (missing on minimal Debian/Ubuntu images).
if ! ldconfig -p | grep -q 'libusb-1.0.so.0'; then
  if [ "$(id -u)" = 0 ]; then
    apt-get update -qq && apt-get install -y -qq libusb-1.0-0 >/dev/null
  else
    echo "setup.sh: open3d needs libusb-1.0; run: sudo apt-get install -y libusb-1.0-0" >&2
    exit 1
  fi
fi

[ -x .venv/bin/python ] || "$python" -m venv .venv
pip=(.venv/bin/python -m pip install -q --disable-pip-version-check)
# The CPU build first: an unpinned torch would pull a multi-GB CUDA build. Elsewhere than this machine use
# --index-url https://download.pytorch.org/whl/cpu for the same effect.
"${pip[@]}" torch==2.13.0
"${pip[@]}" -c .ci/constraints.txt -e ".[test,av2,export]"
# bucketed-scene-flow-eval (metric parity tests) declares the CUDA open3d: install it without its dependencies.
"${pip[@]}" -c .ci/constraints.txt --no-deps bucketed-scene-flow-eval==2.0.25
"${pip[@]}" -c .ci/constraints.txt fvcore iopath opencv-python-headless pyquaternion
echo "setup.sh: .venv ready"
