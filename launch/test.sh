#!/usr/bin/env bash
# Set up, lint, then run the whole test suite (real torchrun, real MuJoCo, a real S3 API server on 127.0.0.1).
# Extra arguments go to pytest: e.g. `-m slurm` runs only the SLURM lane (tests/cluster: a private SLURM cluster;
# skipped with the reason where slurm-wlm and munge are missing or not root), `-m cluster` the multi-node lane (etcd;
# tests/cluster/test_netns.py: machines in network namespaces, as root), `-m "not slurm"` everything else.
set -euo pipefail
cd "$(dirname "$0")/.."
FTRAIN_TEST_DEPS=1 bash launch/setup.sh
.venv/bin/ruff check ftrain tests launch examples
.venv/bin/ruff format --check ftrain tests launch examples
exec .venv/bin/python -m pytest -p no:cacheprovider "$@"
