#!/usr/bin/env bash
# Sets up everything ftrain needs on a fresh Debian machine, idempotently, one line per step:
#   - Debian's Mesa EGL and libOpenGL for headless MuJoCo rendering, python3-venv where the Python lacks ensurepip,
#     etcd-server, and SLURM and munge for the SLURM tests
#     (when run as root and missing; the SLURM tests start daemons of their own, with their own configuration);
#   - a virtualenv in .venv with the CPU build of torch 2.13.0 installed FIRST (a bare torch requirement would
#     pull a multi-GB CUDA build), then ftrain itself with its test, export, render, etcd and bench extras;
#   - for the tests, Azurite (the Azure Blob emulator, from npm) in .venv/azurite.
# torch comes from PyTorch's CPU wheel index when it answers (TORCH_INDEX_URL overrides it), else from the default
# package index (which, on a machine without that index, may serve the CUDA build). A stamp in .venv, keyed by
# pyproject.toml and the torch version, skips the pip steps when nothing changed: a second run starts in seconds.
set -euo pipefail
cd "$(dirname "$0")/.."

TORCH_VERSION=2.13.0
TORCH_INDEX_URL=${TORCH_INDEX_URL:-https://download.pytorch.org/whl/cpu}
say() { echo "setup: $*"; }

# debian_packages WHAT PACKAGE...: install Debian packages that are missing (as root, with apt-get), else warn.
debian_packages() {
  local what=$1
  shift
  dpkg -s "$@" >/dev/null 2>&1 && return 0
  if [[ $(id -u) -eq 0 ]] && command -v apt-get >/dev/null; then
    say "installing $* ($what)..."
    apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq "$@" >/dev/null
  else
    say "warning: $* are missing; install them for $what" >&2
  fi
}
debian_packages "headless rendering: 'ftrain play --video'" libegl1 libegl-mesa0 libgl1-mesa-dri libopengl0
# For the tests only (launch/test.sh sets FTRAIN_TEST_DEPS=1), as they bring daemons and SLURM's own commands, which
# a training node must not get by accident: etcd (3.4 in Debian 12, serving the v2 API torchrun's etcd-v2 rendezvous
# speaks) and SLURM with munge for the private clusters of the tests (which skip without them). Never fatal.
if [[ ${FTRAIN_TEST_DEPS:-0} == 1 ]]; then
  debian_packages "the tests of the etcd-v2 rendezvous" etcd-server || say "warning: etcd-server not installed" >&2
  debian_packages "the private SLURM cluster of tests/cluster" slurm-wlm munge || say "warning: SLURM not installed" >&2
  debian_packages "the failing FUSE mount of tests/failing_mount.py" fuse3 || say "warning: FUSE not installed" >&2
fi

python=${PYTHON:-python3}
if ! "$python" -c "import ensurepip, venv" 2>/dev/null; then  # Debian's python3 makes a virtualenv without pip
  debian_packages "a virtualenv with pip for $python" python3-venv
fi
if ! .venv/bin/python -m pip --version >/dev/null 2>&1; then  # none yet, or one a failed run left without pip
  say "creating .venv with $("$python" --version)..."
  "$python" -m venv --clear .venv
fi

# Azurite, the Azure Blob emulator that the abfs:// tests run against (they skip without it), for the tests only: in
# the virtualenv (no root needed, and gone with it), where tests/helpers.py looks first. Never fatal.
if [[ ${FTRAIN_TEST_DEPS:-0} == 1 && ! -x .venv/azurite/node_modules/.bin/azurite-blob ]]; then
  if command -v npm >/dev/null; then
    say "installing Azurite 3 (npm) into .venv/azurite..."
    npm install --prefix .venv/azurite --no-audit --no-fund --loglevel=error azurite@3 >/dev/null ||
      say "warning: Azurite not installed (npm install failed); the Azure Blob tests skip" >&2
  else
    say "warning: npm is missing; install node and npm for the Azure Blob tests (they skip without Azurite)" >&2
  fi
fi

stamp=".venv/.ftrain-setup-$( (cat pyproject.toml; echo "torch $TORCH_VERSION") | sha256sum | cut -c1-16)"
if [[ -f $stamp ]]; then
  say "up to date (delete $stamp to reinstall)"
  exit 0
fi

pip=(.venv/bin/python -m pip install -q --disable-pip-version-check)
torch_pip=("${pip[@]}")
if [ -t 1 ]; then  # torch's download takes minutes: on a terminal pip shows its progress bar (quiet, it shows none)
  torch_pip=(.venv/bin/python -m pip install --disable-pip-version-check --progress-bar on)
fi
say "upgrading pip..."
"${pip[@]}" --upgrade pip
if ! .venv/bin/python -c "import torch, sys; sys.exit(torch.__version__.split('+')[0] != '$TORCH_VERSION')" 2>/dev/null; then
  if .venv/bin/python -c "import urllib.request, sys; urllib.request.urlopen(sys.argv[1], timeout=5)" \
    "$TORCH_INDEX_URL/torch/" >/dev/null 2>&1; then
    say "installing torch $TORCH_VERSION (CPU build, from $TORCH_INDEX_URL)..."
    "${torch_pip[@]}" --index-url "$TORCH_INDEX_URL" "torch==$TORCH_VERSION"
  else
    say "installing torch $TORCH_VERSION (from the default package index: $TORCH_INDEX_URL does not answer)..."
    "${torch_pip[@]}" "torch==$TORCH_VERSION"
  fi
fi
say "installing ftrain and its test, export, render and bench extras..."
# setuptools' editable install warns, in a banner, that a folder named like the package may shadow it: the checkout
# is that folder, by design
PYTHONWARNINGS="ignore:Editable installation" "${pip[@]}" -e ".[test,bench]"
rm -f .venv/.ftrain-setup-*
touch "$stamp"
say "done"
