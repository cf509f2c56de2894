#!/usr/bin/env bash
# Create .venv with the CPU build of torch, this project (editable) and its test/av2/export/lint/viz extras, and
# compile the teacher's numba kernels. Idempotent.
# Usage: bash setup.sh   (PYTHON=python3.11 bash setup.sh to pick the interpreter)
set -euo pipefail
cd "$(dirname "$0")"
python=${PYTHON:-python3}

# open3d links against the system library libusb-1.0 (missing on minimal Debian/Ubuntu images): as root it is
# installed here, else the copy that the libusb-package wheel ships (a dependency) serves (icpflow/core/open3d_loader.py).
# open3d's offscreen renderer (eval.py render=N) needs Vulkan: the loader and Mesa's drivers (software rendering where
# there is no GPU).
has_library() { ldconfig -p | grep -F "$1" >/dev/null; }  # not grep -q: an early exit fails the pipe (pipefail)
vulkan=()
has_library libvulkan.so.1 || vulkan+=(libvulkan1)
has_library libvulkan_lvp.so || vulkan+=(mesa-vulkan-drivers)
missing=("${vulkan[@]}")
has_library libusb-1.0.so.0 || missing+=(libusb-1.0-0)
if [ ${#missing[@]} -gt 0 ] && [ "$(id -u)" = 0 ]; then
  apt-get update -qq && apt-get install -y -qq "${missing[@]}" >/dev/null
elif [ ${#vulkan[@]} -gt 0 ]; then
  echo "setup.sh: open3d's offscreen render (eval.py render=N) needs Vulkan; run: sudo apt-get install -y" \
    "${vulkan[*]}" >&2
fi

[ -x .venv/bin/python ] || "$python" -m venv .venv
pip=(.venv/bin/python -m pip install -q --disable-pip-version-check)
# torch's CPU build first (PyPI's torch is a multi-GB CUDA build): from PyTorch's CPU index where it answers, else the
# pin from pip's own indexes, which hold the CPU build only where a machine keeps a local wheel of it (as CI's does).
cpu_index=https://download.pytorch.org/whl/cpu
if .venv/bin/python -c "import urllib.request; urllib.request.urlopen('$cpu_index/torch/', timeout=10)" 2>/dev/null \
  && "${pip[@]}" torch==2.13.0 --index-url "$cpu_index"; then
  echo "setup.sh: torch's CPU build from $cpu_index"
else
  echo "setup.sh: $cpu_index unreachable here: torch==2.13.0 from pip's indexes (the CPU build where they hold it)"
  "${pip[@]}" torch==2.13.0
fi
"${pip[@]}" -c .ci/constraints.txt -e ".[dev]"
# bucketed-scene-flow-eval (metric parity tests) declares the CUDA open3d: install it without its dependencies.
"${pip[@]}" -c .ci/constraints.txt --no-deps bucketed-scene-flow-eval==2.0.25
"${pip[@]}" -c .ci/constraints.txt fvcore iopath opencv-python-headless pyquaternion
# The teacher's numba kernels, compiled once here (about 1 min on 2 cores) rather than in the first labelling run
.venv/bin/python -m icpflow.teacher.warmup
echo "setup.sh: .venv ready"
