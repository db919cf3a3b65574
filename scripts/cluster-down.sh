#!/usr/bin/env bash
# Stop and remove the cluster's containers (scripts/cluster-up.sh). The named volumes stay: the
# ledger (head) and the S3 data survive, and the next cluster-up.sh finds them. `--volumes` deletes
# them too (every dataset in the cluster's S3 store and the ledger).
set -euo pipefail
cd "$(dirname "$0")/.."
. scripts/cluster-lib.sh
[ -f "$ENV_FILE" ] && { set -a; . "$ENV_FILE"; set +a; }
cluster_detect_engine
if [ "${1:-}" = --volumes ]; then compose down --volumes; else compose down; fi
