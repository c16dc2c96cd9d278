#!/usr/bin/env bash
#! Soak: a fleet that keeps working for an hour while something breaks every five minutes.
#!
#! Runs, on loopback only: a private control plane (etcd + kube-apiserver), PostgreSQL 15 as the
#! shared event store (its data on a small filesystem of its own when run as root, so the disk
#! can be filled), the operator as two controller processes (leader election) and two or more
#! gateway processes sharing one blob directory, HAProxy spreading new connections over the
#! gateways as a Service would, N simulated robots (`lekiwi-sim`, answering commands as agents
#! do) and some real agents (`lekiwi-fleet`). For --duration it then (bench/soak_driver.py):
#!   - rolls releases out back to back, one every --release-every seconds, in a rotation: some
#!     complete, some have robots that fail their health check (rolled back), some are undone
#!     mid-way, some aborted mid-way (robots that switched keep the release, downloading ones
#!     stop), and some are agent updates (spec.agent);
#!   - every --fault-every seconds breaks one thing, in turn: a gateway SIGKILLed (restarted
#!     30 s later); the controller leader SIGKILLed (restarted); etcd and kube-apiserver
#!     SIGKILLed and restarted; PostgreSQL restarted; 5 % of the robots cut off for 2 minutes
#!     (their simulator SIGSTOPped: connections stalled, not closed); the event store's disk
#!     filled to its last few MB for 2 minutes (root only). One robot's clock is 10 minutes
#!     ahead all along;
#!   - every 10 s samples RSS, open files and threads of every process, and every robot's phase
#!     and gateway from a watch;
#! and at the end prints one table with PASS/FAIL: memory/fd/thread slopes over the last 40
#! minutes against the noise of the first 20, events lost and stored twice (each robot's
#! acknowledged sequence numbers against the store), each rollout's end phase against what its
#! inputs call for, robots left on a release nobody asked for, robots shown Online without a
#! session or not Online with one past the graces, each fault's healing time (for the gateway
#! kill also as a ratio to the API server's write rate in the same run), steady API writes/s
#! against N/300, the event store's and the blob store's size.
#!
#! Usage: bash bench/soak.sh [options]
#!   --robots N           simulated robots (default 10000; 5 % of them in the simulator that
#!                        is cut off)
#!   --agents N           real agents (lekiwi-fleet, default 300, at most 1000)
#!   --duration D         how long the fleet works, seconds (default 3600)
#!   --fault-every S      seconds between faults (default 300)
#!   --release-every S    seconds between rollouts (default 180)
#!   --rotation LIST      the kinds of rollout in turn, comma-separated, from ok (completes),
#!                        fail (robots fail their health check: rolled back), undo (undone
#!                        once the canary switched), agent (an agent update), abort (aborted
#!                        while the first batch downloads); default fail,undo,agent,abort,ok
#!   --gateways G         gateway replicas (default 2)
#!   --events-per-minute E  durable events per simulated robot per minute (default 2)
#!   --no-build           use the binaries already in target/release
#!   --bin DIR            use the binaries in DIR (implies --no-build; e.g. debug builds and
#!                        a small fleet to check the script itself)
#!   --keep               keep the work directory
#!   -h, --help           this text
#!
#! Writes the table to bench/results/soak-latest.txt. Cleans
#! up on exit and Ctrl-C. Needs root or a `postgres` user (PostgreSQL refuses to run as root).
set -euo pipefail

ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
BIN="$ROOT/target/release"
RESULTS="$ROOT/bench/results"
PG_BIN=/usr/lib/postgresql/15/bin

ROBOTS=10000
AGENTS=300
DURATION=3600
FAULT_EVERY=300
RELEASE_EVERY=180
ROTATION=fail,undo,agent,abort,ok
GATEWAYS=2
EPM=2
BUILD=1
KEEP=0
COMMAND="bash bench/soak.sh $*"

# shellcheck source=bench/lib.sh
source "$ROOT/bench/lib.sh"

while [ $# -gt 0 ]; do
  case "$1" in
    --robots) positive_int "$1" "${2:-}"; ROBOTS="$2"; shift 2 ;;
    --agents) positive_int "$1" "${2:-}"; AGENTS="$2"; shift 2 ;;
    --duration) positive_int "$1" "${2:-}"; DURATION="$2"; shift 2 ;;
    --fault-every) positive_int "$1" "${2:-}"; FAULT_EVERY="$2"; shift 2 ;;
    --release-every) positive_int "$1" "${2:-}"; RELEASE_EVERY="$2"; shift 2 ;;
    --rotation)
      [[ "${2:-}" =~ ^(ok|fail|undo|agent|abort)(,(ok|fail|undo|agent|abort))*$ ]] \
        || die "--rotation is a comma-separated list of ok, fail, undo, agent, abort"
      ROTATION="$2"; shift 2 ;;
    --gateways)
      [[ "${2:-}" =~ ^[2-9]$ ]] || die "--gateways is a number from 2 to 9"
      GATEWAYS="$2"; shift 2 ;;
    --events-per-minute) positive_int "$1" "${2:-}"; EPM="$2"; shift 2 ;;
    --no-build) BUILD=0; shift ;;
    --bin) [ -d "${2:-}" ] || die "--bin needs a directory"; BIN="$(cd "$2" && pwd)"; BUILD=0; shift 2 ;;
    --keep) KEEP=1; shift ;;
    -h|--help) usage; exit 0 ;;
    *) usage >&2; die "unknown option: $1" ;;
  esac
done
[ "$AGENTS" -le 1000 ] || die "--agents is at most 1000"
[ "$ROBOTS" -ge 40 ] || die "--robots is at least 40 (5 % of them are cut off)"

WORK="$(mktemp -d "${TMPDIR:-/tmp}/lekiwi-soak.XXXXXX")"
chmod 755 "$WORK"
CP_DIR="$WORK/control-plane"
CP_UP=0
PIDS=()
CLEANUP_GRACE=3
trap_cleanup
take_bench_lock

ulimit -Hn "$(cat /proc/sys/fs/nr_open)" 2>/dev/null || true
ulimit -n "$(ulimit -Hn)" 2>/dev/null || true
FDS="$(ulimit -n)"
[ "$FDS" -gt $((ROBOTS + AGENTS + 2000)) ] \
  || die "open-file limit $FDS is too low for $((ROBOTS + AGENTS)) robots (raise the hard limit)"

log "work directory: $WORK"
release_binaries "lekiwi-operator lekiwi-agent kubectl-lekiwi" lekiwi-operator lekiwi-sim lekiwi-fleet kubectl-lekiwi
run_setup
command -v haproxy >/dev/null || die "haproxy is missing (scripts/setup.sh installs it)"

fact date "$(date -Is)"
fact host "$(nproc) CPUs ($(awk -F': ' '/^model name/ { print $2; exit }' /proc/cpuinfo)), $(awk '/^MemTotal/ { printf "%.0f GiB", $2 / 1048576 }' /proc/meminfo) RAM"
fact_source
fact command "$COMMAND"

# ---- PostgreSQL on a filesystem of its own -------------------------------------------------
as_postgres() { if [ "$(id -u)" = 0 ]; then runuser -u postgres -- "$@"; else "$@"; fi; }
PG_PORT="$(free_port)"
PG_DIR="$WORK/pg"
mkdir -p "$PG_DIR"
PG_DISK_MB=0
if [ "$(id -u)" = 0 ]; then
  # A tmpfs of its own: the disk-full fault fills it without touching the machine's disk. Sized
  # for the whole run: the database grows about 0.55 MiB per robot and hour at the default
  # rates (1 MiB here, for headroom; a tmpfs takes memory only for what it holds), the WAL
  # stays near its 512 MB bound. Too small, the store would fill up for good in the middle of
  # the run, as no fault does.
  PG_DISK_MB=$((768 + (ROBOTS + AGENTS) * DURATION / 3600))
  mount -t tmpfs -o "size=${PG_DISK_MB}m,mode=0755" lekiwi-soak-pg "$PG_DIR" \
    || die "could not mount a tmpfs for PostgreSQL"
  ON_EXIT_UMOUNT="umount -l '$PG_DIR' 2>/dev/null"
  ON_EXIT='eval "$ON_EXIT_UMOUNT"'
  chown postgres: "$PG_DIR"
fi
log "starting PostgreSQL on 127.0.0.1:$PG_PORT"
as_postgres "$PG_BIN/initdb" -D "$PG_DIR/data" -U postgres -A trust -E UTF8 --locale=C --no-sync \
  >"$WORK/initdb.log" 2>&1 || die "initdb failed: $(tail -5 "$WORK/initdb.log")"
touch "$WORK/postgres.log"
[ "$(id -u)" != 0 ] || chown postgres: "$WORK/postgres.log"
pg_start() {
  as_postgres "$PG_BIN/pg_ctl" -D "$PG_DIR/data" -l "$WORK/postgres.log" -w -t 60 \
    -o "-h 127.0.0.1 -p $PG_PORT -k $PG_DIR -c max_connections=200 -c max_wal_size=512MB" \
    start >/dev/null
}
pg_start || die "postgres did not start: $(tail -5 "$WORK/postgres.log")"
ON_EXIT='as_postgres "$PG_BIN/pg_ctl" -D "$PG_DIR/data" stop -m immediate >/dev/null 2>&1; eval "${ON_EXIT_UMOUNT:-}"'
"$PG_BIN/psql" -X -q -h 127.0.0.1 -p "$PG_PORT" -U postgres -c 'CREATE DATABASE lekiwi' >/dev/null
STORE_URL="postgres://postgres@127.0.0.1:$PG_PORT/lekiwi"

# ---- control plane, namespaces, the fleet's Robots --------------------------------------------
start_control_plane
kubectl create namespace lekiwi-system >/dev/null
kubectl create namespace soak >/dev/null
TOKEN="lke_$(openssl rand -hex 32)"
TOKEN_HASH="$(printf %s "$TOKEN" | sha256sum | cut -d' ' -f1)"
printf %s "$TOKEN" >"$WORK/sim-token"
chmod 600 "$WORK/sim-token"
enrollment_token soak "$WORK/enroll-token"
STALLED=$((ROBOTS / 20))
log "provisioning $ROBOTS Robots and token Secrets"
provision_robots soak "$((ROBOTS - STALLED))" "$TOKEN_HASH" sim
provision_robots soak "$STALLED" "$TOKEN_HASH" cut
provision_robots soak 1 "$TOKEN_HASH" skew
# The agent-update rollouts select the simulated robots (the real agents run from a build tree).
kubectl -n soak label robots --all fleet.lekiwi.io/sim=true >/dev/null

# ---- hand over to the driver ---------------------------------------------------------------
mkdir -p "$WORK/blobs"
python3 - "$WORK/config.json" <<PY
import json, sys
json.dump({
    "root": "$ROOT", "work": "$WORK", "bin": "$BIN", "cp_dir": "$CP_DIR",
    "kubeconfig": "$KUBECONFIG", "apiserver_port": int("$APISERVER_PORT"),
    "pg_bin": "$PG_BIN", "pg_dir": "$PG_DIR", "pg_port": int("$PG_PORT"),
    "pg_disk_mb": int("$PG_DISK_MB"), "as_postgres": "$(id -u)" == "0",
    "store_url": "$STORE_URL", "robots": int("$ROBOTS"), "stalled": int("$STALLED"),
    "agents": int("$AGENTS"), "duration": int("$DURATION"),
    "fault_every": int("$FAULT_EVERY"), "release_every": int("$RELEASE_EVERY"),
    "rotation": "$ROTATION".split(","),
    "gateways": int("$GATEWAYS"), "events_per_minute": int("$EPM"),
    "fds": int("$FDS"), "command": """$COMMAND""",
}, open(sys.argv[1], "w"), indent=1)
PY
log "handing over to bench/soak_driver.py for $DURATION s"
start driver python3 -u "$ROOT/bench/soak_driver.py" "$WORK/config.json"
DRIVER_PID=$LAST_PID
tail -n +1 -f "$WORK/driver.log" --pid "$DRIVER_PID" >&2 &
TAIL_PID=$!
PIDS+=("$TAIL_PID")
rc=0
wait "$DRIVER_PID" || rc=$?
forget "$DRIVER_PID"
sleep 1
[ -f "$WORK/report.txt" ] || die "the driver ended ($rc) without a report: $(tail -5 "$WORK/driver.log")"
cp "$WORK/report.txt" "$RESULTS/soak-latest.txt"
cat "$WORK/report.txt"
log "written to bench/results/soak-latest.txt"
exit "$rc"
