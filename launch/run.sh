#!/usr/bin/env bash
# The main job: set up, then supervised 2-process PPO on HalfCheetah-v5 with checkpoints in runs/halfcheetah.
# Extra arguments go to `ftrain supervise` (e.g. iterations=50, --storage s3://bucket/runs/hc).
set -euo pipefail
cd "$(dirname "$0")/.."
bash launch/setup.sh
exec .venv/bin/ftrain supervise --nproc-per-node 2 configs/halfcheetah.yaml --storage runs/halfcheetah "$@"
