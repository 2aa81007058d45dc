#!/usr/bin/env bash
# Set up, lint, then run the test suite (real torchrun, real MuJoCo, a real S3 API server on 127.0.0.1), ending with
# the 15 slowest tests. Lanes:
#   bash launch/test.sh                 the whole suite, what CI runs: everything but the opt-in `scale` lane
#   bash launch/test.sh --lane scale    one lane alone (pytest markers: scale, slurm, cluster, slow; `fast` is
#                                       `not slow`: no servers, no multi-process runs)
#   bash launch/test.sh --all           every lane, `scale` included
# Tests run in FTRAIN_TEST_WORKERS processes (pytest-xdist, default: one per core and two more), a file at a time each
# (`-n 0`: one process). At most one test per core runs at once (tests/conftest.py: CPU_SLOTS); the extra workers are
# for the SLURM lane, which mostly waits for slurmctld, and the tests marked `waits` (expiries, timeouts), which run
# beside the others. The longest files go first (tests/conftest.py: LONGEST_FIRST), so that no worker is left with
# one at the end.
# Further arguments go to pytest (a later `-m` or `-n` wins over the lane's). The SLURM lane (tests/cluster) runs a private
# SLURM cluster and skips with the reason where slurm-wlm and munge are missing or not root; the cluster lane needs
# etcd and, for tests/cluster/test_netns.py, network namespaces (root).
# Before the tests it prints how fast the machine is today (launch/machine_speed.py: the CPU seconds of one cold smoke
# run), since these machines differ 2-3x from day to day: compare suites by minutes per smoke CPU-second.
# FTRAIN_TEST_CPU_LOG=FILE appends each test's CPU and wall seconds to FILE (tests/conftest.py): the suite is
# CPU-bound, so that, not --durations, shows what to cut.
set -euo pipefail
cd "$(dirname "$0")/.."

select=(-m "not scale")
case "${1:-}" in
  --all) select=(); shift ;;
  --lane)
    [[ $# -ge 2 ]] || { echo "launch/test.sh: --lane needs a name: scale, slurm, cluster, slow or fast" >&2; exit 2; }
    lane=$2
    shift 2
    [[ $lane == fast ]] && lane="not slow"
    select=(-m "$lane")
    ;;
esac

FTRAIN_TEST_DEPS=1 bash launch/setup.sh
.venv/bin/ruff check ftrain tests launch examples
.venv/bin/ruff format --check ftrain tests launch examples
.venv/bin/python launch/machine_speed.py
workers=(-n "${FTRAIN_TEST_WORKERS:-$(($(nproc) + 2))}" --dist loadfile --no-loadscope-reorder)  # LONGEST_FIRST's order
exec .venv/bin/python -m pytest -p no:cacheprovider --durations=15 "${workers[@]}" "${select[@]}" "$@"
