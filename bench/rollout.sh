#!/usr/bin/env bash
#! Rollout benchmark: runs a private control plane (etcd + kube-apiserver v1.20.2), the operator
#! (--role all, release build, blob store and SQLite store in the work directory) and a fleet of
#! real agents (`lekiwi-fleet`: the agent's own run loop N times in one process, one state
#! directory per robot), pushes three releases with `kubectl lekiwi release push` and rolls them
#! out with a RobotDeployment, as the issue asks:
#!
#!   v1  FILES random files totalling MBYTES MB in nested directories, installed on every robot
#!       (the "initial install": every robot downloads everything)
#!   v2  v1 with P% of the files rewritten (same sizes), rolled out in batches of 10% (canary 0,
#!       successThreshold 0.8, no pause): total rollout time (target < 60 s) and bytes served
#!       per robot (the gateway's /v1/blobs-served) against the changed bytes
#!   v3  v2 with one more file changed, while 30% of the robots of the SECOND batch fail their
#!       health check: time from the failing batch (phase RollingBack) until every robot
#!       reports v2 again
#!
#! and prints one table (phase, measured, target, PASS/FAIL).
#!
#! Usage: bash bench/rollout.sh [options]
#!   --robots N            simulated robots (default 200)
#!   --files N             files in the release (default 500)
#!   --mbytes N            size of the release, MB (10^6 bytes; default 100)
#!   --changed-percent P   share of the files v2 changes (default 5)
#!   --no-build            use the binaries already in target/release
#!   --keep                keep the work directory (logs, releases, robots' state, JSON records)
#!   -h, --help            this text
#!
#! Needs free disk space for every robot's copy of the release: ROBOTS x MBYTES x 1.5 MB (30 GB
#! with the defaults; checked first). Writes the table to bench/results/rollout-<date>.txt and
#! bench/results/rollout-latest.txt. About 4 minutes with the defaults once built (half of it the
#! initial install, 20 GB written); cleans up on exit, failure and Ctrl-C. Shares the lock of
#! bench/gateway.sh and bench/agent.sh, so two benchmarks never run at once.
set -euo pipefail

ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
BIN="$ROOT/target/release"
RESULTS="$ROOT/bench/results"
REPORT="$ROOT/bench/rollout_report.py"

ROBOTS=200
FILES=500
MBYTES=100
CHANGED_PERCENT=5
BUILD=1
KEEP=0
COMMAND="bash bench/rollout.sh $*"
TARGET_SECONDS=60
NS=bench
OPERATOR_NS=lekiwi-system
# A robot whose state directory holds `fail-health` fails its health check after every switch.
HEALTH='test ! -e "$LEKIWI_RELEASE_DIR/../../fail-health"'

# shellcheck source=bench/lib.sh
source "$ROOT/bench/lib.sh"

while [ $# -gt 0 ]; do
  case "$1" in
    --robots) positive_int "$1" "${2:-}"; ROBOTS="$2"; shift 2 ;;
    --files) positive_int "$1" "${2:-}"; FILES="$2"; shift 2 ;;
    --mbytes) positive_int "$1" "${2:-}"; MBYTES="$2"; shift 2 ;;
    --changed-percent)
      [[ "${2:-}" =~ ^[0-9]+(\.[0-9]+)?$ ]] && awk -v p="$2" 'BEGIN { exit !(p > 0 && p < 100) }' \
        || die "--changed-percent needs a number between 0 and 100, not '${2:-}'"
      CHANGED_PERCENT="$2"; shift 2 ;;
    --no-build) BUILD=0; shift ;;
    --keep) KEEP=1; shift ;;
    -h|--help) usage; exit 0 ;;
    *) usage >&2; die "unknown option: $1" ;;
  esac
done
[ "$ROBOTS" -le 1000 ] || die "--robots is at most 1000 (lekiwi-fleet names robots kiwi-000 to kiwi-999)"
[ "$FILES" -ge 2 ] || die "--files must be at least 2"
# Batches of 10% (rounded up, as the controller does); the second batch has the failing robots.
BATCH=$(((ROBOTS + 9) / 10))
[ "$ROBOTS" -gt "$BATCH" ] || die "--robots must allow a second batch of 10% (at least 2 robots)"

# ---- processes and cleanup ------------------------------------------------------------------
WORK="$(mktemp -d "${TMPDIR:-/tmp}/lekiwi-bench-rollout.XXXXXX")"
CP_DIR="$WORK/control-plane"
CP_UP=0
PIDS=()
# `stop` gives a process 5 s after SIGTERM before SIGKILL.
STOP_GRACE=5

keep_or_remove_work() { # exit status
  if [ $KEEP = 1 ]; then
    log "work directory kept: $WORK"
  elif [ "$1" != 0 ]; then
    # Logs and records stay for the post-mortem; the robots' copies of the release do not (20 GB).
    rm -rf "$WORK/robots" "$WORK/blobs" "$WORK/releases"/v[0-9]*
    log "work directory kept without the robots' state, the blobs and the releases: $WORK"
  else
    rm -rf "$WORK"
  fi
}
trap_cleanup

# Bytes of the blobs in the operator's blob store.
blob_bytes() { find "$WORK/blobs" -type f -path '*/sha256/*' -printf '%s\n' 2>/dev/null | awk '{ s += $1 } END { printf "%d", s }'; }

# ---- preparation ----------------------------------------------------------------------------
# One benchmark at a time on this machine (the same lock as bench/gateway.sh and bench/agent.sh).
take_bench_lock

log "work directory: $WORK"
# Every robot keeps its own copy of the release (blobs, hard-linked into the release directory),
# plus the operator's blob store and the three release directories: 1.5x the fleet's copies.
NEED_MB=$((ROBOTS * MBYTES * 3 / 2 + 4 * MBYTES))
FREE_MB=$(($(df -Pk "$WORK" | awk 'NR == 2 { print $4 }') / 1024))
[ "$FREE_MB" -ge "$NEED_MB" ] \
  || die "$((FREE_MB / 1000)) GB free in $(df -P "$WORK" | awk 'NR == 2 { print $6 }'), need $((NEED_MB / 1000)) GB ($ROBOTS robots x $MBYTES MB x 1.5); set TMPDIR to a larger disk or use fewer --robots / --mbytes"
log "disk: $((FREE_MB / 1000)) GB free, $((ROBOTS * MBYTES / 1000)) GB will be written by the robots"

release_binaries "lekiwi-operator lekiwi-agent kubectl-lekiwi" lekiwi-operator lekiwi-fleet kubectl-lekiwi

run_setup

ulimit -n "$(ulimit -Hn)" 2>/dev/null || true
[ "$(ulimit -n)" -gt $((ROBOTS * 8 + 100)) ] \
  || die "open-file limit $(ulimit -n) is too low for $ROBOTS agents and their downloads"

fact date "$(date -Is)"
fact host "$(nproc) CPUs ($(awk -F': ' '/^model name/ { print $2; exit }' /proc/cpuinfo)), $(awk '/^MemTotal/ { printf "%.0f GiB", $2 / 1048576 }' /proc/meminfo) RAM, kernel $(uname -r), $(df -PT "$WORK" | awk 'NR == 2 { print $2 }') at $(df -P "$WORK" | awk 'NR == 2 { print $6 }'), load average at start $(cut -d' ' -f1-3 /proc/loadavg)"
fact cpus "$(nproc)"
fact_source
fact command "$COMMAND"
fact robots "$ROBOTS"
fact namespace "$NS"
fact target_seconds "$TARGET_SECONDS"

# ---- control plane --------------------------------------------------------------------------
start_control_plane
export APISERVER_PORT

kubectl create namespace "$OPERATOR_NS" >/dev/null
kubectl create namespace "$NS" >/dev/null
# A fleet enrollment token, as scripts/quickstart.sh makes it: the Secret keeps only its SHA-256.
TOKEN_FILE="$WORK/enrollment-token"
enrollment_token "$NS" "$TOKEN_FILE"

# ---- operator (controllers + gateway; defaults apart from addresses and stores) -------------
HTTP_PORT="$(free_port)"
GW_PORT="$(free_port)"
mkdir -p "$WORK/blobs"
log "starting the operator (--role all; gateway :$GW_PORT, http :$HTTP_PORT)"
start operator env RUST_LOG=info,kube=warn "$BIN/lekiwi-operator" --role all \
  --kubeconfig "$KUBECONFIG" --namespace "$OPERATOR_NS" --watch-namespace "$NS" \
  --identity bench-operator --gateway-name bench-gateway \
  --gateway-addr "127.0.0.1:$GW_PORT" --http-addr "127.0.0.1:$HTTP_PORT" \
  --store-url "sqlite://$WORK/events.db" --blob-dir "$WORK/blobs" \
  --max-unauthenticated-per-address 0
OP_PID=$LAST_PID
operator_ready() {
  alive "$OP_PID" || die "operator exited: $(tail -5 "$WORK/operator.log")"
  curl -fsS --max-time 2 "http://127.0.0.1:$HTTP_PORT/readyz" >/dev/null 2>&1
}
wait_for operator 60 operator_ready
fact operator "lekiwi-operator --role all, defaults except --max-unauthenticated-per-address 0 (every robot connects from 127.0.0.1) (heartbeat 30 s, status qps 50 / burst 100, concurrency 16), SQLite store and --blob-dir on the work directory's disk"
export BENCH_NS="$NS" BENCH_OPERATOR_NS="$OPERATOR_NS" BENCH_GW_PORT="$GW_PORT" BENCH_ROBOTS="$ROBOTS"

# ---- releases ---------------------------------------------------------------------------------
log "generating the releases ($FILES files, $MBYTES MB, $CHANGED_PERCENT % changed)"
mkdir -p "$WORK/releases"
python3 "$REPORT" gen "$WORK/releases" "$FILES" "$MBYTES" "$CHANGED_PERCENT" >&2

declare -A DIGEST=()
push() { # v1|v2|v3
  local v="$1" before t0
  before="$(blob_bytes)"
  t0="$(now)"
  "$BIN/kubectl-lekiwi" --kubeconfig "$KUBECONFIG" release push "$WORK/releases/$v" \
    --version "$v" --server "http://127.0.0.1:$GW_PORT" -n "$NS" \
    >"$WORK/push-$v.out" 2>"$WORK/push-$v.log" || die "push $v failed: $(tail -5 "$WORK/push-$v.log")"
  fact "push_${v}_seconds" "$(elapsed "$t0")"
  fact "push_${v}_blob_bytes" "$(($(blob_bytes) - before))"
  DIGEST[$v]="$(tr -d '[:space:]' <"$WORK/push-$v.out")"
  [[ "${DIGEST[$v]}" == sha256:* ]] || die "push $v printed no digest: $(cat "$WORK/push-$v.out")"
  log "  pushed $v in $(awk -F= -v k="push_${v}_seconds" '$1 == k { v = $2 } END { print v }' "$WORK/facts.env") s: $(head -1 "$WORK/push-$v.log")"
}
push v1
push v2
push v3

# ---- the fleet ----------------------------------------------------------------------------------
log "starting lekiwi-fleet with $ROBOTS robots"
T0="$(now)"
start fleet env RUST_LOG=warn,lekiwi_agent::release=info "$BIN/lekiwi-fleet" \
  --gateway "ws://127.0.0.1:$GW_PORT/v1/agent" --enrollment-token-file "$TOKEN_FILE" \
  --namespace "$NS" --robots "$ROBOTS" --state-root "$WORK/robots" \
  --health-command "$HEALTH" --health-timeout-s 2 --backoff-max-ms 2000 --report-every 5 \
  --telemetry-interval-s 0
FLEET_PID=$LAST_PID
fact fleet "$ROBOTS robots in one lekiwi-fleet process (real agents, enrolled with the fleet token; backoff max 2 s; health command: $HEALTH, timeout 2 s)"
python3 "$REPORT" online 300 >"$WORK/online.txt" || die "robots did not come Online: $(tail -3 "$WORK/fleet.log")"
alive "$FLEET_PID" || die "lekiwi-fleet exited: $(tail -5 "$WORK/fleet.log")"
log "all $ROBOTS robots Online after $(elapsed "$T0") s"

APISERVER_PID="$(cat "$CP_DIR/kube-apiserver.pid")"
ETCD_PID="$(cat "$CP_DIR/etcd.pid")"
export BENCH_PIDS="operator:$OP_PID fleet:$FLEET_PID apiserver:$APISERVER_PID etcd:$ETCD_PID"
fact strategy "batchSize 10% ($BATCH robots, $(((ROBOTS + BATCH - 1) / BATCH)) batches, sorted by name), canary 0, successThreshold 0.8, pauseBetweenBatchesSeconds 0; other fields default (robotTimeoutSeconds 600, unavailable Skip)"
fact timing "from sending the create/patch of the RobotDeployment to the arrival of the watch event that shows the change (the deployment's phase for its current generation; every Robot's status.currentRelease)"

rollout() { # MODE VERSION TIMEOUT
  alive "$FLEET_PID" || die "lekiwi-fleet exited: $(tail -5 "$WORK/fleet.log")"
  alive "$OP_PID" || die "operator exited: $(tail -5 "$WORK/operator.log")"
  BENCH_ROLLOUT_TIMEOUT="$3" python3 "$REPORT" rollout "$1" "$2" "${DIGEST[$2]}" \
    "$WORK/rollout-$1.json" || die "$1 rollout failed; see $WORK/operator.log and $WORK/fleet.log"
}

# ---- initial install: v1 everywhere ---------------------------------------------------------------
python3 "$REPORT" served "$WORK/served-0.json"
log "initial install: v1 ($MBYTES MB) to $ROBOTS robots"
rollout install v1 $((ROBOTS * MBYTES / 10 + 600))
python3 "$REPORT" served "$WORK/served-1.json"
log "initial install done in $(python3 -c 'import json,sys; print(round(json.load(open(sys.argv[1]))["phases"]["Completed"], 1))' "$WORK/rollout-install.json") s"
sleep 2

# ---- the measured rollout: v2 -----------------------------------------------------------------------
log "measured rollout: v2 to $ROBOTS robots in batches of $BATCH"
rollout update v2 600
python3 "$REPORT" served "$WORK/served-2.json"
sleep 2

# ---- the rollback: v3 with 30% of the second batch failing their health check --------------------
FAILING=()
NFAIL=$(((BATCH * 3 + 9) / 10))
for k in $(seq 0 $((NFAIL - 1))); do
  FAILING+=("$(printf 'kiwi-%03d' $((BATCH + k * BATCH / NFAIL)))")
done
for r in "${FAILING[@]}"; do : >"$WORK/robots/$r/fail-health"; done
fact failing "v3 while ${#FAILING[@]} of the $BATCH robots of the second batch fail their health check (${FAILING[*]}): $(( (BATCH - ${#FAILING[@]}) * 100 / BATCH ))% < 80% succeed"
log "rollback run: v3 with ${#FAILING[@]} failing robots in the second batch (${FAILING[*]})"
rollout rollback v3 600
python3 "$REPORT" served "$WORK/served-3.json"

stop "$FLEET_PID"
stop "$OP_PID"
# The agents' complaints over the run (the log is text, colored, one event per line).
sed 's/\x1b\[[0-9;]*m//g' "$WORK/fleet.log" | grep -aE '^\S+\s+(WARN|ERROR) ' >"$WORK/fleet-warnings.txt" || true

# ---- report ---------------------------------------------------------------------------------
mkdir -p "$RESULTS"
STAMP="$(date +%Y%m%d-%H%M%S)"
python3 "$REPORT" report "$WORK" >"$WORK/table.txt"
cp "$WORK/table.txt" "$RESULTS/rollout-$STAMP.txt"
cp "$WORK/table.txt" "$RESULTS/rollout-latest.txt"
echo
cat "$WORK/table.txt"
echo
log "written to bench/results/rollout-$STAMP.txt and bench/results/rollout-latest.txt"
