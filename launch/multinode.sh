#!/usr/bin/env bash
# Supervised training on several machines: run this same script on every node, with the node's rank.
#
#   export FTRAIN_RDZV_SECRET=...   # the same on every node: make one with `openssl rand -hex 32`
#   NNODES=2 NODE_RANK=0 HEAD=10.0.0.5 bash launch/multinode.sh configs/halfcheetah.yaml --storage s3://bucket/runs/hc
#   NNODES=2 NODE_RANK=1 HEAD=10.0.0.5 bash launch/multinode.sh configs/halfcheetah.yaml --storage s3://bucket/runs/hc
#
# HEAD is node 0's address, reachable from every node (node 0's supervisor listens on that address only); PORT
# (default 29400) a free port there, where node 0's supervisor agrees each attempt with the others, answering only
# requests signed with FTRAIN_RDZV_SECRET (or with the contents of the file `--rdzv-secret-file FILE` names).
# Storage must be shared by all nodes (s3://, or a shared filesystem). NPROC_PER_NODE defaults to the node's CPU
# count. Extra arguments go to `ftrain supervise`. NNODES=MIN:MAX (e.g. 2:4) trains elastically on as many nodes as
# there are (see README, Supervision); NODE_RANK then only needs to be 0 on the node at HEAD and distinct elsewhere.
# After SIGTERM every node exits 143 once the workers have saved: run the same commands again to continue.
set -euo pipefail
cd "$(dirname "$0")/.."
: "${NNODES:?set NNODES, the number of nodes}" "${NODE_RANK:?set NODE_RANK, 0 .. NNODES-1}" "${HEAD:?set HEAD to the address of node 0}"
[[ -x .venv/bin/ftrain ]] || bash launch/setup.sh
exec .venv/bin/ftrain supervise \
  --nproc-per-node "${NPROC_PER_NODE:-$(nproc)}" \
  --nnodes "$NNODES" --node-rank "$NODE_RANK" --rdzv-endpoint "$HEAD:${PORT:-29400}" \
  "$@"
