# Shared by scripts/cluster-up.sh, cluster-down.sh and cluster-faults.sh (sourced, from the repository
# root). Picks the container engine: `docker compose` where a Docker engine answers, else podman with
# podman-compose and the override file docker-compose.podman.yml (see README "Run on a cluster").

PROJECT=${COMPOSE_PROJECT:-datagen}
ENV_FILE=${ENV_FILE:-.env}
BASE_IMAGE_PODMAN=datagen-base:bookworm
DEBIAN_MIRROR=${DEBIAN_MIRROR:-} # the archive debootstrap uses (default: this machine's apt source)

elapsed() { awk -v a="$1" -v b="$2" 'BEGIN { printf "%.1f", b - a }'; } # elapsed T0 T1 (seconds)

step() { # step NAME COMMAND...: runs COMMAND, then prints "step NAME: N s"
    local name=$1 t0 t1
    shift
    t0=$(date +%s.%N)
    echo "== $name"
    "$@"
    t1=$(date +%s.%N)
    printf '== %s: %s s\n' "$name" "$(elapsed "$t0" "$t1")"
    printf '%s\t%s\n' "$name" "$(elapsed "$t0" "$t1")" >>"${CLUSTER_TIMES:-/dev/null}"
}

die() { echo "error: $*" >&2; exit 2; }

cluster_require_env_file() {
    [ -f "$ENV_FILE" ] || die "no $ENV_FILE: copy .env.example to .env and set S3_SECRET_KEY (credentials never come from the repository)"
    [ "$ENV_FILE" = .env ] || [ "$(realpath "$ENV_FILE")" = "$(realpath .env 2>/dev/null || true)" ] \
        || die "compose reads .env beside docker-compose.yml: copy $ENV_FILE there"
    # shellcheck disable=SC1090
    set -a; . "$ENV_FILE"; set +a
    [ -n "${S3_SECRET_KEY:-}" ] && [ "$S3_SECRET_KEY" != change-me-to-a-long-random-secret ] \
        || die "set S3_SECRET_KEY in $ENV_FILE (not the example's value)"
}

cluster_detect_engine() {
    if [ -n "${CLUSTER_ENGINE:-}" ]; then :
    elif command -v docker >/dev/null && docker info >/dev/null 2>&1 && docker compose version >/dev/null 2>&1; then
        CLUSTER_ENGINE=docker
    else
        CLUSTER_ENGINE=podman
    fi
    if [ "$CLUSTER_ENGINE" = podman ]; then
        BASE_IMAGE=${BASE_IMAGE:-$BASE_IMAGE_PODMAN}
        # torch==2.13.0 from the index (and find-links) the host's pip uses: a CPU build there.
        TORCH_INDEX=${TORCH_INDEX:-https://pypi.org/simple}
    fi
    export BASE_IMAGE TORCH_INDEX CLUSTER_ENGINE
}

compose() {
    if [ "$CLUSTER_ENGINE" = docker ]; then
        docker compose -p "$PROJECT" "$@"
    else
        # podman-compose 1.0.3 prints the merged compose file and every `podman run` line, secrets
        # included: the merged file is dropped and the secret masked.
        podman-compose -p "$PROJECT" -f docker-compose.yml -f docker-compose.podman.yml "$@" 2>&1 \
            | awk '/^ \*\* merged:/ {skip = 1; next} skip && /^}/ {skip = 0; next} !skip' \
            | sed "s/${S3_SECRET_KEY:-@@}/***/g"
        return "${PIPESTATUS[0]}"
    fi
}

engine() { if [ "$CLUSTER_ENGINE" = docker ]; then docker "$@"; else podman "$@"; fi; }

# The name of a service's container (N-th replica): datagen_worker_1 with podman-compose,
# datagen-worker-1 with docker compose.
cname() {
    local sep=_
    [ "$CLUSTER_ENGINE" = docker ] && sep=-
    echo "${PROJECT}${sep}$1${sep}${2:-1}"
}

cluster_install_packages() {
    local need=() pkg
    for pkg in podman podman-compose runc containernetworking-plugins \
        golang-github-containernetworking-plugin-dnsname debootstrap; do
        dpkg-query -W -f='${Status}' "$pkg" 2>/dev/null | grep -q "ok installed" || need+=("$pkg")
    done
    if [ ${#need[@]} -eq 0 ]; then echo "all installed"; return; fi
    [ "$(id -u)" = 0 ] || die "installing ${need[*]} needs root (apt-get)"
    apt-get update -qq
    DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends "${need[@]}" >/dev/null
}

cluster_configure_containers() {
    local conf=/etc/containers/containers.conf
    if [ -f "$conf" ] && grep -Eq '^\s*runtime\s*=' "$conf"; then echo "$conf sets a runtime: left as is"; return; fi
    [ "$(id -u)" = 0 ] || die "writing $conf needs root"
    mkdir -p /etc/containers
    # crun (podman's default) and the default ulimits ask for more than this sandbox allows.
    cat >>"$conf" <<'EOF'
# Written by datagen's scripts/cluster-up.sh: runc, and limits this machine's sandbox accepts.
[containers]
default_ulimits = ["nofile=20000:20000", "nproc=32768:32768"]

[engine]
runtime = "runc"
EOF
    echo "wrote $conf"
}

# The base image: Debian bookworm (minbase) from this machine's own apt archive, with Python 3.11 in
# a virtual environment at /opt/python first on PATH, so that `python` and `python -m pip` are what
# python:3.11-slim-bookworm would give (and pip does not meet Debian's externally-managed marker).
cluster_build_base() {
    if podman image exists "$BASE_IMAGE"; then echo "$BASE_IMAGE present"; return; fi
    local mirror=$DEBIAN_MIRROR root
    if [ -z "$mirror" ]; then
        # the first non-security archive of this machine's apt sources (one-line or deb822 format)
        mirror=$(cat /etc/apt/sources.list /etc/apt/sources.list.d/*.list /etc/apt/sources.list.d/*.sources 2>/dev/null \
            | grep -E '^(URIs:|deb )' | grep -v security | awk '$2 !~ /^\[/ {print $2; exit}' || true)
        mirror=${mirror:-http://deb.debian.org/debian}
    fi
    root=$(mktemp -d /var/tmp/datagen-base.XXXXXX)
    debootstrap --variant=minbase \
        --include=python3,python3-venv,ca-certificates,libgomp1,tini,procps \
        bookworm "$root" "$mirror" >"$root.log" 2>&1 || { tail -20 "$root.log"; die "debootstrap failed (log $root.log)"; }
    chroot "$root" python3 -m venv /opt/python
    rm -rf "$root"/var/lib/apt/lists/* "$root"/var/cache/apt/archives/*.deb
    tar -C "$root" -c . | podman import \
        --change 'ENV PATH=/opt/python/bin:/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin' \
        --change 'ENV LANG=C.UTF-8' \
        --change 'CMD ["python"]' - "$BASE_IMAGE"
    rm -rf "$root" "$root.log"
}

# Mounted into every RUN of the podman builds: the host's CA bundle, its effective pip configuration
# (`pip config list`, environment included, written as one /etc/pip.conf) and the local folders it
# names, so that pip inside reaches what the host's pip reaches. Build-time mounts are not layers:
# nothing of it stays in the image.
_podman_build_mounts() {
    local conf=$1 pins=$1.pins.txt python=${HOST_PYTHON:-python3} p constraint
    [ -x .venv/bin/python ] && python=${HOST_PYTHON:-.venv/bin/python}
    # The host's own versions (its venv) as constraints: the images then run exactly the Ray a host
    # driver needs (Ray client refuses another version) and the numpy, embreex, highspy, torch... a
    # local run used, so that the two make byte-identical datasets. PIN_HOST_VERSIONS=0: no pins.
    : >"$pins"
    if [ "${PIN_HOST_VERSIONS:-1}" = 1 ]; then
        "$python" -m pip freeze --exclude-editable 2>/dev/null | grep -E '^[A-Za-z0-9_.-]+==' >"$pins" || true
    fi
    constraint=$("$python" -m pip config list 2>/dev/null | sed -nE "s/^(:env:|global)\.constraint='(.*)'$/\2/p" | head -1)
    {
        echo "[global]"
        "$python" -m pip config list 2>/dev/null | grep -v '\.constraint=' \
            | sed -E "s/^(:env:|global)\.([a-z-]+)='(.*)'$/\2 = \3/;t;d" | sort -u -t= -k1,1
        echo "constraint = ${constraint:+$constraint }/etc/pip-host-pins.txt"
    } >"$conf"
    printf -- '--volume=%s:/etc/pip.conf:ro\n' "$conf"
    printf -- '--volume=%s:/etc/pip-host-pins.txt:ro\n' "$pins"
    for p in /etc/ssl/certs/ca-certificates.crt /etc/xdg/pip /opt/wheels /opt/pypi /opt/pypi-more; do
        [ -e "$p" ] && printf -- '--volume=%s:%s:ro\n' "$p" "$p"
    done
    return 0
}

cluster_build_images() {
    local tag=${DATAGEN_IMAGE:-datagen:local} s3tag=${S3_IMAGE:-datagen-seaweedfs:local}
    if [ "$CLUSTER_ENGINE" = docker ]; then
        compose build
        return
    fi
    local mounts pipconf
    pipconf=$(mktemp /tmp/datagen-pip.XXXXXX.conf)
    mapfile -t mounts < <(_podman_build_mounts "$pipconf")
    if [ "${REBUILD:-0}" = 1 ] || ! podman image exists "$tag"; then
        podman build --network=host "${mounts[@]}" ${NO_CACHE:+--no-cache} \
            --build-arg "BASE_IMAGE=$BASE_IMAGE" --build-arg "TORCH_INDEX=$TORCH_INDEX" \
            -t "$tag" -f Dockerfile .
    else
        echo "$tag present (REBUILD=1 to rebuild)"
    fi
    if [ "${REBUILD:-0}" = 1 ] || ! podman image exists "$s3tag"; then
        podman build --network=host "${mounts[@]}" ${NO_CACHE:+--no-cache} --build-arg "BASE_IMAGE=$BASE_IMAGE" \
            -t "$s3tag" -f docker/seaweedfs/Dockerfile docker/seaweedfs
    else
        echo "$s3tag present"
    fi
    rm -f "$pipconf" "$pipconf.pins.txt"
}

cluster_up() { # cluster_up WORKERS
    # podman-compose prints every `podman run` line, secrets included: only a failure's tail is shown,
    # with the secret masked.
    local log
    log=$(mktemp)
    if ! WORKERS=$1 compose up -d >"$log" 2>&1; then
        tail -20 "$log" | sed "s/${S3_SECRET_KEY:-@@}/***/g"
        rm -f "$log"
        die "compose up failed"
    fi
    rm -f "$log"
}

healthy() { # healthy CONTAINER: its compose healthcheck passes now
    if [ "$CLUSTER_ENGINE" = docker ]; then
        [ "$(docker inspect --format '{{.State.Health.Status}}' "$1" 2>/dev/null)" = healthy ]
    else
        podman healthcheck run "$1" >/dev/null 2>&1
    fi
}

ray_workers_alive() { # the number of live Ray nodes with CPUs (workers), asked on the head
    engine exec "$(cname head)" python -c "
import logging, ray
ray.init(address='auto', logging_level=logging.ERROR, log_to_driver=False)
print(sum(1 for n in ray.nodes() if n['Alive'] and n['Resources'].get('CPU', 0) > 0))" 2>/dev/null | tail -1
}

cluster_wait_ready() { # cluster_wait_ready WORKERS [TIMEOUT_S]: S3 (bucket made), head and WORKERS Ray workers
    local want=$1 deadline=$(( $(date +%s) + ${2:-600} )) have=""
    until healthy "$(cname s3)"; do
        [ "$(date +%s)" -lt "$deadline" ] || die "S3 not healthy: $(engine logs --tail 20 "$(cname s3)" 2>&1)"
        sleep 2
    done
    echo "s3 healthy"
    until healthy "$(cname head)"; do
        [ "$(date +%s)" -lt "$deadline" ] || die "head not healthy: $(engine logs --tail 20 "$(cname head)" 2>&1)"
        sleep 2
    done
    echo "head healthy"
    until [ "$(ray_workers_alive)" = "$want" ]; do
        [ "$(date +%s)" -lt "$deadline" ] || die "$want Ray workers expected, $(ray_workers_alive) alive"
        sleep 3
    done
    echo "$want Ray workers joined"
}
