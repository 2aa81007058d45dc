#!/usr/bin/env bash
# Sets up everything ftrain needs on a fresh Debian machine, idempotently:
#   - Debian's Mesa EGL libraries for headless MuJoCo rendering (when run as root and missing);
#   - a virtualenv in .venv with the CPU build of torch 2.13.0 installed FIRST (a bare torch requirement would
#     pull a multi-GB CUDA build), then ftrain itself with its test, export, render and bench extras.
set -euo pipefail
cd "$(dirname "$0")/.."

render_packages=(libegl1 libegl-mesa0 libgl1-mesa-dri)
if ! dpkg -s "${render_packages[@]}" >/dev/null 2>&1; then
  if [[ $(id -u) -eq 0 ]] && command -v apt-get >/dev/null; then
    apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq "${render_packages[@]}" >/dev/null
  else
    echo "setup: warning: ${render_packages[*]} are missing; install them for 'ftrain play --video'" >&2
  fi
fi

python=${PYTHON:-python3}
[[ -x .venv/bin/python ]] || "$python" -m venv .venv
.venv/bin/python -m pip install -q --upgrade pip
.venv/bin/python -m pip install -q "torch==2.13.0"
.venv/bin/python -m pip install -q -e ".[test,bench]"
