#!/usr/bin/env bash
#! What one Robot status write costs the API server, by the shape of the write (after a
#! gateway dies, the survivor's status writes for the robots that moved to it are what bounds the
#! recovery, and on a small control plane the API server's CPU is what bounds the writes).
#!
#! Runs, on loopback only: a private control plane (etcd + kube-apiserver) with our CRDs, N Robots,
#! and a few watches of them (as the controller and the gateways hold; their events are part of a
#! write's cost). Every Robot gets a whole gateway status once (not measured), then each shape of
#! bench/status_cost.py writes every Robot once, IN_FLIGHT at a time, ROUNDS times in turn. The
#! table gives per shape the writes per second and the CPU the API server and etcd used per write,
#! and both as ratios against today's write (ssa-full) measured in the same run.
#!
#! Usage: bash bench/status-cost.sh [options]
#!   --robots N      Robots (default 2000)
#!   --in-flight C   requests in flight (default 32, the gateway's --status-concurrency)
#!   --watches W     watches of every Robot besides none (default 5: the controller, two
#!                   gateways with two each)
#!   --rounds R      times each shape writes every Robot (default 2)
#!   --keep          keep the work directory
#!   -h, --help      this text
#! Writes the table to bench/results/status-cost-<date>.txt and bench/results/status-cost-latest.txt.
#! Bounded in time (about 3 minutes at 2,000 Robots), cleans up on exit and Ctrl-C.
set -euo pipefail

ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
RESULTS="$ROOT/bench/results"
ROBOTS=2000
IN_FLIGHT=32
WATCHES=5
ROUNDS=2
KEEP=0
COMMAND="bash bench/status-cost.sh $*"

# shellcheck source=bench/lib.sh
source "$ROOT/bench/lib.sh"

while [ $# -gt 0 ]; do
  case "$1" in
    --robots) positive_int "$1" "${2:-}"; ROBOTS="$2"; shift 2 ;;
    --in-flight) positive_int "$1" "${2:-}"; IN_FLIGHT="$2"; shift 2 ;;
    --watches) [[ "${2:-}" =~ ^[0-9]+$ ]] || die "--watches needs a number"; WATCHES="$2"; shift 2 ;;
    --rounds) positive_int "$1" "${2:-}"; ROUNDS="$2"; shift 2 ;;
    --keep) KEEP=1; shift ;;
    -h|--help) usage; exit 0 ;;
    *) usage >&2; die "unknown option: $1" ;;
  esac
done

WORK="$(mktemp -d "${TMPDIR:-/tmp}/lekiwi-status-cost.XXXXXX")"
CP_DIR="$WORK/control-plane"
CP_UP=0
PIDS=()
trap_cleanup
take_bench_lock
run_setup

fact date "$(date -Is)"
fact host "$(nproc) CPUs, load average at start $(cut -d' ' -f1-3 /proc/loadavg)"
fact_source
start_control_plane
kubectl create namespace bench >/dev/null
provision_robots bench "$ROBOTS" "$(printf x | sha256sum | cut -d' ' -f1)"
API="https://127.0.0.1:$APISERVER_PORT"
CA="$CP_DIR/pki/ca.crt"
TOKEN="$CP_DIR/admin-token"
HEADER="$WORK/auth.header"
(umask 077; printf 'Authorization: Bearer %s\n' "$(cat "$TOKEN")" >"$HEADER")
for i in $(seq 1 "$WATCHES"); do
  start "watch-$i" curl -sS --no-buffer --cacert "$CA" -H "@$HEADER" -o /dev/null \
    "$API/apis/fleet.lekiwi.io/v1alpha1/namespaces/bench/robots?watch=1&timeoutSeconds=3600"
done
APISERVER_PID="$(cat "$CP_DIR/kube-apiserver.pid")"
ETCD_PID="$(cat "$CP_DIR/etcd.pid")"

write_all() { # shape round
  python3 "$ROOT/bench/status_cost.py" "$API" "$CA" "$TOKEN" bench "$1" "$ROBOTS" "$IN_FLIGHT" "$2"
}
log "every Robot gets a whole gateway status first (not measured)"
write_all ssa-full 0 >"$WORK/warmup.json"

SHAPES=(ssa-full ssa-presence merge-full merge-presence)
: >"$WORK/runs.txt"
for round in $(seq 1 "$ROUNDS"); do
  for shape in "${SHAPES[@]}"; do
    sleep 2
    a0="$(cpu_seconds "$APISERVER_PID")"; e0="$(cpu_seconds "$ETCD_PID")"
    result="$(write_all "$shape" "$round")"
    a1="$(cpu_seconds "$APISERVER_PID")"; e1="$(cpu_seconds "$ETCD_PID")"
    echo "$result $a0 $a1 $e0 $e1" >>"$WORK/runs.txt"
    log "round $round, $shape: $result"
  done
done

mkdir -p "$RESULTS"
STAMP="$(date +%Y%m%d-%H%M%S)"
python3 - "$WORK" "$COMMAND" "$ROBOTS" "$IN_FLIGHT" "$WATCHES" >"$RESULTS/status-cost-$STAMP.txt" <<'PY'
import json, sys
from collections import defaultdict
work, command, robots, in_flight, watches = sys.argv[1:6]
facts = dict(l.rstrip("\n").split("=", 1) for l in open(f"{work}/facts.env") if "=" in l)
runs = defaultdict(lambda: {"writes": 0, "seconds": 0.0, "api": 0.0, "etcd": 0.0, "codes": defaultdict(int)})
order = []
for line in open(f"{work}/runs.txt"):
    blob, a0, a1, e0, e1 = line.rsplit(" ", 4)
    r = json.loads(blob)
    s = runs[r["shape"]]
    if r["shape"] not in order:
        order.append(r["shape"])
    s["writes"] += r["writes"]; s["seconds"] += r["seconds"]
    s["api"] += float(a1) - float(a0); s["etcd"] += float(e1) - float(e0)
    for c, n in r["codes"].items():
        s["codes"][c] += n
print(f"# What a Robot status write costs the API server, {facts.get('date')}")
print()
print(f"- source: {facts.get('source', '?')}; command: `{command}`")
print(f"- host: {facts.get('host')}; Kubernetes v1.20.2 API server and etcd on loopback")
print(f"- {robots} Robots, {in_flight} writes in flight, {watches} watches of every Robot; each shape "
      "writes every Robot once per round, the shapes in turn; ratios against ssa-full of the same run")
print()
print("| shape | writes | writes/s | API server CPU per write | etcd CPU per write | writes/s ratio | API CPU ratio | answers |")
print("|---|---|---|---|---|---|---|---|")
base = runs["ssa-full"]
base_rate = base["writes"] / base["seconds"]
base_api = base["api"] / base["writes"]
for shape in order:
    s = runs[shape]
    rate = s["writes"] / s["seconds"]
    api = s["api"] / s["writes"]
    etcd = s["etcd"] / s["writes"]
    print(f"| {shape} | {s['writes']} | {rate:.0f} | {api * 1000:.2f} ms | {etcd * 1000:.2f} ms | "
          f"{rate / base_rate:.2f} | {api / base_api:.2f} | {dict(s['codes'])} |")
PY
cp "$RESULTS/status-cost-$STAMP.txt" "$RESULTS/status-cost-latest.txt"
cat "$RESULTS/status-cost-$STAMP.txt"
log "table written to bench/results/status-cost-$STAMP.txt"
