#!/usr/bin/env bash
#! Gateway benchmark: runs a private control plane (etcd + kube-apiserver v1.20.2), the operator as
#! two processes (--role controller, --role gateway) and the fleet simulator `lekiwi-sim` on this
#! machine, then the same simulator against `lekiwi-bench-echo` (a bare tokio-tungstenite server) as
#! the floor, and prints one table: heartbeat round trip p50/p99/max through the gateway and through
#! the floor, gateway RSS per connection, time until every Robot is Online, API server writes per
#! second at steady state (from the API server's own /metrics), status writes, errors.
#!
#! Two ways for the robots to come in:
#!   enroll     (default) every robot presents the fleet enrollment token on its first connect, so
#!              the gateway creates its Robot and token Secret; "time until all Online" includes
#!              enrollment, exactly as a new fleet's first boot.
#!   provision  the benchmark creates the N Robots and their token Secrets first (as the gateway
#!              would), so the robots connect as known robots: a whole fleet reconnecting, e.g.
#!              after a gateway restart; no API calls on the connection path.
#!
#! Usage: bash bench/gateway.sh [options]
#!   --robots N            simulated robots (default 10000)
#!   --mode enroll|provision  see above (default enroll)
#!   --interval S          heartbeat interval, seconds (default 5)
#!   --duration S          steady-state measurement window, seconds, per phase (default 60)
#!   --connect-rate R      new robots per second while ramping up against the gateway (default
#!                         1000 with --mode provision; 25 with --mode enroll, where each new robot
#!                         costs the API server a Robot and a Secret: see docs/src/benchmarks/gateway.md)
#!   --echo-connect-rate R the same against the echo floor, which does no enrollment (default 1000)
#!   --status-qps Q        gateway --status-qps (default 500)
#!   --status-burst B      gateway --status-burst (default 1000)
#!   --status-refresh S    gateway --status-refresh-seconds (default 300, the operator's default)
#!   --online-timeout S    give up waiting for all robots Online after S seconds (default
#!                         robots / connect rate + robots / 40 + 120, at most 600: a robot coming
#!                         Online costs one status write, an enrolling one about 4 writes, and the
#!                         API server takes ~200 writes/s on 2 cores)
#!   --tls                 the gateway serves wss:// (a CA and certificate made here with openssl)
#!                         and the simulator trusts that CA, as agents in production; the echo
#!                         floor stays plain ws://, so compare RSS per connection with a run
#!                         without --tls
#!   --no-build            use the binaries already in target/release
#!   --keep                keep the work directory (logs, metric scrapes) instead of deleting it
#!   -h, --help            this text
#!
#! Environment: LEKIWI_BENCH_GATEWAY_ENV="K=V ..." adds environment variables to the gateway process
#! only (e.g. MALLOC_ARENA_MAX=2, to see how much of its memory is allocator overhead).
#!
#! Writes the table to bench/results/gateway-<date>.txt and bench/results/gateway-latest.txt. Bounded in
#! time (about 5 minutes for 10,000 robots once built; at most ~15), cleans up on exit and Ctrl-C.
set -euo pipefail

ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
BIN="$ROOT/target/release"
RESULTS="$ROOT/bench/results"

ROBOTS=10000
MODE=enroll
INTERVAL=5
WINDOW=60
CONNECT_RATE=
ECHO_CONNECT_RATE=1000
STATUS_QPS=500
STATUS_BURST=1000
STATUS_REFRESH=300
ONLINE_TIMEOUT=
TLS=0
BUILD=1
KEEP=0
COMMAND="bash bench/gateway.sh $*"

# shellcheck source=bench/lib.sh
source "$ROOT/bench/lib.sh"

while [ $# -gt 0 ]; do
  case "$1" in
    --robots) positive_int "$1" "${2:-}"; ROBOTS="$2"; shift 2 ;;
    --mode)
      case "${2:-}" in enroll|provision) MODE="$2" ;; *) die "--mode is enroll or provision" ;; esac
      shift 2 ;;
    --interval) positive_int "$1" "${2:-}"; INTERVAL="$2"; shift 2 ;;
    --duration) positive_int "$1" "${2:-}"; WINDOW="$2"; shift 2 ;;
    --connect-rate) positive_int "$1" "${2:-}"; CONNECT_RATE="$2"; shift 2 ;;
    --echo-connect-rate) positive_int "$1" "${2:-}"; ECHO_CONNECT_RATE="$2"; shift 2 ;;
    --status-qps) positive_int "$1" "${2:-}"; STATUS_QPS="$2"; shift 2 ;;
    --status-burst) positive_int "$1" "${2:-}"; STATUS_BURST="$2"; shift 2 ;;
    --status-refresh) positive_int "$1" "${2:-}"; STATUS_REFRESH="$2"; shift 2 ;;
    --online-timeout) positive_int "$1" "${2:-}"; ONLINE_TIMEOUT="$2"; shift 2 ;;
    --tls) TLS=1; shift ;;
    --no-build) BUILD=0; shift ;;
    --keep) KEEP=1; shift ;;
    -h|--help) usage; exit 0 ;;
    *) usage >&2; die "unknown option: $1" ;;
  esac
done

if [ -z "$CONNECT_RATE" ]; then
  if [ "$MODE" = enroll ]; then CONNECT_RATE=25; else CONNECT_RATE=1000; fi
fi
if [ -z "$ONLINE_TIMEOUT" ]; then
  ONLINE_TIMEOUT=$((ROBOTS / CONNECT_RATE + ROBOTS / 40 + 120))
  [ $ONLINE_TIMEOUT -le 600 ] || ONLINE_TIMEOUT=600
fi

# ---- processes and cleanup ------------------------------------------------------------------
WORK="$(mktemp -d "${TMPDIR:-/tmp}/lekiwi-bench.XXXXXX")"
CP_DIR="$WORK/control-plane"
CP_UP=0
PIDS=()

trap_cleanup

# The value of the series $2 (exact text up to the value, labels included) in file $1, or empty.
sample() { awk -v s="$2" 'index($0, s " ") == 1 { print $2; exit }' "$1" 2>/dev/null; }

# ---- preparation ----------------------------------------------------------------------------
# One benchmark at a time on this machine: two would share the 2 cores and disturb each other.
take_bench_lock

ulimit -n "$(ulimit -Hn)" 2>/dev/null || true
NOFILE="$(ulimit -n)"
[ "$NOFILE" -gt $((ROBOTS + 100)) ] \
  || die "open-file limit $NOFILE is too low for $ROBOTS connections (raise the hard limit)"

log "work directory: $WORK"
release_binaries "lekiwi-operator lekiwi-agent lekiwi-bench-echo" lekiwi-operator lekiwi-sim lekiwi-bench-echo

run_setup

fact date "$(date -Is)"
fact host "$(nproc) CPUs ($(awk -F': ' '/^model name/ { print $2; exit }' /proc/cpuinfo)), $(awk '/^MemTotal/ { printf "%.0f GiB", $2 / 1048576 }' /proc/meminfo) RAM, load average at start $(cut -d' ' -f1-3 /proc/loadavg)"
fact cpus "$(nproc)"
fact_source
fact command "$COMMAND"
fact robots "$ROBOTS"
fact interval "$INTERVAL"
fact status_refresh "$STATUS_REFRESH"
fact connect_rates "$CONNECT_RATE/s against the gateway, $ECHO_CONNECT_RATE/s against the echo floor"

# ---- control plane --------------------------------------------------------------------------
start_control_plane

kubectl create namespace lekiwi-system >/dev/null
kubectl create namespace bench >/dev/null
TOKEN="lke_$(openssl rand -hex 32)"
TOKEN_HASH="$(printf %s "$TOKEN" | sha256sum | cut -d' ' -f1)"
if [ "$MODE" = enroll ]; then
  kubectl -n bench create secret generic fleet-enrollment --from-literal=sha256="$TOKEN_HASH" >/dev/null
  kubectl -n bench label secret fleet-enrollment fleet.lekiwi.io/token=enrollment >/dev/null
fi

# ---- operator: controller and gateway -------------------------------------------------------
CTRL_HTTP="$(free_port)"
GW_HTTP="$(free_port)"
GW_PORT="$(free_port)"
# Every simulated robot connects from 127.0.0.1: no per-address cap on unauthenticated
# connections (the global one, --max-unauthenticated-connections, stays at its default).
GATEWAY_FLAGS=(
  --max-unauthenticated-per-address 0
  --status-qps "$STATUS_QPS" --status-burst "$STATUS_BURST"
  --status-refresh-seconds "$STATUS_REFRESH" --heartbeat-interval-seconds "$INTERVAL"
)
fact gateway_flags "${GATEWAY_FLAGS[*]} --store-url sqlite://\$WORK/events.db (WAL, synchronous=FULL, ext4)"
GW_SCHEME=ws
SIM_TLS=()
if [ $TLS = 1 ]; then
  make_tls "$WORK"
  GATEWAY_FLAGS+=(--tls-cert "$WORK/tls.crt" --tls-key "$WORK/tls.key")
  GW_SCHEME=wss
  SIM_TLS=(--ca-file "$WORK/ca.crt")
fi
fact tls "$([ $TLS = 1 ] && echo "wss:// to the gateway (rustls, ECDSA P-256 certificate); the echo floor plain ws://" || echo "none (plain ws:// on loopback)")"

log "starting the controller (http :$CTRL_HTTP) and the gateway (ws :$GW_PORT, http :$GW_HTTP)"
start controller env RUST_LOG=warn "$BIN/lekiwi-operator" --role controller \
  --kubeconfig "$KUBECONFIG" --namespace lekiwi-system --watch-namespace bench \
  --identity bench-controller --http-addr "127.0.0.1:$CTRL_HTTP"
CTRL_PID=$LAST_PID
read -r -a GATEWAY_ENV <<<"${LEKIWI_BENCH_GATEWAY_ENV:-}"
[ ${#GATEWAY_ENV[@]} = 0 ] || fact gateway_env "${GATEWAY_ENV[*]}"
start gateway env RUST_LOG=warn "${GATEWAY_ENV[@]}" "$BIN/lekiwi-operator" --role gateway \
  --kubeconfig "$KUBECONFIG" --namespace lekiwi-system --watch-namespace bench \
  --identity bench-gateway --gateway-name bench-gateway \
  --gateway-addr "127.0.0.1:$GW_PORT" --http-addr "127.0.0.1:$GW_HTTP" \
  --store-url "sqlite://$WORK/events.db" "${GATEWAY_FLAGS[@]}"
GW_PID=$LAST_PID
CTRL_METRICS="http://127.0.0.1:$CTRL_HTTP/metrics"
GW_METRICS="http://127.0.0.1:$GW_HTTP/metrics"

ready() { alive "$1" || die "$2 exited: $(tail -5 "$WORK/$2.log")"; curl -fsS --max-time 2 "$3" >/dev/null 2>&1; }
wait_for "gateway" 60 ready "$GW_PID" gateway "http://127.0.0.1:$GW_HTTP/readyz"
leader() { alive "$CTRL_PID" || die "controller exited: $(tail -5 "$WORK/controller.log")"; [ "$(current "$CTRL_METRICS" lekiwi_leader_election_is_leader)" = 1 ]; }
wait_for "controller leadership" 60 leader

sleep 2
GW_RSS_BEFORE="$(rss_kib "$GW_PID")"
fact gateway_rss_before_kib "$GW_RSS_BEFORE"
log "gateway RSS before any robot: $((GW_RSS_BEFORE / 1024)) MiB"

# Provisioning: the N Robots and their token Secrets (labels and hash exactly as the gateway's
# enrollment writes them; all robots share the simulator's one token), created by four parallel
# kubectl processes. Measured from before, so the gateway's per-robot Secret cache still counts
# in its memory per connection.
if [ "$MODE" = provision ]; then
  log "provisioning $ROBOTS Robots and token Secrets"
  T_PROV="$(now)"
  provision_robots bench "$ROBOTS" "$TOKEN_HASH"
  log "provisioned in $(elapsed "$T_PROV") s; waiting for the controller to see $ROBOTS Pending robots"
  pending() { [ "$(current "$CTRL_METRICS" 'lekiwi_robots{phase="Pending"}')" -ge "$ROBOTS" ]; }
  wait_for "all robots Pending" 300 pending
  fact provision_seconds "$(elapsed "$T_PROV")"
  # Let the controller's Pending writes and Events finish before robots connect.
  sleep 5
  fact gateway_rss_provisioned_kib "$(rss_kib "$GW_PID")"
fi
fact mode "$MODE"

# ---- helpers of both phases -----------------------------------------------------------------
# The simulator runs until killed; its RTT figures cover the whole run (ramp included), so the
# steady-state round trips come from the gateway's histogram of agent-reported RTTs instead.
# --telemetry-interval-s 0: the figures measure heartbeats and status writes, as they always did.
SIM_COMMON=(--robots "$ROBOTS" --heartbeat-interval "$INTERVAL" --namespace bench
  --telemetry-interval-s 0 --report-every 5 --duration $((ONLINE_TIMEOUT + WINDOW + 600)))

# What the progress lines add: for the gateway, its open files, its connections to the API server
# and its status queues (the first things to look at when the ramp stalls); a scrape is kept too.
progress_extra() { :; }
gateway_progress() {
  local fds api q
  fds="$(find "/proc/$GW_PID/fd" -mindepth 1 -maxdepth 1 2>/dev/null | wc -l)"
  api="$(ss -Htnp state established "( dport = :$APISERVER_PORT )" 2>/dev/null | grep -c "pid=$GW_PID," || true)"
  scrape "$GW_METRICS" "$WORK/gateway-ramp-$(printf %04d "$SECONDS").txt" || true
  q="$(sample "$WORK/gateway-ramp-$(printf %04d "$SECONDS").txt" 'lekiwi_gateway_status_queue{priority="high"}')"
  printf '; gateway RSS %s MiB, fds %s, API connections %s, high queue %s' \
    "$(( $(rss_kib "$GW_PID") / 1024 ))" "$fds" "$api" "${q:-?}"
}

# Waits until series $2 at $1 reaches $ROBOTS; sets WAITED (seconds since $3) or empty on timeout.
# Also records the first time the series $5 at $4 reached $ROBOTS in WAITED_SECONDARY.
wait_all() {
  local url="$1" series="$2" t0="$3" url2="$4" series2="$5" timeout="$6" watch_pid="$7" sim_log="$8"
  local last_log=$SECONDS v v2
  WAITED="" WAITED_SECONDARY=""
  while :; do
    v="$(current "$url" "$series")"
    if [ -n "$url2" ] && [ -z "$WAITED_SECONDARY" ]; then
      v2="$(current "$url2" "$series2")"
      [ "$v2" -ge "$ROBOTS" ] && WAITED_SECONDARY="$(elapsed "$t0")"
    fi
    if [ "$v" -ge "$ROBOTS" ]; then
      WAITED="$(elapsed "$t0")"
      [ -n "$url2" ] && [ -z "$WAITED_SECONDARY" ] && WAITED_SECONDARY="$WAITED"
      return 0
    fi
    for pid in $watch_pid; do alive "$pid" || die "a process exited early; see $WORK/*.log"; done
    if [ $((SECONDS - last_log)) -ge 10 ]; then
      last_log=$SECONDS
      log "  $(elapsed "$t0") s: $series = $v${url2:+, $series2 = ${v2:-done}}$(progress_extra)"
      log "    sim: $(grep -a 'connected' "$sim_log" | tail -1 | sed 's/^\[ *[0-9.]*s\] //')"
    fi
    if awk -v e="$(elapsed "$t0")" -v t="$timeout" 'BEGIN { exit !(e > t) }'; then
      return 1
    fi
    sleep 1
  done
}

# Steady-state window: scrapes at both ends, RSS sampled every 5 s (max and last kept).
# measure PHASE PID URL... ; files <name>-a.txt and <name>-b.txt for each NAME=URL.
measure() {
  local phase="$1" pid="$2"; shift 2
  local item max=0 r t0 end
  for item in "$@"; do
    if [ "${item%%=*}" = apiserver ]; then scrape_apiserver "$WORK/apiserver-a.txt"
    else scrape "${item#*=}" "$WORK/${item%%=*}-a.txt"; fi
  done
  t0="$(now)"
  end=$((SECONDS + WINDOW))
  while [ $SECONDS -lt $end ]; do
    alive "$pid" || die "$phase server exited during the window"
    r="$(rss_kib "$pid")"; [ "$r" -gt $max ] && max=$r
    sleep $(( end - SECONDS < 5 ? (end - SECONDS > 0 ? end - SECONDS : 0) : 5 ))
  done
  for item in "$@"; do
    if [ "${item%%=*}" = apiserver ]; then scrape_apiserver "$WORK/apiserver-b.txt"
    else scrape "${item#*=}" "$WORK/${item%%=*}-b.txt"; fi
  done
  WINDOW_SECONDS="$(elapsed "$t0")"
  r="$(rss_kib "$pid")"; [ "$r" -gt $max ] && max=$r
  fact "${phase}_rss_after_kib" "$r"
  fact "${phase}_rss_max_kib" "$max"
  fact "window_${phase}_seconds" "$WINDOW_SECONDS"
}

APISERVER_PID="$(cat "$CP_DIR/kube-apiserver.pid")"
ETCD_PID="$(cat "$CP_DIR/etcd.pid")"

# ---- phase 1: the floor, the same simulator against the bare echo server --------------------
# It runs first, while the control plane, the controller and the gateway are up but idle, so the
# floor sees the same background as the gateway will (minus the robots' own load).
ECHO_PORT="$(free_port)"
ECHO_HTTP="$(free_port)"
ECHO_METRICS="http://127.0.0.1:$ECHO_HTTP/metrics"
log "phase 1 (floor): $ROBOTS robots -> lekiwi-bench-echo (ws :$ECHO_PORT, connect rate $ECHO_CONNECT_RATE/s)"
start echo "$BIN/lekiwi-bench-echo" --listen "127.0.0.1:$ECHO_PORT" \
  --metrics "127.0.0.1:$ECHO_HTTP" --heartbeat-interval "$INTERVAL"
ECHO_PID=$LAST_PID
wait_for "echo server" 30 ready "$ECHO_PID" echo "$ECHO_METRICS"
sleep 1
fact echo_rss_before_kib "$(rss_kib "$ECHO_PID")"
T0="$(now)"
start sim-echo "$BIN/lekiwi-sim" --gateway "ws://127.0.0.1:$ECHO_PORT/v1/agent" \
  --enrollment-token unused --connect-rate "$ECHO_CONNECT_RATE" --json "$WORK/sim-echo.json" \
  "${SIM_COMMON[@]}"
SIM_PID=$LAST_PID
if wait_all "$ECHO_METRICS" lekiwi_bench_echo_connections "$T0" "" "" 120 "$SIM_PID $ECHO_PID" \
    "$WORK/sim-echo.log"; then
  fact echo_time_all_sessions_seconds "$WAITED"
  log "all $ROBOTS robots connected to the echo server after $WAITED s"
else
  log "NOT all robots connected to the echo server after 120 s; measuring anyway"
fi
sleep $((2 * INTERVAL))
log "steady state: measuring for $WINDOW s"
cpu_snapshot "echo:$ECHO_PID" "sim:$SIM_PID" "controller:$CTRL_PID" "gateway:$GW_PID" \
  "apiserver:$APISERVER_PID" "etcd:$ETCD_PID"
measure echo "$ECHO_PID" "echo=$ECHO_METRICS"
cpu_report echo "$WINDOW_SECONDS"
fact echo_connections_end "$(sample "$WORK/echo-b.txt" lekiwi_bench_echo_connections)"
stop "$SIM_PID"
stop "$ECHO_PID"
sleep 2

# ---- phase 2: the simulator against the gateway ---------------------------------------------
log "phase 2: $ROBOTS robots -> gateway (connect rate $CONNECT_RATE/s, heartbeat ${INTERVAL}s)"
scrape_apiserver "$WORK/apiserver-start.txt"
T0="$(now)"
start sim-gateway "$BIN/lekiwi-sim" --gateway "$GW_SCHEME://127.0.0.1:$GW_PORT/v1/agent" \
  --enrollment-token "$TOKEN" --connect-rate "$CONNECT_RATE" --json "$WORK/sim-gateway.json" \
  "${SIM_TLS[@]}" "${SIM_COMMON[@]}"
SIM_PID=$LAST_PID
progress_extra() { gateway_progress; }
cpu_snapshot "gateway:$GW_PID" "sim:$SIM_PID" "controller:$CTRL_PID" \
  "apiserver:$APISERVER_PID" "etcd:$ETCD_PID"
if wait_all "$CTRL_METRICS" 'lekiwi_robots{phase="Online"}' "$T0" \
    "$GW_METRICS" lekiwi_gateway_connections "$ONLINE_TIMEOUT" "$SIM_PID $GW_PID $CTRL_PID" \
    "$WORK/sim-gateway.log"; then
  cpu_report ramp "$WAITED"
  scrape_apiserver "$WORK/apiserver-online.txt"
  fact time_all_online_seconds "$WAITED"
  log "all $ROBOTS robots Online after $WAITED s (all sessions open after $WAITED_SECONDARY s)"
else
  log "NOT all robots Online after $ONLINE_TIMEOUT s; measuring the steady state anyway"
fi
[ -n "$WAITED_SECONDARY" ] && fact time_all_sessions_seconds "$WAITED_SECONDARY"
progress_extra() { :; }

# Settle: transitions written, and two heartbeat intervals so that every RTT the agents report
# (each heartbeat carries the previous one's) was measured after the ramp.
drained() { [ "$(current "$GW_METRICS" 'lekiwi_gateway_status_queue{priority="high"}')" -le 0 ]; }
DRAIN_DEADLINE=$((SECONDS + 60))
until drained; do
  if [ $SECONDS -ge $DRAIN_DEADLINE ]; then
    log "the gateway's high-priority status queue did not drain within 60 s; measuring anyway"
    break
  fi
  sleep 1
done
sleep $((2 * INTERVAL))

log "steady state: measuring for $WINDOW s"
cpu_snapshot "gateway:$GW_PID" "sim:$SIM_PID" "controller:$CTRL_PID" \
  "apiserver:$APISERVER_PID" "etcd:$ETCD_PID"
measure gateway "$GW_PID" apiserver=- "gateway=$GW_METRICS" "controller=$CTRL_METRICS"
cpu_report gateway "$WINDOW_SECONDS"
fact gateway_connections_end "$(sample "$WORK/gateway-b.txt" lekiwi_gateway_connections)"

# The gateway goes first, so the simulator's disconnects cause no status writes.
stop "$GW_PID"
stop "$SIM_PID"
stop "$CTRL_PID"

# ---- report ---------------------------------------------------------------------------------
mkdir -p "$RESULTS"
STAMP="$(date +%Y%m%d-%H%M%S)"
python3 "$ROOT/bench/report.py" "$WORK" >"$WORK/table.txt"
cp "$WORK/table.txt" "$RESULTS/gateway-$STAMP.txt"
cp "$WORK/table.txt" "$RESULTS/gateway-latest.txt"
echo
cat "$WORK/table.txt"
echo
log "written to bench/results/gateway-$STAMP.txt and bench/results/gateway-latest.txt"
