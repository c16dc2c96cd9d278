#!/usr/bin/env bash
#! Hostile-peer benchmark: simulated robots heartbeat through the gateway, first in quiet, then
#! while attackers (bench/hostile_attack.py) hit the same gateway with slowloris connections,
#! token-guessing floods, sessions that stop reading and oversized frames. Prints one table:
#! heartbeat round trip p50/p99, the gateway's RSS, the API server's request rate, robots not
#! Online, sim reconnects, quiet vs. attack and their ratio (goal: within 2x, no robot Offline).
#!
#! Everything runs on this machine over loopback: a private control plane (etcd + kube-apiserver
#! v1.20.2), the operator as two processes (--role controller, --role gateway, default flags), the
#! fleet simulator `lekiwi-sim` for the robots (from 127.0.0.1) and the attacker (from 127.0.1.x).
#!
#! The attacker stands for other machines: with 2 or more CPUs it runs pinned to the last CPU and
#! everything else (control plane, operator, simulated robots) to the others, in both windows; the
#! kernel's receive processing of loopback traffic is steered (RPS on `lo`) to the others too, as a
#! network card would deliver the attacker's packets to the gateway host's CPUs. This changes
#! /sys/class/net/lo/queues/rx-0/rps_cpus for the run (root) and restores it on exit. `--no-pin`
#! runs everything on all CPUs (the attacker then also takes CPU from the robots it is compared
#! with: a worst case, not the goal's setting).
#!
#! Usage: bash bench/hostile.sh [options]
#!   --robots N        simulated robots (default 1000)
#!   --interval S      their heartbeat interval, seconds (default 5)
#!   --duration S      length of each measured window, quiet and attack (default 60)
#!   --slowloris N     stalled connections held by the attacker (default 1000)
#!   --flood-rate R    token-guessing requests per second (default 200)
#!   --stuck M         sessions with a stolen token that never read (default 50)
#!   --oversized K     sessions with a stolen token that send oversized frames (default 10)
#!   --no-pin          do not pin the attacker to its own CPU (see above)
#!   --no-build        use the binaries already in target/release
#!   --keep            keep the work directory (logs, scrapes)
#!   -h, --help        this text
#!
#! Writes the table to bench/results/hostile-<date>.txt and bench/results/hostile-latest.txt.
#! Bounded in time (about 2 x duration + 2 minutes once built), cleans up on exit and Ctrl-C.
set -euo pipefail

ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
BIN="$ROOT/target/release"
RESULTS="$ROOT/bench/results"

ROBOTS=1000
INTERVAL=5
WINDOW=60
SLOWLORIS=1000
FLOOD_RATE=200
STUCK=50
OVERSIZED=10
BUILD=1
KEEP=0
PIN=1
COMMAND="bash bench/hostile.sh $*"

# shellcheck source=bench/lib.sh
source "$ROOT/bench/lib.sh"

while [ $# -gt 0 ]; do
  case "$1" in
    --robots) positive_int "$1" "${2:-}"; ROBOTS="$2"; shift 2 ;;
    --interval) positive_int "$1" "${2:-}"; INTERVAL="$2"; shift 2 ;;
    --duration) positive_int "$1" "${2:-}"; WINDOW="$2"; shift 2 ;;
    --slowloris) [[ "${2:-}" =~ ^[0-9]+$ ]] || die "$1 needs a count"; SLOWLORIS="$2"; shift 2 ;;
    --flood-rate) [[ "${2:-}" =~ ^[0-9]+$ ]] || die "$1 needs a rate"; FLOOD_RATE="$2"; shift 2 ;;
    --stuck) [[ "${2:-}" =~ ^[0-9]+$ ]] || die "$1 needs a count"; STUCK="$2"; shift 2 ;;
    --oversized) [[ "${2:-}" =~ ^[0-9]+$ ]] || die "$1 needs a count"; OVERSIZED="$2"; shift 2 ;;
    --no-pin) PIN=0; shift ;;
    --no-build) BUILD=0; shift ;;
    --keep) KEEP=1; shift ;;
    -h|--help) usage; exit 0 ;;
    *) usage >&2; die "unknown option: $1" ;;
  esac
done

WORK="$(mktemp -d "${TMPDIR:-/tmp}/lekiwi-bench.XXXXXX")"
CP_DIR="$WORK/control-plane"
CP_UP=0
PIDS=()
trap_cleanup

# Pins this script (so everything it starts) to all CPUs but the last, which the attacker gets,
# and steers loopback receive processing to the same CPUs; sets ATTACK_CPU.
ATTACK_CPU=
RPS=/sys/class/net/lo/queues/rx-0/rps_cpus
pin_cpus() {
  local n
  n="$(nproc)"
  if [ "$n" -lt 2 ]; then
    log "one CPU: the attacker shares it (as with --no-pin)"
    return
  fi
  ATTACK_CPU=$((n - 1))
  taskset -p -c "0-$((n - 2))" $$ >/dev/null || die "taskset failed"
  local old
  old="$(cat "$RPS")"
  printf '%x' $(((1 << (n - 1)) - 1)) >"$RPS" 2>/dev/null \
    || die "cannot write $RPS (run as root, or use --no-pin)"
  ON_EXIT="printf %s '$old' >$RPS"
  fact pinning "attacker on CPU $ATTACK_CPU; everything else and loopback RPS on CPUs 0-$((n - 2))"
}

# Simulated robots (sim-*) whose Robot is not Online right now.
not_online() {
  kubectl -n bench get robots -o jsonpath='{range .items[*]}{.metadata.name} {.status.phase}{"\n"}{end}' \
    | awk '$1 ~ /^sim-/ && $2 != "Online" { n++ } END { print n + 0 }'
}
# The simulator's cumulative reconnect count (last progress line).
sim_reconnects() { grep -ao 'reconnects [0-9]*' "$WORK/sim.log" | tail -1 | awk '{ print $2 + 0 }'; }

take_bench_lock
ulimit -n "$(ulimit -Hn)" 2>/dev/null || true
[ "$(ulimit -n)" -gt $((ROBOTS + SLOWLORIS * 2 + 4000)) ] \
  || die "open-file limit $(ulimit -n) is too low (raise the hard limit)"

log "work directory: $WORK"
release_binaries "lekiwi-operator lekiwi-agent" lekiwi-operator lekiwi-sim
run_setup

fact date "$(date -Is)"
fact host "$(nproc) CPUs, $(awk '/^MemTotal/ { printf "%.0f GiB", $2 / 1048576 }' /proc/meminfo) RAM, load average at start $(cut -d' ' -f1-3 /proc/loadavg)"
fact_source
fact command "$COMMAND"
fact robots "$ROBOTS"
fact interval "$INTERVAL"
fact attack "slowloris $SLOWLORIS, flood $FLOOD_RATE/s, stuck $STUCK, oversized $OVERSIZED"
if [ $PIN = 1 ]; then pin_cpus; else fact pinning "none (--no-pin): the attacker shares every CPU"; fi

# ---- control plane, robots, operator -------------------------------------------------------------
start_control_plane
kubectl create namespace lekiwi-system >/dev/null
kubectl create namespace bench >/dev/null
TOKEN="lkr_$(openssl rand -hex 32)"
printf %s "$TOKEN" >"$WORK/stolen-token"
TOKEN_HASH="$(printf %s "$TOKEN" | sha256sum | cut -d' ' -f1)"

# The robots and their token Secrets, as the gateway's enrollment writes them; the simulated robots
# and the attacker's "stolen" robots (stuck-*, big-*) share one token.
log "provisioning $ROBOTS robots and $((STUCK + OVERSIZED)) attacker robots"
python3 - "$ROBOTS" "$STUCK" "$OVERSIZED" "$TOKEN_HASH" "$WORK" <<'PY'
import base64, json, sys
robots, stuck, big, digest, work = int(sys.argv[1]), int(sys.argv[2]), int(sys.argv[3]), sys.argv[4], sys.argv[5]
data = base64.b64encode(digest.encode()).decode()
names = [f"sim-{i + 1:05d}" for i in range(robots)]
with open(f"{work}/robots.txt", "w") as out:
    out.write("\n".join(names) + "\n")
names += [f"stuck-{i + 1:03d}" for i in range(stuck)] + [f"big-{i + 1:03d}" for i in range(big)]
for part in range(4):
    items = []
    for name in names[part::4]:
        items.append({"apiVersion": "fleet.lekiwi.io/v1alpha1", "kind": "Robot",
                      "metadata": {"name": name}, "spec": {}})
        items.append({"apiVersion": "v1", "kind": "Secret", "type": "Opaque",
                      "metadata": {"name": f"{name}-agent-token",
                                   "labels": {"fleet.lekiwi.io/token": "robot",
                                              "fleet.lekiwi.io/robot": name}},
                      "data": {"sha256": data}})
    with open(f"{work}/provision-{part}.json", "w") as out:
        json.dump({"apiVersion": "v1", "kind": "List", "items": items}, out)
PY
for part in 0 1 2 3; do
  kubectl -n bench create -f "$WORK/provision-$part.json" >"$WORK/provision-$part.log" 2>&1 \
    || die "provisioning failed: $(tail -3 "$WORK/provision-$part.log")"
done

CTRL_HTTP="$(free_port)"
GW_HTTP="$(free_port)"
GW_PORT="$(free_port)"
log "starting the controller and the gateway (ws :$GW_PORT, http :$GW_HTTP), default flags"
start controller env RUST_LOG=warn "$BIN/lekiwi-operator" --role controller \
  --kubeconfig "$KUBECONFIG" --namespace lekiwi-system --watch-namespace bench \
  --identity bench-controller --http-addr "127.0.0.1:$CTRL_HTTP"
CTRL_PID=$LAST_PID
start gateway env RUST_LOG=warn "$BIN/lekiwi-operator" --role gateway \
  --kubeconfig "$KUBECONFIG" --namespace lekiwi-system --watch-namespace bench \
  --identity bench-gateway --gateway-name bench-gateway \
  --gateway-addr "127.0.0.1:$GW_PORT" --http-addr "127.0.0.1:$GW_HTTP" \
  --store-url "sqlite://$WORK/events.db" --heartbeat-interval-seconds "$INTERVAL"
GW_PID=$LAST_PID
CTRL_METRICS="http://127.0.0.1:$CTRL_HTTP/metrics"
GW_METRICS="http://127.0.0.1:$GW_HTTP/metrics"
ready() { alive "$1" || die "$2 exited: $(tail -5 "$WORK/$2.log")"; curl -fsS --max-time 2 "$3" >/dev/null 2>&1; }
wait_for "gateway" 60 ready "$GW_PID" gateway "http://127.0.0.1:$GW_HTTP/readyz"

log "$ROBOTS simulated robots connect"
start sim "$BIN/lekiwi-sim" --gateway "ws://127.0.0.1:$GW_PORT/v1/agent" \
  --enrollment-token "$TOKEN" --namespace bench --robots "$ROBOTS" \
  --heartbeat-interval "$INTERVAL" --connect-rate 500 --report-every 5 --telemetry-interval-s 0
SIM_PID=$LAST_PID
online() {
  alive "$SIM_PID" || die "the simulator exited: $(tail -5 "$WORK/sim.log")"
  [ "$(current "$CTRL_METRICS" 'lekiwi_robots{phase="Online"}')" -ge "$ROBOTS" ]
}
wait_for "all robots Online" 300 online
APISERVER_PID="$(cat "$CP_DIR/kube-apiserver.pid")"
ATTACK_PID=
sleep $((2 * INTERVAL))

# ---- the two windows ----------------------------------------------------------------------------
# measure PHASE: scrapes at both ends, RSS and robots-not-Online sampled every 5 s.
measure() {
  local phase="$1" max_rss=0 max_down=0 r d t0 end
  scrape "$GW_METRICS" "$WORK/gateway-$phase-a.txt"
  scrape_apiserver "$WORK/apiserver-$phase-a.txt"
  local reconnects0
  reconnects0="$(sim_reconnects)"
  cpu_snapshot "gateway:$GW_PID" "sim:$SIM_PID" "controller:$CTRL_PID" "apiserver:$APISERVER_PID" \
    ${ATTACK_PID:+"attacker:$ATTACK_PID"}
  t0="$(now)"
  end=$((SECONDS + WINDOW))
  while [ $SECONDS -lt $end ]; do
    alive "$GW_PID" || die "the gateway exited during the $phase window: $(tail -5 "$WORK/gateway.log")"
    r="$(rss_kib "$GW_PID")"; [ "$r" -gt $max_rss ] && max_rss=$r
    d="$(not_online)"; [ "$d" -gt $max_down ] && max_down=$d
    sleep 5
  done
  scrape "$GW_METRICS" "$WORK/gateway-$phase-b.txt"
  scrape_apiserver "$WORK/apiserver-$phase-b.txt"
  fact "${phase}_seconds" "$(elapsed "$t0")"
  cpu_report "$phase" "$(elapsed "$t0")"
  fact "${phase}_rss_max_kib" "$max_rss"
  fact "${phase}_not_online_max" "$max_down"
  fact "${phase}_sim_reconnects" "$(( $(sim_reconnects) - reconnects0 ))"
  fact "${phase}_healthz" "$(curl -s -o /dev/null -w '%{http_code} in %{time_total}s' --max-time 5 "http://127.0.0.1:$GW_HTTP/healthz" || true)"
}

log "quiet window: $WINDOW s"
measure quiet

log "attack window: $WINDOW s (the attacker starts 10 s before it)"
ATTACK=(${ATTACK_CPU:+taskset -c "$ATTACK_CPU"} python3 "$ROOT/bench/hostile_attack.py" --port "$GW_PORT" --duration $((WINDOW + 15))
  --namespace bench --robots-file "$WORK/robots.txt" --token-file "$WORK/stolen-token"
  --slowloris "$SLOWLORIS" --flood-rate "$FLOOD_RATE" --stuck "$STUCK" --oversized "$OVERSIZED"
  --json "$WORK/attack.json")
start attacker "${ATTACK[@]}"
ATTACK_PID=$LAST_PID
sleep 10
measure attack
wait "$ATTACK_PID" 2>/dev/null || log "the attacker ended with an error: $(tail -3 "$WORK/attacker.log")"
forget "$ATTACK_PID"
sleep 3
fact after_not_online "$(not_online)"
fact after_rss_kib "$(rss_kib "$GW_PID")"

stop "$GW_PID"
stop "$SIM_PID"
stop "$CTRL_PID"

mkdir -p "$RESULTS"
STAMP="$(date +%Y%m%d-%H%M%S)"
python3 "$ROOT/bench/hostile_report.py" "$WORK" >"$WORK/table.txt"
cp "$WORK/table.txt" "$RESULTS/hostile-$STAMP.txt"
cp "$WORK/table.txt" "$RESULTS/hostile-latest.txt"
echo
cat "$WORK/table.txt"
echo
log "written to bench/results/hostile-$STAMP.txt and bench/results/hostile-latest.txt"
