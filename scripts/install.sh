#!/usr/bin/env bash
# Install evtrack with its dependencies into ./.venv (created when missing).
#
#   ./scripts/install.sh          # runtime + dev tools (pytest, hypothesis, ruff, filterpy)
#
# torch: torch 2.13.0 is installed unless the environment already has a torch (install your
# CUDA build of torch first to use a GPU). pip takes the wheel its indexes offer: on a machine
# with a local CPU wheel (a find-links folder) that one; from PyPI on Linux the CUDA build,
# gigabytes. For the CPU build from PyTorch's own index:
#   EVTRACK_TORCH_INDEX=https://download.pytorch.org/whl/cpu ./scripts/install.sh
# A looser spec than ==2.13.0 would pull a newer torch and its CUDA wheels.
# System libraries: the simulator renders headless through EGL (Mesa llvmpipe on CPU, or the
# NVIDIA driver). When no EGL context can be made, this script installs Debian's Mesa packages
# if it runs as root with apt-get, and otherwise prints the command to run.
set -euo pipefail
cd "$(dirname "$0")/.."

PYTHON=${PYTHON:-python3}
[ -x .venv/bin/python ] || "$PYTHON" -m venv .venv
PY=.venv/bin/python

"$PY" -m pip install -q --upgrade pip
if ! "$PY" -c "import torch" 2>/dev/null; then
    if [ -n "${EVTRACK_TORCH_INDEX:-}" ]; then
        "$PY" -m pip install -q --index-url "$EVTRACK_TORCH_INDEX" "torch==2.13.0"
    else
        "$PY" -m pip install -q "torch==2.13.0"
    fi
fi
"$PY" -m pip install -q -e ".[dev]"

APT_PACKAGES="libegl1 libgl1 libgl1-mesa-dri libgbm1"
if ! "$PY" -c "import moderngl; moderngl.create_standalone_context(backend='egl').release()" \
        >/dev/null 2>&1; then
    if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null; then
        echo "install.sh: no EGL context; installing $APT_PACKAGES" >&2
        apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq $APT_PACKAGES
    else
        echo "install.sh: warning: headless OpenGL (EGL) is unavailable, so the simulator" \
             "cannot render. Install: sudo apt-get install $APT_PACKAGES" >&2
    fi
fi
echo "install.sh: evtrack installed in .venv ($("$PY" -c 'import evtrack; print(evtrack.__version__)'))"
