#!/usr/bin/env bash
#! Fleet API benchmark: runs a private control plane (etcd + kube-apiserver v1.20.2), creates N
#! Robots in namespace `bench` (label `room`: N/100 rooms of 100 Robots, robot i in room i mod N/100, so
#! a room's Robots are spread over the whole namespace), the operator's
#! gateway (--role gateway, rate limit out of the way) and `wrk` (Debian), and prints one table:
#! requests per second and latency p50/p99 of the Fleet API next to the API server's own answer to
#! the same question, with the same ServiceAccount token (bound to a viewer role):
#!   one robot       GET /api/v1/namespaces/bench/robots/robot-NNNNN
#!                   vs GET /apis/fleet.lekiwi.io/v1alpha1/namespaces/bench/robots/robot-NNNNN
#!   list of 100     GET /api/v1/namespaces/bench/robots?labelSelector=room%3DrK&limit=100 (K: the middle room)
#!                   vs the API server's list with the same labelSelector and limit
#! Each is measured twice: latency with one connection (one request at a time), and throughput
#! with --connections connections on two wrk threads. wrk shares the machine's cores with the
#! servers it measures.
#! Then subscription fan-out: --subscribers GraphQL WebSockets (graphql-transport-ws, the same
#! token) subscribe to robotChanges of room r0 and the script's client (tests/src/bin/
#! graphql-fanout.rs) flips robot-00000's phase 5 times through the API server: p50/p99/max from
#! just before each write to each subscriber's receipt (goal p99 < 100 ms).
#!
#! Usage: bash bench/api.sh [options]
#!   --robots N         Robots created (default 10000)
#!   --duration S       seconds per wrk run (default 10; 8 runs)
#!   --connections C    connections of the throughput runs (default 32)
#!   --subscribers S    GraphQL subscribers of the fan-out run (default 1000; 0 skips it)
#!   --no-build         use the binaries already built
#!   --debug            use (and build) the debug binaries: a smoke test of this script, not a
#!                      measurement (the table says so)
#!   --keep             keep the work directory (logs, wrk output)
#!   -h, --help         this text
#!
#! Writes the table to bench/results/api-<date>.txt and bench/results/api-latest.txt. Takes about
#! two minutes plus the Robots' creation (about a minute per 10,000) once built; cleans up on
#! exit, failure and Ctrl-C; shares the benchmark lock of bench/gateway.sh.
set -euo pipefail

ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
TARGET="${CARGO_TARGET_DIR:-$ROOT/target}"
RESULTS="$ROOT/bench/results"
ROBOTS=10000
DURATION=10
CONNECTIONS=32
SUBSCRIBERS=1000
BUILD=1
PROFILE=release
KEEP=0
CP_UP=0
PIDS=()
COMMAND="bash bench/api.sh $*"

# shellcheck source=bench/lib.sh
source "$ROOT/bench/lib.sh"

while [ $# -gt 0 ]; do
  case "$1" in
    --robots) positive_int "$1" "${2:-}"; ROBOTS="$2"; shift 2 ;;
    --duration) positive_int "$1" "${2:-}"; DURATION="$2"; shift 2 ;;
    --connections) positive_int "$1" "${2:-}"; CONNECTIONS="$2"; shift 2 ;;
    --subscribers) [[ "${2:-}" =~ ^[0-9]+$ ]] || die "--subscribers needs a number"; SUBSCRIBERS="$2"; shift 2 ;;
    --no-build) BUILD=0; shift ;;
    --debug) PROFILE=debug; shift ;;
    --keep) KEEP=1; shift ;;
    -h|--help) usage; exit 0 ;;
    *) usage >&2; die "unknown option: $1" ;;
  esac
done
[ "$ROBOTS" -ge 100 ] || die "--robots must be at least 100 (the list reads 100 of them)"

take_bench_lock
WORK="$(mktemp -d "${TMPDIR:-/tmp}/lekiwi-bench-api.XXXXXX")"
CP_DIR="$WORK/control-plane"
trap_cleanup

if [ "$BUILD" = 1 ]; then
  log "building the operator ($PROFILE)"
  flag=(); [ "$PROFILE" = release ] && flag=(--release)
  (cd "$ROOT" && cargo build "${flag[@]}" --bin lekiwi-operator --bin graphql-fanout) >"$WORK/build.log" 2>&1 \
    || { tail -30 "$WORK/build.log" >&2; die "build failed"; }
fi
OPERATOR="$TARGET/$PROFILE/lekiwi-operator"
FANOUT="$TARGET/$PROFILE/graphql-fanout"
[ -x "$OPERATOR" ] || die "$OPERATOR is missing (drop --no-build)"
[ "$SUBSCRIBERS" = 0 ] || [ -x "$FANOUT" ] || die "$FANOUT is missing (drop --no-build)"
log "scripts/setup.sh"
bash "$ROOT/scripts/setup.sh" >"$WORK/setup.log" 2>&1 || { tail -30 "$WORK/setup.log" >&2; die "setup failed"; }
command -v wrk >/dev/null || die "wrk is missing (scripts/setup.sh installs Debian's wrk)"
: >"$WORK/facts.env"
fact_source
start_control_plane
API_SERVER="https://127.0.0.1:$APISERVER_PORT"

# ---- the fleet ------------------------------------------------------------------------------
# Robots in chunks of 1,000, four `kubectl create` at once (each one request per Robot).
create_robots() {
  local chunk
  kubectl create namespace bench >/dev/null
  mkdir -p "$WORK/robots"
  python3 - "$ROBOTS" "$ROOMS" "$WORK/robots" <<'EOF'
import sys
n, rooms, out = int(sys.argv[1]), int(sys.argv[2]), sys.argv[3]
for start in range(0, n, 1000):
    with open(f"{out}/{start:06d}.yaml", "w") as f:
        for i in range(start, min(n, start + 1000)):
            f.write(f"---\napiVersion: fleet.lekiwi.io/v1alpha1\nkind: Robot\nmetadata:\n"
                    f"  name: robot-{i:05d}\n  namespace: bench\n  labels: {{room: r{i % rooms}}}\n"
                    f"spec:\n  displayName: Bench robot {i}\n")
EOF
  find "$WORK/robots" -name '*.yaml' -print0 | sort -z \
    | xargs -0 -P 4 -I{} kubectl create -f {} -o name >"$WORK/create.log" 2>&1 \
    || die "creating Robots failed: $(tail -3 "$WORK/create.log")"
}
ROOMS=$((ROBOTS / 100))
log "creating $ROBOTS Robots in $ROOMS rooms"
T0="$(now)"
create_robots
fact create_seconds "$(elapsed "$T0")"

# A viewer ServiceAccount: the same token for both servers.
kubectl create clusterrole bench-viewer --verb=get,list,watch \
  --resource=robots.fleet.lekiwi.io,robotdeployments.fleet.lekiwi.io >/dev/null
kubectl -n bench create serviceaccount reader >/dev/null
kubectl -n bench create rolebinding reader --clusterrole bench-viewer --serviceaccount bench:reader >/dev/null
TOKEN="$(kubectl -n bench create token reader --duration=1h)"

# ---- the gateway ----------------------------------------------------------------------------
GW_PORT="$(free_port)"
GW_HTTP="$(free_port)"
log "starting the gateway (:$GW_PORT)"
start gateway env RUST_LOG=warn "$OPERATOR" --role gateway \
  --kubeconfig "$KUBECONFIG" --namespace bench --watch-namespace bench \
  --identity bench-api --gateway-name bench-api \
  --gateway-addr "127.0.0.1:$GW_PORT" --http-addr "127.0.0.1:$GW_HTTP" \
  --store-url "sqlite://$WORK/events.db" --blob-dir "$WORK/blobs" \
  --api-rate 1000000000 --api-burst 1000000000 --max-unauthenticated-per-address 0 \
  --graphql-max-connections $((SUBSCRIBERS + 100)) --graphql-max-subscriptions-per-user $((SUBSCRIBERS + 100)) \
  --graphql-max-connections-per-user $((SUBSCRIBERS + 100))
GW_PID=$LAST_PID
FLEET="http://127.0.0.1:$GW_PORT/api/v1/namespaces/bench/robots"
LAST="robot-$(printf %05d $((ROBOTS - 1)))"
cached() {
  alive "$GW_PID" || die "gateway exited: $(tail -5 "$WORK/gateway.log")"
  curl -fsS --max-time 2 -H "Authorization: Bearer $TOKEN" "$FLEET/$LAST" >/dev/null 2>&1
}
T0="$(now)"
wait_for "the gateway's Robot cache" 120 cached
fact cache_seconds "$(elapsed "$T0")"
fact gateway_rss_mib "$(( $(rss_kib "$GW_PID") / 1024 ))"

# ---- measuring ------------------------------------------------------------------------------
ONE="robot-$(printf %05d $((ROBOTS / 2)))"
LIST="labelSelector=room%3Dr$((ROOMS / 2))&limit=100"
KUBE="$API_SERVER/apis/fleet.lekiwi.io/v1alpha1/namespaces/bench/robots"
# Both answer what they should before anything is timed.
curl -fsS -H "Authorization: Bearer $TOKEN" "$FLEET?$LIST" | python3 -c \
  'import json,sys; n=len(json.load(sys.stdin)["items"]); sys.exit(0 if n == 100 else f"Fleet API list: {n} items")'
curl -fsS -k -H "Authorization: Bearer $TOKEN" "$KUBE?$LIST" | python3 -c \
  'import json,sys; n=len(json.load(sys.stdin)["items"]); sys.exit(0 if n == 100 else f"API server list: {n} items")'

run_wrk() { # name connections threads url
  log "wrk $1 (${DURATION}s)"
  wrk -t"$3" -c"$2" -d"${DURATION}s" --timeout 10s --latency -H "Authorization: Bearer $TOKEN" "$4" >"$WORK/wrk-$1.txt" 2>&1 \
    || die "wrk $1 failed: $(tail -3 "$WORK/wrk-$1.txt")"
}
for server in fleet kube; do
  if [ "$server" = fleet ]; then base="$FLEET"; else base="$KUBE"; fi
  run_wrk "$server-one-lat" 1 1 "$base/$ONE"
  run_wrk "$server-list-lat" 1 1 "$base?$LIST"
  run_wrk "$server-one-rps" "$CONNECTIONS" 2 "$base/$ONE"
  run_wrk "$server-list-rps" "$CONNECTIONS" 2 "$base?$LIST"
done

if [ "$SUBSCRIBERS" -gt 0 ]; then
  log "subscription fan-out: $SUBSCRIBERS subscribers"
  # Each subscriber holds a socket here and one in the gateway.
  ulimit -n "$(ulimit -Hn)"
  "$FANOUT" --port "$GW_PORT" --token "$TOKEN" --namespace bench --robot robot-00000 \
    --selector room=r0 --subscribers "$SUBSCRIBERS" --rounds 5 >"$WORK/fanout.json" 2>"$WORK/fanout.log" \
    || die "fan-out client failed: $(tail -3 "$WORK/fanout.log")"
fi

# ---- the table ------------------------------------------------------------------------------
STAMP="$(date +%Y%m%d-%H%M%S)"
mkdir -p "$RESULTS"
python3 "$ROOT/bench/api_report.py" "$WORK" "$ROBOTS" "$DURATION" "$CONNECTIONS" "$PROFILE" "$COMMAND" \
  | tee "$RESULTS/api-$STAMP.txt"
cp "$RESULTS/api-$STAMP.txt" "$RESULTS/api-latest.txt"
log "written to bench/results/api-$STAMP.txt and bench/results/api-latest.txt"
