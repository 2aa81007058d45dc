#!/usr/bin/env bash
# Issue #34's many-rank rows, as one prepared command for a lent 16-core machine (the tool library's `device`: 15
# minutes in all, at most 10 a command). First weak scaling against the machine's own ceiling at 1, 2, 4, 8 and 16
# ranks (launch/bench_scale.py, one round each, the ceiling measured on both sides of it), with each N's phases, mean
# and slowest rank; then strong scaling: configs/halfcheetah_large.yaml's global batch (ENVS=256 environments x 16
# steps) shared by 2, 4, 8 and 16 ranks, against N whole 1-rank jobs side by side. MODE=weak or MODE=strong runs one
# part alone. Each run prints its transport, and a collective that falls back to gloo fails the script (bench_scale.py
# exits 1). Each table goes to $OUT (the device's return folder) or runs/device_scale as it is printed, so a run
# cut short by its timeout still returns what finished.
#
# That machine's image has Python 3.12 and torch 2.11 (enough: ftrain needs torch>=2.6), numpy, PyYAML, fsspec and
# tensorboard; the rest travels as wheels in .whl/ (ignored by git: `echo /.whl/ >> .git/info/exclude`), made here with
#   python3 -m pip download --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
#     --platform manylinux_2_28_x86_64 --platform manylinux_2_17_x86_64 --platform manylinux2014_x86_64 \
#     --platform any -d .whl mujoco==4.0.1 mujoco-core==4.0.1 mujoco-studio==4.0.1 gymnasium==1.4.0 \
#     rsl-rl-lib==5.5.1 tensordict==0.15.3 pyvers==0.2.3 glfw==2.11.0 PyOpenGL==3.1.10 Farama-Notifications==0.0.6 \
#     setproctitle==1.3.8 GitPython gitdb smmap botocore jmespath
# (39 MB; tensordict 0.15 wants torch>=2.11, which that image has; botocore: the checkpoint code imports its
# exceptions). Then the device's run, with carry [".whl"] and a timeout of 560 s: `bash launch/device_scale.sh` (8
# minutes there on 2026-12-04, the machine's start not counted; MODE=strong reruns the second part alone). MODE
# (both, weak or strong), ENVS, SCALE_CONFIG, RANKS, ROUNDS and ITERATIONS override the defaults below;
# on this 2-core machine `RANKS="1 2" bash launch/device_scale.sh` tries the same path (without .whl/ it uses the
# venv).
set -euo pipefail
cd "$(dirname "$0")/.."
python=python3
if [ -d .whl ] && [ -n "${OUT:-}" ]; then  # on the device: its python3, with the wheels beside it
  python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl
  export PYTHONPATH="/tmp/site:$PWD"
elif [ -x .venv/bin/python ]; then
  python=.venv/bin/python
fi
export PYTHONUNBUFFERED=1 OMP_NUM_THREADS=1
out="${OUT:-runs/device_scale}"
mkdir -p "$out"
"$python" -c 'import torch, mujoco; print("torch", torch.__version__, "mujoco", mujoco.__version__)' \
  | tee "$out/versions.txt"
# shellcheck disable=SC2086 # RANKS and ENVS are lists
weak() {
  "$python" launch/bench_scale.py --ranks ${RANKS:-1 2 4 8 16} --rounds "${ROUNDS:-1}" \
    --iterations "${ITERATIONS:-30}" 2>&1 | tee "$out/bench_scale.txt"
}
# shellcheck disable=SC2086 # RANKS and ENVS are lists
strong() {
  "$python" launch/bench_scale.py --strong ${ENVS:-256} --config "${SCALE_CONFIG:-halfcheetah_large}" \
    --ranks ${RANKS:-2 4 8 16} --rounds "${ROUNDS:-1}" --iterations "${ITERATIONS:-12}" 2>&1 \
    | tee "$out/bench_scale_strong.txt"
}
case "${MODE:-both}" in
  both) weak && strong ;;
  weak) weak ;;
  strong) strong ;;
  *)
    echo "device_scale.sh: MODE=${MODE} is none of both, weak and strong" >&2
    exit 2 ;;
esac
