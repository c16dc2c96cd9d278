#!/usr/bin/env bash
#! Recovery benchmark: a fleet on two gateway replicas loses one to SIGKILL.
#!
#! Runs, on loopback only: a private control plane (etcd + kube-apiserver), PostgreSQL 15 as the
#! shared event store, the operator as three processes (one --role controller, two --role gateway
#! with their own identities), HAProxy (Debian's) in TCP mode spreading new connections over the two
#! gateways as a Kubernetes Service would, and `lekiwi-sim` with N provisioned robots that heartbeat
#! and send durable events at a steady rate. Once every robot is Online it SIGKILLs one gateway and
#! measures, from a watch of every Robot:
#!   - time from the kill until each robot that was on the killed gateway is Online through the
#!     survivor (p50, p99, max, all), and whether any robot showed Unknown/Offline after that;
#!   - API-server write requests during the recovery (until the watch shows every robot Online
#!     through the survivor, and 30 s more), by resource, per robot moved;
#!   - API-server 429s and 5xx, and the watches and lists of Robots it served;
#!   - the survivor's status writes per 20 s by queue (moved robots shown Unknown/Offline,
#!     moves, other transitions, routine refreshes), from its own metrics;
#! then restarts the killed gateway and measures the writes and sessions after it (does the fleet
#! rebalance?), and finally drains the simulator and compares events sent with events stored.
#!
#! A second scenario, --scenario first-boot, is a fleet's first boot: M incumbent robots are
#! Online, then N new robots enroll at once (no connect-rate limit); it measures the time until all
#! are enrolled and Online, the gateways' refusals (Retry-After), API 429/5xx, the gateways'
#! open files, and whether any incumbent robot left Online meanwhile.
#!
#! A third, --scenario steady, is the steady state as the fleet grows: for each size of
#! --steady-sizes (default 10000,50000) it brings that many robots Online, spread directly over the
#! gateways (the simulator's comma-separated --gateway list: one address pair has only ~28,000
#! ephemeral ports), started as simulator processes of at most (open-file limit - 2,000) robots
#! each; every gateway holds its share of the fleet, so the open-file limit caps the fleet at about
#! --gateways times it (20,000 here: 38,000 robots on two; 50,000 needs three), and over a window
#! of --window seconds measures heartbeat
#! round trip p99 (the robots' own, as they report it), gateway RSS per connection, API-server
#! writes per second against N/300 (one status refresh per robot per 5 minutes) and the
#! gateways' CPU.
#!
#! Usage: bash bench/recovery.sh [options]
#!   --scenario kill|first-boot|steady  see above (default kill)
#!   --steady-sizes A,B,... steady: fleet sizes to measure, ascending (default 10000,50000)
#!   --window S             steady: measurement window per size, seconds (default 60)
#!   --connect-rate R       steady: new connections per second while a size ramps up, over all
#!                          its simulators together (default 1000; 50,000 robots on this machine
#!                          need less: at 1,000 per simulator the starved simulators missed
#!                          their handshakes and heartbeats and the gateways closed them)
#!   --gateways G           steady: gateway replicas (default 2, at most 26; the other
#!                          scenarios always run two)
#!   --incumbents M         first-boot: robots Online before the new fleet comes (default 1000)
#!   --robots N             simulated robots (default 10000)
#!   --events-per-minute E  durable events per robot per minute (default 6)
#!   --interval S           heartbeat interval, seconds (default 5)
#!   --settle S             steady state before the kill, seconds (default 30)
#!   --late-share F         kill: this share (0 to 1) of the robots waits --late-delay seconds more
#!                          before reconnecting after the kill, as robots on a poor network would
#!                          (default 0): they come back after the dead gateway's Lease expired, so
#!                          the controller marks them Unknown first
#!   --late-delay S         kill: that extra wait, seconds (default 30)
#!   --recovery-timeout S   give up waiting for recovery after S seconds (default 180)
#!   --after-restart S      observation window after the killed gateway restarts (default 60)
#!   --tls                  the gateways serve wss:// (a CA and certificate made here with openssl;
#!                          HAProxy passes TLS through, as a TCP Service does)
#!   --no-build             use the binaries already in target/release
#!   --bin DIR              use the binaries in DIR instead (implies --no-build; e.g. a quick
#!                          check of the script itself with debug builds and --robots 200)
#!   --keep                 keep the work directory (logs, watch log, scrapes)
#!   --world-nice N         run the simulated robots and HAProxy (the world outside the cluster:
#!                          in production they are other machines) at this CPU niceness, so on a
#!                          small host they take CPU from the control plane only when it has some
#!                          to spare (default 10; 0 = same priority as the control plane)
#!   --control-plane-nice N etcd and the API server at this CPU niceness (-20 to 19, default 0;
#!                          e.g. -5 gives them the CPU first, as a cluster's own control-plane
#!                          nodes would: the control plane this benchmark measures stays at 0)
#!   --audit                kill, first-boot: the API server writes an audit log of every Robot
#!                          request
#!                          (level Metadata); the results then say who was refused (409), who
#!                          listed and watched, by client (bench/audit_report.py)
#!   --profile S            kill: a CPU profile of the API server over the S seconds from the kill
#!                          (its /debug/pprof), summed by what the API server did (bench/
#!                          apiserver_profile.py; needs `go`, which scripts/setup.sh installs to
#!                          build the API server); the profile is kept with --keep
#!   -h, --help             this text
#!
#! Writes the table to bench/results/recovery-<scenario>-<date>.txt and
#! bench/results/recovery-<scenario>-latest.txt.
#! Environment: LEKIWI_BENCH_LOG (the processes' RUST_LOG, default warn); LEKIWI_BENCH_GATEWAY_ARGS
#! (more flags for both gateways, split on spaces, e.g. "--status-qps 100").
#! Bounded in time (about 10 minutes for 10,000 robots once built; at most ~25), cleans up on exit
#! and Ctrl-C. Needs root or a `postgres` user (PostgreSQL refuses to run as root).
set -euo pipefail

ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
BIN="$ROOT/target/release"
RESULTS="$ROOT/bench/results"
PG_BIN=/usr/lib/postgresql/15/bin

ROBOTS=10000
SCENARIO=kill
INCUMBENTS=1000
STEADY_SIZES=10000,50000
WINDOW=60
CONNECT_RATE=1000
EPM=6
INTERVAL=5
SETTLE=30
RECOVERY_TIMEOUT=180
AFTER_RESTART=60
BUILD=1
LATE_SHARE=0
LATE_DELAY=30
KEEP=0
AUDIT=0
PROFILE=0
CP_NICE=0
WORLD_NICE=10
TLS=0
GATEWAYS=2
COMMAND="bash bench/recovery.sh $*"

# shellcheck source=bench/lib.sh
source "$ROOT/bench/lib.sh"

while [ $# -gt 0 ]; do
  case "$1" in
    --robots) positive_int "$1" "${2:-}"; ROBOTS="$2"; shift 2 ;;
    --scenario)
      case "${2:-}" in kill|first-boot|steady) SCENARIO="$2" ;; *) die "--scenario is kill, first-boot or steady" ;; esac
      shift 2 ;;
    --incumbents) positive_int "$1" "${2:-}"; INCUMBENTS="$2"; shift 2 ;;
    --steady-sizes)
      [[ "${2:-}" =~ ^[1-9][0-9]*(,[1-9][0-9]*)*$ ]] || die "--steady-sizes is a comma-separated list of counts"
      STEADY_SIZES="$2"; shift 2 ;;
    --window) positive_int "$1" "${2:-}"; WINDOW="$2"; shift 2 ;;
    --connect-rate) positive_int "$1" "${2:-}"; CONNECT_RATE="$2"; shift 2 ;;
    --gateways)
      [[ "${2:-}" =~ ^([2-9]|1[0-9]|2[0-6])$ ]] || die "--gateways is a number from 2 to 26"
      GATEWAYS="$2"; shift 2 ;;
    --events-per-minute) positive_int "$1" "${2:-}"; EPM="$2"; shift 2 ;;
    --interval) positive_int "$1" "${2:-}"; INTERVAL="$2"; shift 2 ;;
    --settle) positive_int "$1" "${2:-}"; SETTLE="$2"; shift 2 ;;
    --late-share)
      [[ "${2:-}" =~ ^(0(\.[0-9]+)?|1(\.0+)?)$ ]] || die "--late-share is a number from 0 to 1"
      LATE_SHARE="$2"; shift 2 ;;
    --late-delay) positive_int "$1" "${2:-}"; LATE_DELAY="$2"; shift 2 ;;
    --recovery-timeout) positive_int "$1" "${2:-}"; RECOVERY_TIMEOUT="$2"; shift 2 ;;
    --after-restart) positive_int "$1" "${2:-}"; AFTER_RESTART="$2"; shift 2 ;;
    --tls) TLS=1; shift ;;
    --no-build) BUILD=0; shift ;;
    --bin) [ -d "${2:-}" ] || die "--bin needs a directory"; BIN="$(cd "$2" && pwd)"; BUILD=0; shift 2 ;;
    --keep) KEEP=1; shift ;;
    --audit) AUDIT=1; shift ;;
    --control-plane-nice)
      [[ "${2:-}" =~ ^-?([0-9]|1[0-9]|20)$ ]] && [ "$2" -le 19 ] || die "--control-plane-nice is a niceness from -20 to 19"
      CP_NICE="$2"; shift 2 ;;
    --profile) positive_int "$1" "${2:-}"; PROFILE="$2"; shift 2 ;;
    --world-nice)
      [[ "${2:-}" =~ ^([0-9]|1[0-9])$ ]] || die "--world-nice is a niceness from 0 to 19"
      WORLD_NICE="$2"; shift 2 ;;
    -h|--help) usage; exit 0 ;;
    *) usage >&2; die "unknown option: $1" ;;
  esac
done

WORK="$(mktemp -d "${TMPDIR:-/tmp}/lekiwi-recovery.XXXXXX")"
chmod 755 "$WORK"
CP_DIR="$WORK/control-plane"
CP_UP=0
PIDS=()
CLEANUP_GRACE=3
trap_cleanup
take_bench_lock

[ "$SCENARIO" != steady ] || ROBOTS="${STEADY_SIZES##*,}"
[ "$SCENARIO" = steady ] || [ "$GATEWAYS" = 2 ] || die "--gateways is for --scenario steady (kill and first-boot run two)"
[ "$AUDIT" = 0 ] || [ "$SCENARIO" != steady ] || die "--audit is for --scenario kill or first-boot"
[ "$PROFILE" = 0 ] || [ "$SCENARIO" = kill ] || die "--profile is for --scenario kill"
[ "$PROFILE" = 0 ] || command -v go >/dev/null || die "--profile needs go (apt-get install golang-go)"
# The replicas' names: gw-a, gw-b, ...
GW_NAMES=()
for ((i = 0; i < GATEWAYS; i++)); do GW_NAMES+=("gw-$(printf "\\$(printf %o $((97 + i)))")"); done
[ "$SCENARIO" = first-boot ] || INCUMBENTS=0
# Every robot holds one descriptor in the simulator and one in a gateway; a proxy holds two
# (client and server side), so the robots are spread over as many HAProxy instances as the
# open-file limit needs (root may raise the hard limit up to fs.nr_open; here it may not).
ulimit -Hn "$(cat /proc/sys/fs/nr_open)" 2>/dev/null || true
ulimit -n "$(ulimit -Hn)" 2>/dev/null || true
FDS="$(ulimit -n)"
if [ "$SCENARIO" = steady ]; then
  # The steady scenario starts its robots as several simulator processes of at most SIM_CHUNK
  # robots each, straight to the gateways; each gateway holds its share of them.
  SIM_CHUNK=$((FDS - 2000))
  PER_GATEWAY=$(( (ROBOTS + GATEWAYS - 1) / GATEWAYS ))
  [ "$FDS" -gt $((PER_GATEWAY + 1000)) ] \
    || die "open-file limit $FDS is too low for $PER_GATEWAY robots per gateway (raise the hard limit, or --gateways $(( (ROBOTS + FDS - 1001) / (FDS - 1000) )); at most $(( (FDS - 1000) * GATEWAYS )) robots fit on $GATEWAYS gateways)"
else
  [ "$FDS" -gt $((ROBOTS + INCUMBENTS + 1000)) ] \
    || die "open-file limit $FDS is too low for $((ROBOTS + INCUMBENTS)) robots (raise the hard limit)"
fi
LB_COUNT=$(( (2 * (ROBOTS + INCUMBENTS) + FDS - 1001) / (FDS - 1000) ))

log "work directory: $WORK"
release_binaries "lekiwi-operator lekiwi-agent" lekiwi-operator lekiwi-sim
run_setup
command -v haproxy >/dev/null || die "haproxy is missing (scripts/setup.sh installs it)"

fact date "$(date -Is)"
fact host "$(nproc) CPUs ($(awk -F': ' '/^model name/ { print $2; exit }' /proc/cpuinfo)), $(awk '/^MemTotal/ { printf "%.0f GiB", $2 / 1048576 }' /proc/meminfo) RAM, load average at start $(cut -d' ' -f1-3 /proc/loadavg)"
fact_source
fact command "${LEKIWI_BENCH_GATEWAY_ARGS:+LEKIWI_BENCH_GATEWAY_ARGS='$LEKIWI_BENCH_GATEWAY_ARGS' }$COMMAND"
fact robots "$ROBOTS"
fact gateways "${GW_NAMES[*]}"
fact scenario "$SCENARIO"
fact events_per_minute "$EPM"
fact interval "$INTERVAL"
fact world_nice "$WORLD_NICE"

# ---- PostgreSQL: the replicas' shared event store -------------------------------------------
as_postgres() { if [ "$(id -u)" = 0 ]; then runuser -u postgres -- "$@"; else "$@"; fi; }
PG_PORT="$(free_port)"
PG_DIR="$WORK/pg"
mkdir -p "$PG_DIR"
[ "$(id -u)" != 0 ] || chown postgres: "$PG_DIR"
log "starting PostgreSQL on 127.0.0.1:$PG_PORT"
as_postgres "$PG_BIN/initdb" -D "$PG_DIR/data" -U postgres -A trust -E UTF8 --locale=C --no-sync \
  >"$WORK/initdb.log" 2>&1 || die "initdb failed: $(tail -5 "$WORK/initdb.log")"
start postgres as_postgres "$PG_BIN/postgres" -D "$PG_DIR/data" -h 127.0.0.1 -p "$PG_PORT" \
  -k "$PG_DIR" -c max_connections=200 -c fsync=on -c synchronous_commit=on
PG_PID=$LAST_PID
# As root, PG_PID is runuser's, and killing it leaves the postmaster running: stop it by its
# data directory on exit as well.
ON_EXIT='as_postgres "$PG_BIN/pg_ctl" -D "$PG_DIR/data" stop -m immediate >/dev/null 2>&1'
pg_ready() { alive "$PG_PID" || die "postgres exited: $(tail -5 "$WORK/postgres.log")"; "$PG_BIN/pg_isready" -q -h 127.0.0.1 -p "$PG_PORT"; }
wait_for postgres 60 pg_ready
psql_do() { "$PG_BIN/psql" -X -q -At -h 127.0.0.1 -p "$PG_PORT" -U postgres -d "${2:-postgres}" -c "$1"; }
psql_do 'CREATE DATABASE lekiwi' >/dev/null
STORE_URL="postgres://postgres@127.0.0.1:$PG_PORT/lekiwi"

# ---- control plane and operator --------------------------------------------------------------
if [ "$AUDIT" = 1 ]; then
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
fi
start_control_plane
if [ "$CP_NICE" != 0 ]; then
  # Every thread: renice changes one thread only, and threads started later take their
  # creator's niceness.
  for pid in "$(cat "$CP_DIR/etcd.pid")" "$(cat "$CP_DIR/kube-apiserver.pid")"; do
    for task in /proc/"$pid"/task/*; do renice -n "$CP_NICE" -p "${task##*/}" >/dev/null; done
  done
fi
fact control_plane_nice "$CP_NICE"
kubectl create namespace lekiwi-system >/dev/null
kubectl create namespace bench >/dev/null
TOKEN="lke_$(openssl rand -hex 32)"
TOKEN_HASH="$(printf %s "$TOKEN" | sha256sum | cut -d' ' -f1)"

CTRL_HTTP="$(free_port)"
LB_PORTS=()
for _ in $(seq 1 "$LB_COUNT"); do LB_PORTS+=("$(free_port)"); done
# --tls: every gateway serves wss:// with one certificate; every simulator trusts its CA.
SCHEME=ws
TLS_FLAGS=()
SIM_TLS=()
if [ "$TLS" = 1 ]; then
  make_tls "$WORK"
  SCHEME=wss
  TLS_FLAGS=(--tls-cert "$WORK/tls.crt" --tls-key "$WORK/tls.key")
  SIM_TLS=(--ca-file "$WORK/ca.crt")
fi
fact transport "$([ "$TLS" = 1 ] && echo "wss:// to the gateways (rustls, ECDSA P-256), passed through by HAProxy" || echo "plain ws:// on loopback")"
LB_URLS="$(printf "$SCHEME://127.0.0.1:%s/v1/agent," "${LB_PORTS[@]}")"
LB_URLS="${LB_URLS%,}"
declare -A GW_PORT GW_HTTP GW_PID
for g in "${GW_NAMES[@]}"; do GW_PORT[$g]="$(free_port)"; GW_HTTP[$g]="$(free_port)"; done
COMMON=(--kubeconfig "$KUBECONFIG" --namespace lekiwi-system --watch-namespace bench)
start controller env RUST_LOG="${LEKIWI_BENCH_LOG:-warn}" "$BIN/lekiwi-operator" --role controller "${COMMON[@]}" \
  --identity bench-controller --http-addr "127.0.0.1:$CTRL_HTTP"
CTRL_PID=$LAST_PID
CTRL_METRICS="http://127.0.0.1:$CTRL_HTTP/metrics"

# start_gateway NAME: one replica, its log appended across restarts.
start_gateway() {
  local g="$1"
  env RUST_LOG="${LEKIWI_BENCH_LOG:-warn}" "$BIN/lekiwi-operator" --role gateway "${COMMON[@]}" \
    --identity "$g" --gateway-name "$g" \
    --gateway-addr "127.0.0.1:${GW_PORT[$g]}" --http-addr "127.0.0.1:${GW_HTTP[$g]}" \
    --store-url "$STORE_URL" --max-unauthenticated-per-address 0 \
    --heartbeat-interval-seconds "$INTERVAL" "${TLS_FLAGS[@]}" ${LEKIWI_BENCH_GATEWAY_ARGS:-} >>"$WORK/$g.log" 2>&1 8>&- </dev/null &
  GW_PID[$g]=$!
  PIDS+=("${GW_PID[$g]}")
}
ready() { alive "$1" || die "$2 exited: $(tail -5 "$WORK/$2.log")"; curl -fsS --max-time 2 "$3" >/dev/null 2>&1; }
for g in "${GW_NAMES[@]}"; do
  start_gateway "$g"
  wait_for "$g" 60 ready "${GW_PID[$g]}" "$g" "http://127.0.0.1:${GW_HTTP[$g]}/readyz"
done
leader() { alive "$CTRL_PID" || die "controller exited: $(tail -5 "$WORK/controller.log")"; [ "$(current "$CTRL_METRICS" lekiwi_leader_election_is_leader)" = 1 ]; }
wait_for "controller leadership" 60 leader

# HAProxy: layer-4 round robin over the replicas, health-checked like a Service's endpoints
# (a readiness probe of /readyz every second; two failures take a replica out). With more than
# one instance (see LB_COUNT), the simulator spreads its robots over them by its URL list; each
# balances over every gateway, as every node's kube-proxy does for a Service.
LB_PIDS=()
SERVERS=""
for g in "${GW_NAMES[@]}"; do
  SERVERS+="  server $g 127.0.0.1:${GW_PORT[$g]} check port ${GW_HTTP[$g]} inter 1s fall 2 rise 2"$'\n'
done
for i in "${!LB_PORTS[@]}"; do
  cat >"$WORK/haproxy-$i.cfg" <<EOF
global
  maxconn $((FDS / 2 - 500))
defaults
  mode tcp
  timeout connect 5s
  timeout client 1h
  timeout server 1h
  timeout tunnel 1h
frontend agents
  bind 127.0.0.1:${LB_PORTS[$i]}
  default_backend gateways
backend gateways
  balance roundrobin
  option httpchk GET /readyz
${SERVERS%$'\n'}
EOF
  start "haproxy-$i" nice -n "$WORLD_NICE" haproxy -db -f "$WORK/haproxy-$i.cfg"
  LB_PIDS+=("$LAST_PID")
  sleep 1
  alive "$LAST_PID" || die "haproxy exited: $(tail -5 "$WORK/haproxy-$i.log")"
done
fact load_balancers "$LB_COUNT HAProxy instance(s)"

# ---- the fleet -------------------------------------------------------------------------------
# Every change of every Robot, time-stamped on arrival: name phase gateway connected. Started
# once the first COUNT Robots exist, and waited for until it listed them.
start_watch() { # count
  log "watching every Robot"
  start watch python3 -u "$ROOT/bench/recovery_watch.py" "https://127.0.0.1:$APISERVER_PORT" \
    "$CP_DIR/pki/ca.crt" "$CP_DIR/admin-token" bench "$WORK/robots.log"
  WATCH_PID=$LAST_PID
  listed() {
    alive "$WATCH_PID" || die "the Robot watch exited: $(tail -5 "$WORK/watch.log")"
    [ -f "$WORK/robots.log" ] && [ "$(grep -c '|ADDED|' "$WORK/robots.log" || true)" -ge "$1" ]
  }
  wait_for "the Robot watch" 120 listed "$1"
}

# Provisions COUNT robots (sim-00001...) whose token Secrets hold the hash of $TOKEN: the
# simulator presents it as every robot's own token (a fleet enrolled long ago, as
# bench/gateway.sh --mode provision does), and starts them; sets SIM_PID.
provisioned_fleet() { # count
  log "provisioning $1 Robots and token Secrets"
  provision_robots bench "$1" "$TOKEN_HASH"
  pending() { [ "$(current "$CTRL_METRICS" 'lekiwi_robots{phase="Pending"}')" -ge "$1" ]; }
  wait_for "all robots Pending" 300 pending "$1"
  sleep 5
  start_watch "$1"
  log "starting $1 simulated robots through $LB_COUNT HAProxy instance(s) ($EPM events/min each)"
  start sim nice -n "$WORLD_NICE" "$BIN/lekiwi-sim" "${SIM_TLS[@]}" --gateway "$LB_URLS" \
    --enrollment-token "$TOKEN" --namespace bench \
    --robots "$1" --heartbeat-interval "$INTERVAL" --connect-rate 1000 \
    --events-per-minute "$EPM" --drain-seconds 120 --report-every 10 --json "$WORK/sim.json" \
    --late-share "$LATE_SHARE" --late-delay "$LATE_DELAY" --telemetry-interval-s 0
  SIM_PID=$LAST_PID
  online() {
    alive "$SIM_PID" || die "the simulator exited: $(tail -5 "$WORK/sim.log")"
    [ "$(current "$CTRL_METRICS" 'lekiwi_robots{phase="Online"}')" -ge "$1" ]
  }
  local t0
  t0="$(now)"
  # At about 30 first writes a second per gateway: 10,000 robots took 223 to 376 s here.
  wait_for "all $1 robots Online" $(($1 / 25 + 180)) online "$1"
  fact all_online_seconds "$(elapsed "$t0")"
  log "all $1 robots Online after $(elapsed "$t0") s"
}

# ---- scenario kill ---------------------------------------------------------------------------
scenario_kill() {
  provisioned_fleet "$ROBOTS"
  log "steady state for $SETTLE s"
  sleep "$SETTLE"
  for g in gw-a gw-b; do
    fact "sessions_before_$g" "$(current "http://127.0.0.1:${GW_HTTP[$g]}/metrics" lekiwi_gateway_connections)"
  done

  # ---- the kill --------------------------------------------------------------------------------
  scrape_apiserver "$WORK/apiserver-before-kill.txt"
  T_KILL="$(now)"
  AUDIT_FROM="$T_KILL"
  fact kill_time "$T_KILL"
  log "SIGKILL gw-a (pid ${GW_PID[gw-a]})"
  kill -KILL "${GW_PID[gw-a]}"
  if [ "$PROFILE" != 0 ]; then
    start apiserver-profile curl -fsS --max-time $((PROFILE + 60)) --cacert "$CP_DIR/pki/ca.crt" \
      -H "Authorization: Bearer $(cat "$CP_DIR/admin-token")" -o "$WORK/apiserver.pprof" \
      "https://127.0.0.1:$APISERVER_PORT/debug/pprof/profile?seconds=$PROFILE"
    PROFILE_PID=$LAST_PID
  fi
  wait "${GW_PID[gw-a]}" 2>/dev/null || true
  forget "${GW_PID[gw-a]}"
  # The survivor's own counts (its status writes by queue and result) every 10 s from the kill,
  # for the report's timeline of what it wrote and why.
  mkdir -p "$WORK/survivor-metrics"
  start survivor-metrics bash -c 'while :; do
      curl -fsS --max-time 5 "$1" -o "$2/$(date +%s.%N).txt" 2>/dev/null; sleep 10; done' \
    sampler "http://127.0.0.1:${GW_HTTP[gw-b]}/metrics" "$WORK/survivor-metrics"
  SAMPLER_PID=$LAST_PID
  # Where the machine's CPU goes while the survivor takes over (reported over the window below).
  local lbs=() i
  for i in "${!LB_PIDS[@]}"; do lbs+=("haproxy-$i:${LB_PIDS[$i]}"); done
  cpu_snapshot "gw-b:${GW_PID[gw-b]}" "controller:$CTRL_PID" "sim:$SIM_PID" "postgres:$PG_PID" \
    "apiserver:$(cat "$CP_DIR/kube-apiserver.pid")" "etcd:$(cat "$CP_DIR/etcd.pid")" \
    "watch:$WATCH_PID" "${lbs[@]}"
  # Sessions moved: the survivor holds every session and the controller counts every robot
  # Online (a moved robot stays Online, through the dead gateway, until the survivor writes it).
  # Recovered: besides, the Robot watch shows every robot Online through the survivor. The API
  # writes are counted up to then (and 30 s more), so every moved robot's write is in them.
  # The watch log is read every 5 s only (its per-robot times come from the log itself).
  local moved_at="" through=0 timed_out=0 deadline last
  sessions_moved() {
    [ "$(current "http://127.0.0.1:${GW_HTTP[gw-b]}/metrics" lekiwi_gateway_connections)" -ge "$ROBOTS" ] \
      && [ "$(current "$CTRL_METRICS" 'lekiwi_robots{phase="Online"}')" -ge "$ROBOTS" ]
  }
  on_survivor() {
    awk -F'|' '{ s[$3] = ($4 == "Online" && $5 == "gw-b" && $6 == "true") }
      END { n = 0; for (r in s) n += s[r]; print n }' "$WORK/robots.log"
  }
  deadline=$((SECONDS + RECOVERY_TIMEOUT))
  last=$((SECONDS - 5))
  while :; do
    alive "$SIM_PID" || die "the simulator exited: $(tail -5 "$WORK/sim.log")"
    if [ -z "$moved_at" ] && sessions_moved; then
      moved_at="$(elapsed "$T_KILL")"
      fact sessions_moved_seconds "$moved_at"
    fi
    if [ $((SECONDS - last)) -ge 5 ]; then
      last=$SECONDS
      through="$(on_survivor)"
      [ -n "$moved_at" ] && [ "$through" -ge "$ROBOTS" ] && break
      log "  $(elapsed "$T_KILL") s: gw-b sessions $(current "http://127.0.0.1:${GW_HTTP[gw-b]}/metrics" lekiwi_gateway_connections), Online $(current "$CTRL_METRICS" 'lekiwi_robots{phase="Online"}'), Unknown $(current "$CTRL_METRICS" 'lekiwi_robots{phase="Unknown"}'), Offline $(current "$CTRL_METRICS" 'lekiwi_robots{phase="Offline"}'), Online through gw-b $through"
    fi
    if [ $SECONDS -ge $deadline ]; then log "not recovered after $RECOVERY_TIMEOUT s"; timed_out=1; break; fi
    sleep 0.5
  done
  [ "$timed_out" = 1 ] || fact recovered_seconds_by_watch "$(elapsed "$T_KILL")"
  # The writes that follow the recovery (the controller's Unknown checks, the dead gateway's
  # Lease) belong to it too: count them over a fixed window that covers the Lease's expiry.
  sleep 30
  scrape_apiserver "$WORK/apiserver-after-recovery.txt"
  fact recovery_window_seconds "$(elapsed "$T_KILL")"
  cpu_report recovery "$(elapsed "$T_KILL")"

  # ---- the restart -----------------------------------------------------------------------------
  log "restarting gw-a; observing for $AFTER_RESTART s"
  T_START="$(now)"
  start_gateway gw-a
  wait_for gw-a 300 ready "${GW_PID[gw-a]}" gw-a "http://127.0.0.1:${GW_HTTP[gw-a]}/readyz"
  fact restart_ready_seconds "$(elapsed "$T_START")"
  # The writes after it is ready are what a rebalancing would cost; those while it lists count
  # with the recovery.
  scrape_apiserver "$WORK/apiserver-restart-ready.txt"
  T_RESTART="$(now)"
  fact restart_time "$T_RESTART"
  sleep "$AFTER_RESTART"
  scrape_apiserver "$WORK/apiserver-after-restart.txt"
  fact after_restart_seconds "$(elapsed "$T_RESTART")"
  for g in gw-a gw-b; do
    fact "sessions_after_restart_$g" "$(current "http://127.0.0.1:${GW_HTTP[$g]}/metrics" lekiwi_gateway_connections)"
  done
  AUDIT_TO="$(now)"
  stop "$SAMPLER_PID"

  # ---- drain and count -------------------------------------------------------------------------
  log "stopping the simulator (it drains its unacknowledged events first, at most 120 s)"
  kill -TERM "$SIM_PID"
  for _ in $(seq 1 300); do alive "$SIM_PID" || break; sleep 0.5; done
  wait "$SIM_PID" 2>/dev/null || true
  forget "$SIM_PID"
  [ -s "$WORK/sim.json" ] || die "the simulator wrote no summary: $(tail -5 "$WORK/sim.log")"
  psql_do "SELECT count(*), count(DISTINCT (robot, seq)), count(DISTINCT robot),
    coalesce(sum(CASE WHEN seq > 0 THEN 1 ELSE 0 END), 0) FROM events WHERE namespace = 'bench'" lekiwi \
    >"$WORK/stored.txt"
  psql_do "SELECT count(*) FROM (SELECT robot FROM events WHERE namespace = 'bench'
    GROUP BY robot HAVING max(seq) <> count(*)) gaps" lekiwi >"$WORK/gaps.txt"
  stop "$WATCH_PID"
}

# ---- scenario first-boot ---------------------------------------------------------------------
# The gateways' open files, sampled while the new fleet enrolls (docs/src/benchmarks/gateway.md:
# enrollment beyond what the API server sustains once exhausted them).
fds() { find "/proc/$1/fd" -mindepth 1 -maxdepth 1 2>/dev/null | wc -l; }
scenario_first_boot() {
  TOKEN_ENROLL="lke_$(openssl rand -hex 32)"
  kubectl -n bench create secret generic fleet-enrollment \
    --from-literal=sha256="$(printf %s "$TOKEN_ENROLL" | sha256sum | cut -d' ' -f1)" >/dev/null
  kubectl -n bench label secret fleet-enrollment fleet.lekiwi.io/token=enrollment >/dev/null
  provisioned_fleet "$INCUMBENTS"
  sleep 5
  scrape_apiserver "$WORK/apiserver-before-boot.txt"
  local t0 total=$((INCUMBENTS + ROBOTS)) last=$SECONDS max_a=0 max_b=0 f
  t0="$(now)"
  AUDIT_FROM="$t0"
  fact boot_time "$t0"
  log "first boot: $ROBOTS new robots enroll at once"
  start sim-new nice -n "$WORLD_NICE" "$BIN/lekiwi-sim" "${SIM_TLS[@]}" --gateway "$LB_URLS" \
    --enrollment-token "$TOKEN_ENROLL" --namespace bench --prefix new --robots "$ROBOTS" \
    --heartbeat-interval "$INTERVAL" --connect-rate 1000000 --connect-timeout 300 \
    --token-file "$WORK/new-tokens.json" --report-every 10 --json "$WORK/sim-new.json" \
    --telemetry-interval-s 0
  local new_pid=$LAST_PID
  local deadline=$((SECONDS + RECOVERY_TIMEOUT + ROBOTS / 20))
  until [ "$(current "$CTRL_METRICS" 'lekiwi_robots{phase="Online"}')" -ge "$total" ]; do
    alive "$new_pid" || die "the new fleet's simulator exited: $(tail -5 "$WORK/sim-new.log")"
    f="$(fds "${GW_PID[gw-a]}")"; [ "$f" -gt "$max_a" ] && max_a=$f
    f="$(fds "${GW_PID[gw-b]}")"; [ "$f" -gt "$max_b" ] && max_b=$f
    if [ $SECONDS -ge $deadline ]; then log "not all Online after $(elapsed "$t0") s"; break; fi
    if [ $((SECONDS % 10)) = 0 ]; then
      log "  $(elapsed "$t0") s: Online $(current "$CTRL_METRICS" 'lekiwi_robots{phase="Online"}')/$total, gateway fds $max_a/$max_b"
    fi
    sleep 1
  done
  fact all_enrolled_online_seconds "$(elapsed "$t0")"
  AUDIT_TO="$(now)"
  fact gateway_fds_max "$max_a / $max_b"
  for g in gw-a gw-b; do
    scrape "http://127.0.0.1:${GW_HTTP[$g]}/metrics" "$WORK/$g-after-boot.txt"
  done
  scrape_apiserver "$WORK/apiserver-after-boot.txt"
  stop "$new_pid"
  stop "$SIM_PID"
  stop "$WATCH_PID"
  fact incumbents "$INCUMBENTS"
}

# ---- scenario steady -------------------------------------------------------------------------
# For $2 seconds, every 5 s: the fewest robots the controller counts Online and the largest
# status lag a gateway declares (lekiwi_gateway_status_lag_seconds), as facts for size $1.
window_watch() {
  local size="$1" end=$((SECONDS + $2)) fewest="" lag=0 v g
  while [ $SECONDS -lt $end ]; do
    v="$(current "$CTRL_METRICS" 'lekiwi_robots{phase="Online"}')"
    if [ "$v" -ge 0 ] && { [ -z "$fewest" ] || [ "$v" -lt "$fewest" ]; }; then fewest="$v"; fi
    for g in "${GW_NAMES[@]}"; do
      v="$(current "http://127.0.0.1:${GW_HTTP[$g]}/metrics" lekiwi_gateway_status_lag_seconds)"
      lag="$(awk -v a="$lag" -v b="${v:-0}" 'BEGIN { print (b > a ? b : a) }')"
    done
    sleep $(( end - SECONDS < 5 ? (end - SECONDS > 0 ? end - SECONDS : 0) : 5 ))
  done
  fact "steady_${size}_fewest_online" "${fewest:-?}"
  fact "steady_${size}_max_status_lag" "$lag"
}

scenario_steady() {
  local size have=0 part=0 t0 gw_urls="" g i chunk left n rate gws=() sims=() chunks
  for g in "${GW_NAMES[@]}"; do
    gw_urls+="${gw_urls:+,}$SCHEME://127.0.0.1:${GW_PORT[$g]}/v1/agent"
    gws+=("$g:${GW_PID[$g]}")
  done
  sleep 2
  for g in "${GW_NAMES[@]}"; do fact "rss_base_$g" "$(rss_kib "${GW_PID[$g]}")"; done
  fact steady_sizes "$STEADY_SIZES"
  for size in ${STEADY_SIZES//,/ }; do
    [ "$size" -gt "$have" ] || die "--steady-sizes must ascend"
    part=$((part + 1))
    log "steady state at $size robots: provisioning $((size - have)) more"
    # In simulator processes of at most SIM_CHUNK robots (one open file each). Every chunk's
    # Robots and Secrets are created before any of them connects: provisioning while tens of
    # thousands of robots already heartbeat competes with them for the machine's two cores
    # (session 25's 50,000 run provisioned 32,000 Robots in 18 minutes that way).
    t0="$(now)"
    chunks=()
    for ((left = size - have; left > 0; left -= n)); do
      n=$((left < SIM_CHUNK ? left : SIM_CHUNK))
      chunks+=("$n")
      provision_robots bench "$n" "$TOKEN_HASH" "s$part-${#chunks[@]}"
    done
    fact "steady_${size}_provision_seconds" "$(elapsed "$t0")"
    # The ramp's rate is shared by the step's simulators (at least one connection/s each).
    rate=$((CONNECT_RATE / ${#chunks[@]} > 0 ? CONNECT_RATE / ${#chunks[@]} : 1))
    log "  provisioned in $(elapsed "$t0") s; starting ${#chunks[@]} simulator(s), $rate new connections/s each"
    for i in "${!chunks[@]}"; do
      n="${chunks[$i]}"
      chunk=$((i + 1))
      start "sim-$part-$chunk" nice -n "$WORLD_NICE" "$BIN/lekiwi-sim" "${SIM_TLS[@]}" --gateway "$gw_urls" --enrollment-token "$TOKEN" \
        --namespace bench --prefix "s$part-$chunk" --robots "$n" \
        --heartbeat-interval "$INTERVAL" --connect-rate "$rate" --report-every 30 --telemetry-interval-s 0
      sims+=("sim-$part-$chunk:$LAST_PID")
    done
    have=$size
    t0="$(now)"
    online_n() { [ "$(current "$CTRL_METRICS" 'lekiwi_robots{phase="Online"}')" -ge "$1" ]; }
    wait_for "$size robots Online" $((size / 20 + 300)) online_n "$size"
    fact "steady_${size}_online_seconds" "$(elapsed "$t0")"
    log "  $size Online after $(elapsed "$t0") s; settling 30 s, then a $WINDOW s window"
    sleep 30
    scrape_apiserver "$WORK/apiserver-$size-a.txt"
    for g in "${GW_NAMES[@]}"; do scrape "http://127.0.0.1:${GW_HTTP[$g]}/metrics" "$WORK/$g-$size-a.txt"; done
    cpu_snapshot "${gws[@]}" "apiserver:$(cat "$CP_DIR/kube-apiserver.pid")" "${sims[@]}"
    t0="$(now)"
    window_watch "$size" "$WINDOW"
    scrape_apiserver "$WORK/apiserver-$size-b.txt"
    for g in "${GW_NAMES[@]}"; do
      scrape "http://127.0.0.1:${GW_HTTP[$g]}/metrics" "$WORK/$g-$size-b.txt"
      fact "rss_${size}_$g" "$(rss_kib "${GW_PID[$g]}")"
      fact "connections_${size}_$g" "$(current "http://127.0.0.1:${GW_HTTP[$g]}/metrics" lekiwi_gateway_connections)"
    done
    fact "window_${size}_seconds" "$(elapsed "$t0")"
    cpu_report "$size" "$(elapsed "$t0")"
  done
}

case "$SCENARIO" in
  kill) scenario_kill ;;
  first-boot) scenario_first_boot ;;
  steady) scenario_steady ;;
esac

mkdir -p "$RESULTS"
OUT="$RESULTS/recovery-$SCENARIO-$(date +%Y%m%d-%H%M%S).txt"
python3 "$ROOT/bench/recovery_report.py" "$WORK" | tee "$OUT"
if [ "$AUDIT" = 1 ] && [ -n "${AUDIT_TO:-}" ]; then
  { echo; python3 "$ROOT/bench/audit_report.py" "$WORK/audit.log" "$AUDIT_FROM" "$AUDIT_TO" "$WORK/robots.log"; } | tee -a "$OUT"
fi
if [ "$PROFILE" != 0 ] && [ -n "${PROFILE_PID:-}" ]; then
  wait "$PROFILE_PID" 2>/dev/null || true
  forget "$PROFILE_PID"
  if [ -s "$WORK/apiserver.pprof" ]; then
    { echo; python3 "$ROOT/bench/apiserver_profile.py" "$WORK/apiserver.pprof"; } | tee -a "$OUT"
  else
    log "no API server profile: $(tail -2 "$WORK/apiserver-profile.log")"
  fi
fi
cp "$OUT" "$RESULTS/recovery-$SCENARIO-latest.txt"
log "table written to $OUT"
