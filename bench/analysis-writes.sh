#!/usr/bin/env bash
#! Analysis-writes benchmark: what a rollout, and the time after it, costs the API
#! server in Robot writes, without and with post-switch analysis (`spec.analysis`).
#!
#! Runs a private control plane (etcd + kube-apiserver v1.20.2) whose audit log records every
#! Robot request, the operator as two processes (--role controller, --role gateway; defaults:
#! 30 s heartbeat, 300 s routine status refresh) and a fleet of real agents (`lekiwi-fleet`). Then:
#!
#!   1. a RobotDeployment without analysis rolls a small release out to every robot (batches of
#!      --batch-size, canary 0), and the fleet is left alone for --after seconds;
#!   2. the same deployment rolls a second release out with spec.analysis (windowSeconds
#!      --window, no thresholds), and the fleet is left alone for --after seconds again.
#!
#! and prints, for each rollout and each quiet time after it, the Robot status writes (by the
#! gateway and by the controller; from the audit log), per robot and per second, against the
#! goal: at most 2 status writes per robot for a rollout (its routine refreshes aside), and the
#! routine N/300 a second after it.
#!
#! Usage: bash bench/analysis-writes.sh [options]
#!   --robots N         real agents (default 400; at most 1000)
#!   --after S          seconds the fleet is watched after each rollout (default 600: the longest
#!                      analysis window; less for a quick run)
#!   --window S         windowSeconds of the second rollout (default 60)
#!   --batch-size B     the deployments' batchSize (default 50%)
#!   --bin DIR          take lekiwi-operator, lekiwi-fleet and kubectl-lekiwi from DIR and build
#!                      nothing (e.g. another checkout's target/debug, to measure it)
#!   --no-build         use the binaries already in target/release
#!   --keep             keep the work directory (logs, audit log, JSON records)
#!   -h, --help         this text
#!
#! Writes the table to bench/results/analysis-writes-latest.txt (earlier runs are in git's
#! history). About 2 x --after plus 5 minutes once built; cleans up on exit, failure and Ctrl-C;
#! shares the lock of the other benchmarks.
set -euo pipefail

ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
BIN="$ROOT/target/release"
RESULTS="$ROOT/bench/results"
DRIVER="$ROOT/bench/analysis_writes.py"

ROBOTS=400
AFTER=600
WINDOW=60
BATCH=50%
BUILD=1
KEEP=0
COMMAND="bash bench/analysis-writes.sh $*"
NS=bench
OPERATOR_NS=lekiwi-system

# shellcheck source=bench/lib.sh
source "$ROOT/bench/lib.sh"

while [ $# -gt 0 ]; do
  case "$1" in
    --robots) positive_int "$1" "${2:-}"; ROBOTS="$2"; shift 2 ;;
    --after) positive_int "$1" "${2:-}"; AFTER="$2"; shift 2 ;;
    --window) positive_int "$1" "${2:-}"; WINDOW="$2"; shift 2 ;;
    --batch-size)
      [[ "${2:-}" =~ ^[1-9][0-9]*%?$ ]] || die "--batch-size needs a count or a percentage, not '${2:-}'"
      BATCH="$2"; shift 2 ;;
    --bin) [ -d "${2:-}" ] || die "--bin needs a directory"; BIN="$(cd "$2" && pwd)"; BUILD=0; shift 2 ;;
    --no-build) BUILD=0; shift ;;
    --keep) KEEP=1; shift ;;
    -h|--help) usage; exit 0 ;;
    *) usage >&2; die "unknown option: $1" ;;
  esac
done
[ "$ROBOTS" -le 1000 ] || die "--robots is at most 1000 (lekiwi-fleet names robots kiwi-000 to kiwi-999)"
[ "$WINDOW" -le 600 ] || die "--window is at most 600 (spec.analysis.windowSeconds)"

WORK="$(mktemp -d "${TMPDIR:-/tmp}/lekiwi-bench-analysis.XXXXXX")"
CP_DIR="$WORK/control-plane"
CP_UP=0
PIDS=()
trap_cleanup
take_bench_lock
log "work directory: $WORK"

release_binaries "lekiwi-operator lekiwi-agent kubectl-lekiwi" lekiwi-operator lekiwi-fleet kubectl-lekiwi
run_setup
ulimit -n "$(ulimit -Hn)" 2>/dev/null || true
[ "$(ulimit -n)" -gt $((ROBOTS * 8 + 100)) ] || die "open-file limit $(ulimit -n) is too low for $ROBOTS agents"

fact date "$(date -Is)"
fact host "$(nproc) CPUs ($(awk -F': ' '/^model name/ { print $2; exit }' /proc/cpuinfo)), $(awk '/^MemTotal/ { printf "%.0f GiB", $2 / 1048576 }' /proc/meminfo) RAM, load average at start $(cut -d' ' -f1-3 /proc/loadavg)"
fact_source
fact command "$COMMAND"
fact binaries "$BIN ($(git -C "$(dirname "$BIN")/.." rev-parse --short HEAD 2>/dev/null || echo '?'))"
fact robots "$ROBOTS"
fact after_seconds "$AFTER"

# ---- control plane, with an audit log of every Robot request ----------------------------------
cat >"$WORK/audit-policy.yaml" <<'EOF'
apiVersion: audit.k8s.io/v1
kind: Policy
omitStages: [RequestReceived]
rules:
  - level: Metadata
    resources:
      - group: fleet.lekiwi.io
        resources: [robots, robots/status]
  - level: None
EOF
export LEKIWI_APISERVER_ARGS="--audit-policy-file=$WORK/audit-policy.yaml --audit-log-path=$WORK/audit.log"
start_control_plane
export APISERVER_PORT
kubectl create namespace "$OPERATOR_NS" >/dev/null
kubectl create namespace "$NS" >/dev/null
TOKEN_FILE="$WORK/enrollment-token"
enrollment_token "$NS" "$TOKEN_FILE"

# ---- operator: controller and gateway, defaults apart from addresses and stores ---------------
CTRL_HTTP="$(free_port)"
GW_HTTP="$(free_port)"
GW_PORT="$(free_port)"
mkdir -p "$WORK/blobs"
start controller env RUST_LOG=info,kube=warn "$BIN/lekiwi-operator" --role controller \
  --kubeconfig "$KUBECONFIG" --namespace "$OPERATOR_NS" --watch-namespace "$NS" \
  --identity bench-controller --http-addr "127.0.0.1:$CTRL_HTTP"
CTRL_PID=$LAST_PID
start gateway env RUST_LOG=info,kube=warn "$BIN/lekiwi-operator" --role gateway \
  --kubeconfig "$KUBECONFIG" --namespace "$OPERATOR_NS" --watch-namespace "$NS" \
  --identity bench-gateway --gateway-name bench-gateway \
  --gateway-addr "127.0.0.1:$GW_PORT" --http-addr "127.0.0.1:$GW_HTTP" \
  --store-url "sqlite://$WORK/events.db" --blob-dir "$WORK/blobs" \
  --max-unauthenticated-per-address 0
GW_PID=$LAST_PID
ready() { # pid port
  alive "$1" || die "operator exited: $(tail -5 "$WORK/controller.log" "$WORK/gateway.log")"
  curl -fsS --max-time 2 "http://127.0.0.1:$2/readyz" >/dev/null 2>&1
}
wait_for controller 60 ready "$CTRL_PID" "$CTRL_HTTP"
wait_for gateway 60 ready "$GW_PID" "$GW_HTTP"
fact operator "lekiwi-operator --role controller and --role gateway, defaults (heartbeat 30 s, status refresh 300 s) except --max-unauthenticated-per-address 0 (every agent connects from 127.0.0.1)"
export BENCH_NS="$NS" BENCH_ROBOTS="$ROBOTS"

# ---- releases: one small file each --------------------------------------------------------------
declare -A DIGEST=()
for v in 1.0.0 2.0.0; do
  mkdir -p "$WORK/releases/$v"
  printf 'release %s\n' "$v" >"$WORK/releases/$v/VERSION"
  "$BIN/kubectl-lekiwi" --kubeconfig "$KUBECONFIG" release push "$WORK/releases/$v" \
    --version "$v" --server "http://127.0.0.1:$GW_PORT" -n "$NS" \
    >"$WORK/push-$v.out" 2>"$WORK/push-$v.log" || die "push $v failed: $(tail -5 "$WORK/push-$v.log")"
  DIGEST[$v]="$(tr -d '[:space:]' <"$WORK/push-$v.out")"
done
fact release "two releases of one small file each (the download is not what is measured)"

# ---- the fleet ----------------------------------------------------------------------------------
log "starting lekiwi-fleet with $ROBOTS robots"
start fleet env RUST_LOG=warn "$BIN/lekiwi-fleet" \
  --gateway "ws://127.0.0.1:$GW_PORT/v1/agent" --enrollment-token-file "$TOKEN_FILE" \
  --namespace "$NS" --robots "$ROBOTS" --state-root "$WORK/robots" \
  --health-command true --health-timeout-s 5 --backoff-max-ms 2000 --report-every 30
FLEET_PID=$LAST_PID
fact fleet "$ROBOTS real agents in one lekiwi-fleet process, enrolled with the fleet token"
python3 "$ROOT/bench/rollout_report.py" online 600 >/dev/null \
  || die "robots did not come Online: $(tail -3 "$WORK/fleet.log")"
log "all $ROBOTS robots Online"
fact strategy "batchSize $BATCH, canary 0, successThreshold 0.8, no pause; other fields default"

measure() { # name version window
  alive "$FLEET_PID" && alive "$GW_PID" && alive "$CTRL_PID" || die "a process exited; see $WORK"
  log "rollout of $2 (windowSeconds ${3/#0/none}), then $AFTER s of nothing"
  python3 "$DRIVER" rollout "$2" "${DIGEST[$2]}" "$3" "$BATCH" "$WORK/rollout-$1.json" \
    || die "the rollout of $2 failed; see $WORK/controller.log"
  sleep "$AFTER"
}
measure plain 1.0.0 0
measure analysis 2.0.0 "$WINDOW"

stop "$FLEET_PID"
stop "$GW_PID"
stop "$CTRL_PID"

mkdir -p "$RESULTS"
python3 "$DRIVER" report "$WORK" >"$WORK/table.txt"
cp "$WORK/table.txt" "$RESULTS/analysis-writes-latest.txt"
echo
cat "$WORK/table.txt"
echo
log "written to bench/results/analysis-writes-latest.txt"
