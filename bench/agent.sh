#!/usr/bin/env bash
#! Agent footprint benchmark: runs one real `lekiwi-agent` (`agent` profile build, default intervals, mDNS
#! on, status endpoint on) against a private control plane (etcd + kube-apiserver v1.20.2) and the
#! operator (--role all, SQLite store, its default 30 s heartbeat interval), next to Debian's
#! `prometheus-node-exporter` started the same way (a plain child process, default collectors,
#! /metrics scraped once a minute) as the reference, and prints one table: RSS at the end and max
#! (target: agent < 10 MB), the ratio of the two RSS, CPU seconds per hour of both, the agent's
#! bytes sent per hour (its /status `bytesSent`, cross-checked with the kernel's TCP counter),
#! outbox left at the end, what the gateway stored, and the binary sizes.
#!
#! Both processes are sampled every 10 s (VmRSS from /proc/PID/status, utime+stime from
#! /proc/PID/stat). Rates are measured after the first minute (after half the run when --duration
#! is below 120 s) up to the end, and extrapolated to one hour.
#!
#! Usage: bash bench/agent.sh [options]
#!   --duration S   seconds both processes run and are sampled (default 600: "RSS after 10 minutes")
#!   --no-build     use the binaries already in target/release
#!   --keep         keep the work directory (logs, samples, smaps, the gateway's SQLite store)
#!   -h, --help     this text
#!
#! Environment: LEKIWI_BENCH_AGENT_ENV="K=V ..." adds environment variables to the agent only
#! (e.g. MALLOC_ARENA_MAX=1, to see how much of its memory is allocator arenas).
#!
#! Writes the table to bench/results/agent-<date>.txt and bench/results/agent-latest.txt. Takes
#! --duration plus about one minute once built; cleans up on exit, failure and Ctrl-C. Shares the
#! lock of bench/gateway.sh, so two benchmarks never run at once.
set -euo pipefail

ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
BIN="$ROOT/target/release"
# The agent as shipped: the size-optimised `agent` profile (see the workspace Cargo.toml).
AGENT_BIN="$ROOT/target/agent/lekiwi-agent"
RESULTS="$ROOT/bench/results"
NODE_EXPORTER=/usr/bin/prometheus-node-exporter

DURATION=600
BUILD=1
KEEP=0
COMMAND="bash bench/agent.sh $*"
SAMPLE_EVERY=10
SCRAPE_EVERY=60
STATUS_OFFSET=5

# shellcheck source=bench/lib.sh
source "$ROOT/bench/lib.sh"

while [ $# -gt 0 ]; do
  case "$1" in
    --duration) positive_int "$1" "${2:-}"; DURATION="$2"; shift 2 ;;
    --no-build) BUILD=0; shift ;;
    --keep) KEEP=1; shift ;;
    -h|--help) usage; exit 0 ;;
    *) usage >&2; die "unknown option: $1" ;;
  esac
done
[ "$DURATION" -ge 20 ] || die "--duration must be at least 20 s"
# The first minute (start-up, enrollment, first telemetry batch) is left out of the rates.
if [ "$DURATION" -ge 120 ]; then WARMUP=60; else WARMUP=$((DURATION / 2)); fi

# ---- processes and cleanup ------------------------------------------------------------------
WORK="$(mktemp -d "${TMPDIR:-/tmp}/lekiwi-bench-agent.XXXXXX")"
CP_DIR="$WORK/control-plane"
CP_UP=0
PIDS=()
# SIGTERM first, so the agent withdraws its mDNS advertisement from the LAN; then SIGKILL.
CLEANUP_GRACE=3
trap_cleanup

# "RSS_KIB TICKS THREADS" of a process (utime + stime in clock ticks), or "0 0 0" once it is gone.
proc_sample() {
  local rss threads ticks
  rss="$(awk '/^VmRSS:/ { print $2 }' "/proc/$1/status" 2>/dev/null)" || true
  threads="$(awk '/^Threads:/ { print $2 }' "/proc/$1/status" 2>/dev/null)" || true
  ticks="$(awk '{ print $14 + $15 }' "/proc/$1/stat" 2>/dev/null)" || true
  echo "${rss:-0} ${ticks:-0} ${threads:-0}"
}
proc_ticks() { awk '{ print $14 + $15 }' "/proc/$1/stat" 2>/dev/null || echo 0; }
# Busy clock ticks of the whole machine (all cores): user, nice, system, irq, softirq.
machine_ticks() { awk '/^cpu / { print $2 + $3 + $4 + $7 + $8 }' /proc/stat; }

# The agent's /status into file $1 (fails if the endpoint does not answer).
agent_status() { curl -fsS --max-time 5 "http://127.0.0.1:$STATUS_PORT/status" -o "$1"; }
json_field() { python3 -c 'import json, sys; print(json.load(open(sys.argv[1])).get(sys.argv[2]))' "$1" "$2"; }
# "BYTES SEGMENTS": TCP payload bytes and segments the kernel sent on the agent's connection to
# the gateway over its whole life, or empty.
tcp_sent() {
  ss -Htin state established "( dport = :$GW_PORT )" 2>/dev/null | awk '
    { for (i = 1; i <= NF; i++) { split($i, kv, ":"); if (kv[1] == "bytes_sent") b = kv[2]; if (kv[1] == "segs_out") s = kv[2] } }
    END { if (b != "") print b, s }'
}

# ---- preparation ----------------------------------------------------------------------------
# One benchmark at a time on this machine (the same lock as bench/gateway.sh).
take_bench_lock

log "work directory: $WORK"
if [ $BUILD = 1 ]; then
  log "building the operator (release) and the agent (agent profile)"
  (cd "$ROOT" && cargo build --release -p lekiwi-operator \
    && cargo build --profile agent -p lekiwi-agent --bin lekiwi-agent) \
    >"$WORK/build.log" 2>&1 || { tail -30 "$WORK/build.log" >&2; die "build failed"; }
fi
[ -x "$BIN/lekiwi-operator" ] || die "$BIN/lekiwi-operator is missing (run without --no-build)"
[ -x "$AGENT_BIN" ] || die "$AGENT_BIN is missing (run without --no-build)"

# setup.sh installs the apt packages (prometheus-node-exporter among them) and the control plane.
run_setup
[ -x "$NODE_EXPORTER" ] \
  || die "$NODE_EXPORTER is missing: run scripts/setup.sh (it installs the Debian package prometheus-node-exporter)"

fact date "$(date -Is)"
fact host "$(nproc) CPUs ($(awk -F': ' '/^model name/ { print $2; exit }' /proc/cpuinfo)), $(awk '/^MemTotal/ { printf "%.0f GiB", $2 / 1048576 }' /proc/meminfo) RAM, kernel $(uname -r), $(. /etc/os-release && echo "$PRETTY_NAME"), load average at start $(cut -d' ' -f1-3 /proc/loadavg)"
fact_source
fact command "$COMMAND"
fact duration "$DURATION"
fact warmup "$WARMUP"
fact clk_tck "$(getconf CLK_TCK)"
fact agent_version "$("$AGENT_BIN" --version | awk '{ print $NF }')"
fact node_exporter_version "$("$NODE_EXPORTER" --version 2>&1 | awk 'NR == 1 { print $3 }') (Debian $(dpkg-query -W -f='${Version}' prometheus-node-exporter 2>/dev/null || echo '?'))"

# ---- control plane --------------------------------------------------------------------------
start_control_plane

NS=bench
ROBOT=bench-robot
kubectl create namespace lekiwi-system >/dev/null
kubectl create namespace "$NS" >/dev/null
# A fleet enrollment token, as scripts/quickstart.sh makes it: the Secret keeps only its SHA-256.
TOKEN_FILE="$WORK/enrollment-token"
enrollment_token "$NS" "$TOKEN_FILE"

# ---- operator (controllers + gateway, defaults apart from addresses and the store) ----------
HTTP_PORT="$(free_port)"
GW_PORT="$(free_port)"
log "starting the operator (--role all; gateway ws :$GW_PORT, http :$HTTP_PORT)"
start operator "$BIN/lekiwi-operator" --role all --kubeconfig "$KUBECONFIG" \
  --namespace lekiwi-system --identity bench-operator --gateway-name bench-gateway \
  --gateway-addr "127.0.0.1:$GW_PORT" --http-addr "127.0.0.1:$HTTP_PORT" \
  --store-url "sqlite://$WORK/events.db"
OP_PID=$LAST_PID
operator_ready() {
  alive "$OP_PID" || die "operator exited: $(tail -5 "$WORK/operator.log")"
  curl -fsS --max-time 2 "http://127.0.0.1:$HTTP_PORT/readyz" >/dev/null 2>&1
}
wait_for operator 60 operator_ready
fact operator_flags "--role all, defaults (heartbeat interval 30 s, status refresh 300 s), --store-url sqlite://\$WORK/events.db"

# ---- the agent and the reference, started together -----------------------------------------
STATUS_PORT="$(free_port)"
NE_PORT="$(free_port)"
AGENT_FLAGS=(--config /nonexistent --gateway "ws://127.0.0.1:$GW_PORT/v1/agent"
  --robot-name "$NS/$ROBOT" --enrollment-token-file "$TOKEN_FILE"
  --state-dir "$WORK/agent-state" --status-listen "127.0.0.1:$STATUS_PORT")
# A robot's systemd unit gives the agent a clean environment; so does this (plus the knob).
CLEAN_ENV=(env -i PATH=/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin)
read -r -a AGENT_ENV <<<"${LEKIWI_BENCH_AGENT_ENV:-}"
[ ${#AGENT_ENV[@]} = 0 ] || fact agent_env "${AGENT_ENV[*]}"
"${CLEAN_ENV[@]}" "$AGENT_BIN" "${AGENT_FLAGS[@]}" --print-config >"$WORK/agent-config.yaml"
fact agent_intervals "$(python3 - "$WORK/agent-config.yaml" <<'PY'
import sys
c = dict(line.split(": ", 1) for line in open(sys.argv[1]).read().splitlines() if ": " in line)
keys = ["Cpu", "Memory", "Network", "Temperature", "Disk", "Full", "Batch"]
print(", ".join(f"{k.lower()} {c['telemetry' + k + 'IntervalS']}" for k in keys)
      + f" s; teleoperation check {c['teleopIntervalS']} s; mDNS {c['mdns']}")
PY
)"

log "starting lekiwi-agent (status :$STATUS_PORT) and prometheus-node-exporter (:$NE_PORT)"
T0="$(now)"
start agent "${CLEAN_ENV[@]}" "${AGENT_ENV[@]}" "$AGENT_BIN" "${AGENT_FLAGS[@]}"
AGENT_PID=$LAST_PID
start node-exporter "${CLEAN_ENV[@]}" "$NODE_EXPORTER" --web.listen-address="127.0.0.1:$NE_PORT"
NE_PID=$LAST_PID

agent_connected() {
  alive "$AGENT_PID" || die "agent exited: $(tail -5 "$WORK/agent.log")"
  agent_status "$WORK/status-start.json" 2>/dev/null && [ "$(json_field "$WORK/status-start.json" connected)" = True ]
}
wait_for "agent connection" 30 agent_connected
fact agent_connected_after_seconds "$(elapsed "$T0")"
ne_ready() {
  alive "$NE_PID" || die "node-exporter exited: $(tail -5 "$WORK/node-exporter.log")"
  curl -fsS --max-time 2 "http://127.0.0.1:$NE_PORT/" -o /dev/null 2>/dev/null
}
wait_for "node-exporter" 30 ne_ready
log "agent connected after $(elapsed "$T0") s; sampling every $SAMPLE_EVERY s for $DURATION s"

APISERVER_PID="$(cat "$CP_DIR/kube-apiserver.pid")"
ETCD_PID="$(cat "$CP_DIR/etcd.pid")"
printf 't agent_rss_kib agent_ticks agent_threads ne_rss_kib ne_ticks ne_threads operator_ticks apiserver_ticks etcd_ticks machine_ticks\n' \
  >"$WORK/samples.tsv"
sample_all() {
  alive "$AGENT_PID" || die "the agent exited during the run: $(tail -5 "$WORK/agent.log")"
  alive "$NE_PID" || die "node-exporter exited during the run: $(tail -5 "$WORK/node-exporter.log")"
  printf '%s %s %s %s %s %s %s\n' "$1" "$(proc_sample "$AGENT_PID")" "$(proc_sample "$NE_PID")" \
    "$(proc_ticks "$OP_PID")" "$(proc_ticks "$APISERVER_PID")" "$(proc_ticks "$ETCD_PID")" \
    "$(machine_ticks)" >>"$WORK/samples.tsv"
}

# ---- the run ----------------------------------------------------------------------------------
# Samples at 0, 10, 20 ... s after the start and at exactly --duration; node-exporter's /metrics
# is scraped right after the samples at 0, 60, 120 ... s, as a Prometheus would.
NEXT=0
WARM_DONE=0
while :; do
  T="$(elapsed "$T0")"
  delay="$(awk -v n="$NEXT" -v t="$T" 'BEGIN { d = n - t; printf "%.2f", (d > 0 ? d : 0) }')"
  sleep "$delay"
  sample_all "$(elapsed "$T0")"
  # After the sample, so the window [warm-up, end] holds one scrape per minute.
  if [ $((NEXT % SCRAPE_EVERY)) = 0 ] && [ "$NEXT" -lt "$DURATION" ]; then
    curl -fsS --max-time 10 "http://127.0.0.1:$NE_PORT/metrics" -o "$WORK/node-exporter-metrics.txt" \
      || log "node-exporter scrape failed at $NEXT s"
  fi
  if [ $WARM_DONE = 0 ] && [ "$NEXT" -ge "$WARMUP" ]; then
    WARM_DONE=1
    # The agent sends its telemetry batch every 60 s from its start and refreshes /status once a
    # second: reading 5 s after a minute mark never races a batch, and both reads (here and at
    # the end) sit at the same phase, so the window holds whole batch intervals.
    sleep "$STATUS_OFFSET"
    agent_status "$WORK/status-warmup.json" || die "the agent's /status did not answer"
    fact t_warmup "$(elapsed "$T0")"
    fact tcp_sent_warmup "$(tcp_sent)"
  fi
  if [ "$NEXT" -ge "$DURATION" ]; then break; fi
  if [ $((NEXT % 60)) = 0 ] && [ "$NEXT" -gt 0 ]; then
    log "  $NEXT s: agent RSS $(awk 'END { printf "%.2f", $2 * 1024 / 1e6 }' "$WORK/samples.tsv") MB, node-exporter $(awk 'END { printf "%.2f", $5 * 1024 / 1e6 }' "$WORK/samples.tsv") MB"
  fi
  NEXT=$((NEXT + SAMPLE_EVERY))
  [ "$NEXT" -le "$DURATION" ] || NEXT=$DURATION
done

# ---- at the end: what the agent says, what the kernel and the gateway saw ----------------------
sleep "$STATUS_OFFSET"
agent_status "$WORK/status-end.json" || die "the agent's /status did not answer"
fact t_end "$(elapsed "$T0")"
fact tcp_sent_end "$(tcp_sent)"
cat "/proc/$AGENT_PID/smaps_rollup" >"$WORK/smaps-agent.txt"
cat "/proc/$NE_PID/smaps_rollup" >"$WORK/smaps-node-exporter.txt"
cp "/proc/$AGENT_PID/smaps" "$WORK/smaps-agent-full.txt" 2>/dev/null || true
fact robot_phase "$(kubectl -n "$NS" get robot "$ROBOT" -o jsonpath='{.status.phase}' 2>/dev/null || echo '?')"
fact store "$(python3 - "$WORK/events.db" "$NS" "$ROBOT" <<'PY'
import sqlite3, sys
db = sqlite3.connect(f"file:{sys.argv[1]}?mode=ro", uri=True, timeout=10)
args = (sys.argv[2], sys.argv[3])
def count(table):
    return db.execute(f"SELECT count(*) FROM {table} WHERE namespace = ? AND robot = ?", args).fetchone()[0]
metrics = db.execute("SELECT count(DISTINCT metric) FROM samples WHERE namespace = ? AND robot = ?", args).fetchone()[0]
print(f"{count('telemetry_batches')} telemetry batches, {count('samples')} samples of {metrics} metrics, "
      f"{count('events')} events, {count('connections')} sessions")
PY
)"

cp "$AGENT_BIN" "$WORK/lekiwi-agent.stripped"
strip "$WORK/lekiwi-agent.stripped"
fact agent_binary_bytes "$(stat -c %s "$AGENT_BIN")"
fact agent_stripped_bytes "$(stat -c %s "$WORK/lekiwi-agent.stripped")"
fact node_exporter_binary_bytes "$(stat -c %s "$NODE_EXPORTER")"
fact node_exporter_scrape_bytes "$(stat -c %s "$WORK/node-exporter-metrics.txt" 2>/dev/null || echo 0)"

# The agent's own complaints over the run (its log is text, one event per line).
sed 's/\x1b\[[0-9;]*m//g' "$WORK/agent.log" | grep -aE '^\S+\s+(WARN|ERROR) ' >"$WORK/agent-warnings.txt" || true

# ---- report ---------------------------------------------------------------------------------
mkdir -p "$RESULTS"
STAMP="$(date +%Y%m%d-%H%M%S)"
python3 "$ROOT/bench/agent_report.py" "$WORK" >"$WORK/table.txt"
cp "$WORK/table.txt" "$RESULTS/agent-$STAMP.txt"
cp "$WORK/table.txt" "$RESULTS/agent-latest.txt"
echo
cat "$WORK/table.txt"
echo
log "written to bench/results/agent-$STAMP.txt and bench/results/agent-latest.txt"
