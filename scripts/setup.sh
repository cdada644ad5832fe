#!/usr/bin/env bash
# Set up dp5k on a fresh machine that has Python 3.11: system packages, a virtual environment in .venv,
# PyTorch 2.13.0 (CPU build), the project with its dev and peer extras. Idempotent: re-running is cheap.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3.11}
command -v "$PY" >/dev/null || PY=python3

need_apt=()
# libusb-1.0-0: pyusb's backend and `import open3d`; umockdev + socat: capture peer tests.
for pkg in libusb-1.0-0 umockdev socat libgomp1; do
  dpkg -s "$pkg" >/dev/null 2>&1 || need_apt+=("$pkg")
done
if [ ${#need_apt[@]} -gt 0 ]; then
  SUDO=""; [ "$(id -u)" -ne 0 ] && SUDO="sudo"
  echo "setup: installing system packages: ${need_apt[*]}"
  $SUDO apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq "${need_apt[@]}" >/dev/null
fi

if [ ! -x .venv/bin/python ]; then
  echo "setup: creating .venv"
  "$PY" -m venv .venv
fi
. .venv/bin/activate
stamp=.venv/.dp5k-installed
if [ ! -f "$stamp" ] || [ pyproject.toml -nt "$stamp" ]; then
  python -m pip install -q --upgrade pip
  # Pin torch first: an unpinned torch would pull several GB of CUDA wheels.
  python -m pip install -q "torch==2.13.0"
  python -m pip install -q -e ".[dev,peers]"
  touch "$stamp"
fi
echo "setup: ready ($(python -c 'import torch, cv2; print("torch", torch.__version__, "opencv", cv2.__version__)'))"
