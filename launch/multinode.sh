#!/usr/bin/env bash
# Supervised training on several machines: run this same script on every node.
#
# Nodes meet through node 0 (c10d, the default): give each node its rank, and node 0's address as HEAD.
#   export FTRAIN_RDZV_SECRET=...   # the same on every node: make one with `openssl rand -hex 32`
#   NNODES=2 NODE_RANK=0 HEAD=10.0.0.5 bash launch/multinode.sh configs/halfcheetah.yaml --storage s3://bucket/runs/hc
#   NNODES=2 NODE_RANK=1 HEAD=10.0.0.5 bash launch/multinode.sh configs/halfcheetah.yaml --storage s3://bucket/runs/hc
# HEAD is node 0's address, reachable from every node (node 0's supervisor listens on that address only); PORT
# (default 29400) a free port there, where node 0's supervisor agrees each attempt with the others, answering only
# requests signed with FTRAIN_RDZV_SECRET (or with the contents of the file `--rdzv-secret-file FILE` names).
# Node 0 must live.
#
# Or through an etcd server outside the nodes (no special node: any node may be lost; see docs/clusters.md):
#   ETCD=10.0.0.9:2379 RUN_ID=hc-1 NNODES=2:4 bash launch/multinode.sh configs/halfcheetah.yaml env.num_envs=4 --storage s3://bucket/runs/hc
# the same line on every node, no rank, no secret (env.num_envs counts per rank: the config's 32 environments in all
# are not shared by every world from 2 to 4 nodes, and the supervisor refuses them). Start etcd first (etcd 3.4 or 3.5, v2 API on), e.g. Debian's:
#   etcd --enable-v2 --data-dir /var/lib/ftrain-etcd --listen-client-urls http://10.0.0.9:2379 --advertise-client-urls http://10.0.0.9:2379
# ETCD_CONF passes etcd's TLS settings as files: protocol=https,ca_cert=FILE,ssl_cert=FILE,ssl_cert_key=FILE.
#
# Storage must be shared by all nodes (s3://, or a shared filesystem). NPROC_PER_NODE defaults to the node's CPU
# count; the shipped configs count their environments in all (configs/halfcheetah.yaml: 32), which the ranks must
# divide: add env.num_envs=N to count them per rank instead. Extra arguments go to `ftrain supervise`. NNODES=MIN:MAX (e.g. 2:4) trains elastically on as many nodes as
# there are (see docs/clusters.md); with c10d NODE_RANK then only needs to be 0 on the node at HEAD and distinct
# elsewhere. After SIGTERM every node exits 143 once the workers have saved: run the same commands again to continue.
set -euo pipefail
cd "$(dirname "$0")/.."
: "${NNODES:?set NNODES, the number of nodes (or MIN:MAX)}"
if [[ -n ${ETCD:-} ]]; then
  : "${RUN_ID:?set RUN_ID, a name for the run, the same on every node}"
  nodes=(--rdzv-backend etcd-v2 --rdzv-endpoint "$ETCD" --rdzv-id "$RUN_ID" ${ETCD_CONF:+--rdzv-conf "$ETCD_CONF"})
else
  : "${NODE_RANK:?set NODE_RANK, 0 .. NNODES-1 (or ETCD)}" "${HEAD:?set HEAD to the address of node 0 (or ETCD)}"
  nodes=(--node-rank "$NODE_RANK" --rdzv-endpoint "$HEAD:${PORT:-29400}")
fi
[[ -x .venv/bin/ftrain ]] || bash launch/setup.sh
exec .venv/bin/ftrain supervise --nproc-per-node "${NPROC_PER_NODE:-$(nproc)}" --nnodes "$NNODES" "${nodes[@]}" "$@"
