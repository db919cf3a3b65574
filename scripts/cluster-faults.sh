#!/usr/bin/env bash
# The cluster check, end to end, against the cluster of scripts/cluster-up.sh (started if it is not
# up): a job submitted from this host, then four faults, each measured, each dataset compared by
# content digest (datagen shards digest) with a local run of the same job.
#
#   bash scripts/cluster-faults.sh [WORKDIR]     # default WORKDIR: a new /tmp/datagen-cluster-check.*
#
#   local      the job on a local Ray (the reference digest)
#   submit     `datagen submit --address ray://127.0.0.1:$RAY_CLIENT_PORT --out s3://...` from the
#              host; `shards validate` and `shards ls` from the host
#   worker     kill -9 of a worker container while the job runs
#   driver     kill -9 of the host's driver (`datagen submit`) mid-job, then `datagen resume` at once
#   head       a job queued for the head's `datagen serve`; the head is stopped and started while it
#              runs (the ledger is on the head's volume); the restarted serve finishes the job
#   s3         the S3 server restarted while the job runs
#   down-up    `compose down` then `up`: the ledger and the datasets are still there
# Each case prints one `RESULT` line (name, seconds, outcome, digest); the script exits 1 if any
# case did not end with a complete dataset of the local run's digest. Needs the project's venv
# (datagen with Ray client support: pip install -e ".[s3,cluster]") active or at .venv.
set -euo pipefail
cd "$(dirname "$0")/.."
. scripts/cluster-lib.sh
cluster_require_env_file
cluster_detect_engine
[ -n "${VIRTUAL_ENV:-}" ] || { [ -f .venv/bin/activate ] && . .venv/bin/activate; }
export OPENBLAS_NUM_THREADS=1

WORK=${1:-$(mktemp -d /tmp/datagen-cluster-check.XXXXXX)}
mkdir -p "$WORK"
OBJECTS=${CHECK_OBJECTS:-examples/cluster.txt}
CONFIG=${CHECK_CONFIG:-examples/cluster.toml}
BUCKET=${DATAGEN_BUCKET:-datasets}
RUN=$(date +%Y%m%d-%H%M%S)
WORKERS=${WORKERS:-2}
export AWS_ENDPOINT_URL=http://127.0.0.1:${S3_PORT:-8333} AWS_ACCESS_KEY_ID=$S3_ACCESS_ID \
    AWS_SECRET_ACCESS_KEY=$S3_SECRET_KEY AWS_DEFAULT_REGION=${AWS_DEFAULT_REGION:-us-east-1}
ADDRESS=ray://127.0.0.1:${RAY_CLIENT_PORT:-10001}
HOST_HOME=$WORK/home
RESULTS=$WORK/results.tsv
FAILED=0
: >"$RESULTS"

now() { date +%s.%N; }
since() { elapsed "$1" "$(now)"; }
result() { # result NAME SECONDS OUTCOME DIGEST
    printf 'RESULT\t%s\t%s\t%s\t%s\n' "$@" | tee -a "$RESULTS"
}

# done/total tasks of a job in a ledger file (host) or in the head's ledger (head)
job_counts() { # job_counts host|head JOB -> "DONE TOTAL STATE"
    local code="
import sqlite3, sys
c = sqlite3.connect(sys.argv[1])
done, total = c.execute(\"select sum(state = 'done'), count(*) from tasks where job_id = ?\", (sys.argv[2],)).fetchone()
state = c.execute('select state from jobs where job_id = ?', (sys.argv[2],)).fetchone()
print(done or 0, total, state[0] if state else '-')"
    if [ "$1" = host ]; then python -c "$code" "$HOST_HOME/ledger.db" "$2"
    else engine exec "$(cname head)" python -c "$code" /var/lib/datagen/ledger.db "$2" 2>/dev/null || echo "? ? ?"
    fi
}

wait_done_at_least() { # wait_done_at_least host|head JOB N TIMEOUT: until N tasks are done
    local deadline=$(( $(date +%s) + $4 )) counts
    while :; do
        counts=$(job_counts "$1" "$2" 2>/dev/null || echo "0 0 -")
        [ "${counts%% *}" != "?" ] && [ "${counts%% *}" -ge "$3" ] 2>/dev/null && { echo "$counts"; return 0; }
        [ "$(date +%s)" -lt "$deadline" ] || { echo "$counts"; return 1; }
        sleep 0.3
    done
}

job_id_from() { # the job id a submit printed ("job ID: N tasks -> URL" or "queued job ID ...")
    local deadline=$(( $(date +%s) + 120 )) id
    until id=$(grep -oE '[0-9]{8}-[0-9]{6}-[0-9a-f]{6}' "$1" | head -1) && [ -n "$id" ]; do
        [ "$(date +%s)" -lt "$deadline" ] || { echo "no job id in $1" >&2; cat "$1" >&2; return 1; }
        sleep 0.3
    done
    echo "$id"
}

check_dataset() { # check_dataset NAME URL T0: validate, compare the digest, print the RESULT line
    local name=$1 url=$2 t0=$3 digest samples outcome
    if ! datagen shards validate "$url" >"$WORK/$name.validate" 2>&1; then
        FAILED=1; result "$name" "$(since "$t0")" "validate FAILED: $(tail -1 "$WORK/$name.validate")" -; return
    fi
    read -r digest samples unique _ < <(datagen shards digest "$url")
    if [ "$digest" = "$REFERENCE" ] && [ "$samples" = "$unique" ]; then
        outcome="complete: $samples samples, $unique distinct, validate ok, digest = local run"
    else
        FAILED=1; outcome="MISMATCH: $samples samples ($unique distinct), digest != local run"
    fi
    result "$name" "$(since "$t0")" "$outcome${4:+; $4}" "${digest:0:16}"
}

host_submit() { # host_submit NAME: start a host-driven job in the background; sets JOB and SUBMIT_PID
    datagen submit --objects "$OBJECTS" --config "$CONFIG" --address "$ADDRESS" \
        --out "s3://$BUCKET/$RUN/$1" --home "$HOST_HOME" >"$WORK/$1.log" 2>&1 &
    SUBMIT_PID=$!
    JOB=$(job_id_from "$WORK/$1.log")
}

# --- the cluster and the reference ------------------------------------------------------------
healthy "$(cname head)" 2>/dev/null || bash scripts/cluster-up.sh

t0=$(now)
datagen submit --objects "$OBJECTS" --config "$CONFIG" --out "$WORK/local" --home "$WORK/local-home" \
    --workers "$WORKERS" >"$WORK/local.log" 2>&1
read -r REFERENCE samples unique _ < <(datagen shards digest "$WORK/local")
result local "$(since "$t0")" "reference: $samples samples, $unique distinct (local Ray, $WORKERS CPUs)" "${REFERENCE:0:16}"

# --- a job from the host ------------------------------------------------------------------------
t0=$(now)
host_submit submit
wait "$SUBMIT_PID" || { FAILED=1; tail -5 "$WORK/submit.log"; }
datagen shards ls "s3://$BUCKET/$RUN/submit" >"$WORK/submit.ls" 2>&1 || FAILED=1
nodes=$(python -c "
import sqlite3, sys
c = sqlite3.connect(sys.argv[1])
print(len({p.split('@')[-1] for (p,) in c.execute('select placement from tasks where job_id = ? and state = \"done\"', (sys.argv[2],))}))" \
    "$HOST_HOME/ledger.db" "$JOB")
check_dataset submit "s3://$BUCKET/$RUN/submit" "$t0" "tasks ran on $nodes worker containers; shards ls: $(tail -1 "$WORK/submit.ls" | xargs)"

# --- kill -9 of a worker container mid-job ------------------------------------------------------
t0=$(now)
host_submit worker
counts=$(wait_done_at_least host "$JOB" 1 300)
tk=$(now)
# SIGKILL to the container's init from the host, as a crash or the OOM killer would: `podman kill`
# or `docker kill` would count as a user's stop, and the restart policy would not bring it back.
kill -9 "$(engine inspect --format '{{.State.Pid}}' "$(cname worker 1)")"
wait "$SUBMIT_PID" || { FAILED=1; tail -5 "$WORK/worker.log"; }
attempts=$(python -c "
import sqlite3, sys
c = sqlite3.connect(sys.argv[1])
print(c.execute('select sum(attempts) from tasks where job_id = ?', (sys.argv[2],)).fetchone()[0])" "$HOST_HOME/ledger.db" "$JOB")
check_dataset worker "s3://$BUCKET/$RUN/worker" "$t0" \
    "killed $(cname worker 1) at ${counts%% *}/6 done, job ended $(since "$tk") s later, $attempts attempts for 6 tasks"
# the killed worker comes back (restart policy) and rejoins
step "worker back" cluster_wait_ready "$WORKERS" 300 >/dev/null

# --- SIGKILL of the host's driver mid-job, then `datagen resume` at once -------------------------
# The Ray client server still holds the dead driver's session for a while; resume must wait it out
# by itself (saying so once) and finish the job, not fail with the server's refusal.
t0=$(now)
host_submit driver
counts=$(wait_done_at_least host "$JOB" 1 300)
td=$(now)
kill -9 "$SUBMIT_PID"
wait "$SUBMIT_PID" 2>/dev/null || true
tr=$(now)
datagen resume "$JOB" --address "$ADDRESS" --home "$HOST_HOME" >"$WORK/driver-resume.log" 2>&1 \
    || { FAILED=1; tail -5 "$WORK/driver-resume.log"; }
resumed_s=$(since "$tr")
waited=$(grep -c "refused a new session" "$WORK/driver-resume.log" || true)
check_dataset driver "s3://$BUCKET/$RUN/driver" "$t0" \
    "driver killed at ${counts%% *}/6 done; resume started $(elapsed "$td" "$tr") s after the kill, ended $resumed_s s later; notices of a held session: $waited; job in the host's ledger: $(job_counts host "$JOB")"

# --- stop and start the head while its serve runs a queued job ----------------------------------
t0=$(now)
engine cp "$OBJECTS" "$(cname head):/tmp/check-objects.txt"
engine cp "$CONFIG" "$(cname head):/tmp/check-config.toml"
engine exec "$(cname head)" datagen submit --detach --objects /tmp/check-objects.txt \
    --config /tmp/check-config.toml --out "s3://$BUCKET/$RUN/head" >"$WORK/head.log" 2>&1
JOB=$(job_id_from "$WORK/head.log")
at_stop=$(wait_done_at_least head "$JOB" 1 300)
th=$(now)
engine stop --time 10 "$(cname head)" >/dev/null
engine start "$(cname head)" >/dev/null
restart_s=$(since "$th")
counts=$(wait_done_at_least head "$JOB" 6 900) || FAILED=1
deadline=$(( $(date +%s) + 300 ))
until [[ "$(job_counts head "$JOB" | awk '{print $3}')" =~ ^(done|failed|cancelled)$ ]]; do
    [ "$(date +%s)" -lt "$deadline" ] || { FAILED=1; break; }
    sleep 1
done
check_dataset head "s3://$BUCKET/$RUN/head" "$t0" \
    "head stopped at ${at_stop%% *}/6 done, restarted in $restart_s s, job done $(since "$th") s after the stop; job state in the head's ledger: $(job_counts head "$JOB")"
step "workers back" cluster_wait_ready "$WORKERS" 300 >/dev/null

# --- restart the S3 server mid-job --------------------------------------------------------------
store_waits() { # lines "the store failed under a task" in every worker's Ray logs
    local n total=0 i
    for i in $(seq 1 "$WORKERS"); do
        n=$(engine exec "$(cname worker "$i")" sh -c 'cat /tmp/ray/session_*/logs/worker-*.err 2>/dev/null' \
            | grep -c "the store failed under a task" || true)
        total=$((total + n))
    done
    echo "$total"
}
waits_before=$(store_waits)
t0=$(now)
host_submit s3
counts=$(wait_done_at_least host "$JOB" 1 300)
ts=$(now)
engine restart "$(cname s3)" >/dev/null
s3_restart=$(since "$ts")
wait "$SUBMIT_PID" || { FAILED=1; tail -5 "$WORK/s3.log"; }
attempts=$(python -c "
import sqlite3, sys
c = sqlite3.connect(sys.argv[1])
print(c.execute('select sum(attempts) from tasks where job_id = ?', (sys.argv[2],)).fetchone()[0])" "$HOST_HOME/ledger.db" "$JOB")
ended=$(since "$ts")
check_dataset s3 "s3://$BUCKET/$RUN/s3" "$t0" \
    "S3 restarted at ${counts%% *}/6 done (restart took $s3_restart s), job ended $ended s after; $attempts attempts for 6 tasks; $(( $(store_waits) - waits_before )) store waits in the workers' logs"

# --- compose down, then up: the ledger and the datasets survive ---------------------------------
t0=$(now)
head_jobs() { # "JOBS DONE" in the head's ledger
    engine exec "$(cname head)" python -c "
import sqlite3
c = sqlite3.connect('/var/lib/datagen/ledger.db')
print(*c.execute(\"select count(*), sum(state = 'done') from jobs\").fetchone())" 2>/dev/null
}
jobs_before=$(head_jobs)
bash scripts/cluster-down.sh >/dev/null 2>&1
down_s=$(since "$t0")
tu=$(now)
bash scripts/cluster-up.sh >/dev/null 2>&1
up_s=$(since "$tu")
jobs_after=$(head_jobs)
[ "$jobs_before" = "$jobs_after" ] && [ "${jobs_after%% *}" -gt 0 ] || FAILED=1
for name in submit worker driver head s3; do
    check_dataset "down-up:$name" "s3://$BUCKET/$RUN/$name" "$t0" \
        "down $down_s s, up (healthy, workers joined) $up_s s; head's ledger: jobs, done = $jobs_after (before: $jobs_before)"
done

echo "results: $RESULTS (work folder $WORK)"
exit $FAILED
