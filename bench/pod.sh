#!/usr/bin/env bash
#! Operator Pod benchmark on the real node of scripts/testbed/cluster.sh: installs the chart (image from
#! scripts/image.sh, defaults except a 200Mi claim, the gateway as a NodePort and plain ws://, which
#! is all lekiwi-sim speaks), then reads the operator container's cgroup (v1 `memory`, `cpuacct`)
#! from the host at idle and with N robots of `lekiwi-sim` connected through the NodePort, and
#! prints one table against the chart's requests and limits. Removes its release and namespace at
#! the end; leaves the cluster up.
#!
#! Usage: bash bench/pod.sh [--robots N] [--sample S]
#!   --robots N   simulated robots (default 1000)
#!   --sample S   seconds each CPU sample spans (default 10)
#! Environment: CARGO_TARGET_DIR (where the debug binaries are built, default target/).
set -euo pipefail

ROOT="$(cd "$(dirname "$0")/.." && pwd)"
# shellcheck source=bench/lib.sh
source "$ROOT/bench/lib.sh"

ROBOTS=1000
SAMPLE=10
while [ $# -gt 0 ]; do
  case "$1" in
    --robots) ROBOTS="$2"; shift ;;
    --sample) SAMPLE="$2"; shift ;;
    -h|--help) usage; exit 0 ;;
    *) die "unknown option $1 (see --help)" ;;
  esac
  shift
done
positive_int --robots "$ROBOTS"
positive_int --sample "$SAMPLE"

cd "$ROOT"
BIN="${CARGO_TARGET_DIR:-$ROOT/target}/debug"
export PATH="$HOME/.cache/lekiwi/bin:$PATH"
NS="bench-pod-$$"
WORK="$(mktemp -d)"
SIM_PID=""

cleanup() {
  [ -n "$SIM_PID" ] && kill "$SIM_PID" 2>/dev/null && wait "$SIM_PID" 2>/dev/null
  helm uninstall "$NS" -n "$NS" >/dev/null 2>&1 || true
  kubectl delete namespace "$NS" --wait=false >/dev/null 2>&1 || true
  rm -rf "$WORK"
}
trap cleanup EXIT

log "cluster, binaries and image"
bash scripts/testbed/cluster.sh up >&2
eval "$(bash scripts/testbed/cluster.sh env)"
cargo build --quiet --workspace --bins
bash scripts/image.sh operator --arch amd64 --load ctr --address "$CONTAINERD_ADDRESS" >/dev/null

log "helm install $NS"
kubectl create namespace "$NS" >/dev/null
helm install "$NS" charts/lekiwi-operator -n "$NS" --set image.pullPolicy=Never \
  --set rbac.userRoles=false --set persistence.size=200Mi --set gateway.service.type=NodePort \
  --set gateway.tls.enabled=false >/dev/null
kubectl -n "$NS" wait --for=condition=Ready pod -l app.kubernetes.io/component=operator \
  --timeout=120s >/dev/null
sel=app.kubernetes.io/component=operator
cid="$(kubectl -n "$NS" get pod -l "$sel" -o jsonpath='{.items[0].status.containerStatuses[0].containerID}')"
cid="${cid#containerd://}"
pid="$(ctr --address "$CONTAINERD_ADDRESS" -n k8s.io tasks ls | awk -v id="$cid" '$1 == id {print $2}')"
[ -n "$pid" ] || die "no task for container $cid"
cg() { awk -F: -v c="$1" '{n = split($2, a, ","); for (i = 1; i <= n; i++) if (a[i] == c) print $3}' "/proc/$pid/cgroup"; }
MEM="/sys/fs/cgroup/memory$(cg memory)"
CPU="/sys/fs/cgroup/cpuacct$(cg cpuacct)"
[ -r "$MEM/memory.usage_in_bytes" ] || die "no cgroup v1 memory controller at $MEM"

# One row: what, charged memory, its peak, RSS, CPU (millicores over $SAMPLE s), CPU total.
row() {
  local a b
  a="$(cat "$CPU/cpuacct.usage")"; sleep "$SAMPLE"; b="$(cat "$CPU/cpuacct.usage")"
  printf '%-22s %9s %9s %9s %10s %9s\n' "$1" \
    "$(( $(cat "$MEM/memory.usage_in_bytes") / 1048576 ))Mi" \
    "$(( $(cat "$MEM/memory.max_usage_in_bytes") / 1048576 ))Mi" \
    "$(( $(awk '/^VmRSS:/ {print $2}' "/proc/$pid/status") / 1024 ))Mi" \
    "$(( (b - a) / SAMPLE / 1000000 ))m" "$(( b / 1000000 ))ms"
}

log "idle"
{
  printf '%-22s %9s %9s %9s %10s %9s\n' "state" "memory" "peak" "RSS" "CPU" "CPU total"
  row "idle"
} >"$WORK/table"

log "$ROBOTS robots (lekiwi-sim) through the NodePort"
token="$("$BIN/kubectl-lekiwi" -n "$NS" enroll-token | grep -o 'lke_[A-Za-z0-9_-]*' | head -1)"
port="$(kubectl -n "$NS" get service "$NS-lekiwi-operator-gateway" -o jsonpath='{.spec.ports[0].nodePort}')"
: >"$WORK/sim.log"
"$BIN/lekiwi-sim" --gateway "ws://$LEKIWI_NODE_IP:$port/v1/agent" --enrollment-token "$token" \
  --namespace "$NS" --robots "$ROBOTS" --connect-rate 100 --report-every 5 --telemetry-interval-s 0 \
  >"$WORK/sim.log" 2>&1 </dev/null &
SIM_PID=$!
deadline=$((SECONDS + 300))
until grep -q "connected $ROBOTS/$ROBOTS" "$WORK/sim.log"; do
  [ "$SECONDS" -lt "$deadline" ] || die "not every robot connected: $(tail -1 "$WORK/sim.log")"
  kill -0 "$SIM_PID" 2>/dev/null || die "lekiwi-sim ended: $(tail -3 "$WORK/sim.log")"
  sleep 1
done
row "$ROBOTS robots connected" >>"$WORK/table"
kill "$SIM_PID"; wait "$SIM_PID" 2>/dev/null || true; SIM_PID=""

cat "$WORK/table"
printf 'chart defaults: %s\n' \
  "$(kubectl -n "$NS" get deployment "$NS-lekiwi-operator" -o jsonpath='{.spec.template.spec.containers[0].resources}')"
