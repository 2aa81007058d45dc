#!/usr/bin/env bash
# The main job: set up, then supervised 2-process PPO on HalfCheetah-v5 with checkpoints in runs/halfcheetah.
# Extra arguments go to `ftrain supervise` (e.g. iterations=50, --storage s3://bucket/runs/hc in place of runs/halfcheetah).
set -euo pipefail
cd "$(dirname "$0")/.."
bash launch/setup.sh
storage=(--storage runs/halfcheetah)
for argument in "$@"; do
    case "$argument" in --storage | --storage=* | storage.url=*) storage=() ;; esac
done
exec .venv/bin/ftrain supervise --nproc-per-node 2 configs/halfcheetah.yaml ${storage[@]+"${storage[@]}"} "$@"
