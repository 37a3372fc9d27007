#!/usr/bin/env bash
# One-time set-up: Debian packages (headless Chromium for the browser tests, Mesa EGL for MuJoCo
# rendering), a virtual environment in .venv, the CPU build of torch 2.13.0 pinned through
# constraints.txt (an unpinned torch would pull several GB of CUDA), then the package with all extras
# (Atari, Fetch, the labeling server, plots, tests) and the documentation tools.
set -euo pipefail
cd "$(dirname "$0")/.."
if [ ! -x /usr/bin/chromium ] || [ ! -e /usr/lib/x86_64-linux-gnu/libEGL_mesa.so.0 ]; then
  SUDO=""; [ "$(id -u)" -ne 0 ] && SUDO="sudo"
  $SUDO apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq chromium chromium-driver libegl1 libegl-mesa0 libgl1-mesa-dri >/dev/null
fi
[ -d .venv ] || python3.11 -m venv .venv 2>/dev/null || python3 -m venv .venv
. .venv/bin/activate
python -m pip install -q --upgrade pip
python -m pip install -q torch==2.13.0
python -m pip install -q -c constraints.txt -e ".[all,docs]"
