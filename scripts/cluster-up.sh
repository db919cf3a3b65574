#!/usr/bin/env bash
# Start the datagen cluster of docker-compose.yml on this machine: a Ray head running `datagen serve`,
# Ray workers (2 by default) and the S3 server (SeaweedFS) with its bucket and credentials.
#
#   cp .env.example .env        # then set S3_SECRET_KEY (and the rest) in .env
#   bash scripts/cluster-up.sh  # prints each step with its time; ends with `compose ps`
#
# With a Docker engine (`docker compose` works) it only builds and starts the compose file. Without
# one, as on a Debian 12 machine with no image registry (the project's CI kind, run as root), it
# first makes what Docker would have given:
#   1. installs podman, podman-compose, runc, the CNI plugins (with dnsname, so service names
#      resolve) and debootstrap with apt, only those missing;
#   2. sets `runtime = "runc"` and default ulimits this sandbox accepts in
#      /etc/containers/containers.conf, only if that file sets no runtime;
#   3. builds the base image ($BASE_IMAGE, Debian bookworm with its Python 3.11 as `python`) with
#      debootstrap from the apt archive the machine already uses, and `podman import`s it;
#   4. builds the project image and the S3 server's image from that base, with the host's CA bundle,
#      pip configuration and local wheel folders mounted into the build (torch==2.13.0 comes from
#      wherever the host's pip takes it);
#   5. `podman-compose -f docker-compose.yml -f docker-compose.podman.yml up -d`.
# Every step that is already done (package installed, image present) is skipped: a second run
# costs seconds. Variables: WORKERS (2), REBUILD=1 (rebuild the project images; NO_CACHE=1 too: from
# the base up, no cached layer), ENV_FILE (.env),
# COMPOSE (the compose command, detected), BASE_IMAGE (datagen-base:bookworm on podman).
set -euo pipefail
cd "$(dirname "$0")/.."
. scripts/cluster-lib.sh

WORKERS=${WORKERS:-2}

cluster_require_env_file
cluster_detect_engine
if [ "$CLUSTER_ENGINE" = podman ]; then
    step "host packages" cluster_install_packages
    step "containers.conf" cluster_configure_containers
    step "base image $BASE_IMAGE" cluster_build_base
fi
step "project images" cluster_build_images
step "up ($WORKERS workers)" cluster_up "$WORKERS"
step "healthy" cluster_wait_ready "$WORKERS"
engine ps --filter "label=com.docker.compose.project=$PROJECT"
echo "cluster up: Ray client ray://127.0.0.1:${RAY_CLIENT_PORT:-10001}," \
    "S3 http://127.0.0.1:${S3_PORT:-8333} (bucket ${DATAGEN_BUCKET:-datasets}); README 'Run on a cluster'"
