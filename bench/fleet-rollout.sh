#!/usr/bin/env bash
#! Fleet-rollout benchmark: rollouts at the fleet's size, on one private control plane
#! (etcd + kube-apiserver v1.20.2), the operator as two processes (--role controller, --role
#! gateway; SQLite store, blob store in the work directory) and N simulated robots
#! (`lekiwi-sim`, which answers deploy commands over the real blob API). Then:
#!
#!   1. one RobotDeployment over every robot (canary 1, batches of 10%) of a pushed release:
#!      apply -> Completed (goal <= 3 min), API writes per robot (goal <= 2), blob bytes served
#!      per robot against the release's bytes, the controller's CPU seconds per Robot status write;
#!   2. the same deployment to a release 5% of the robots fail the health check of
#!      (successThreshold 0.99): apply -> RolledBack, and until every robot is back;
#!   3. 10, then --deployments RobotDeployments over disjoint selections applied at once: all
#!      Completed (goal <= 5 min), API writes per robot, the controller's CPU seconds per Robot
#!      status write (against 1 deployment: it should not grow);
#!   4. `rollout undo` of a rollout whose first batch (10%) is downloading (every download of
#!      that release stalls): until the gateway has sent every downloading robot `cancel`
#!      (goal <= 2 s; from the gateway's log of the commands it sends);
#!   5. an agent-update rollout (spec.agent) over every robot: time, API writes per robot;
#!
#! and prints one table with PASS/FAIL. API writes are the API server's own
#! apiserver_request_total (POST, PUT, PATCH, APPLY, DELETE) of robots, robots/status and
#! robotdeployments/status, less the gateway's routine status refreshes (its own count).
#!
#! Usage: bash bench/fleet-rollout.sh [options]
#!   --robots N        simulated robots (default 10000; a multiple of --deployments)
#!   --deployments D   deployments of phase 3 (default 100)
#!   --bin DIR         take lekiwi-operator, lekiwi-sim and kubectl-lekiwi from DIR, build nothing
#!   --no-build        use the binaries already in target/release
#!   --keep            keep the work directory (logs, metrics)
#!   -h, --help        this text
#!
#! Writes the table to bench/results/fleet-rollout-latest.txt. Cleans up on exit, failure and
#! Ctrl-C; shares the lock of the other benchmarks.
set -euo pipefail

ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
BIN="$ROOT/target/release"
RESULTS="$ROOT/bench/results"
ROBOTS=10000
DEPLOYMENTS=100
BUILD=1
KEEP=0
COMMAND="bash bench/fleet-rollout.sh $*"
NS=bench

# shellcheck source=bench/lib.sh
source "$ROOT/bench/lib.sh"

while [ $# -gt 0 ]; do
  case "$1" in
    --robots) positive_int "$1" "${2:-}"; ROBOTS="$2"; shift 2 ;;
    --deployments) positive_int "$1" "${2:-}"; DEPLOYMENTS="$2"; shift 2 ;;
    --bin) [ -d "${2:-}" ] || die "--bin needs a directory"; BIN="$(cd "$2" && pwd)"; BUILD=0; shift 2 ;;
    --no-build) BUILD=0; shift ;;
    --keep) KEEP=1; shift ;;
    -h|--help) usage; exit 0 ;;
    *) usage >&2; die "unknown option: $1" ;;
  esac
done
[ $((ROBOTS % DEPLOYMENTS)) = 0 ] || die "--robots must be a multiple of --deployments"
[ $((DEPLOYMENTS % 10)) = 0 ] || die "--deployments must be a multiple of 10"

WORK="$(mktemp -d "${TMPDIR:-/tmp}/lekiwi-bench-fleet.XXXXXX")"
CP_DIR="$WORK/control-plane"
CP_UP=0
PIDS=()
trap_cleanup
take_bench_lock
log "work directory: $WORK"
release_binaries "lekiwi-operator lekiwi-agent kubectl-lekiwi" lekiwi-operator lekiwi-sim kubectl-lekiwi
run_setup
ulimit -n "$(ulimit -Hn)" 2>/dev/null || true

ROWS="$WORK/rows.txt"
: >"$ROWS"
row() { printf '%-62s %-22s %-10s %s\n' "$@" >>"$ROWS"; }
verdict() { awk -v v="$1" -v g="$2" 'BEGIN { print (v != "" && v + 0 <= g + 0) ? "PASS" : "FAIL" }'; }

# ---- control plane, operator, fleet ------------------------------------------------------------
start_control_plane
export APISERVER_PORT
APISERVER_PID="$(cat "$CP_DIR/kube-apiserver.pid")"
ETCD_PID="$(cat "$CP_DIR/etcd.pid")"
kubectl create namespace lekiwi-system >/dev/null
kubectl create namespace "$NS" >/dev/null
enrollment_token "$NS" "$WORK/enrollment-token"
CTRL_HTTP="$(free_port)"
OP_HTTP="$(free_port)"
GW_PORT="$(free_port)"
mkdir -p "$WORK/blobs"
start controller env RUST_LOG=warn "$BIN/lekiwi-operator" --role controller \
  --kubeconfig "$KUBECONFIG" --namespace lekiwi-system --watch-namespace "$NS" \
  --identity bench-controller --http-addr "127.0.0.1:$CTRL_HTTP"
CTRL_PID=$LAST_PID
# The gateway logs each command it sends (the undo phase reads when the cancels went out).
start gateway env RUST_LOG=warn,lekiwi_gateway::session::serve=info "$BIN/lekiwi-operator" --role gateway \
  --kubeconfig "$KUBECONFIG" --namespace lekiwi-system --watch-namespace "$NS" \
  --identity bench-gateway --gateway-name bench-gateway \
  --gateway-addr "127.0.0.1:$GW_PORT" --http-addr "127.0.0.1:$OP_HTTP" \
  --store-url "sqlite://$WORK/events.db" --blob-dir "$WORK/blobs" \
  --max-unauthenticated-per-address 0 --enroll-rate 50 --enroll-burst 100
OP_PID=$LAST_PID
ready() { # pid port
  alive "$1" || die "operator exited: $(tail -5 "$WORK/controller.log" "$WORK/gateway.log")"
  curl -fsS --max-time 2 "http://127.0.0.1:$2/readyz" >/dev/null 2>&1
}
wait_for controller 120 ready "$CTRL_PID" "$CTRL_HTTP"
wait_for gateway 120 ready "$OP_PID" "$OP_HTTP"

# Peak RSS of the gateway, sampled each second.
( peak=0; while kill -0 "$OP_PID" 2>/dev/null; do
    r="$(rss_kib "$OP_PID" 2>/dev/null || true)"; r="${r:-0}"
    if [ "$r" -gt "$peak" ]; then peak=$r; echo "$peak" >"$WORK/peak-rss"; fi
    sleep 1; done ) 8>&- &
PIDS+=($!)

start sim "$BIN/lekiwi-sim" --gateway "ws://127.0.0.1:$GW_PORT/v1/agent" \
  --enrollment-token "$(cat "$WORK/enrollment-token")" --namespace "$NS" --robots "$ROBOTS" \
  --connect-rate 200 --telemetry-interval-s 0 --release-version 1.0.0 \
  --fail-health-share 0.05 --fail-health-versions 3.0.0 --health-timeout-seconds 5 \
  --timeout-share 1 --timeout-versions 5.0.0 --json "$WORK/sim.json"
SIM_PID=$LAST_PID
online() {
  alive "$SIM_PID" || die "lekiwi-sim exited: $(tail -5 "$WORK/sim.log")"
  [ "$(kubectl -n "$NS" get robots -o jsonpath='{range .items[*]}{.status.phase}{"\n"}{end}' 2>/dev/null | grep -c '^Online$')" -ge "$ROBOTS" ]
}
t="$(now)"
wait_for "$ROBOTS robots Online" $((ROBOTS / 20 + 300)) online
ONLINE_S="$(elapsed "$t")"

# ---- releases -----------------------------------------------------------------------------------
declare -A DIGEST=()
for v in 2.0.0 3.0.0 4.0.0 5.0.0 6.0.0; do
  mkdir -p "$WORK/releases/$v/lekiwi"
  for i in $(seq 1 20); do printf 'file %s\n' "$i" | head -c 4096 >"$WORK/releases/$v/lekiwi/f$i.py"; done
  head -c 262144 /dev/urandom >"$WORK/releases/$v/policy.safetensors"
  printf 'release %s\n' "$v" >"$WORK/releases/$v/VERSION"
  DIGEST[$v]="$("$BIN/kubectl-lekiwi" --kubeconfig "$KUBECONFIG" -n "$NS" release push "$WORK/releases/$v" \
    --version "$v" --server "http://127.0.0.1:$GW_PORT" 2>>"$WORK/push.log")"
done
RELEASE_BYTES="$(du -sb "$WORK/releases/2.0.0" | cut -f1)"

# ---- measuring ------------------------------------------------------------------------------------
writes() { # metrics file -> robots robots/status robotdeployments/status
  awk '/^apiserver_request_total\{/ && /verb="(POST|PUT|PATCH|APPLY|DELETE)"/ {
         r = ""; s = ""
         if (match($0, /resource="[^"]*"/)) r = substr($0, RSTART + 10, RLENGTH - 11)
         if (match($0, /subresource="[^"]*"/)) s = substr($0, RSTART + 13, RLENGTH - 14)
         if (r == "robots" && s == "") a += $NF
         if (r == "robots" && s == "status") b += $NF
         if (r == "robotdeployments" && s == "status") c += $NF
       } END { printf "%d %d %d\n", a, b, c }' "$1"
}
snap() {
  scrape_apiserver "$WORK/m-$1.prom"; writes "$WORK/m-$1.prom" >"$WORK/w-$1"
  cpu_seconds "$CTRL_PID" >"$WORK/cpu-$1"; date +%s.%N >"$WORK/t-$1"; gateway_writes >"$WORK/g-$1"
  echo "$(cpu_seconds "$APISERVER_PID") $(cpu_seconds "$ETCD_PID") $(cpu_seconds "$OP_PID")" \
    "$(cpu_seconds "$CTRL_PID") $(cpu_seconds "$SIM_PID") $(machine_busy)" >"$WORK/procs-$1"
}
# Cores each process kept busy from snapshot $1 to $2 (CPU seconds over wall seconds): where a
# phase's time goes on a machine the API server, etcd, the operator and the fleet share.
cores() {
  paste "$WORK/procs-$1" "$WORK/procs-$2" | awk -v t0="$(cat "$WORK/t-$1")" -v t1="$(cat "$WORK/t-$2")" '
    { s = t1 - t0; printf "apiserver %.2f, etcd %.2f, gateway %.2f, controller %.2f, sim %.2f; machine %.2f of '"$(nproc)"'\n",
        ($7 - $1) / s, ($8 - $2) / s, ($9 - $3) / s, ($10 - $4) / s, ($11 - $5) / s, ($12 - $6) / s }'
}
# The gateway's own count of its Robot status writes: its outcome and transition writes
# (priority high), its routine refreshes (priority low: heartbeat time, every robot once per
# status refresh period whatever happens), and all.
gateway_writes() {
  curl -fsS --max-time 5 "http://127.0.0.1:$OP_HTTP/metrics" 2>/dev/null | awk '
    index($0, "lekiwi_gateway_status_writes_total{") == 1 && /result="ok"/ {
      all += $2; if (/priority="high"/) high += $2; if (/priority="low"/) low += $2 }
    END { printf "%d %d %d\n", high, low, all }'
}
served() { current "http://127.0.0.1:$OP_HTTP/metrics" lekiwi_gateway_blob_bytes_served_total; }
phase_of() { kubectl -n "$NS" get robotdeployment "$1" -o jsonpath='{.status.phase}' 2>/dev/null; }
# The phase of the deployment's current spec: empty while the status is of an earlier generation
# (a re-applied deployment still shows the phase its previous rollout ended in).
current_phase() {
  kubectl -n "$NS" get robotdeployment "$1" \
    -o jsonpath='{.metadata.generation} {.status.observedGeneration} {.status.phase}' 2>/dev/null |
    awk '$1 == $2 { print $3 }'
}
wait_phase() { # name phases-regex timeout_s
  local deadline=$((SECONDS + $3))
  until current_phase "$1" | grep -Eq "^($2)$"; do
    [ $SECONDS -lt $deadline ] || return 1
    sleep 0.5
  done
}
deployment() { # name release-version selector-yaml threshold
  cat <<EOF
apiVersion: fleet.lekiwi.io/v1alpha1
kind: RobotDeployment
metadata: {name: $1}
spec:
  selector: $3
  release: {version: "$2", digest: "${DIGEST[$2]}"}
  strategy: {canary: 1, batchSize: "10%", successThreshold: $4, robotTimeoutSeconds: 300}
EOF
}
# Writes per robot of the phase from snapshot $1 to $2: every write of robots, robots/status and
# robotdeployments/status but the gateway's routine refreshes, which the fleet costs (N per status
# refresh period) whether anything rolls out or not; then the breakdown.
per_robot() {
  read -r a0 b0 c0 <"$WORK/w-$1"; read -r a1 b1 c1 <"$WORK/w-$2"
  read -r h0 l0 g0 <"$WORK/g-$1"; read -r h1 l1 g1 <"$WORK/g-$2"
  awk -v a=$((a1 - a0)) -v b=$((b1 - b0)) -v c=$((c1 - c0)) -v n="$ROBOTS" \
    -v h=$((h1 - h0)) -v l=$((l1 - l0)) -v g=$((g1 - g0)) \
    'BEGIN { printf "%.2f (robots %.2f, robots/status %.2f [the gateway'"'"'s outcome writes %.2f, the controller'"'"'s %.2f], robotdeployments/status %.3f; routine refreshes left out %.2f)\n", (a + b - l + c) / n, a / n, (b - l) / n, h / n, (b - g) / n, c / n, l / n }'
}
cpu_per_write() { # from to
  read -r _ b0 _ <"$WORK/w-$1"; read -r _ b1 _ <"$WORK/w-$2"
  awk -v c0="$(cat "$WORK/cpu-$1")" -v c1="$(cat "$WORK/cpu-$2")" -v n=$((b1 - b0)) \
    'BEGIN { printf "%.4f", (n > 0 ? (c1 - c0) / n : 0) }'
}

# ---- 1. one deployment over every robot ---------------------------------------------------------
snap a0; s0="$(served)"; t="$(now)"
deployment fleet 2.0.0 '{}' 0.8 | kubectl -n "$NS" apply -f - >/dev/null
if wait_phase fleet 'Completed|RolledBack|Failed' 1800; then A_S="$(elapsed "$t")"; else A_S=""; fi
sleep 5; snap a1; s1="$(served)"
A_PHASE="$(phase_of fleet)"
A_W="$(per_robot a0 a1)"
row "1 deployment over $ROBOTS robots: apply -> $A_PHASE, s" "${A_S:-timeout}" "<= 180" "$(verdict "$A_S" 180)"
row "  API writes per robot" "${A_W%% *}" "<= 2" "$(verdict "${A_W%% *}" 2)"
row "  ${A_W#* }" "" "" ""
row "  blob bytes served per robot / release bytes" "$(awk -v a="$s0" -v b="$s1" -v n="$ROBOTS" -v r="$RELEASE_BYTES" 'BEGIN { printf "%.2f", (b - a) / n / r }')" "~1.0" "info"
row "  controller CPU s per Robot status write (1 deployment)" "$(cpu_per_write a0 a1)" "flat" "info"
row "  cores busy: $(cores a0 a1)" "" "" ""

# ---- 2. 5% failing: rolled back ------------------------------------------------------------------
snap b0; t="$(now)"
# No canary: the first batch (10 %) is judged, with its 5 % failing robots among it (a canary
# that happened to be one of them would end the rollout before any batch).
deployment fleet 3.0.0 '{}' 0.99 | sed 's/canary: 1/canary: 0/' | kubectl -n "$NS" apply -f - >/dev/null
if wait_phase fleet 'RolledBack|Failed|Completed' 1800; then B_S="$(elapsed "$t")"; else B_S=""; fi
back() { [ "$(kubectl -n "$NS" get robots -o jsonpath='{range .items[*]}{.status.currentRelease.version}{"\n"}{end}' | grep -c '^2\.0\.0$')" -ge "$ROBOTS" ]; }
deadline=$((SECONDS + 600)); BACK_S=""
until back; do [ $SECONDS -lt $deadline ] || break; sleep 1; done
back && BACK_S="$(elapsed "$t")"
row "5% of a batch failing: apply -> $(phase_of fleet), s" "${B_S:-timeout}" "RolledBack" "$([ "$(phase_of fleet)" = RolledBack ] && echo PASS || echo FAIL)"
row "  every robot back on 2.0.0, s after apply" "${BACK_S:-not all}" "reported" "info"
kubectl -n "$NS" delete robotdeployment fleet >/dev/null

# ---- 3. many deployments over disjoint selections -------------------------------------------------
names=()
for i in $(seq 1 "$ROBOTS"); do names+=("$(printf 'sim-%05d' "$i")"); done
ended() { # count
  [ "$(kubectl -n "$NS" get robotdeployments -o jsonpath='{range .items[*]}{.status.phase}{"\n"}{end}' | grep -Ec '^(Completed|RolledBack|Failed)$')" -ge "$1" ]
}
# Labels every robot with its group of both phases at once, g10=gI and gD=gJ (D = --deployments),
# a hundred robots a kubectl at a time and eight kubectls at once: kubectl patches one Robot at a
# time, and one kubectl alone labelled a 10,000-robot fleet at about 6 a second.
label_groups() {
  local per=$((ROBOTS / DEPLOYMENTS)) g
  for g in $(seq 0 $((DEPLOYMENTS - 1))); do
    printf '%s\n' "g10=g$((g * per / (ROBOTS / 10))) g$DEPLOYMENTS=g$g ${names[*]:$((g * per)):$per}"
  done | xargs -P 8 -L 1 sh -c 'a="$1" b="$2"; shift 2; kubectl -n "$0" label robots --overwrite "$@" "$a" "$b" >/dev/null' "$NS"
}
many() { # count release goal_s
  local count="$1" v="$2" goal="$3" g deadline done_s="" completed w t
  kubectl -n "$NS" delete robotdeployments --all >/dev/null
  : >"$WORK/many-$count.yaml"
  for g in $(seq 0 $((count - 1))); do
    { deployment "d$count-$g" "$v" "{matchLabels: {g$count: g$g}}" 0.8; echo ---; } >>"$WORK/many-$count.yaml"
  done
  snap "m$count-0"; t="$(now)"
  kubectl -n "$NS" apply -f "$WORK/many-$count.yaml" >/dev/null
  deadline=$((SECONDS + 1800))
  until ended "$count"; do [ $SECONDS -lt $deadline ] || break; sleep 1; done
  ended "$count" && done_s="$(elapsed "$t")"
  sleep 5; snap "m$count-1"
  w="$(per_robot "m$count-0" "m$count-1")"
  completed="$(kubectl -n "$NS" get robotdeployments -o jsonpath='{range .items[*]}{.status.phase}{"\n"}{end}' | grep -c '^Completed$' || true)"
  row "$count deployments at once: all ended ($completed Completed), s" "${done_s:-timeout}" "<= $goal" "$( [ "$completed" = "$count" ] && verdict "$done_s" "$goal" || echo FAIL)"
  row "  API writes per robot" "${w%% *}" "<= 2" "$(verdict "${w%% *}" 2)"
  row "  ${w#* }" "" "" ""
  row "  controller CPU s per Robot status write ($count deployments)" "$(cpu_per_write "m$count-0" "m$count-1")" "flat" "info"
  row "  cores busy: $(cores "m$count-0" "m$count-1")" "" "" ""
}
log "labelling the robots with their groups"
label_groups
many 10 4.0.0 300
many "$DEPLOYMENTS" 6.0.0 300

# ---- 4. undo in flight: every downloading robot told to stop --------------------------------------
# Every robot's download of 5.0.0 stalls (lekiwi-sim --timeout-versions 5.0.0): the first batch
# (10%, no canary) is downloading when `rollout undo` is sent.
kubectl -n "$NS" delete robotdeployments --all >/dev/null
deployment stall 5.0.0 '{}' 0.8 | sed 's/canary: 1/canary: 0/' | kubectl -n "$NS" apply -f - >/dev/null
deploys() { grep -a 'sending command' "$WORK/gateway.log" | grep -ac 'version: "5.0.0"' || true; }
cancels() { echo $(( $(grep -ac 'command=Cancel' "$WORK/gateway.log" || true) - CANCELS0 )); }
deadline=$((SECONDS + 300))
until [ "$(deploys)" -ge $((ROBOTS / 10)) ] || [ $SECONDS -ge $deadline ]; do sleep 1; done
sleep 3
DOWNLOADING="$(deploys)"
CANCELS0="$(grep -ac 'command=Cancel' "$WORK/gateway.log" || true)"
UNDO_T="$(now)"
"$BIN/kubectl-lekiwi" --kubeconfig "$KUBECONFIG" -n "$NS" rollout undo stall >/dev/null
deadline=$((SECONDS + 120))
until [ "$(cancels)" -ge "$DOWNLOADING" ] || [ $SECONDS -ge $deadline ]; do sleep 0.5; done
UNDO_S="$(grep -a 'command=Cancel' "$WORK/gateway.log" | tail -n "$(cancels)" | python3 -c '
import sys, datetime
t0 = float(sys.argv[1]); last = 0.0
for line in sys.stdin:
    ts = datetime.datetime.fromisoformat(line.split()[0].replace("Z", "+00:00")).timestamp()
    last = max(last, ts)
print(f"{last - t0:.2f}" if last else "")' "$UNDO_T")"
row "rollout undo in flight: $(cancels) of $DOWNLOADING downloading robots told to stop, s" "${UNDO_S:-none}" "<= 2" "$( [ "$(cancels)" -ge "$DOWNLOADING" ] && verdict "$UNDO_S" 2 || echo FAIL)"

# ---- 5. an agent-update rollout -------------------------------------------------------------------
kubectl -n "$NS" delete robotdeployments --all >/dev/null
head -c 2000000 /dev/urandom >"$WORK/agent-build"
AGENT_DIGEST="$("$BIN/kubectl-lekiwi" --kubeconfig "$KUBECONFIG" -n "$NS" agent push --version 9.0.0 \
  --arch arm64 "$WORK/agent-build" --server "http://127.0.0.1:$GW_PORT" 2>>"$WORK/push.log")"
snap e0; t="$(now)"
cat >"$WORK/agents.yaml" <<EOF
apiVersion: fleet.lekiwi.io/v1alpha1
kind: RobotDeployment
metadata: {name: agents}
spec:
  selector: {}
  agent: {version: "9.0.0", builds: [{arch: arm64, digest: "$AGENT_DIGEST"}]}
  strategy: {canary: 1, batchSize: "10%", successThreshold: 0.8, robotTimeoutSeconds: 300}
EOF
kubectl -n "$NS" apply -f "$WORK/agents.yaml" >/dev/null
if wait_phase agents 'Completed|RolledBack|Failed' 1800; then E_S="$(elapsed "$t")"; else E_S=""; fi
sleep 5; snap e1
E_W="$(per_robot e0 e1)"
row "agent-update rollout over $ROBOTS robots: apply -> $(phase_of agents), s" "${E_S:-timeout}" "reported" "info"
row "  API writes per robot" "${E_W%% *}" "<= 2" "$(verdict "${E_W%% *}" 2)"
row "  ${E_W#* }" "" "" ""
row "  cores busy: $(cores e0 e1)" "" "" ""
row "gateway peak RSS, MiB" "$(awk '{ printf "%.0f", $1 / 1024 }' "$WORK/peak-rss")" "" "info"

# ---- the table ------------------------------------------------------------------------------------
OUT="$RESULTS/fleet-rollout-latest.txt"
{
  echo "LeKiwi fleet-rollout benchmark, $(date -Is)"
  echo "host: $(nproc) CPUs ($(awk -F': ' '/^model name/ { print $2; exit }' /proc/cpuinfo)), $(awk '/^MemTotal/ { printf "%.0f GiB", $2 / 1048576 }' /proc/meminfo) RAM"
  echo "source: $(git -C "$ROOT" rev-parse --short HEAD)"
  echo "command: $COMMAND"
  echo "fleet: $ROBOTS lekiwi-sim robots, Online after ${ONLINE_S} s; release: 21 files, $RELEASE_BYTES bytes"
  echo "operator: lekiwi-operator --role controller and --role gateway, defaults (heartbeat 30 s, status refresh 300 s) except --max-unauthenticated-per-address 0 and --enroll-rate 50 (the whole fleet enrolls at once)"
  echo "counted: apiserver_request_total writes of robots, robots/status, robotdeployments/status, less the gateway's routine status refreshes (lekiwi_gateway_status_writes_total{priority=\"low\"})"
  echo
  printf '%-62s %-22s %-10s %s\n' phase measured goal verdict
  cat "$ROWS"
} | tee "$OUT"
